"""Prediction and residual bit-length coding of :mod:`lidarscan.codec` (version 2), in numpy.

This is the reference (and the test oracle) of what the format header of :mod:`lidarscan.codec`
specifies: the predictors (none, left, up, planar, a reference grid) with wrapping integer
arithmetic, the masked pixels that hold their own prediction, zigzag, and the bit-length
coding: a zigzag residual z of bit length b becomes the symbol byte ``b << extra | t`` (t: the
``e = min(b - 1, extra)`` bits below the leading one) and ``k = b - 1 - e`` raw low bits, the
low bits of all values forming one stream grouped by k ascending (value order inside a group),
each value's bits most significant first, packed most significant bit first.

The hot steps are the fields of a :class:`ResidualCoder`; :data:`NUMPY` holds the functions
below. The compiled coder (:mod:`lidarscan.codec._compiled`, chosen by
:func:`lidarscan.codec.residual_coder`) has the same signatures and gives the same bytes. All
arrays are native byte order.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

__all__ = ["LEFT", "NONE", "NUMPY", "PLANAR", "REF", "UP", "ResidualCoder", "bitlen",
           "bitlen_table", "fill", "masked_residuals", "predicted_fill", "residual", "roll",
           "symbol_tables", "unmask_residuals", "unpack", "unresidual", "unzigzag", "zigzag"]

#: Predictors (format header of :mod:`lidarscan.codec`).
NONE, LEFT, UP, PLANAR, REF = 0, 1, 2, 3, 4


class ResidualCoder(NamedTuple):
    """The residual coding's hot steps (all arrays 1-D, native order).

    Attributes:
        name: "numpy" (the reference) or the compiled backend's name.
        symbols: ``(z uint32, table uint8[65536]) -> (sym1, k1, sym2, k2, bits1, bits2)``: the
            symbols and low-bit counts (uint8) with extra 1 and with extra 2 and the total low
            bits (int) of each (``table``: :func:`bitlen_table`).
        pack_low: ``(z uint32, k uint8) -> uint8``: the packed low-bit stream.
        low_counts: ``(symbols uint8, extra) -> int64[33]``: values per low-bit count k.
        residuals: ``(x (H, W, C) unsigned, valid bool (H, W, C) or None, predictor, ref (H,
            W, C) or None) -> uint32``: :func:`masked_residuals`.
        costs: ``(x, valid or None, ref or None) -> int64[5]``: the sum of the bit lengths of
            the residuals under each predictor 0..4 (-1 for REF without ``ref``).
        decode: ``(symbols uint8, extra, counts int64[33], low uint8, valid or None,
            predictor, ref or None, out (H, W, C) unsigned) -> out``: the grid, written into
            ``out``: :func:`unpack` then :func:`unmask_residuals` (the caller checked the
            symbols' bit lengths and the stream's size: ``low`` holds at least its bytes).
        quantise: ``(v float32 (n,), step) -> (q int32, exceptions bool)``: q = rint(v / step)
            where float32(float64(q) * step) has v's bits, else an exception and q = 0.
        dequantise: ``(q int32 (n,), step) -> float32``: float32(float64(q) * step).
        roll: ``(x (H, W, C), shifts int64[H] or None, sign) -> x rolled``: :func:`roll`.
        xfit: format version 3's table fit, ``lidarscan.codec._v3.fit``'s arguments and
            result, or None: that reference.
        xpredict: format version 3's prediction and its residual, in one pass,
            ``lidarscan.codec._v3.residual``'s arguments and result, or None: that reference.
    """

    name: str
    symbols: Callable[..., Any]
    pack_low: Callable[..., Any]
    low_counts: Callable[..., Any]
    residuals: Callable[..., Any]
    costs: Callable[..., Any]
    decode: Callable[..., Any]
    quantise: Callable[..., Any]
    dequantise: Callable[..., Any]
    roll: Callable[..., Any]
    xfit: Callable[..., Any] | None = None
    xpredict: Callable[..., Any] | None = None


# ------------------------------------------------------------------ prediction

def residual(x: np.ndarray[Any, Any], predictor: int,
             ref: np.ndarray[Any, Any] | None = None) -> np.ndarray[Any, Any]:
    """x - prediction in x's (unsigned, native) dtype, wrapping; x (and ref, the grid REF
    predicts from) is (H, W, C)."""
    if predictor == REF:
        return x - ref
    r = x.copy()
    if predictor in (UP, PLANAR):
        r[1:] -= x[:-1]
    if predictor in (LEFT, PLANAR):
        r[:, 1:] -= r[:, :-1].copy() if predictor == PLANAR else x[:, :-1]
    return r


def unresidual(r: np.ndarray[Any, Any], predictor: int,
               ref: np.ndarray[Any, Any] | None = None) -> np.ndarray[Any, Any]:
    if predictor == REF:
        return r + ref
    x = r
    if predictor in (LEFT, PLANAR):
        x = np.cumsum(x, axis=1, dtype=r.dtype)
    if predictor in (UP, PLANAR):
        # row by row: numpy's cumulative sum along the outer axis is ~5x slower than H adds
        x = x.copy() if x is r else x
        for row in range(1, x.shape[0]):
            np.add(x[row], x[row - 1], out=x[row])
    return x


def roll(x: np.ndarray[Any, Any], shifts: np.ndarray[Any, Any] | None, sign: int
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


def zigzag(r: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """Unsigned residuals (wrapping) -> zigzag order: 0, -1, 1, -2, ... -> 0, 1, 2, 3, ..."""
    bits = r.dtype.itemsize * 8
    s = r.view(r.dtype.str.replace("u", "i"))
    return ((s << 1) ^ (s >> (bits - 1))).view(r.dtype)


def unzigzag(z: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    one = z.dtype.type(1)
    return (z >> one) ^ (np.zeros_like(z) - (z & one))


def fill(x: np.ndarray[Any, Any], valid: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """x (H, W, C) with every invalid pixel replaced by the last valid value to its left in
    its row (0 if none)."""
    cols = np.arange(valid.shape[1]).reshape(1, -1, 1)
    index = np.maximum.accumulate(np.where(valid, cols, -1), axis=1)
    got = np.take_along_axis(x, np.maximum(index, 0), axis=1)
    return np.where(index >= 0, got, x.dtype.type(0))


def predicted_fill(x: np.ndarray[Any, Any], valid: np.ndarray[Any, Any], predictor: int,
                   ref: np.ndarray[Any, Any] | None = None) -> np.ndarray[Any, Any]:
    """The grid f (H, W, C) equal to x at valid pixels and to its own prediction at invalid
    ones (their residual is 0): NONE 0, LEFT the last valid value to the left, UP the last
    valid value above, PLANAR the row above plus the last valid (x - row above) to the left,
    REF the reference grid's value."""
    if predictor == REF:
        return np.where(valid, x, ref)
    if predictor == NONE:
        return np.where(valid, x, x.dtype.type(0))
    if predictor == LEFT:
        return fill(x, valid)
    if predictor == UP:  # row by row: faster than gathering along the outer axis
        out = np.empty_like(x)
        prev = np.zeros(x.shape[1:], x.dtype)
        for row in range(x.shape[0]):
            prev = np.where(valid[row], x[row], prev)
            out[row] = prev
        return out
    out = np.empty_like(x)
    prev = np.zeros(x.shape[1:], x.dtype)
    for row in range(x.shape[0]):
        prev = prev + fill((x[row] - prev)[None], valid[row][None])[0]
        out[row] = prev
    return out


def masked_residuals(x: np.ndarray[Any, Any], valid: np.ndarray[Any, Any] | None,
                     predictor: int, ref: np.ndarray[Any, Any] | None = None
                     ) -> np.ndarray[Any, Any]:
    """Zigzag residuals of the valid pixels of x (H, W, C), row-major; invalid pixels take
    their predicted value (:func:`predicted_fill`)."""
    if valid is None:
        return zigzag(residual(x, predictor, ref)).reshape(-1)
    return zigzag(residual(predicted_fill(x, valid, predictor, ref), predictor, ref))[valid]


def unmask_residuals(z: np.ndarray[Any, Any], valid: np.ndarray[Any, Any] | None,
                     shape: tuple[int, int, int], predictor: int,
                     ref: np.ndarray[Any, Any] | None = None) -> np.ndarray[Any, Any]:
    """The grid from the valid pixels' zigzag residuals, invalid pixels' residuals being 0
    (inverse of :func:`masked_residuals`; invalid pixels hold their predicted value)."""
    if valid is None:
        return unresidual(unzigzag(z).reshape(shape), predictor, ref)
    r = np.zeros(shape, z.dtype)
    r[valid] = unzigzag(z)
    return unresidual(r, predictor, ref)


# ------------------------------------------------------------- bit-length coding

@functools.lru_cache(maxsize=1)
def bitlen_table() -> np.ndarray[Any, Any]:
    """Bit length of 0 .. 65535 (uint8)."""
    return np.frexp(np.arange(1 << 16, dtype=np.float64))[1].astype(np.uint8)


def bitlen(z: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """Bit length of every value of an unsigned array of at most 32 bits (0 for 0), as uint8."""
    table = bitlen_table()
    if z.dtype.itemsize <= 2:
        return table[z]
    hi = (z >> z.dtype.type(16)).astype(np.uint16)
    lo = (z & z.dtype.type(0xFFFF)).astype(np.uint16)
    return np.where(hi > 0, table[hi] + np.uint8(16), table[lo])


def _symbols(z: np.ndarray[Any, Any], table: np.ndarray[Any, Any]
             ) -> tuple[np.ndarray[Any, Any], ...]:
    b = bitlen(z)
    b1 = np.maximum(b, np.uint8(1)) - np.uint8(1)            # bits below the leading one
    e2 = np.minimum(b1, np.uint8(2))
    k2 = b1 - e2
    top2 = ((z >> k2.astype(np.uint32)) & np.uint32(3)).astype(np.uint8)
    top2 &= (np.uint8(1) << e2) - np.uint8(1)
    wide = b1 >= 2                                           # e = 2 -> e = 1 drops a bit
    top1 = np.where(wide, top2 >> np.uint8(1), top2)
    k1 = k2 + wide.astype(np.uint8)
    bits2 = int(k2.sum(dtype=np.int64))
    return ((b << np.uint8(1)) | top1, k1, (b << np.uint8(2)) | top2, k2,
            bits2 + int(np.count_nonzero(wide)), bits2)


def _pack_low(z: np.ndarray[Any, Any], k: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    order = np.argsort(k, kind="stable")
    counts = np.bincount(k, minlength=33)
    low = z[order] & ((np.uint32(1) << k[order].astype(np.uint32)) - np.uint32(1))
    pieces, pos = [], int(counts[0])
    for width in range(1, 33):
        n = int(counts[width])
        if n:
            nbytes = (width + 7) // 8
            words = low[pos:pos + n].astype(">u4").view(np.uint8).reshape(n, 4)[:, 4 - nbytes:]
            bits = np.unpackbits(np.ascontiguousarray(words).reshape(-1))  # whole rows of 8
            pieces.append(bits.reshape(n, 8 * nbytes)[:, 8 * nbytes - width:].reshape(-1))
            pos += n
    bits = np.concatenate(pieces) if pieces else np.zeros(0, np.uint8)
    return np.packbits(bits)


def _parts(symbols: np.ndarray[Any, Any], extra: int
           ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """(b, e, k) uint8 of the symbols."""
    b = symbols >> np.uint8(extra)
    below = np.maximum(b, np.uint8(1)) - np.uint8(1)
    e = np.minimum(below, np.uint8(extra))
    return b, e, below - e


def _low_counts(symbols: np.ndarray[Any, Any], extra: int) -> np.ndarray[Any, Any]:
    return np.bincount(np.minimum(_parts(symbols, extra)[2], 32), minlength=33)[:33].astype(
        np.int64)


def unpack(symbols: np.ndarray[Any, Any], extra: int, counts: np.ndarray[Any, Any],
           low_bytes: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """The zigzag residuals (uint32) of the symbols and the low-bit stream (``counts``:
    values per low-bit count, :attr:`ResidualCoder.low_counts`)."""
    b, e, k = _parts(symbols, extra)
    n = symbols.size
    top = (symbols & ((np.uint8(1) << e) - np.uint8(1))).astype(np.uint32)
    z = np.where(b > 0, np.uint32(1) << (np.maximum(b, 1) - 1).astype(np.uint32), np.uint32(0))
    z |= top << k.astype(np.uint32)
    total = int((counts * np.arange(counts.size)).sum())
    bits = np.unpackbits(low_bytes, count=total)
    order = np.argsort(k, kind="stable")
    low = np.zeros(n, np.uint32)
    pos, start = int(counts[0]), 0
    for width in range(1, 33):
        m = int(counts[width])
        if m:
            nbytes = (width + 7) // 8
            grid = np.zeros((m, 8 * nbytes), np.uint8)
            grid[:, 8 * nbytes - width:] = bits[start:start + m * width].reshape(m, width)
            packed = np.zeros((m, 4), np.uint8)
            packed[:, 4 - nbytes:] = np.packbits(grid.reshape(-1)).reshape(m, nbytes)
            low[pos:pos + m] = packed.view(">u4").reshape(-1)
            pos += m
            start += m * width
    z[order] |= low
    return z


def _residuals(x: np.ndarray[Any, Any], valid: np.ndarray[Any, Any] | None, predictor: int,
               ref: np.ndarray[Any, Any] | None) -> np.ndarray[Any, Any]:
    return masked_residuals(x, valid, predictor, ref).astype(np.uint32)


def _costs(x: np.ndarray[Any, Any], valid: np.ndarray[Any, Any] | None,
           ref: np.ndarray[Any, Any] | None) -> np.ndarray[Any, Any]:
    out = np.full(5, -1, np.int64)
    for predictor in range(5 if ref is not None else 4):
        out[predictor] = int(bitlen(_residuals(x, valid, predictor, ref)).sum(dtype=np.int64))
    return out


@functools.lru_cache(maxsize=4)
def symbol_tables(extra: int) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """(value bits above the low bits, low-bit count k) of every symbol byte with ``extra``,
    int64[256] each (bit lengths above 32 give k = 32: the decoder rejects them first)."""
    base = np.zeros(256, np.int64)
    kk = np.zeros(256, np.int64)
    for s in range(256):
        b = s >> extra
        below = max(b - 1, 0)
        e = min(below, extra)
        kk[s] = min(below - e, 32)
        if 0 < b <= 32:
            base[s] = (1 << below) | ((s & ((1 << e) - 1)) << int(kk[s]))
    return base, kk


def _decode(symbols: np.ndarray[Any, Any], extra: int, counts: np.ndarray[Any, Any],
            low: np.ndarray[Any, Any], valid: np.ndarray[Any, Any] | None, predictor: int,
            ref: np.ndarray[Any, Any] | None, out: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    out[...] = unmask_residuals(unpack(symbols, extra, counts, low).astype(out.dtype), valid,
                                out.shape, predictor, ref)
    return out


def _quantise(v: np.ndarray[Any, Any], step: float
              ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    with np.errstate(invalid="ignore", over="ignore"):
        qf = np.rint(v.astype(np.float64) / step)
        q = np.where(np.abs(qf) < 2**31, qf, 0.0).astype(np.int32)
    exc = _dequantise(q, step).view(np.uint32) != v.view(np.uint32)
    q[exc] = 0
    return q, exc


def _dequantise(q: np.ndarray[Any, Any], step: float) -> np.ndarray[Any, Any]:
    return (q.astype(np.float64) * step).astype(np.float32)


#: The reference coder (numpy, one pass per bit width).
NUMPY = ResidualCoder("numpy", _symbols, _pack_low, _low_counts, _residuals, _costs, _decode,
                      _quantise, _dequantise, roll)
