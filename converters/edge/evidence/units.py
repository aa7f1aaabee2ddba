"""Question 3c: integer range units vs float32 metres for the range channel, per real sensor.

Each real Ouster frame is imported twice by :func:`converters.sources.ouster.metadata.scan_from_frame`: ``range``
as float32 metres (canonical) and as the sensor's native UINT32 millimetres (decoded with the
info's ``range_multiplier`` = 0.001). The Velodyne and Hesai rotations of the codec study come
from their packet decoders in the sensors' native integer units (uint16, ``range_multiplier``
0.004 m) and are converted to float32 metres by ``lidarscan.range_m`` (0 -> +Inf). Deterministic
block: the range block's bytes raw and compressed (zstd-3, byte shuffle + zstd-3, the range
segment of :mod:`lidarscan.codec`), and the precision on this frame (worst |float32 metres −
units × multiplier|, and whether every integer comes back from float32 exactly). Timing block:
what each form costs in the receiver paths, through their public API:
``converters.to_pointcloud2`` (the driver's layout) and ``converters.SliceConverter`` (three
bands), and ``lidarscan.range_m``."""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np

from converters.edge.evidence._common import (
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


FLOAT_FORM = "float32 m"


def _as_metres(scan: Any, info: Any) -> Any:
    """The scan with every integer range channel as float32 metres (``lidarscan.range_m``)."""
    import lidarscan as ls
    from lidarscan.stamps import to_ns
    chans = {c.name: (ls.range_m(scan, info, c.name) if c.name.startswith("range")
                      else ls.channel(scan, c.name)) for c in scan.channels}
    return ls.make_scan(info, chans, to_ns(scan.header.stamp),
                        frame_id=scan.header.frame_id, is_destaggered=scan.is_destaggered,
                        column_time_offsets=scan.column_time_offsets,
                        column_azimuth_angles=scan.column_azimuth_angles, as_dataclass=True)


def _scans() -> list[tuple[str, Any, dict[str, Any], str]]:
    """(label, info, form -> scan, driver's PointCloud2 preset) per real frame: the Ouster
    frames in both range encodings, the Velodyne / Hesai rotations of the codec study in their
    native integer units and as float32 metres."""
    from converters.edge.evidence import codec_study
    from converters.sources.ouster.metadata import scan_from_frame
    out = []
    for meta, frame_path in ouster_files():
        if frame_path is None:
            continue
        info = ouster_info(meta)
        frame = load_frame(frame_path)
        label = short_name(meta) + (" dual" if "range2_mm" in frame else "")
        out.append((label, info, {form: scan_from_frame(frame, info, range_encoding=enc,
                                                        as_dataclass=True)
                                  for form, enc in FORMS.items()}, "ouster"))
    for label, preset, load in codec_study._nebula_sources():
        info, scan = load()
        native = next(c for c in scan.channels if c.name == "range")
        size = {2: 8, 4: 16, 6: 32}.get(int(native.datatype), 0)
        int_form = f"uint{size} native units (range_multiplier {float(info.range_multiplier):g})"
        out.append((label, info, {FLOAT_FORM: _as_metres(scan, info), int_form: scan}, preset))
    return out


@lru_cache(maxsize=1)
def measure() -> list[dict[str, Any]]:
    """Per real frame and range form: bytes raw / zstd-3 / shuffle+zstd-3 / codec segment."""
    import lidarscan as ls
    from converters.edge.evidence.compression import CODECS
    from lidarscan import codec
    out = []
    for label, info, scans, _ in _scans():
        int_form = next(f for f in scans if f != FLOAT_FORM)
        mult = float(info.range_multiplier)
        units = np.ascontiguousarray(ls.channel(scans[int_form], "range")).astype(np.int64)
        metres = np.ascontiguousarray(ls.channel(scans[FLOAT_FORM], "range"))
        hit = units > 0
        exact_m = units[hit] * mult  # float64: the value the integer stands for
        err_um = float(np.abs(metres[hit].astype(np.float64) - exact_m).max()) * 1e6
        back = np.rint(metres[hit].astype(np.float64) / mult).astype(np.int64)
        for form, scan in scans.items():
            block = np.ascontiguousarray(ls.channel(scan, "range"))
            packed = codec.compress_scan(scan, info)
            offset = next(int(c.offset) for c in scan.channels if c.name == "range")
            seg = next(s for s in codec.segments(packed) if s["offset"] == offset)
            out.append({"label": label, "form": form, "raw": block.nbytes,
                        "zstd-3": len(CODECS["zstd-3"]()[0](block)),
                        "shuffle+zstd-3": len(CODECS["shuffle+zstd-3"]()[0](block)),
                        "codec": seg["payload_bytes"], "codec_method": seg["method"],
                        "err_um": 0.0 if form != FLOAT_FORM else err_um,
                        "exact": bool(np.array_equal(back, units[hit]))
                        if form == FLOAT_FORM else True,
                        "max_m": float(units.max()) * mult})
    return out


def _timing() -> str:
    import lidarscan as ls
    from converters import SliceConverter, to_pointcloud2
    from converters.edge.evidence.transport import SLICES
    rows = []
    for label, info, scans, preset in _scans():
        slicer = SliceConverter(info, {k: {"min_height": lo, "max_height": hi}
                                       for k, (lo, hi) in SLICES.items()},
                                intensity_channel=None)
        base: dict[str, float] = {}
        for form, scan in scans.items():
            cases = {"range_m (float32 metres view)": lambda s=scan: ls.range_m(s, info),
                     f"to_pointcloud2 ({preset} layout)":
                         lambda s=scan: to_pointcloud2(s, info, preset=preset),
                     f"SliceConverter ({len(SLICES)} bands)": lambda s=scan: slicer.convert(s)}
            for step, fn in cases.items():
                t = time_call(fn, repeat=5)
                base.setdefault(step, t)
                rows.append([label, form, step, f"{t * 1e3:.3f}", f"{t / base[step]:.2f}"])
    return table(["frame", "range form", "receiver step", "ms per frame", "÷ float32 m"], rows,
                 ["l", "l", "l", "r", "r"])


def blocks(timing: bool = True) -> list[Block]:
    """``int-vs-float`` (sizes, precision) and ``timing-int-vs-float``."""
    from converters.edge.evidence.compression import _versions
    rows = []
    for r in measure():
        rows.append([r["label"], r["form"], fmt_int(r["raw"]), fmt_int(r["zstd-3"]),
                     fmt_int(r["shuffle+zstd-3"]), f"{fmt_int(r['codec'])} ({r['codec_method']})",
                     f"{r['err_um']:.2f}", "yes" if r["exact"] else "**no**",
                     f"{r['max_m']:.3f}"])
    out = [Block("int-vs-float", f"Range channel of the real frames ({_versions()}), bytes:\n\n"
                 + table(["frame", "range form", "raw", "zstd-3", "shuffle+zstd-3",
                          "lidarscan.codec segment", "worst error vs the integer (µm)",
                          "every integer recovered", "max range in frame (m)"], rows,
                         ["l", "l", "r", "r", "r", "r", "r", "l", "r"]))]
    if timing:
        out.append(Block("timing-int-vs-float", _timing(), deterministic=False))
    return out
