"""Question 3c: integer millimetres vs float32 metres for the range channel, per real sensor.

Each real frame is imported twice by :func:`converters.ouster.scan_from_frame`: ``range`` as
float32 metres (canonical) and as the sensor's native UINT32 millimetres (decoded with the
info's ``range_multiplier`` = 0.001). Deterministic block: the range block's bytes raw and
compressed (zstd-3, byte shuffle + zstd-3, the range segment of :mod:`lidarscan.codec`), and the
precision on this frame (worst |float32 metres − mm / 1000|, and whether every mm value comes
back from float32 exactly). Timing block: what each form costs in the receiver paths, through
their public API: ``converters.to_pointcloud2`` (ouster-ros layout) and
``converters.SliceConverter`` (three bands), and ``lidarscan.range_m``.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np

from converters.evidence._common import (
    Block,
    fmt_int,
    load_frame,
    ouster_files,
    ouster_info,
    short_name,
    table,
    time_call,
)

__all__ = ["blocks", "measure"]

FORMS = {"float32 m": "float32", "uint32 mm (range_multiplier 0.001)": "uint32_mm"}


def _scans() -> list[tuple[str, Any, dict[str, Any]]]:
    from converters.ouster import scan_from_frame
    out = []
    for meta, frame_path in ouster_files():
        if frame_path is None:
            continue
        info = ouster_info(meta)
        frame = load_frame(frame_path)
        label = short_name(meta) + (" dual" if "range2_mm" in frame else "")
        out.append((label, info, {form: scan_from_frame(frame, info, range_encoding=enc,
                                                        as_dataclass=True)
                                  for form, enc in FORMS.items()}))
    return out


@lru_cache(maxsize=1)
def measure() -> list[dict[str, Any]]:
    """Per real frame and range form: bytes raw / zstd-3 / shuffle+zstd-3 / codec segment."""
    import lidarscan as ls
    from converters.evidence.compression import CODECS
    from lidarscan import codec
    out = []
    for label, info, scans in _scans():
        mm = np.ascontiguousarray(ls.channel(scans["uint32 mm (range_multiplier 0.001)"],
                                             "range"))
        metres = np.ascontiguousarray(ls.channel(scans["float32 m"], "range"))
        hit = mm > 0
        exact = (mm[hit] * 0.001).astype(np.float32)
        err_um = float(np.abs(exact.astype(np.float64) - mm[hit] / 1000.0).max()) * 1e6
        back = np.rint(metres[hit].astype(np.float64) * 1000).astype(np.int64)
        for form, scan in scans.items():
            block = np.ascontiguousarray(ls.channel(scan, "range"))
            packed = codec.compress_scan(scan, info)
            offset = next(int(c.offset) for c in scan.channels if c.name == "range")
            seg = next(s for s in codec.segments(packed) if s["offset"] == offset)
            out.append({"label": label, "form": form, "raw": block.nbytes,
                        "zstd-3": len(CODECS["zstd-3"]()[0](block)),
                        "shuffle+zstd-3": len(CODECS["shuffle+zstd-3"]()[0](block)),
                        "codec": seg["payload_bytes"], "codec_method": seg["method"],
                        "err_um": 0.0 if form != "float32 m" else err_um,
                        "exact": bool(np.array_equal(back, mm[hit]))
                        if form == "float32 m" else True,
                        "max_m": float(mm.max()) / 1000})
    return out


def _timing() -> str:
    import lidarscan as ls
    from converters import SliceConverter, to_pointcloud2
    from converters.evidence.transport import SLICES
    rows = []
    for label, info, scans in _scans():
        slicer = SliceConverter(info, {k: {"min_height": lo, "max_height": hi}
                                       for k, (lo, hi) in SLICES.items()},
                                intensity_channel=None)
        base: dict[str, float] = {}
        for form, scan in scans.items():
            cases = {"range_m (float32 metres view)": lambda s=scan: ls.range_m(s, info),
                     "to_pointcloud2 (ouster-ros layout)":
                         lambda s=scan: to_pointcloud2(s, info, preset="ouster"),
                     f"SliceConverter ({len(SLICES)} bands)": lambda s=scan: slicer.convert(s)}
            for step, fn in cases.items():
                t = time_call(fn, repeat=5)
                base.setdefault(step, t)
                rows.append([label, form, step, f"{t * 1e3:.3f}", f"{t / base[step]:.2f}"])
    return table(["frame", "range form", "receiver step", "ms per frame", "÷ float32 m"], rows,
                 ["l", "l", "l", "r", "r"])


def blocks(timing: bool = True) -> list[Block]:
    """``int-vs-float`` (sizes, precision) and ``timing-int-vs-float``."""
    from converters.evidence.compression import _versions
    rows = []
    for r in measure():
        rows.append([r["label"], r["form"], fmt_int(r["raw"]), fmt_int(r["zstd-3"]),
                     fmt_int(r["shuffle+zstd-3"]), f"{fmt_int(r['codec'])} ({r['codec_method']})",
                     f"{r['err_um']:.2f}", "yes" if r["exact"] else "**no**",
                     f"{r['max_m']:.3f}"])
    out = [Block("int-vs-float", f"Range channel of the real frames ({_versions()}), bytes:\n\n"
                 + table(["frame", "range form", "raw", "zstd-3", "shuffle+zstd-3",
                          "lidarscan.codec segment", "worst error vs mm (µm)",
                          "every mm value recovered", "max range in frame (m)"], rows,
                         ["l", "l", "r", "r", "r", "r", "r", "l", "r"]))]
    if timing:
        out.append(Block("timing-int-vs-float", _timing(), deterministic=False))
    return out
