"""A lossless, versioned compressed form of a LidarScan (``compress_scan`` / ``decompress_scan``).

The message itself stays uncompressed (receivers get zero-copy views); this module is for storage
and transports that compress: MCAP channels with the message encoding
:data:`lidarscan.mcap.CODEC_ENCODING` (``lidarscan convert --compress``; documented in
``msgs/README.md``). It beats compressing the whole CDR buffer with zstd (what MCAP's chunk
compression does) because it knows the channel layout: every channel block is coded on its own,
integer blocks by prediction, float32 blocks in metres through the integer grid they come from.

Byte format, version 2 (every integer little-endian; version 1 is the same container with
methods 0..4 only: this module still decodes it). Version 3, written by default
(``compress_scan(..., version=2)`` still writes version 2), is the same container with version
byte 3 and one more method, 7 XPREDICT: an integer block predicted from two earlier blocks
(Ouster reflectivity from signal and range), its byte format in :mod:`lidarscan._codec_v3`;
a scan without such blocks is coded as in version 2, with version byte 3::

    "LSCZ"  u8 version=2 (3)  u8 flags=0  u16 n_segments
    u32 skeleton_len  skeleton          zstd frame of the CDR (lidarscan.encode) of the scan with
                                        empty ``data`` and empty per-column arrays: header, info
                                        stamp, sizes, byte order, stagger flag, channel
                                        descriptors (version 1: with the per-column arrays)
    u32 columns_len  columns            (version 2 only) the per-column arrays, see below
    u32 data_len                        len(scan.data)
    n_segments x segment                contiguous, in order, covering data[0:data_len] exactly

    segment := u32 offset  u32 length  u8 method  u16 params_len  params  u32 payload_len  payload

Every zstd frame carries its content checksum (a damaged payload raises, never decodes to
other values). Methods (a segment is a channel block, or the bytes between/after blocks);
the encoder writes 1, 2, 5 and 6 (and 7 in version 3):

====  =========  ==========================================================================
id    name       params / payload
====  =========  ==========================================================================
0     RAW        - / the bytes
1     ZSTD       - / zstd frame of the bytes
2     SHUFFLE    u8 itemsize / zstd frame of the byte planes: the least significant byte
                 of every value (little-endian reading of the block), then every second
                 byte, ...
3     PREDICT    (version 1) u8 datatype, u8 bigendian, u32 H, u32 W, u32 count,
                 u8 predictor, u8 rolled [, H x i32 row shifts when rolled] / zstd frame of
                 the byte planes of zigzag(residual), residuals in the unsigned type of the
                 channel's size (wrapping: every value is exact)
4     QUANT      (version 1) u8 datatype (FLOAT32), u8 bigendian, u32 H, u32 W, u32 count,
                 u8 predictor, u8 rolled, f64 step [, H x i32 row shifts] /
                 u32 n + the PREDICT payload of the int32 grid q (n bytes),
                 u32 n + zstd frame of the packed exception mask (n bytes, row-major,
                 numpy packbits order), zstd frame of the exceptions' original 4 bytes.
                 Exceptions take their left neighbour's q (0 at a row start).
5     PREDICT2   u8 datatype (an integer type), u8 bigendian, u32 H, u32 W, u32 count,
                 u8 predictor, u8 rolled, u8 extra (1 or 2), u8 masked [, u32 reference
                 offset when predictor = 4] [, H x i32 row shifts] / parts, each
                 ``u32 n + n bytes``: [mask,] symbols, low bits.
                 masked = 1: pixels whose value is 0 are not coded (mask: zstd frame of the
                 packed "value != 0" bits, row-major over (H, W, count), numpy packbits
                 order); they decode to 0.
6     QUANT2     u8 datatype (FLOAT32), u8 bigendian, u32 H, u32 W, u32 count, u8 predictor,
                 u8 rolled, u8 extra, u8 masked, f64 step [, H x i32 row shifts] / parts:
                 [mask,] symbols, low bits [, exception words]. A value v is coded as the
                 int32 q = rint(v / step) when float32(float64(q) * step) has v's exact bits
                 (the decode rule of :func:`lidarscan.range_m`); every other value (NaN,
                 +-Inf, -0, off-grid) is an exception: masked = 1, mask bit 0, its original 4
                 bytes in the zstd frame of exception words (row-major order).
7     XPREDICT   (version 3) see :mod:`lidarscan._codec_v3`
====  =========  ==========================================================================

Predictors (on the (H, W, C) array, per count index): 0 none, 1 left (x[r, c-1]), 2 up
(x[r-1, c]), 3 planar (left + up - up-left); out-of-grid neighbours are 0; 4 (PREDICT2 only)
the same pixel of the earlier channel block at the reference offset, which has this block's
datatype, count and size (a second return predicted from the first), read as unsigned values
in the scan's byte order and rolled like this block. Residuals are
computed and inverted with wrapping integer arithmetic (decoding: cumulative sums).
"Rolled": before prediction row r was rotated right by its shift s_r (element c moved to
(c + s_r) mod W): a staggered scan is predicted in destaggered order, where the row above sees
the same azimuth; the decoder rotates back.

Version 2 per-column arrays: ``u32 n_time  u32 n_azimuth``, then two parts ``u32 n + n
bytes``: the zstd frame of the byte planes (as SHUFFLE, itemsize 8) of zigzag(first
difference) of ``column_time_offsets`` (int64, wrapping, the first value against 0), and the
same of ``column_azimuth_angles`` read as the uint64 bit patterns of the float64 values
(regular azimuths and firing times make the differences repeat).

Version 2 residual coding (methods 5, 6). Pixels left out by the mask hold their own
prediction (residual 0, not stored), so the decoder fills the grid with zero residuals and
inverts the predictor; the valid pixels' residuals r become z = zigzag(r) (0, -1, 1, -2 ->
0, 1, 2, 3) in the unsigned type of the grid. A value z of bit length b (0 for z = 0) is the
symbol ``b << extra | t`` (one byte; t: the e = min(b - 1, extra) bits below the leading one,
none when b <= 1) and k = b - 1 - e raw low bits. Symbols: zstd frame of one byte per valid
pixel, row-major. Low bits: zstd frame of one bit stream in which the values are grouped by k
ascending (pixel order inside a group), each value's k bits most significant first, packed
most significant bit first, the last byte padded with zeros. The sizes of the symbols are
what zstd's entropy coder sees; the low bits are close to uniform and cost about k bits.

Code layout: this module holds the container and the encoder's choices; the numpy reference of
the prediction and of the residual coding (the test oracle) is :mod:`lidarscan._codec_bits`,
whose hot steps a :class:`ResidualCoder` bundles (``coder=``: converters pass the compiled one,
``converters._kernels.select("codec")``; every coder writes the same bytes); the version 1
methods decode in :mod:`lidarscan._codec_v1`.

``decompress_scan`` returns a :class:`lidarscan.types.LidarScan` whose CDR (``lidarscan.encode``)
is byte-identical to the input's (any version). Errors: :class:`lidarscan.errors.EncodeError` (a scan that does
not encode), :class:`lidarscan.errors.DecodeError` (a buffer that is not this format).
"""

from __future__ import annotations

import dataclasses
import struct
import threading
from typing import Any

import numpy as np

from lidarscan._codec_bits import (
    LEFT,
    NONE,
    NUMPY,
    PLANAR,
    REF,
    UP,
    ResidualCoder,
    bitlen_table,
    residual,
    unzigzag,
    zigzag,
)
from lidarscan.errors import DecodeError, EncodeError

__all__ = [
    "MAGIC",
    "VERSION",
    "RAW",
    "ZSTD",
    "SHUFFLE",
    "PREDICT",
    "QUANT",
    "PREDICT2",
    "QUANT2",
    "XPREDICT",
    "REF",
    "ResidualCoder",
    "compress_scan",
    "decompress_scan",
    "segments",
]

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


# --------------------------------------------------------------------------- QUANT

def _quantise(v: np.ndarray[Any, Any], step: float, coder: ResidualCoder = NUMPY
              ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]] | None:
    """(int32 grid q, 0 at exceptions; exception mask) or None when no value is on the grid.
    v: native float32 (H, W, C)."""
    q, exc = coder.quantise(np.ascontiguousarray(v, np.float32).reshape(-1), step)
    if exc.all() and v.size:
        return None
    return q.reshape(v.shape), exc.reshape(v.shape)


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


# ------------------------------------------------------------ version 2: bit-length coding

def _bits_cost(z: np.ndarray[Any, Any]) -> int:
    """Size proxy of zigzag residuals for the bit-length coding: the sum of bit lengths
    (through float32 exponents: exact below 2**24, a bit more above; a proxy only)."""
    return int(np.frexp(z.astype(np.float32))[1].sum(dtype=np.int64))


def _pack_residuals(z: np.ndarray[Any, Any], level: int, coder: ResidualCoder = NUMPY
                    ) -> tuple[int, bytes, bytes]:
    """(extra, zstd frame of the symbols, zstd frame of the low bits) of zigzag residuals
    ``z`` (1-D unsigned, at most 32 bits); extra 1 or 2, whichever is smaller (the coding:
    :mod:`lidarscan._codec_bits`). Both symbol streams are compressed: an order-0 entropy
    estimate from their histograms picked the larger one on real range grids (bench/README.md)."""
    z = np.ascontiguousarray(z, np.uint32)
    sym1, k1, sym2, k2, bits1, bits2 = coder.symbols(z, bitlen_table())
    options = []
    for extra, sym, k, bits in ((1, sym1, k1, bits1), (2, sym2, k2, bits2)):
        frame = _zc(level).compress(sym)
        options.append((len(frame) + (int(bits) + 7) // 8, extra, frame, k, int(bits)))
    _, extra, frame, k, bits = min(options, key=lambda option: option[0])
    low = coder.pack_low(z, k) if bits else b""  # no low bits (e.g. a constant grid)
    return extra, frame, _zc(level).compress(low)


def _unpack_residuals(frame: bytes, raw: bytes, n: int, itemsize: int, extra: int,
                      what: str, coder: ResidualCoder = NUMPY
                      ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """(symbols, values per low-bit count, low-bit stream) of :func:`_pack_residuals`'s parts
    for n zigzag residuals of at most ``8 * itemsize`` bits, checked (``coder.decode`` takes
    them)."""
    symbols = np.frombuffer(_zd(frame, n, what), np.uint8)
    if symbols.size != n:
        raise DecodeError(what, symbols.size, f"{n} residual symbols")
    if n and int(symbols.max()) >> extra > 8 * itemsize:
        raise DecodeError(what, int(symbols.max()) >> extra,
                          f"bit lengths of at most {8 * itemsize}")
    counts = coder.low_counts(symbols, extra)
    total = int((counts * np.arange(counts.size)).sum())
    low = _zd(raw, (total + 7) // 8, what)
    if len(low) != (total + 7) // 8:
        raise DecodeError(what, len(low), f"{(total + 7) // 8} bytes of low bits")
    return symbols, counts, np.frombuffer(low, np.uint8)


def _choose_masked(x: np.ndarray[Any, Any], valid: np.ndarray[Any, Any] | None,
                   ref: np.ndarray[Any, Any] | None = None, coder: ResidualCoder = NUMPY
                   ) -> tuple[int, int]:
    """(predictor, its residual bits) with the fewest residual bits on a band of up to 32
    rows (bits: the sum of the residuals' bit lengths on the band); REF only with a ref."""
    start = max(0, x.shape[0] // 2 - 16)
    band = x[start:start + 32]
    vband = None if valid is None else valid[start:start + 32]
    rband = None if ref is None else ref[start:start + 32]
    bits = coder.costs(band, vband, rband)
    costs = {p: int(bits[p]) for p in (UP, LEFT, PLANAR, NONE) + ((REF,) if ref is not None
                                                                   else ())}
    best = min(costs, key=lambda p: costs[p])
    return best, costs[best]


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


def _code_grid(x: np.ndarray[Any, Any], valid: np.ndarray[Any, Any] | None, level: int,
               predictor: int | None = None, ref: np.ndarray[Any, Any] | None = None,
               coder: ResidualCoder = NUMPY) -> tuple[int, int, list[bytes]]:
    """(predictor, extra, [symbols frame, low bits]) of the valid pixels of grid x."""
    if predictor is None:
        predictor = _choose_masked(x, valid, ref, coder)[0]
    extra, frame, low = _pack_residuals(coder.residuals(x, valid, predictor, ref), level,
                                        coder)
    return predictor, extra, [frame, low]


def _mask_frame(valid: np.ndarray[Any, Any], level: int) -> bytes:
    return _zc(level).compress(np.packbits(valid.reshape(-1)).tobytes())


def _unmask_frame(frame: bytes, n: int, what: str) -> np.ndarray[Any, Any]:
    packed = _zd(frame, (n + 7) // 8, what)
    if len(packed) != (n + 7) // 8:
        raise DecodeError(what, len(packed), f"{(n + 7) // 8} bytes of pixel mask")
    return np.unpackbits(np.frombuffer(packed, np.uint8), count=n).astype(bool)


def _encode_int2(u: np.ndarray[Any, Any], level: int, ref: np.ndarray[Any, Any] | None = None,
                 coder: ResidualCoder = NUMPY, masked_only: float = 1.0
                 ) -> tuple[int, int, bool, bytes]:
    """(predictor, extra, masked, payload) of an unsigned (H, W, C) grid (ref: an earlier
    channel's grid REF may predict from). With at least 2 % zero values the grid is also
    coded with the zeros masked (not coded); the smaller coding wins. With at least the
    fraction ``masked_only`` of zero values (and a non-zero value) it is coded masked only."""
    zeros = int(np.count_nonzero(u == 0))
    if masked_only * u.size <= zeros < u.size:
        valid = u != 0
        predictor, extra, parts = _code_grid(u, valid, level, None, ref, coder)
        return predictor, extra, True, _parts(_mask_frame(valid, level), *parts)
    predictor, extra, parts = _code_grid(u, None, level, None, ref, coder)
    best = (predictor, extra, False, _parts(*parts))
    if 0.02 * u.size <= zeros < u.size:
        valid = u != 0
        predictor, extra, parts = _code_grid(u, valid, level, None, ref, coder)
        masked = _parts(_mask_frame(valid, level), *parts)
        if len(masked) < len(best[3]):
            best = (predictor, extra, True, masked)
    return best


def _decode_int2(payload: bytes, shape: tuple[int, int, int], itemsize: int, predictor: int,
                 extra: int, masked: bool, what: str, ref: np.ndarray[Any, Any] | None = None,
                 coder: ResidualCoder = NUMPY) -> np.ndarray[Any, Any]:
    n = shape[0] * shape[1] * shape[2]
    parts = _split(payload, 3 if masked else 2, what)
    valid = _unmask_frame(parts[0], n, what).reshape(shape) if masked else None
    count = n if valid is None else int(valid.sum())
    symbols, counts, low = _unpack_residuals(parts[-2], parts[-1], count, itemsize, extra, what,
                                             coder)
    f = coder.decode(symbols, extra, counts, low, valid, predictor, ref,
                     np.empty(shape, f"u{itemsize}"))
    return f if valid is None else np.where(valid, f, f.dtype.type(0))


def _encode_quant2(v: np.ndarray[Any, Any], raw_words: np.ndarray[Any, Any], step: float,
                   level: int, coder: ResidualCoder = NUMPY
                   ) -> tuple[int, int, bool, float, bytes] | None:
    """(predictor, extra, masked, step, payload) of a native float32 (H, W, C) grid, or None
    when it does not fit the int32 grid; exceptions are masked and kept bit for bit. The step
    is ``step`` times the greatest common divisor of the grid values when that coarser grid
    has no more exceptions."""
    got = _quantise(v, step, coder)
    if got is None:
        return None
    q, exc = got
    common = 0  # gcd of the grid values; exceptions are 0 (gcd(0, a) = a)
    flat = q.reshape(-1)
    for stop in (8192, flat.size):  # the gcd of all divides that of the first ones: 1 there
        common = int(np.gcd.reduce(np.abs(flat[:stop].astype(np.int64))))  # is 1 overall
        if common == 1:
            break
    if common > 1:  # e.g. 4 mm units in metres: the coarser grid, if it is as exact
        coarse = _quantise(v, step * common, coder)
        if coarse is not None and int(coarse[1].sum()) <= int(exc.sum()):
            step, (q, exc) = step * common, coarse
    u = q.view(np.uint32)
    if not exc.any():
        predictor, extra, parts = _code_grid(u, None, level, coder=coder)
        return predictor, extra, False, step, _parts(*parts)
    valid = ~exc
    predictor, extra, parts = _code_grid(u, valid, level, coder=coder)
    words = _zc(level).compress(raw_words[exc].tobytes())
    return predictor, extra, True, step, _parts(_mask_frame(valid, level), *parts, words)


def _decode_quant2(payload: bytes, shape: tuple[int, int, int], predictor: int, extra: int,
                   masked: bool, step: float, bigendian: bool, what: str,
                   coder: ResidualCoder = NUMPY) -> bytes:
    n = shape[0] * shape[1] * shape[2]
    parts = _split(payload, 4 if masked else 2, what)
    valid = _unmask_frame(parts[0], n, what).reshape(shape) if masked else None
    count = n if valid is None else int(valid.sum())
    sym, low = (parts[1], parts[2]) if masked else (parts[0], parts[1])
    symbols, counts, bits = _unpack_residuals(sym, low, count, 4, extra, what, coder)
    q = coder.decode(symbols, extra, counts, bits, valid, predictor, None,
                     np.empty(shape, np.uint32)).view(np.int32)
    return _float_bits(q, step, bigendian, None if valid is None else ~valid,
                       parts[3] if masked else b"", what, coder)


# --------------------------------------------------------------------- segmentation

def _layout(scan: Any, data_len: int) -> list[tuple[int, int, Any]] | None:
    """Channel blocks as (offset, length, descriptor), sorted; None when they overlap or do not
    fit inside ``data`` (then the whole buffer is one ZSTD segment)."""
    height, width = int(scan.height), int(scan.width)
    blocks = []
    for desc in scan.channels:
        size = _SIZES.get(int(desc.datatype))
        if size is None or int(desc.count) < 1:
            return None
        length = height * width * int(desc.count) * size
        blocks.append((int(desc.offset), length, desc))
    blocks.sort(key=lambda b: b[0])
    end = 0
    for offset, length, _ in blocks:
        if offset < end or offset + length > data_len:
            return None
        end = offset + length
    return [b for b in blocks if b[1] > 0]


def _encode_block(block: memoryview, desc: Any, scan: Any, level: int, float_step: float | None,
                  shifts: np.ndarray[Any, Any] | None,
                  refs: dict[int, np.ndarray[Any, Any]], coder: ResidualCoder = NUMPY,
                  version: int = VERSION) -> tuple[int, bytes, bytes]:
    """(method, params, payload) of one channel block (the version 2 methods; version 3 also
    tries XPREDICT on integer blocks, :mod:`lidarscan._codec_v3`). ``refs``:
    offset -> rolled unsigned grid of the earlier integer blocks; this block's grid is added
    when it is an integer block."""
    datatype, big = int(desc.datatype), bool(scan.is_bigendian)
    shape = (int(scan.height), int(scan.width), int(desc.count))
    size = _SIZES[datatype]
    rolled = shifts is not None
    if datatype in _INT_CODES:
        u = np.frombuffer(block, np.dtype((">" if big else "<") + f"u{size}")).reshape(shape)
        u = coder.roll(_as_unsigned(u), shifts, 1)
        same = {off: g for off, g in refs.items() if g.dtype == u.dtype and g.shape == u.shape}
        ref_offset = None  # the earlier grid closest to this one (a second return's first
        if same:  # return; the only one needs no comparison)
            ref_offset = min(same, key=lambda off: _bits_cost(
                zigzag(residual(u[::8], REF, same[off][::8])))) if len(same) > 1 else [*same][0]
        refs[int(desc.offset)] = u
        ref = None if ref_offset is None else same[ref_offset]
        cross = None
        if version >= 3:
            from lidarscan import _codec_v3
            cross = _codec_v3.encode_block(block, desc, scan, level, shifts, coder, u, ref)
            if cross is not None and cross[2]:  # clearly smaller: no version 2 coding
                return XPREDICT, cross[0], cross[1]
        predictor, extra, masked, payload = _encode_int2(u, level, ref, coder)
        ref_param = struct.pack("<I", ref_offset) if predictor == REF else b""
        params = (_GRID2.pack(datatype, big, *shape, predictor, rolled, extra, masked)
                  + ref_param + _shift_params(shifts))
        if cross is not None and len(cross[0]) + len(cross[1]) < len(params) + len(payload):
            return XPREDICT, cross[0], cross[1]
        return PREDICT2, params, payload
    if datatype == _FLOAT32 and float_step:
        raw = np.frombuffer(block, ">f4" if big else "<f4").reshape(shape)
        native = coder.roll(raw.astype(np.float32, copy=False), shifts, 1)
        words = (native.view(np.uint32) if raw.dtype.isnative  # the block's own bytes
                 else coder.roll(np.frombuffer(block, np.uint32).reshape(shape), shifts, 1))
        got = _encode_quant2(native, words, float_step, level, coder)
        if got is not None:
            predictor, extra, masked, step, payload = got
            shuffled = None
            if len(payload) > len(block) // 2:  # mostly off-grid: compare with SHUFFLE
                shuffled = _zc(level).compress(_planes(np.frombuffer(block, f"<u{size}")))
            if shuffled is None or len(payload) <= len(shuffled):
                return (QUANT2, _GRID2.pack(datatype, big, *shape, predictor, rolled, extra,
                                            masked)
                        + struct.pack("<d", step) + _shift_params(shifts), payload)
            return SHUFFLE, bytes([size]), shuffled
    return SHUFFLE, bytes([size]), _zc(level).compress(_planes(
        np.frombuffer(block, f"<u{size}")))


def compress_scan(scan: Any, info: Any = None, *, level: int = 1,
                  float_step: float | None = 0.001, coder: ResidualCoder | None = None,
                  version: int = VERSION) -> bytes:
    """Compress a LidarScan losslessly (format above).

    Args:
        scan: a LidarScan, rclpy message or :class:`lidarscan.types.LidarScan`; any channel
            datatypes, counts and byte order.
        info: its LidarInfo, optional: a staggered scan is then predicted in destaggered order
            (``pixel_shift_by_row``; the shifts travel in the format, decoding needs no info).
        level: zstd level of every part (1..22). 1, the default, is the measured best: on the
            residual symbols (one byte per pixel, few repeats) higher levels search for
            matches that are not there, taking 2-8x the time for the same or more bytes.
        float_step: grid of float32 channels in their unit (0.001: metres from millimetres;
            a multiple of it when every value is on that coarser grid, e.g. 0.004 for 4 mm
            units); None codes float32 channels by byte shuffle only.
        coder: the residual coding's implementation (:class:`ResidualCoder`): None = the numpy
            reference; converters pass the compiled one (``converters._kernels.select("codec")``).
            Every coder writes the same bytes.
        version: the format version written: 3 (the default: version 2 plus the
            cross-channel prediction of :mod:`lidarscan._codec_v3`, smaller on Ouster scans,
            whose reflectivity it predicts from signal and range) or 2 (for readers of this
            library's versions before 3 was written by default).

    Returns:
        The compressed bytes; :func:`decompress_scan` restores the scan bit for bit.

    Raises:
        EncodeError: the scan does not encode as CDR, or a size exceeds the format's u32 fields.
    """
    from lidarscan.cdr import encode
    from lidarscan.scan import data_view
    from lidarscan.types import LidarScan as ScanDC
    coder = coder or NUMPY
    if version not in (2, 3):
        raise EncodeError("version", version, "2 or 3 (the format versions this library writes)")

    data = data_view(scan)
    data_len = int(data.size)
    skeleton_scan = ScanDC(
        header=scan.header, lidar_info_time=scan.lidar_info_time, height=int(scan.height),
        width=int(scan.width), is_bigendian=bool(scan.is_bigendian),
        is_destaggered=bool(scan.is_destaggered),
        column_time_offsets=np.zeros(0, np.int64), column_azimuth_angles=np.zeros(0, np.float64),
        channels=tuple(scan.channels), data=np.zeros(0, np.uint8))
    skeleton = _zc(level).compress(encode(skeleton_scan))
    columns = _encode_columns(np.asarray(scan.column_time_offsets, np.int64),
                              np.asarray(scan.column_azimuth_angles, np.float64), level)
    if data_len >= 2**32:
        raise EncodeError("scan.data", data_len, "fewer than 2**32 bytes")
    raw = memoryview(np.ascontiguousarray(data, np.uint8)).cast("B")
    segs: list[tuple[int, int, int, bytes, bytes]] = []

    def gap(start: int, stop: int) -> None:
        if stop > start:
            chunk = raw[start:stop]
            segs.append((start, stop - start, ZSTD, b"", _zc(level).compress(chunk)))

    shifts = None
    if info is not None and not bool(scan.is_destaggered):
        found = np.asarray(info.pixel_shift_by_row, np.int64).reshape(-1)
        if (found.size == int(scan.height) and np.any(found) and int(scan.width)
                and 4 * found.size + 32 < 2**16):
            shifts = found % int(scan.width)
    layout = _layout(scan, data_len)
    refs: dict[int, np.ndarray[Any, Any]] = {}
    if layout is None:
        gap(0, data_len)
    else:
        pos = 0
        for offset, length, desc in layout:
            gap(pos, offset)
            method, params, payload = _encode_block(raw[offset:offset + length], desc, scan,
                                                    level, float_step, shifts, refs, coder,
                                                    version)
            segs.append((offset, length, method, params, payload))
            pos = offset + length
        gap(pos, data_len)
    if len(segs) >= 2**16:
        raise EncodeError("scan.channels", len(scan.channels), "fewer than 32768 channels")
    out = [_HEAD.pack(MAGIC, version, 0, len(segs)), struct.pack("<I", len(skeleton)), skeleton,
           struct.pack("<I", len(columns)), columns, struct.pack("<I", data_len)]
    for offset, length, method, params, payload in segs:
        out += [_SEG.pack(offset, length, method, len(params)), params,
                struct.pack("<I", len(payload)), payload]
    return b"".join(out)


def segments(buf: bytes) -> list[dict[str, Any]]:
    """The segments of a compressed scan: offset, length, method name, payload bytes, params.

    For inspection (the evidence tables, the CLI's ``info``); raises DecodeError like
    :func:`decompress_scan`.
    """
    return [{"offset": o, "length": n, "method": _METHOD_NAMES.get(m, str(m)),
             "payload_bytes": len(p), "params": prm}
            for o, n, m, prm, p in _parse(buf)[3]]


def _parse(buf: bytes) -> tuple[bytes, int, list[tuple[int, int, int, bytes, bytes]]]:
    mv = memoryview(buf)
    if len(mv) < _HEAD.size + 4:
        raise DecodeError("compressed scan", len(mv), f"at least {_HEAD.size + 4} bytes")
    magic, version, _flags, nseg = _HEAD.unpack_from(mv, 0)
    if magic != MAGIC:
        raise DecodeError("compressed scan magic", bytes(magic), f"{MAGIC!r}")
    if version not in (1, 2, 3):
        raise DecodeError("compressed scan version", version, "1, 2 or 3 (this library)")
    pos = _HEAD.size

    def take(n: int, what: str) -> bytes:
        nonlocal pos
        if pos + n > len(mv):
            raise DecodeError(what, n, f"at most {len(mv) - pos} bytes left in the buffer")
        part = bytes(mv[pos:pos + n])
        pos += n
        return part

    (skel_len,) = struct.unpack("<I", take(4, "skeleton length"))
    skeleton = take(skel_len, "skeleton")
    columns = None
    if version >= 2:
        (col_len,) = struct.unpack("<I", take(4, "columns length"))
        columns = take(col_len, "columns")
    (data_len,) = struct.unpack("<I", take(4, "data length"))
    segs = []
    expect = 0
    for i in range(nseg):
        offset, length, method, plen = _SEG.unpack(take(_SEG.size, f"segment {i} header"))
        params = take(plen, f"segment {i} params")
        (n,) = struct.unpack("<I", take(4, f"segment {i} payload length"))
        payload = take(n, f"segment {i} payload")
        if offset != expect or offset + length > data_len:
            raise DecodeError(f"segment {i} offset", offset,
                              f"{expect} (segments contiguous inside {data_len} bytes)")
        expect = offset + length
        segs.append((offset, length, method, params, payload))
    if expect != data_len:
        raise DecodeError("segments", expect, f"to cover all {data_len} data bytes")
    if pos != len(mv):
        raise DecodeError("compressed scan", len(mv), f"{pos} bytes (trailing bytes)")
    if version == 1 and any(seg[2] > QUANT for seg in segs):
        raise DecodeError("compressed scan method", max(seg[2] for seg in segs),
                          "0..4 in a version 1 buffer")
    if version == 2 and any(seg[2] > QUANT2 for seg in segs):
        raise DecodeError("compressed scan method", max(seg[2] for seg in segs),
                          "0..6 in a version 2 buffer")
    return skeleton, columns, data_len, segs


def _encode_columns(times: np.ndarray[Any, Any], azimuths: np.ndarray[Any, Any], level: int
                    ) -> bytes:
    """The version 2 per-column part (format above)."""
    def delta(words: np.ndarray[Any, Any]) -> bytes:
        r = words.copy()
        r[1:] -= words[:-1]
        return _zc(level).compress(_planes(zigzag(r)))
    head = struct.pack("<II", times.size, azimuths.size)
    return head + _parts(delta(times.view(np.uint64)), delta(azimuths.view(np.uint64)))


def _decode_columns(buf: bytes) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """(column_time_offsets int64, column_azimuth_angles float64) of the per-column part."""
    if len(buf) < 8:
        raise DecodeError("columns", len(buf), "at least 8 bytes")
    n_time, n_az = struct.unpack_from("<II", buf)
    out = []
    for n, part in zip((n_time, n_az), _split(buf[8:], 2, "columns"), strict=True):
        z = _unplanes(_zd(part, 8 * n, "columns"), 8, n, "columns").view(np.uint64)
        out.append(np.cumsum(unzigzag(z), dtype=np.uint64))
    return out[0].view(np.int64), out[1].view(np.float64)


def _decode_segment(i: int, offset: int, length: int, method: int, params: bytes,
                    payload: bytes, data: np.ndarray[Any, Any], coder: ResidualCoder = NUMPY
                    ) -> bytes | np.ndarray[Any, Any]:
    """The bytes of segment i (bytes or a uint8 array); ``data``: the scan's data, decoded up
    to ``offset``."""
    what = f"segment {i}"
    if method == RAW:
        out = payload
    elif method == ZSTD:
        out = _zd(payload, length, what)
    elif method == SHUFFLE:
        if len(params) != 1 or params[0] not in (1, 2, 4, 8) or length % params[0]:
            raise DecodeError(f"{what} params", params, "one itemsize byte dividing the length")
        size = params[0]
        out = _unplanes(_zd(payload, length, what), size, length // size, what)
    elif method in (PREDICT, QUANT):
        from lidarscan._codec_v1 import decode_v1
        out = decode_v1(what, length, method, params, payload)
    elif method in (PREDICT2, QUANT2):
        out = _decode_v2(what, offset, length, method, params, payload, data, coder)
    elif method == XPREDICT:
        from lidarscan._codec_v3 import decode_block
        out = decode_block(what, offset, length, params, payload, data, coder)
    else:
        raise DecodeError(f"{what} method", method,
                          "0..7 (RAW, ZSTD, SHUFFLE, PREDICT, QUANT, PREDICT2, QUANT2, XPREDICT)")
    if memoryview(out).nbytes != length:
        raise DecodeError(f"{what} length", memoryview(out).nbytes, f"{length} bytes")
    return out


def _read_grid2(what: str, method: int, length: int, params: bytes
                ) -> tuple[int, bool, tuple[int, int, int], int, int, bool,
                           np.ndarray[Any, Any] | None, int]:
    """(datatype, bigendian, (H, W, C), predictor, extra, masked, row shifts or None, end) of
    the grid params of a PREDICT2, QUANT2 or XPREDICT segment of ``length`` bytes, checked
    (DecodeError); ``end``: where the row shifts end (XPREDICT's tables follow; the other
    methods' params end there)."""
    if len(params) < _GRID2.size:
        raise DecodeError(f"{what} params", len(params), f"at least {_GRID2.size} bytes")
    datatype, big, h, w, c, predictor, rolled, extra, masked = _GRID2.unpack_from(params)
    ok_type = datatype == _FLOAT32 if method == QUANT2 else datatype in _INT_CODES
    top = REF if method == PREDICT2 else PLANAR
    if (not ok_type or predictor > top or extra > 2 or masked > 1
            or (method == XPREDICT and c != 1)
            or h * w * c * _SIZES.get(datatype, 0) != length):
        raise DecodeError(f"{what} params", (datatype, h, w, c, predictor, extra, masked),
                          f"a grid of {length} bytes with a known datatype and predictor"
                          + (", count 1" if method == XPREDICT else ""))
    base = _GRID2.size + (8 if method == QUANT2 else 0) + (4 if predictor == REF else 0)
    end = base + (4 * h if rolled else 0)
    if len(params) < end or (method != XPREDICT and len(params) != end):
        raise DecodeError(f"{what} params", len(params), f"{end} bytes")
    shifts = np.frombuffer(params, "<i4", h, base).astype(np.int64) if rolled else None
    return datatype, bool(big), (h, w, c), predictor, extra, bool(masked), shifts, end


def _decode_v2(what: str, offset: int, length: int, method: int, params: bytes, payload: bytes,
               data: np.ndarray[Any, Any], coder: ResidualCoder = NUMPY) -> np.ndarray[Any, Any]:
    datatype, big, (h, w, c), predictor, extra, masked, shifts, _ = _read_grid2(
        what, method, length, params)
    if method == PREDICT2:
        size = _SIZES[datatype]
        ref = None
        if predictor == REF:
            (ref_offset,) = struct.unpack_from("<I", params, _GRID2.size)
            if ref_offset + length > offset:
                raise DecodeError(f"{what} reference offset", ref_offset,
                                  f"a block of {length} bytes decoded before offset {offset}")
            grid = np.frombuffer(data[ref_offset:ref_offset + length].tobytes(),
                                 (">" if big else "<") + f"u{size}").reshape(h, w, c)
            ref = coder.roll(_as_unsigned(grid), shifts, 1)
        u = _decode_int2(payload, (h, w, c), size, predictor, extra, masked, what, ref, coder)
        u = coder.roll(u, shifts, -1)
        return u.astype(u.dtype.newbyteorder(">" if big else "<"), copy=False).reshape(
            -1).view(np.uint8)
    (step,) = struct.unpack_from("<d", params, _GRID2.size)
    bits = _decode_quant2(payload, (h, w, c), predictor, extra, masked, step, big, what, coder)
    return coder.roll(np.frombuffer(bits, np.uint32).reshape(h, w, c), shifts, -1).reshape(
        -1).view(np.uint8)


def decompress_scan(buf: bytes, *, coder: ResidualCoder | None = None) -> Any:
    """The LidarScan of :func:`compress_scan`'s bytes, as a :class:`lidarscan.types.LidarScan`
    (``data`` a read-only uint8 array) whose CDR equals the original's byte for byte.

    Args:
        buf: the compressed bytes.
        coder: as for :func:`compress_scan` (None: the numpy reference); same result.

    Raises:
        DecodeError: not this format, another version, or a damaged buffer.
    """
    from lidarscan.cdr import decode_scan
    coder = coder or NUMPY
    skeleton, columns, data_len, segs = _parse(buf)
    try:
        skel = decode_scan(_zd(skeleton, 1 << 30, "skeleton"))
    except DecodeError:
        raise
    except Exception as err:  # noqa: BLE001 - any failure means a damaged skeleton
        raise DecodeError("skeleton", len(skeleton), f"the CDR of a LidarScan ({err})") from None
    data = np.empty(data_len, np.uint8)
    for i, (offset, length, method, params, payload) in enumerate(segs):
        data[offset:offset + length] = np.frombuffer(
            _decode_segment(i, offset, length, method, params, payload, data, coder), np.uint8)
    data.flags.writeable = False
    if columns is None:
        return dataclasses.replace(skel, data=data)
    times, azimuths = _decode_columns(columns)
    return dataclasses.replace(skel, data=data, column_time_offsets=times,
                               column_azimuth_angles=azimuths)
