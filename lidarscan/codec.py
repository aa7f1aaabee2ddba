"""A lossless, versioned compressed form of a LidarScan (``compress_scan`` / ``decompress_scan``).

The message itself stays uncompressed (receivers get zero-copy views); this module is for storage
and transports that compress (an MCAP channel with a custom encoding, a ``--compress`` option of
the CLI). It beats compressing the whole CDR buffer with zstd (what MCAP's chunk compression does)
because it knows the channel layout: every channel block is coded on its own, integer blocks by
prediction, float32 blocks in metres through the integer grid they come from.

Byte format, version 1 (every integer little-endian)::

    "LSCZ"  u8 version=1  u8 flags=0  u16 n_segments
    u32 skeleton_len  skeleton          zstd frame of the CDR (lidarscan.encode) of the scan with
                                        empty ``data``: header, info stamp, sizes, byte order,
                                        stagger flag, per-column arrays, channel descriptors
    u32 data_len                        len(scan.data)
    n_segments x segment                contiguous, in order, covering data[0:data_len] exactly

    segment := u32 offset  u32 length  u8 method  u16 params_len  params  u32 payload_len  payload

Every zstd frame carries its content checksum (a damaged payload raises, never decodes to
other values). Methods (a segment is a channel block, or the bytes between/after blocks):

====  =========  ==========================================================================
id    name       params / payload
====  =========  ==========================================================================
0     RAW        - / the bytes
1     ZSTD       - / zstd frame of the bytes
2     SHUFFLE    u8 itemsize / zstd frame of the byte planes: the least significant byte
                 of every value (little-endian reading of the block), then every second
                 byte, ...
3     PREDICT    u8 datatype, u8 bigendian, u32 H, u32 W, u32 count, u8 predictor,
                 u8 rolled [, H x i32 row shifts when rolled] / zstd frame of the byte
                 planes of zigzag(residual), residuals in the unsigned type of the
                 channel's size (wrapping: every value is exact)
4     QUANT      u8 datatype (FLOAT32), u8 bigendian, u32 H, u32 W, u32 count,
                 u8 predictor, u8 rolled, f64 step [, H x i32 row shifts] /
                 u32 n + the PREDICT payload of the int32 grid q (n bytes),
                 u32 n + zstd frame of the packed exception mask (n bytes, row-major,
                 numpy packbits order), zstd frame of the exceptions' original 4 bytes.
                 A value v is coded as q = rint(v / step) when float32(float64(q) * step)
                 has v's exact bits (the decode rule of :func:`lidarscan.range_m`); every
                 other value (NaN, +-Inf, -0, off-grid) is an exception kept bit for bit.
                 Exceptions take their left neighbour's q (0 at a row start) so they cost
                 no residual.
====  =========  ==========================================================================

Predictors (on the (H, W, count) array, per count index): 0 none, 1 left (x[r, c-1]), 2 up
(x[r-1, c]), 3 planar (left + up - up-left); out-of-grid neighbours are 0. Residuals are
computed and inverted with wrapping integer arithmetic (decoding: cumulative sums).
"Rolled": before prediction row r was rotated right by its shift s_r (element c moved to
(c + s_r) mod W): a staggered scan is predicted in destaggered order, where the row above sees
the same azimuth; the decoder rotates back.

``decompress_scan`` returns a :class:`lidarscan.types.LidarScan` whose CDR (``lidarscan.encode``)
is byte-identical to the input's. Errors: :class:`lidarscan.errors.EncodeError` (a scan that does
not encode), :class:`lidarscan.errors.DecodeError` (a buffer that is not this format).
"""

from __future__ import annotations

import dataclasses
import struct
from typing import Any

import numpy as np

from lidarscan.errors import DecodeError, EncodeError

__all__ = [
    "MAGIC",
    "VERSION",
    "RAW",
    "ZSTD",
    "SHUFFLE",
    "PREDICT",
    "QUANT",
    "compress_scan",
    "decompress_scan",
    "segments",
]

MAGIC = b"LSCZ"
VERSION = 1
RAW, ZSTD, SHUFFLE, PREDICT, QUANT = 0, 1, 2, 3, 4
_METHOD_NAMES = {RAW: "raw", ZSTD: "zstd", SHUFFLE: "shuffle", PREDICT: "predict",
                 QUANT: "quant"}
NONE, LEFT, UP, PLANAR = 0, 1, 2, 3

_INT_CODES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4"}
_FLOAT32, _FLOAT64 = 7, 8
_SIZES = {1: 1, 2: 1, 3: 2, 4: 2, 5: 4, 6: 4, 7: 4, 8: 8}
_GRID = struct.Struct("<BBIIIBB")  # datatype, bigendian, H, W, count, predictor, rolled
_SEG = struct.Struct("<IIBH")       # offset, length, method, params_len
_HEAD = struct.Struct("<4sBBH")


# ----------------------------------------------------------------------------- zstd

def _zc(level: int) -> Any:
    import zstandard
    return zstandard.ZstdCompressor(level=level, write_checksum=True)


def _zd(frame: bytes, limit: int, what: str) -> bytes:
    import zstandard
    try:
        out = zstandard.ZstdDecompressor().decompress(frame, max_output_size=limit)
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


def _residual(x: np.ndarray[Any, Any], predictor: int) -> np.ndarray[Any, Any]:
    """x - prediction in x's (unsigned, native) dtype, wrapping; x is (H, W, C)."""
    r = x.copy()
    if predictor in (UP, PLANAR):
        r[1:] -= x[:-1]
    if predictor in (LEFT, PLANAR):
        r[:, 1:] -= r[:, :-1].copy() if predictor == PLANAR else x[:, :-1]
    return r


def _unresidual(r: np.ndarray[Any, Any], predictor: int) -> np.ndarray[Any, Any]:
    x = r
    if predictor in (LEFT, PLANAR):
        x = np.cumsum(x, axis=1, dtype=r.dtype)
    if predictor in (UP, PLANAR):
        # row by row: numpy's cumulative sum along the outer axis is ~5x slower than H adds
        x = x.copy() if x is r else x
        for row in range(1, x.shape[0]):
            np.add(x[row], x[row - 1], out=x[row])
    return x


def _zigzag(r: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """Unsigned residuals (wrapping) -> zigzag order: 0, -1, 1, -2, ... -> 0, 1, 2, 3, ..."""
    bits = r.dtype.itemsize * 8
    s = r.view(r.dtype.str.replace("u", "i"))
    return ((s << 1) ^ (s >> (bits - 1))).view(r.dtype)


def _unzigzag(z: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    one = z.dtype.type(1)
    return (z >> one) ^ (np.zeros_like(z) - (z & one))


def _cost(r: np.ndarray[Any, Any]) -> int:
    """Size proxy of residuals: the sum of their magnitudes (zigzag values)."""
    return int(_zigzag(r).sum(dtype=np.uint64))


def _choose(x: np.ndarray[Any, Any]) -> int:
    """The predictor with the smallest estimated residuals on a band of up to 32 rows."""
    start = max(0, x.shape[0] // 2 - 16)
    band = x[start:start + 32]
    return min((LEFT, UP, PLANAR, NONE), key=lambda p: _cost(_residual(band, p)))


def _as_unsigned(arr: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """Native-order unsigned view/copy of an integer or float array (same bytes per value)."""
    native = arr.astype(arr.dtype.newbyteorder("="), copy=False)
    return native.view(f"u{arr.dtype.itemsize}")


def _predict_payload(u: np.ndarray[Any, Any], predictor: int, level: int) -> bytes:
    return _zc(level).compress(_planes(_zigzag(_residual(u, predictor))))


def _unpredict(payload: bytes, shape: tuple[int, int, int], itemsize: int, predictor: int,
               what: str) -> np.ndarray[Any, Any]:
    n = shape[0] * shape[1] * shape[2]
    z = _unplanes(_zd(payload, n * itemsize, what), itemsize, n, what).view(f"u{itemsize}")
    return _unresidual(_unzigzag(z).reshape(shape), predictor)


def _roll(x: np.ndarray[Any, Any], shifts: np.ndarray[Any, Any] | None, sign: int
          ) -> np.ndarray[Any, Any]:
    """Rotate row r of (H, W, C) right by sign * shifts[r] (None: unchanged); rows sharing a
    shift are moved together (spinning sensors have a handful of distinct shifts)."""
    if shifts is None:
        return x
    width = x.shape[1]
    out = np.empty_like(x)
    for shift in np.unique(shifts):
        rows = np.flatnonzero(shifts == shift)
        k = int(sign * shift) % max(width, 1)
        src = x[rows]
        out[rows, k:] = src[:, :width - k]
        out[rows, :k] = src[:, width - k:]
    return out


def _shift_params(shifts: np.ndarray[Any, Any] | None) -> bytes:
    return b"" if shifts is None else shifts.astype("<i4").tobytes()


# --------------------------------------------------------------------------- QUANT

def _quantise(v: np.ndarray[Any, Any], step: float
              ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]] | None:
    """(int32 grid q with exceptions filled from the left, exception mask) or None when the
    grid does not fit int32. v: native float32 (H, W, C)."""
    with np.errstate(invalid="ignore", over="ignore"):
        qf = np.rint(v.astype(np.float64) / step)
        fits = np.abs(qf) < 2**31
        qf = np.where(fits, qf, 0.0)
        q = qf.astype(np.int32)
        back = (q.astype(np.float64) * step).astype(np.float32)
    exc = back.view(np.uint32) != v.view(np.uint32)
    if exc.all() and v.size:
        return None
    if exc.any():
        q[exc] = 0
        cols = np.arange(q.shape[1]).reshape(1, -1, 1)
        idx = np.maximum.accumulate(np.where(exc, 0, cols), axis=1)
        q = np.take_along_axis(q, idx, axis=1)
    return q, exc


def _quant_payload(v: np.ndarray[Any, Any], raw_words: np.ndarray[Any, Any], step: float,
                   level: int) -> tuple[bytes, int] | None:
    got = _quantise(v, step)
    if got is None:
        return None
    q, exc = got
    u = q.view(np.uint32)
    predictor = _choose(u)
    grid = _predict_payload(u, predictor, level)
    mask = _zc(level).compress(np.packbits(exc.reshape(-1)).tobytes())
    words = _zc(level).compress(raw_words.reshape(-1)[exc.reshape(-1)].tobytes())
    return (struct.pack("<I", len(grid)) + grid + struct.pack("<I", len(mask)) + mask + words,
            predictor)


def _unquant(payload: bytes, shape: tuple[int, int, int], predictor: int, step: float,
             bigendian: bool, what: str) -> bytes:
    n = shape[0] * shape[1] * shape[2]
    pos = 0

    def take() -> bytes:
        nonlocal pos
        if pos + 4 > len(payload):
            raise DecodeError(what, len(payload), "a length-prefixed QUANT part")
        (k,) = struct.unpack_from("<I", payload, pos)
        if pos + 4 + k > len(payload):
            raise DecodeError(what, k, f"at most {len(payload) - pos - 4} bytes")
        part = payload[pos + 4: pos + 4 + k]
        pos += 4 + k
        return part

    q = _unpredict(take(), shape, 4, predictor, what).view(np.int32)
    mask_bytes = _zd(take(), (n + 7) // 8, what)
    if len(mask_bytes) != (n + 7) // 8:
        raise DecodeError(what, len(mask_bytes), f"{(n + 7) // 8} bytes of exception mask")
    exc = np.unpackbits(np.frombuffer(mask_bytes, np.uint8), count=n).astype(bool)
    words = np.frombuffer(_zd(payload[pos:], 4 * n, what), np.uint32)
    if words.size != int(exc.sum()):
        raise DecodeError(what, words.size, f"{int(exc.sum())} exception words")
    out = (q.astype(np.float64) * step).astype(np.float32).reshape(-1)
    if bigendian:
        out = out.astype(">f4")
    bits = out.view(np.uint32).copy()
    bits[exc] = words
    return bits.tobytes()


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


def _encode_block(block: bytes, desc: Any, scan: Any, level: int, float_step: float | None,
                  shifts: np.ndarray[Any, Any] | None) -> tuple[int, bytes, bytes]:
    """(method, params, payload) of one channel block."""
    datatype, big = int(desc.datatype), bool(scan.is_bigendian)
    shape = (int(scan.height), int(scan.width), int(desc.count))
    size = _SIZES[datatype]
    rolled = shifts is not None
    if datatype in _INT_CODES:
        u = np.frombuffer(block, np.dtype((">" if big else "<") + f"u{size}")).reshape(shape)
        u = _roll(_as_unsigned(u), shifts, 1)
        predictor = _choose(u)
        return (PREDICT, _GRID.pack(datatype, big, *shape, predictor, rolled)
                + _shift_params(shifts), _predict_payload(u, predictor, level))
    if datatype == _FLOAT32 and float_step:
        raw = np.frombuffer(block, ">f4" if big else "<f4").reshape(shape)
        native = _roll(raw.astype(np.float32), shifts, 1)
        words = _roll(np.frombuffer(block, np.uint32).reshape(shape), shifts, 1)
        got = _quant_payload(native, words, float_step, level)
        if got is not None:
            payload, predictor = got
            shuffled = None
            if len(payload) > len(block) // 2:  # mostly off-grid: compare with SHUFFLE
                shuffled = _zc(level).compress(_planes(np.frombuffer(block, f"<u{size}")))
            if shuffled is None or len(payload) <= len(shuffled):
                return (QUANT, _GRID.pack(datatype, big, *shape, predictor, rolled)
                        + struct.pack("<d", float_step) + _shift_params(shifts), payload)
            return SHUFFLE, bytes([size]), shuffled
    return SHUFFLE, bytes([size]), _zc(level).compress(_planes(
        np.frombuffer(block, f"<u{size}")))


def compress_scan(scan: Any, info: Any = None, *, level: int = 3,
                  float_step: float | None = 0.001) -> bytes:
    """Compress a LidarScan losslessly (format above).

    Args:
        scan: a LidarScan, rclpy message or :class:`lidarscan.types.LidarScan`; any channel
            datatypes, counts and byte order.
        info: its LidarInfo, optional: a staggered scan is then predicted in destaggered order
            (``pixel_shift_by_row``; the shifts travel in the format, decoding needs no info).
        level: zstd level of every part (1..22; 3 is the measured speed/size balance).
        float_step: grid of float32 channels in their unit (0.001: metres from millimetres);
            None codes float32 channels by byte shuffle only.

    Returns:
        The compressed bytes; :func:`decompress_scan` restores the scan bit for bit.

    Raises:
        EncodeError: the scan does not encode as CDR, or a size exceeds the format's u32 fields.
    """
    from lidarscan.cdr import encode
    from lidarscan.scan import data_view
    from lidarscan.types import LidarScan as ScanDC

    data = data_view(scan)
    data_len = int(data.size)
    skeleton_scan = ScanDC(
        header=scan.header, lidar_info_time=scan.lidar_info_time, height=int(scan.height),
        width=int(scan.width), is_bigendian=bool(scan.is_bigendian),
        is_destaggered=bool(scan.is_destaggered),
        column_time_offsets=np.asarray(scan.column_time_offsets, np.int64),
        column_azimuth_angles=np.asarray(scan.column_azimuth_angles, np.float64),
        channels=tuple(scan.channels), data=np.zeros(0, np.uint8))
    skeleton = _zc(level).compress(encode(skeleton_scan))
    if data_len >= 2**32:
        raise EncodeError("scan.data", data_len, "fewer than 2**32 bytes")
    raw = data.tobytes()
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
    if layout is None:
        gap(0, data_len)
    else:
        pos = 0
        for offset, length, desc in layout:
            gap(pos, offset)
            method, params, payload = _encode_block(raw[offset:offset + length], desc, scan,
                                                    level, float_step, shifts)
            segs.append((offset, length, method, params, payload))
            pos = offset + length
        gap(pos, data_len)
    if len(segs) >= 2**16:
        raise EncodeError("scan.channels", len(scan.channels), "fewer than 32768 channels")
    out = [_HEAD.pack(MAGIC, VERSION, 0, len(segs)), struct.pack("<I", len(skeleton)), skeleton,
           struct.pack("<I", data_len)]
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
            for o, n, m, prm, p in _parse(buf)[2]]


def _parse(buf: bytes) -> tuple[bytes, int, list[tuple[int, int, int, bytes, bytes]]]:
    mv = memoryview(buf)
    if len(mv) < _HEAD.size + 4:
        raise DecodeError("compressed scan", len(mv), f"at least {_HEAD.size + 4} bytes")
    magic, version, _flags, nseg = _HEAD.unpack_from(mv, 0)
    if magic != MAGIC:
        raise DecodeError("compressed scan magic", bytes(magic), f"{MAGIC!r}")
    if version != VERSION:
        raise DecodeError("compressed scan version", version, f"{VERSION} (this library)")
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
    return skeleton, data_len, segs


def _decode_segment(i: int, length: int, method: int, params: bytes, payload: bytes) -> bytes:
    what = f"segment {i}"
    if method == RAW:
        out = payload
    elif method == ZSTD:
        out = _zd(payload, length, what)
    elif method == SHUFFLE:
        if len(params) != 1 or params[0] not in (1, 2, 4, 8) or length % params[0]:
            raise DecodeError(f"{what} params", params, "one itemsize byte dividing the length")
        size = params[0]
        out = _unplanes(_zd(payload, length, what), size, length // size, what).tobytes()
    elif method in (PREDICT, QUANT):
        if len(params) < _GRID.size:
            raise DecodeError(f"{what} params", len(params), f"at least {_GRID.size} bytes")
        datatype, big, h, w, c, predictor, rolled = _GRID.unpack_from(params)
        base = _GRID.size + (8 if method == QUANT else 0)
        want = base + (4 * h if rolled else 0)
        if len(params) != want:
            raise DecodeError(f"{what} params", len(params), f"{want} bytes")
        ok_type = datatype in _INT_CODES if method == PREDICT else datatype == _FLOAT32
        if not ok_type or predictor > PLANAR or h * w * c * _SIZES.get(datatype, 0) != length:
            raise DecodeError(f"{what} params", (datatype, h, w, c, predictor),
                              f"a grid of {length} bytes with a known datatype and predictor")
        shifts = (np.frombuffer(params, "<i4", h, base).astype(np.int64) if rolled else None)
        if method == PREDICT:
            size = _SIZES[datatype]
            u = _roll(_unpredict(payload, (h, w, c), size, predictor, what), shifts, -1)
            out = u.astype(u.dtype.newbyteorder(">" if big else "<")).tobytes()
        else:
            (step,) = struct.unpack_from("<d", params, _GRID.size)
            bits = _unquant(payload, (h, w, c), predictor, step, bool(big), what)
            out = _roll(np.frombuffer(bits, np.uint32).reshape(h, w, c), shifts, -1).tobytes()
    else:
        raise DecodeError(f"{what} method", method, "0..4 (RAW, ZSTD, SHUFFLE, PREDICT, QUANT)")
    if len(out) != length:
        raise DecodeError(f"{what} length", len(out), f"{length} bytes")
    return out


def decompress_scan(buf: bytes) -> Any:
    """The LidarScan of :func:`compress_scan`'s bytes, as a :class:`lidarscan.types.LidarScan`
    (``data`` a read-only uint8 array) whose CDR equals the original's byte for byte.

    Raises:
        DecodeError: not this format, another version, or a damaged buffer.
    """
    from lidarscan.cdr import decode_scan
    skeleton, data_len, segs = _parse(buf)
    try:
        skel = decode_scan(_zd(skeleton, 1 << 30, "skeleton"))
    except DecodeError:
        raise
    except Exception as err:  # noqa: BLE001 - any failure means a damaged skeleton
        raise DecodeError("skeleton", len(skeleton), f"the CDR of a LidarScan ({err})") from None
    data = np.empty(data_len, np.uint8)
    for i, (offset, length, method, params, payload) in enumerate(segs):
        data[offset:offset + length] = np.frombuffer(
            _decode_segment(i, length, method, params, payload), np.uint8)
    data.flags.writeable = False
    return dataclasses.replace(skel, data=data)
