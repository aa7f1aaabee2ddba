"""Question 1c: compressed against compressed, real frames: driver's PointCloud2 vs LidarScan.

For every real frame (:data:`SOURCES`: the Ouster fixtures; another sensor is one more line
there, once its decoder exists) the driver's cloud (``converters.to_pointcloud2`` with the
driver's preset, organized, as the driver publishes it) and the LidarScan (canonical float32
range, staggered as published) are coded with:

* cloud: raw, lz4, zstd-3, zstd-19 (lossless; the best of them is the baseline "best lossless
  cloud"), Draco with a 1 mm quantisation grid on x, y, z only (lossy; points without a return
  dropped, order not kept: Draco cannot hold NaN points);
* LidarScan: raw, lz4 / zstd-3 / zstd-19 of the whole ``data`` buffer (what an MCAP chunk
  compressor does), byte shuffle + zstd-3 per block, the project's codec
  (:mod:`lidarscan.codec`, zstd level 3), and the image codecs of ``imagecodecs``: 16-bit PNG
  and lossless JPEG-XL of every 8/16-bit channel and of the range in integer millimetres (split
  into its low and high 16-bit words when it exceeds 65.535 m, so the images stay lossless).

Every lossless coding is decoded and compared byte for byte before its size is reported. Sizes
are deterministic for given library versions (named in the block's first line); encode/decode
times (one thread) go to ``timing-codec``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import lru_cache
from typing import Any

import numpy as np

from converters.evidence._common import Block, fmt_int, table, time_call

__all__ = ["GOALS", "SOURCES", "blocks", "measure", "sources"]

#: Goals of the issue, per real sensor: all channels lossless <= 0.2 x the best lossless coding
#: of the driver's cloud; the range channel lossless <= 0.4 x Draco's lossy 1 mm x,y,z; encode
#: and decode >= 50 Hz on one core for 128 x 2048 pixels.
GOALS = {"all": 0.2, "range": 0.4, "hz": 50.0, "pixels": 128 * 2048}


def _ouster_sources() -> list[tuple[str, str, Callable[[], tuple[Any, Any]]]]:
    from converters.evidence.compression import real_scans
    return [(label, "ouster", (lambda i=info, s=scan: (i, s)))
            for label, info, scan, _ in real_scans()]


def sources() -> list[tuple[str, str, Callable[[], tuple[Any, Any]]]]:
    """(label, driver's PointCloud2 preset, loader -> (info, scan dataclass)) of every real frame.

    A new sensor is one more entry in :data:`SOURCES` (a function returning such triples).
    """
    out = []
    for make in SOURCES:
        out += make()
    return out


#: Producers of real frames; add a sensor here, e.g. a ``_velodyne_sources`` returning
#: ``[("VLP-16 <fixture>", "velodyne", lambda: (info, scan))]``.
SOURCES: list[Callable[[], list[tuple[str, str, Callable[[], tuple[Any, Any]]]]]] = [
    _ouster_sources]


def _versions() -> str:
    import lz4
    import zstandard
    parts = [f"zstandard {zstandard.__version__}", f"lz4 {lz4.__version__}"]
    for mod, name in (("DracoPy", "DracoPy"), ("imagecodecs", "imagecodecs")):
        try:
            import importlib
            m = importlib.import_module(mod)
            parts.append(f"{name} {getattr(m, '__version__', '') or _dist_version(mod)}")
        except ImportError:
            parts.append(f"{name} missing")
    return ", ".join(parts)


def _dist_version(mod: str) -> str:
    from importlib.metadata import version
    try:
        return version(mod)
    except Exception:  # noqa: BLE001
        return "?"


# ----------------------------------------------------------------------------- codings

def _zstd(level: int) -> tuple[Callable[[bytes], bytes], Callable[[bytes], bytes]]:
    import zstandard
    comp, dec = zstandard.ZstdCompressor(level=level), zstandard.ZstdDecompressor()
    return comp.compress, dec.decompress


def _lz4() -> tuple[Callable[[bytes], bytes], Callable[[bytes], bytes]]:
    import lz4.frame
    return lz4.frame.compress, lz4.frame.decompress


def _mm_words(scan: Any) -> list[np.ndarray[Any, Any]]:
    """The range channel as lossless 16-bit images of integer mm (low word, high word if any),
    or [] when the float32 ranges are not all on the mm grid (+Inf -> 0 is exact for them)."""
    from lidarscan import channel
    r = np.asarray(channel(scan, "range"), np.float32)
    finite = np.isfinite(r)
    mm = np.where(finite, np.rint(r.astype(np.float64) * 1000), 0).astype(np.int64)
    back = np.where(mm == 0, np.float32(np.inf), (mm * 0.001).astype(np.float32))
    if not np.array_equal(back.view(np.uint32), r.view(np.uint32)) or mm.min() < 0:
        return []
    words = [(mm & 0xFFFF).astype(np.uint16)]
    if mm.max() > 0xFFFF:
        words.append((mm >> 16).astype(np.uint16))
    return words


def _image_planes(scan: Any) -> dict[str, list[np.ndarray[Any, Any]]]:
    """channel name -> the 2-D uint8/uint16 images that hold it losslessly."""
    from lidarscan import channel
    out: dict[str, list[np.ndarray[Any, Any]]] = {}
    for desc in scan.channels:
        arr = np.asarray(channel(scan, desc.name))
        if desc.name.startswith("range"):
            if desc.name == "range":
                out[desc.name] = _mm_words(scan)
            else:  # second returns: same rule, via a scan view of that channel
                out[desc.name] = _mm_words(_renamed(scan, desc.name))
        elif arr.dtype.kind == "u" and arr.dtype.itemsize <= 2 and arr.ndim == 2:
            out[desc.name] = [np.ascontiguousarray(arr.astype(arr.dtype.newbyteorder("=")))]
        else:
            out[desc.name] = []
    return out


def _renamed(scan: Any, name: str) -> Any:
    import dataclasses
    chans = tuple(dataclasses.replace(c, name="range" if c.name == name else
                                      ("_" + c.name if c.name == "range" else c.name))
                  for c in scan.channels)
    return dataclasses.replace(scan, channels=chans)


def _image_codec(kind: str) -> tuple[Callable[[np.ndarray[Any, Any]], bytes],
                                     Callable[[bytes], np.ndarray[Any, Any]]]:
    import imagecodecs
    if kind == "PNG":
        return (lambda a: imagecodecs.png_encode(a, level=6), imagecodecs.png_decode)
    return (lambda a: imagecodecs.jpegxl_encode(a, lossless=True, effort=1,
                                                  numthreads=1),
            imagecodecs.jpegxl_decode)


def _draco(xyz: np.ndarray[Any, Any]) -> tuple[int, float, Callable[[], bytes],
                                               Callable[[bytes], Any]]:
    """(bytes, grid step m, encode fn, decode fn) of Draco with a 1 mm grid on finite x,y,z
    (compression level 7, point order not kept)."""
    import DracoPy
    pts = np.ascontiguousarray(xyz[np.isfinite(xyz).all(axis=1)], np.float32)
    extent = float((pts.max(axis=0) - pts.min(axis=0)).max())
    bits = max(1, math.ceil(math.log2(extent / 0.001 + 1)))
    qrange = (2 ** bits - 1) * 0.001

    def enc() -> bytes:
        return bytes(DracoPy.encode(pts, quantization_bits=bits, compression_level=7,
                                    quantization_range=qrange,
                                    quantization_origin=pts.min(axis=0).tolist()))

    blob = enc()
    back = np.asarray(DracoPy.decode(blob).points).reshape(-1, 3)
    if len(back) != len(pts):
        raise AssertionError(f"Draco returned {len(back)} of {len(pts)} points")
    step = qrange / (2 ** bits - 1)  # Draco's grid; each coordinate within step / 2
    return len(blob), step, enc, DracoPy.decode


def _cloud_xyz(cloud: Any) -> np.ndarray[Any, Any]:
    from converters.pointcloud2 import read_points
    pts = read_points(cloud).reshape(-1)
    return np.stack([pts["x"], pts["y"], pts["z"]], axis=1).astype(np.float32)


def _have(mod: str) -> bool:
    try:
        __import__(mod)
    except ImportError:
        return False
    return True


@lru_cache(maxsize=2)
def measure(timing: bool = False) -> list[dict[str, Any]]:
    """One record per real frame: sizes (bytes) per coding, and times (s) when ``timing``.

    Record keys: label, pixels, cloud {coding: bytes}, scan {coding: bytes}, range {coding:
    bytes}, draco_step_m, times {coding: (encode s, decode s)}.
    """
    from lidarscan import codec
    from lidarscan.scan import data_view
    from converters.pointcloud2 import to_pointcloud2
    out = []
    for label, preset, load in sources():
        info, scan = load()
        rec: dict[str, Any] = {"label": label, "pixels": int(scan.height) * int(scan.width),
                               "cloud": {}, "scan": {}, "range": {}, "times": {}}
        cloud = to_pointcloud2(scan, info, preset=preset)
        cloud_raw = bytes(np.frombuffer(cloud.data, np.uint8))
        data = data_view(scan).tobytes()
        codings = {"lz4": _lz4(), "zstd-3": _zstd(3), "zstd-19": _zstd(19)}
        rec["cloud"]["raw"] = len(cloud_raw)
        rec["scan"]["raw"] = len(data)
        for name, (enc, dec) in codings.items():
            for key, buf in (("cloud", cloud_raw), ("scan", data)):
                packed = enc(buf)
                if dec(packed) != buf:
                    raise AssertionError(f"{label}: {name} of the {key} is not lossless")
                rec[key][name] = len(packed)
                if timing and name != "zstd-19":
                    rec["times"][f"{key} {name}"] = (time_call(lambda: enc(buf), repeat=3),
                                                     time_call(lambda: dec(packed), repeat=3))
        # per-block byte shuffle, and the project's codec
        from converters.evidence.compression import CODECS, _blocks_of
        enc_s, _ = CODECS["shuffle+zstd-3"]()
        rec["scan"]["shuffle+zstd-3 per block"] = sum(len(enc_s(a))
                                                     for a in _blocks_of(scan).values())
        packed = codec.compress_scan(scan, info)
        back = codec.decompress_scan(packed)
        if data_view(back).tobytes() != data:
            raise AssertionError(f"{label}: lidarscan.codec is not lossless")
        rec["scan"]["lidarscan.codec"] = len(packed)
        segs = codec.segments(packed)
        offsets = {c.name: int(c.offset) for c in scan.channels}
        rec["range"]["lidarscan.codec"] = next(s["payload_bytes"] for s in segs
                                               if s["offset"] == offsets["range"])
        if timing:
            rec["times"]["scan lidarscan.codec"] = (
                time_call(lambda: codec.compress_scan(scan, info), repeat=5),
                time_call(lambda: codec.decompress_scan(packed), repeat=5))
        if _have("imagecodecs"):
            planes = _image_planes(scan)
            for kind in ("PNG", "JPEG-XL"):
                enc_i, dec_i = _image_codec(kind)
                total, complete = 0, True
                for name, images in planes.items():
                    if not images:
                        complete = False
                        continue
                    size = 0
                    for img in images:
                        blob = enc_i(img)
                        if not np.array_equal(np.asarray(dec_i(blob)), img):
                            raise AssertionError(f"{label}: {kind} of {name} is not lossless")
                        size += len(blob)
                    total += size
                    if name == "range":
                        rec["range"][f"{kind} (16-bit images)"] = size
                if complete:
                    rec["scan"][f"{kind} (16-bit images)"] = total
                if timing and complete:
                    imgs = [i for v in planes.values() for i in v]
                    blobs = [enc_i(i) for i in imgs]
                    rec["times"][f"scan {kind}"] = (
                        time_call(lambda: [enc_i(i) for i in imgs], repeat=3, min_time=0),
                        time_call(lambda: [dec_i(b) for b in blobs], repeat=3, min_time=0))
        if _have("DracoPy"):
            size, step, enc_d, dec_d = _draco(_cloud_xyz(cloud))
            rec["cloud"]["Draco 1 mm x,y,z (lossy)"] = size
            rec["draco_step_m"] = step
            if timing:
                blob = enc_d()
                rec["times"]["cloud Draco 1 mm"] = (time_call(enc_d, repeat=3, min_time=0),
                                                    time_call(lambda: dec_d(blob), repeat=3,
                                                              min_time=0))
        rec["range"]["raw"] = rec["pixels"] * 4  # float32
        out.append(rec)
    return out


def _best_cloud(rec: dict[str, Any]) -> tuple[str, int]:
    lossless = {k: v for k, v in rec["cloud"].items() if "lossy" not in k}
    name = min(lossless, key=lambda k: lossless[k])
    return name, lossless[name]


def goal_lines(records: list[dict[str, Any]] | None = None) -> list[str]:
    """One sentence per frame: the goals, met or not, with their numbers (deterministic)."""
    lines = []
    for rec in records if records is not None else measure(False):
        best_name, best = _best_cloud(rec)
        ours = rec["scan"]["lidarscan.codec"]
        rng = rec["range"]["lidarscan.codec"]
        draco = rec["cloud"].get("Draco 1 mm x,y,z (lossy)")
        line = (f"**{rec['label']}.** All channels with `lidarscan.codec`: {fmt_int(ours)} B = "
                f"{ours / best:.3f}× the best lossless coding of the driver's cloud "
                f"({best_name}, {fmt_int(best)} B): goal ≤ {GOALS['all']}× "
                f"{'met' if ours / best <= GOALS['all'] else '**not met**'}; "
                f"{ours / rec['scan']['zstd-3']:.2f}× zstd-3 of the LidarScan buffer.")
        if draco:
            line += (f" Range channel, lossless: {fmt_int(rng)} B = {rng / draco:.3f}× Draco's "
                     f"lossy 1 mm x,y,z ({fmt_int(draco)} B, grid step "
                     f"{rec['draco_step_m'] * 1e3:.3f} mm, points reordered): "
                     f"goal ≤ {GOALS['range']}× "
                     f"{'met' if rng / draco <= GOALS['range'] else '**not met**'}.")
        lines.append(line)
    return lines


def _size_table(records: list[dict[str, Any]]) -> str:
    rows = []
    for rec in records:
        best_name, best = _best_cloud(rec)
        for key, what in (("cloud", "PointCloud2 (driver's preset, organized)"),
                          ("scan", "LidarScan data (all channels)")):
            raw = rec[key]["raw"]
            for coding, size in rec[key].items():
                rng = rec["range"].get(coding) if key == "scan" else None
                rows.append([rec["label"], what, coding, fmt_int(size), f"{raw / size:.2f}",
                             f"{size / best:.3f}", "—" if rng is None else fmt_int(rng)])
    return table(["frame", "message", "coding", "bytes", "ratio to raw",
                  "÷ best lossless cloud", "range channel bytes"], rows,
                 ["l", "l", "l", "r", "r", "r", "r"])


def _timing_table(records: list[dict[str, Any]]) -> str:
    rows = []
    for rec in records:
        base = rec["times"].get("scan zstd-3")
        scale = GOALS["pixels"] / rec["pixels"]
        for coding, (enc, dec) in rec["times"].items():
            rows.append([rec["label"], coding, f"{enc * 1e3:.2f}", f"{dec * 1e3:.2f}",
                         f"{1 / (enc * scale):.0f}", f"{1 / (dec * scale):.0f}",
                         "—" if not base else f"{enc / base[0]:.2f}"])
    return table(["frame", "coding", "encode ms", "decode ms",
                  "encode Hz at 128×2048 (scaled)", "decode Hz at 128×2048 (scaled)",
                  "encode ÷ zstd-3 of the LidarScan buffer"], rows,
                 ["l", "l", "r", "r", "r", "r", "r"])


def blocks(timing: bool = True) -> list[Block]:
    """``codec-study`` and ``codec-goals`` (sizes) and ``timing-codec`` (times)."""
    records = measure(False)
    out = [Block("codec-study", f"Real frames, bytes per frame ({_versions()}); every lossless "
                 "coding decoded and compared before its size is counted:\n\n"
                 + _size_table(records)),
           Block("codec-goals", f"Goals per real sensor ({_versions()}):\n\n"
                 + "\n".join(f"- {line}" for line in goal_lines(records)))]
    if timing:
        timed = measure(True)
        out.append(Block("timing-codec", "Encode/decode time per frame on one thread (best of "
                         "repeated runs; Hz scaled linearly to 128×2048 pixels; last column: "
                         "ratio to zstd-3 of the raw LidarScan buffer in the same run):\n\n"
                         + _timing_table(timed), deterministic=False))
    return out

