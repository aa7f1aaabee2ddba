"""Question 1b and 3b: lossless compression of the channel blocks of REAL frames.

The real Ouster frames (``tests/data/ouster/*_frame*.npz``) become LidarScans through
:func:`converters.sources.ouster.metadata.scan_from_frame`; each channel block is compressed on its own (what a
channel-aware transport or file format would do) and the whole ``data`` buffer at once (what an
MCAP chunk compressor does). Codecs: zstd levels 1/3/9, lz4 (frame, default level), a byte-plane
shuffle followed by zstd-3, and PNG (the image-based alternative: 16-bit and 8-bit images; a
float32 range image has no PNG form, so PNG stores range as ouster-ros's 16-bit range image in
4 mm steps, which is *lossy*). Sizes are deterministic for given library versions (printed in the
block); encode/decode times go to a separate timing block.

Synthetic scans compress unrealistically (no noise, no texture): one row shows by how much.
"""

from __future__ import annotations

import io
import time
from collections.abc import Callable
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
)

__all__ = ["CODECS", "blocks", "measure", "real_scans"]


def _shuffle(arr: np.ndarray[Any, Any]) -> bytes:
    """Byte planes of a numeric array (all first bytes, then all second bytes, ...)."""
    raw = np.ascontiguousarray(arr).view(np.uint8).reshape(-1, arr.dtype.itemsize)
    return np.ascontiguousarray(raw.T).tobytes()


def _unshuffle(buf: bytes, dtype: np.dtype[Any], shape: tuple[int, ...]) -> np.ndarray[Any, Any]:
    planes = np.frombuffer(buf, np.uint8).reshape(dtype.itemsize, -1)
    return np.ascontiguousarray(planes.T).view(dtype).reshape(shape)


def _zstd(level: int) -> tuple[Callable[[np.ndarray[Any, Any]], bytes],
                               Callable[[bytes, np.ndarray[Any, Any]], np.ndarray[Any, Any]]]:
    import zstandard
    comp = zstandard.ZstdCompressor(level=level)
    dec = zstandard.ZstdDecompressor()
    return (lambda a: comp.compress(np.ascontiguousarray(a).tobytes()),
            lambda b, like: np.frombuffer(dec.decompress(b), like.dtype).reshape(like.shape))


def _lz4() -> tuple[Callable[[np.ndarray[Any, Any]], bytes],
                    Callable[[bytes, np.ndarray[Any, Any]], np.ndarray[Any, Any]]]:
    import lz4.frame
    return (lambda a: lz4.frame.compress(np.ascontiguousarray(a).tobytes()),
            lambda b, like: np.frombuffer(lz4.frame.decompress(b), like.dtype).reshape(like.shape))


def _shuffle_zstd(level: int) -> tuple[Callable[[np.ndarray[Any, Any]], bytes],
                                       Callable[[bytes, np.ndarray[Any, Any]],
                                                np.ndarray[Any, Any]]]:
    import zstandard
    comp = zstandard.ZstdCompressor(level=level)
    dec = zstandard.ZstdDecompressor()
    return (lambda a: comp.compress(_shuffle(a)),
            lambda b, like: _unshuffle(dec.decompress(b), like.dtype, like.shape))


def png_image(arr: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """The image PNG stores for a channel block: u8/u16 as is, anything else as u16 4 mm steps.

    A float32 range in metres becomes ouster-ros's ``range_image``: round(r / 4 mm), 0 for no
    return and for ranges beyond 65535 * 4 mm = 262.14 m (lossy).
    """
    if arr.dtype in (np.uint8, np.uint16) and arr.ndim == 2:
        return arr
    r = np.asarray(arr, np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        steps = np.where(np.isfinite(r) & (r > 0), np.rint(r / 0.004), 0)
    steps[steps > 65535] = 0
    return steps.astype(np.uint16)


def _png() -> tuple[Callable[[np.ndarray[Any, Any]], bytes],
                    Callable[[bytes, np.ndarray[Any, Any]], np.ndarray[Any, Any]]]:
    from PIL import Image

    def enc(a: np.ndarray[Any, Any]) -> bytes:
        img = png_image(a)
        out = io.BytesIO()
        Image.fromarray(np.ascontiguousarray(img)).save(out, format="PNG", compress_level=6)
        return out.getvalue()

    def dec(b: bytes, like: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        img = np.asarray(Image.open(io.BytesIO(b)))
        return img

    return enc, dec


#: codec label -> factory of (encode(array) -> bytes, decode(bytes, like) -> array); lossless
#: except PNG for non-16/8-bit blocks.
CODECS: dict[str, Callable[[], Any]] = {
    "zstd-1": lambda: _zstd(1),
    "zstd-3": lambda: _zstd(3),
    "zstd-9": lambda: _zstd(9),
    "lz4": _lz4,
    "shuffle+zstd-3": lambda: _shuffle_zstd(3),
    "PNG": _png,
}


def real_scans() -> list[tuple[str, Any, Any, dict[str, Any]]]:
    """(label, info, scan (float32 range), frame arrays) for every real Ouster frame."""
    from converters.sources.ouster.metadata import scan_from_frame
    out = []
    for meta, frame_path in ouster_files():
        if frame_path is None:
            continue
        info = ouster_info(meta)
        frame = load_frame(frame_path)
        scan = scan_from_frame(frame, info, as_dataclass=True)
        out.append((short_name(meta) + (" dual" if "range2_mm" in frame else ""), info, scan,
                    frame))
    return out


def _blocks_of(scan: Any) -> dict[str, np.ndarray[Any, Any]]:
    from lidarscan import channel
    return {c.name: np.ascontiguousarray(channel(scan, c.name)) for c in scan.channels}


def synthetic_like(info: Any, scan: Any) -> Any:
    """A noise-free synthetic scan of the same sensor: a 40 m x 30 m box room seen from 1.5 m
    height, ranges quantised to mm, constant intensity/reflectivity/ambient, flags 0."""
    import lidarscan as ls
    proj = ls.make_projector(info)
    d = proj.directions.astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.full(d.shape[:2], np.inf)
        for axis, lo, hi in ((0, -15.0, 25.0), (1, -12.0, 18.0), (2, -1.5, 4.0)):
            comp = d[..., axis]
            cand = np.where(comp > 0, hi / comp, np.where(comp < 0, lo / comp, np.inf))
            t = np.minimum(t, cand)
    ranges = (np.rint(t * 1000) / 1000).astype(np.float32)
    channels: dict[str, Any] = {}
    for name, arr in _blocks_of(scan).items():
        if name.startswith("range"):
            channels[name] = ranges if name == "range" else np.full_like(arr, np.inf)
        else:
            channels[name] = np.full_like(arr, 100 if arr.dtype != np.uint8 else 50)
            if name.startswith("flags"):
                channels[name] = np.zeros_like(arr)
    return ls.make_scan(info, channels, 0, as_dataclass=True)


def _compress_scan(scan: Any, codecs: dict[str, Any], timing: bool
                   ) -> dict[str, dict[str, Any]]:
    blocks = _blocks_of(scan)
    whole = np.frombuffer(bytes(np.asarray(scan.data)), np.uint8)
    out: dict[str, dict[str, Any]] = {}
    raw = {n: a.nbytes for n, a in blocks.items()}
    out["none"] = {"range": sum(v for n, v in raw.items() if n.startswith("range")),
                   "total": sum(raw.values()), "whole": whole.nbytes, "enc": 0.0, "dec": 0.0}
    for label, factory in codecs.items():
        enc, dec = factory()
        sizes: dict[str, int] = {}
        enc_t = dec_t = 0.0
        for name, arr in blocks.items():
            start = time.perf_counter()
            packed = enc(arr)
            enc_t += time.perf_counter() - start
            sizes[name] = len(packed)
            if timing:
                start = time.perf_counter()
                dec(packed, arr)
                dec_t += time.perf_counter() - start
        rec: dict[str, Any] = {"range": sum(v for n, v in sizes.items()
                                            if n.startswith("range")),
               "total": sum(sizes.values()), "enc": enc_t, "dec": dec_t}
        # PNG has no form for a byte buffer; shuffling bytes (itemsize 1) is the identity
        rec["whole"] = len(enc(whole)) if label not in ("PNG", "shuffle+zstd-3") else None
        out[label] = rec
    return out


def check_lossless() -> list[str]:
    """Round-trip every lossless codec on every real block; returns failures (empty = all ok)."""
    bad = []
    for label, _, scan, _ in real_scans():
        for codec, factory in CODECS.items():
            enc, dec = factory()
            for name, arr in _blocks_of(scan).items():
                expect = png_image(arr) if codec == "PNG" else arr
                back = dec(enc(arr), arr)
                if not np.array_equal(np.asarray(back).view(np.uint8),
                                      np.ascontiguousarray(expect).view(np.uint8)):
                    bad.append(f"{label} {codec} {name}")
    return bad


@lru_cache(maxsize=2)
def measure(timing: bool = False) -> dict[str, Any]:
    """Compressed sizes (and times when ``timing``) for every real frame and its synthetic twin."""
    results: dict[str, Any] = {}
    for label, info, scan, _ in real_scans():
        results[label] = _compress_scan(scan, CODECS, timing)
        for _ in range(4 if timing else 0):  # timings: best of 5 runs
            again = _compress_scan(scan, CODECS, timing)
            for codec, rec in again.items():
                for key in ("enc", "dec"):
                    results[label][codec][key] = min(results[label][codec][key], rec[key])
        if not timing:
            results[label + " — synthetic twin"] = _compress_scan(
                synthetic_like(info, scan), {"zstd-3": CODECS["zstd-3"]}, False)
    return results


@lru_cache(maxsize=1)
def range_encodings() -> dict[str, dict[str, Any]]:
    """Range block only, real frames: float32 m vs uint32 mm vs uint16 (mm / 4 mm), compressed.

    Returns label -> encoding -> {raw, zstd-3, lz4, shuffle+zstd-3, lossless, max_m}.
    """
    out: dict[str, dict[str, Any]] = {}
    for label, _, scan, frame in real_scans():
        from lidarscan import channel
        r32 = np.ascontiguousarray(channel(scan, "range"))
        mm = np.asarray(frame["range_mm"]).astype(np.uint32)
        valid = np.isfinite(r32)
        mm = np.where(valid, mm, 0).astype(np.uint32)  # columns the importer marked invalid
        variants = {
            "float32 m (canonical)": (r32, True),
            "uint32 mm (Ouster native, multiplier 0.001)": (mm, True),
            "uint16 mm (multiplier 0.001)": (mm.astype(np.uint16), bool(mm.max() <= 65535)),
            "uint16 4 mm (multiplier 0.004, ouster-ros range_image)": (png_image(r32), False),
        }
        enc: dict[str, Any] = {}
        for name, (arr, lossless) in variants.items():
            rec: dict[str, Any] = {"raw": arr.nbytes, "lossless": lossless}
            for codec in ("zstd-3", "lz4", "shuffle+zstd-3"):
                rec[codec] = len(CODECS[codec]()[0](arr))
            enc[name] = rec
        out[label] = enc
    return out


def _versions() -> str:
    import lz4
    import PIL
    import zstandard
    return f"zstandard {zstandard.__version__}, lz4 {lz4.__version__}, Pillow {PIL.__version__}"


def blocks(timing: bool = True) -> list[Block]:
    """``compression`` (sizes), ``range-encoding`` (sizes) and ``timing-compression`` blocks."""
    sizes = measure(timing=False)
    rows = []
    for label, recs in sizes.items():
        raw = recs["none"]["total"]
        for codec, rec in recs.items():
            whole = rec.get("whole")
            lossy = " (range lossy: 4 mm)" if codec == "PNG" else ""
            rows.append([label, codec + lossy, fmt_int(rec["range"]), fmt_int(rec["total"]),
                         f"{raw / rec['total']:.2f}",
                         "—" if whole is None else fmt_int(whole)])
    text = (f"Channel blocks of the real frames ({_versions()}); bytes per frame, each block "
            "compressed on its own, and the whole `data` buffer compressed at once:\n\n"
            + table(["frame", "codec", "range block(s)", "all blocks", "ratio",
                     "whole buffer"], rows, ["l", "l", "r", "r", "r", "r"]))
    enc_rows = []
    for label, recs in range_encodings().items():
        for name, rec in recs.items():
            enc_rows.append([label, name, "yes" if rec["lossless"] else "**no**",
                             fmt_int(rec["raw"]), fmt_int(rec["zstd-3"]), fmt_int(rec["lz4"]),
                             fmt_int(rec["shuffle+zstd-3"])])
    enc_text = (f"Range block of the real frames in each encoding ({_versions()}), bytes:\n\n"
                + table(["frame", "range encoding", "lossless for this frame", "raw", "zstd-3",
                         "lz4", "shuffle+zstd-3"], enc_rows, ["l", "l", "l", "r", "r", "r", "r"]))
    out = [Block("compression", text), Block("range-encoding", enc_text)]
    if timing:
        timed = measure(timing=True)
        trows = []
        for label, recs in timed.items():
            base = recs["zstd-1"]["enc"]
            for codec, rec in recs.items():
                if codec == "none":
                    continue
                trows.append([label, codec, f"{rec['enc'] * 1e3:.1f}", f"{rec['dec'] * 1e3:.1f}",
                              f"{rec['enc'] / base:.1f}"])
        out.append(Block("timing-compression",
                         "Encode/decode time per frame, all blocks (ms, best of 5 runs on the "
                         "machine above; last column: encode time ÷ zstd-1 encode time of the same "
                         "run):\n\n" + table(["frame", "codec", "encode ms", "decode ms",
                                              "encode ÷ zstd-1"], trows,
                                             ["l", "l", "r", "r", "r"]),
                         deterministic=False))
    return out
