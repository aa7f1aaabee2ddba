"""Format version 2 of :mod:`lidarscan.codec` (spec: its module docstring): the methods
PREDICT2 and QUANT2 (prediction, the residuals' bit-length coding, the int32 grid of float32
channels) and the per-column arrays.

Built on the format primitives (:mod:`lidarscan.codec._format`) and the residual coding's hot
steps, a :class:`lidarscan.codec._bits.ResidualCoder` passed in by the container (numpy
reference or compiled: the same bytes); version 3 (:mod:`lidarscan.codec._v3`) codes its
residual grid with :func:`_encode_int2` / :func:`_decode_int2`.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

from lidarscan.codec._bits import (
    LEFT,
    NONE,
    NUMPY,
    PLANAR,
    REF,
    UP,
    ResidualCoder,
    bitlen_table,
    unzigzag,
    zigzag,
)
from lidarscan.codec._format import (
    _FLOAT32,
    _GRID2,
    _INT_CODES,
    _SIZES,
    PREDICT2,
    QUANT2,
    XPREDICT,
    _as_unsigned,
    _float_bits,
    _mask_frame,
    _parts,
    _planes,
    _split,
    _unmask_frame,
    _unplanes,
    _zc,
    _zd,
)
from lidarscan.errors import DecodeError

# --------------------------------------------------------------------------- QUANT

def _quantise(v: np.ndarray[Any, Any], step: float, coder: ResidualCoder = NUMPY
              ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]] | None:
    """(int32 grid q, 0 at exceptions; exception mask) or None when no value is on the grid.
    v: native float32 (H, W, C)."""
    q, exc = coder.quantise(np.ascontiguousarray(v, np.float32).reshape(-1), step)
    if exc.all() and v.size:
        return None
    return q.reshape(v.shape), exc.reshape(v.shape)



# ------------------------------------------------------------ version 2: bit-length coding

def _bits_cost(z: np.ndarray[Any, Any]) -> int:
    """Size proxy of zigzag residuals for the bit-length coding: the sum of bit lengths
    (through float32 exponents: exact below 2**24, a bit more above; a proxy only)."""
    return int(np.frexp(z.astype(np.float32))[1].sum(dtype=np.int64))


def _pack_residuals(z: np.ndarray[Any, Any], level: int, coder: ResidualCoder = NUMPY
                    ) -> tuple[int, bytes, bytes]:
    """(extra, zstd frame of the symbols, zstd frame of the low bits) of zigzag residuals
    ``z`` (1-D unsigned, at most 32 bits); extra 1 or 2, whichever is smaller (the coding:
    :mod:`lidarscan.codec._bits`). Both symbol streams are compressed: an order-0 entropy
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



def _code_grid(x: np.ndarray[Any, Any], valid: np.ndarray[Any, Any] | None, level: int,
               predictor: int | None = None, ref: np.ndarray[Any, Any] | None = None,
               coder: ResidualCoder = NUMPY) -> tuple[int, int, list[bytes]]:
    """(predictor, extra, [symbols frame, low bits]) of the valid pixels of grid x."""
    if predictor is None:
        predictor = _choose_masked(x, valid, ref, coder)[0]
    extra, frame, low = _pack_residuals(coder.residuals(x, valid, predictor, ref), level,
                                        coder)
    return predictor, extra, [frame, low]



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



# ------------------------------------------------------- per-column arrays

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



# ------------------------------------------------------------ block decoding

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

