"""The format primitives of :mod:`lidarscan.codec` (spec: its module docstring): constants,
zstd frames, byte planes, length-prefixed parts, pixel masks, row-shift params and the float32
bits of an int32 grid.

Below every format version (:mod:`lidarscan.codec._v1`, :mod:`lidarscan.codec._v2`,
:mod:`lidarscan.codec._v3`) and the container (:mod:`lidarscan.codec`); imports nothing of the
codec but the numpy reference of the residual coding (:mod:`lidarscan.codec._bits`).
"""

from __future__ import annotations

import struct
import threading
from typing import Any

import numpy as np

from lidarscan.codec._bits import NUMPY, ResidualCoder
from lidarscan.errors import DecodeError

MAGIC = b"LSCZ"
VERSION = 3  # written by default; versions 1 and 2 decode
RAW, ZSTD, SHUFFLE, PREDICT, QUANT, PREDICT2, QUANT2, XPREDICT = 0, 1, 2, 3, 4, 5, 6, 7
_METHOD_NAMES = {RAW: "raw", ZSTD: "zstd", SHUFFLE: "shuffle", PREDICT: "predict",
                 QUANT: "quant", PREDICT2: "predict2", QUANT2: "quant2", XPREDICT: "xpredict"}

_INT_CODES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4"}
_FLOAT32, _FLOAT64 = 7, 8
_SIZES = {1: 1, 2: 1, 3: 2, 4: 2, 5: 4, 6: 4, 7: 4, 8: 8}
_GRID = struct.Struct("<BBIIIBB")  # datatype, bigendian, H, W, count, predictor, rolled
_GRID2 = struct.Struct("<BBIIIBBBB")  # ... + extra (symbol bits), masked
_SEG = struct.Struct("<IIBH")       # offset, length, method, params_len
_HEAD = struct.Struct("<4sBBH")


# ----------------------------------------------------------------------------- zstd

_LOCAL = threading.local()


def _zc(level: int) -> Any:
    """This thread's zstd compressor of ``level`` (content checksums on), made once: its
    context is reused from frame to frame."""
    made = getattr(_LOCAL, "compressors", None)
    if made is None:
        made = _LOCAL.compressors = {}
    if level not in made:
        import zstandard
        made[level] = zstandard.ZstdCompressor(level=level, write_checksum=True)
    return made[level]


def _zd(frame: bytes, limit: int, what: str) -> bytes:
    import zstandard
    made = getattr(_LOCAL, "decompressor", None)
    if made is None:
        made = _LOCAL.decompressor = zstandard.ZstdDecompressor()
    try:
        out = made.decompress(frame, max_output_size=limit)
    except zstandard.ZstdError as err:
        raise DecodeError(what, len(frame), f"a zstd frame ({err})") from None
    return out


# ------------------------------------------------------------------------ transforms

def _planes(arr: np.ndarray[Any, Any]) -> bytes:
    """Byte planes of a numeric array's values: all least significant bytes, then all second
    bytes, ... (the value's little-endian bytes, whatever the array's byte order)."""
    size = arr.dtype.itemsize
    little = np.ascontiguousarray(arr).astype(arr.dtype.newbyteorder("<"), copy=False)
    raw = little.reshape(-1).view(np.uint8).reshape(-1, size)
    return np.ascontiguousarray(raw.T).tobytes()


def _unplanes(buf: bytes, itemsize: int, n: int, what: str) -> np.ndarray[Any, Any]:
    if len(buf) != itemsize * n:
        raise DecodeError(what, len(buf), f"{itemsize * n} bytes of byte planes")
    planes = np.frombuffer(buf, np.uint8).reshape(itemsize, n)
    out = planes[0].astype(f"<u{itemsize}")
    for k in range(1, itemsize):
        out |= planes[k].astype(out.dtype) << out.dtype.type(8 * k)
    return out.view(np.uint8)


def _as_unsigned(arr: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """Native-order unsigned view/copy of an integer or float array (same bytes per value)."""
    native = arr.astype(arr.dtype.newbyteorder("="), copy=False)
    return native.view(f"u{arr.dtype.itemsize}")


def _shift_params(shifts: np.ndarray[Any, Any] | None) -> bytes:
    return b"" if shifts is None else shifts.astype("<i4").tobytes()


def _float_bits(q: np.ndarray[Any, Any], step: float, bigendian: bool,
                exc: np.ndarray[Any, Any] | None, words_frame: bytes, what: str,
                coder: ResidualCoder = NUMPY) -> bytes:
    """The float32 bytes of the int32 grid q (value ``float32(float64(q) * step)``) with the
    exception pixels (mask ``exc``) replaced by the words of the zstd frame ``words_frame``."""
    out = coder.dequantise(np.ascontiguousarray(q).reshape(-1), step)
    if bigendian:
        out = out.astype(">f4")
    if exc is None:
        return out.tobytes()
    exc = exc.reshape(-1)
    words = np.frombuffer(_zd(words_frame, 4 * exc.size, what), np.uint32)
    if words.size != int(exc.sum()):
        raise DecodeError(what, words.size, f"{int(exc.sum())} exception words")
    bits = out.view(np.uint32).copy()
    bits[exc] = words
    return bits.tobytes()



def _parts(*parts: bytes) -> bytes:
    return b"".join(struct.pack("<I", len(p)) + p for p in parts)


def _split(payload: bytes, count: int, what: str) -> list[bytes]:
    out, pos = [], 0
    for _ in range(count):
        if pos + 4 > len(payload):
            raise DecodeError(what, len(payload), f"{count} length-prefixed parts")
        (k,) = struct.unpack_from("<I", payload, pos)
        if pos + 4 + k > len(payload):
            raise DecodeError(what, k, f"at most {len(payload) - pos - 4} bytes")
        out.append(payload[pos + 4:pos + 4 + k])
        pos += 4 + k
    if pos != len(payload):
        raise DecodeError(what, len(payload), f"{pos} bytes ({count} parts)")
    return out



def _mask_frame(valid: np.ndarray[Any, Any], level: int) -> bytes:
    return _zc(level).compress(np.packbits(valid.reshape(-1)).tobytes())


def _unmask_frame(frame: bytes, n: int, what: str) -> np.ndarray[Any, Any]:
    packed = _zd(frame, (n + 7) // 8, what)
    if len(packed) != (n + 7) // 8:
        raise DecodeError(what, len(packed), f"{(n + 7) // 8} bytes of pixel mask")
    return np.unpackbits(np.frombuffer(packed, np.uint8), count=n).astype(bool)

