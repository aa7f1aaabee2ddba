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
(Ouster reflectivity from signal and range), its byte format in :mod:`lidarscan.codec._v3`;
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
7     XPREDICT   (version 3) see :mod:`lidarscan.codec._v3`
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

Code layout (each module imports only those above it in this list): the numpy reference of the
prediction and of the residual coding (the test oracle), :mod:`lidarscan.codec._bits`, whose hot
steps a :class:`ResidualCoder` bundles; the format primitives, :mod:`lidarscan.codec._format`;
the versions: version 1's decoding :mod:`lidarscan.codec._v1`, version 2's methods and
per-column arrays :mod:`lidarscan.codec._v2`, version 3's XPREDICT :mod:`lidarscan.codec._v3`;
the compiled coder (numba, optional: the same bytes, :mod:`lidarscan.codec._compiled` with
version 3's fit and prediction in :mod:`lidarscan.codec._compiled_v3`); and this module, the
container and the encoder's choices. ``coder=`` chooses the residual coder
(:func:`residual_coder`): by default the compiled one when numba is installed and enabled
(``LIDARSCAN_NUMBA``, read by :mod:`lidarscan._backends`), else the numpy reference; numba is
imported and the kernels compiled or loaded from numba's on-disk cache at the first call that
needs them, never at import.

``decompress_scan`` returns a :class:`lidarscan.types.LidarScan` whose CDR (``lidarscan.encode``)
is byte-identical to the input's (any version). Errors: :class:`lidarscan.errors.EncodeError` (a scan that does
not encode), :class:`lidarscan.errors.DecodeError` (a buffer that is not this format).
"""

from __future__ import annotations

import dataclasses
import struct
from typing import Any

import numpy as np

from lidarscan._backends import numba_enabled
from lidarscan.codec import _v3
from lidarscan.codec._bits import NUMPY, REF, ResidualCoder, residual, zigzag
from lidarscan.codec._format import (
    _FLOAT32,
    _GRID2,
    _HEAD,
    _INT_CODES,
    _METHOD_NAMES,
    _SEG,
    _SIZES,
    MAGIC,
    PREDICT,
    PREDICT2,
    QUANT,
    QUANT2,
    RAW,
    SHUFFLE,
    VERSION,
    XPREDICT,
    ZSTD,
    _as_unsigned,
    _planes,
    _shift_params,
    _unplanes,
    _zc,
    _zd,
)
from lidarscan.codec._v1 import decode_v1
from lidarscan.codec._v2 import (  # the three "as": addressed through this module by tests
    _bits_cost,
    _decode_columns,
    _decode_v2,
    _encode_columns,
    _encode_int2,
    _encode_quant2,
    _pack_residuals as _pack_residuals,
    _quantise as _quantise,
    _unpack_residuals as _unpack_residuals,
)
from lidarscan.errors import ConfigError, DecodeError, EncodeError

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
    "NUMPY",
    "ResidualCoder",
    "residual_coder",
    "compress_scan",
    "decompress_scan",
    "segments",
]


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
    tries XPREDICT on integer blocks, :mod:`lidarscan.codec._v3`). ``refs``:
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
            cross = _v3.encode_block(block, desc, scan, level, shifts, coder, u, ref)
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


def residual_coder(backend: str | ResidualCoder | None = "auto") -> ResidualCoder:
    """The residual coder that ``coder=backend`` of :func:`compress_scan` /
    :func:`decompress_scan` runs (every coder writes and reads the same bytes).

    Args:
        backend: ``"auto"`` (the default of every entry point): the compiled coder (numba) when
            numba is installed and not switched off (``LIDARSCAN_NUMBA=0``), else the numpy
            reference; ``"numba"``: the compiled coder, or an error; ``"numpy"`` or None: the
            numpy reference (:data:`NUMPY`, the test oracle); a :class:`ResidualCoder`: itself.
            The compiled coder is compiled, or loaded from numba's on-disk cache, at the first
            call that needs it in the process (a large part of a second from the cache).

    Raises:
        ConfigError: an unknown backend, or ``"numba"`` without numba (or switched off).
    """
    if isinstance(backend, ResidualCoder):
        return backend
    if backend is None or backend == "numpy":
        return NUMPY
    if backend not in ("auto", "numba"):
        raise ConfigError("coder", backend, "'auto', 'numba', 'numpy', None (numpy) or a "
                          "ResidualCoder")
    compiled = None
    if numba_enabled():
        from lidarscan.codec import _compiled
        compiled = _compiled.coder()
    if compiled is None and backend == "numba":
        raise ConfigError("coder", backend, "numba installed (pip install numba) and "
                          "LIDARSCAN_NUMBA not 0")
    return compiled or NUMPY


def compress_scan(scan: Any, info: Any = None, *, level: int = 1,
                  float_step: float | None = 0.001,
                  coder: str | ResidualCoder | None = "auto",
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
        coder: the residual coding's implementation (:func:`residual_coder`): ``"auto"``
            (default) the compiled one when numba is installed, else the numpy reference;
            ``"numba"``; ``"numpy"`` or None the numpy reference; or a :class:`ResidualCoder`.
            Every coder writes the same bytes.
        version: the format version written: 3 (the default: version 2 plus the
            cross-channel prediction of :mod:`lidarscan.codec._v3`, smaller on Ouster scans,
            whose reflectivity it predicts from signal and range) or 2 (for readers of this
            library's versions before 3 was written by default).

    Returns:
        The compressed bytes; :func:`decompress_scan` restores the scan bit for bit.

    Raises:
        EncodeError: the scan does not encode as CDR, or a size exceeds the format's u32 fields.
        ConfigError: an unknown ``coder``, or ``"numba"`` without numba.
    """
    from lidarscan.cdr import encode
    from lidarscan.scan import data_view
    from lidarscan.types import LidarScan as ScanDC
    coder = residual_coder(coder)
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
        out = decode_v1(what, length, method, params, payload)
    elif method in (PREDICT2, QUANT2):
        out = _decode_v2(what, offset, length, method, params, payload, data, coder)
    elif method == XPREDICT:
        out = _v3.decode_block(what, offset, length, params, payload, data, coder)
    else:
        raise DecodeError(f"{what} method", method,
                          "0..7 (RAW, ZSTD, SHUFFLE, PREDICT, QUANT, PREDICT2, QUANT2, XPREDICT)")
    if memoryview(out).nbytes != length:
        raise DecodeError(f"{what} length", memoryview(out).nbytes, f"{length} bytes")
    return out


def decompress_scan(buf: bytes, *, coder: str | ResidualCoder | None = "auto") -> Any:
    """The LidarScan of :func:`compress_scan`'s bytes, as a :class:`lidarscan.types.LidarScan`
    (``data`` a read-only uint8 array) whose CDR equals the original's byte for byte.

    Args:
        buf: the compressed bytes.
        coder: as for :func:`compress_scan` (default ``"auto"``: the compiled coder when numba
            is installed; ``"numpy"`` or None: the numpy reference); the same result.

    Raises:
        DecodeError: not this format, another version, or a damaged buffer.
        ConfigError: an unknown ``coder``, or ``"numba"`` without numba.
    """
    from lidarscan.cdr import decode_scan
    coder = residual_coder(coder)
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
