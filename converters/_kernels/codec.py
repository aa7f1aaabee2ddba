"""Optional compiled (numba) path of :mod:`lidarscan.codec`: prediction and residual coding.

The format's version 2 residual coding (methods PREDICT2 and QUANT2, spec in the header of
:mod:`lidarscan.codec`) predicts every pixel of a channel grid, turns the zigzag residuals into
one symbol byte per value plus a bit stream of low bits grouped by their width. Its numpy
reference (:mod:`lidarscan._codec_bits`, the test oracle) makes one pass per predictor step
and per bit width; the kernels here make one pass over the values and give the same bytes
(integer arithmetic only: bit-identical by construction, and tested so).

:func:`coder` bundles them as a :class:`lidarscan.codec.ResidualCoder` (the fields and their
arguments are documented there: ``symbols``, ``pack_low``, ``low_counts``, ``unpack``,
``residuals``, ``unresiduals``, ``costs``); ``compress_scan`` / ``decompress_scan`` take it as
``coder=``. It is chosen by :func:`converters._kernels.select` (``"codec"``), which reads the
switches. The core package never imports this module (layering): converters-level entry
points (the evidence, the bench, ``McapWriter(codec_coder=...)`` from the CLI) pass it.

The grid kernels take flattened C-order arrays plus the shape (H, W, C); the wrappers in
:func:`_load` flatten, pad the low-bit stream by 5 bytes (the 40-bit read window) and stand in
x for an absent reference grid (only predictor 4 reads it).
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from converters._kernels._loader import LoadOnce, numba_jit


def _symbols(z: Any, table: Any) -> Any:  # pragma: no cover - compiled
    """z (n,) uint32 -> (sym1, k1, sym2, k2) (n,) uint8 each (see the reference)."""
    n = z.shape[0]
    sym1 = np.empty(n, np.uint8)
    k1 = np.empty(n, np.uint8)
    sym2 = np.empty(n, np.uint8)
    k2 = np.empty(n, np.uint8)
    for i in range(n):
        v = np.int64(z[i])
        hi = v >> 16
        b = np.int64(table[hi]) + 16 if hi else np.int64(table[v])
        below = b - 1 if b > 0 else 0
        e2 = below if below < 2 else 2
        kk2 = below - e2
        top2 = (v >> kk2) & ((1 << e2) - 1)
        if below >= 2:
            top1 = top2 >> 1
            kk1 = kk2 + 1
        else:
            top1 = top2
            kk1 = kk2
        sym1[i] = np.uint8(((b << 1) | top1) & 0xFF)
        k1[i] = np.uint8(kk1)
        sym2[i] = np.uint8(((b << 2) | top2) & 0xFF)
        k2[i] = np.uint8(kk2)
    return sym1, k1, sym2, k2


def _pack_low(z: Any, k: Any) -> Any:  # pragma: no cover - compiled
    """The low-bit stream: values grouped by k ascending (value order inside a group), each
    value's k low bits most significant first, packed MSB first, zero padded."""
    counts = np.zeros(33, np.int64)
    for i in range(k.shape[0]):
        counts[k[i]] += 1
    start = np.zeros(33, np.int64)
    bit = 0
    for w in range(33):
        start[w] = bit
        bit += counts[w] * w
    nbytes = (bit + 7) // 8
    out = np.zeros(nbytes + 5, np.uint8)  # + 5: a 40-bit window never leaves the array
    for i in range(z.shape[0]):
        w = np.int64(k[i])
        if w == 0:
            continue
        p = start[w]
        start[w] = p + w
        win = (np.int64(z[i]) & ((np.int64(1) << w) - 1)) << (40 - (p & 7) - w)
        at = p >> 3
        out[at] |= np.uint8(win >> 32)
        out[at + 1] |= np.uint8((win >> 24) & 0xFF)
        out[at + 2] |= np.uint8((win >> 16) & 0xFF)
        out[at + 3] |= np.uint8((win >> 8) & 0xFF)
        out[at + 4] |= np.uint8(win & 0xFF)
    return out[:nbytes]


@functools.lru_cache(maxsize=4)
def _symbol_tables(extra: int) -> tuple[Any, Any]:
    """(value bits above the low bits, low-bit count k) of every symbol byte, int64[256]."""
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


def _low_counts(symbols: Any, kk: Any) -> Any:  # pragma: no cover - compiled
    """Number of values per low-bit width 0 .. 32 (int64) of the symbols (kk: the symbols'
    low-bit counts, :func:`_symbol_tables`)."""
    hist = np.zeros(256, np.int64)
    for i in range(symbols.shape[0]):
        hist[symbols[i]] += 1
    counts = np.zeros(33, np.int64)
    for s in range(256):
        counts[kk[s]] += hist[s]
    return counts


def _unpack(symbols: Any, base: Any, kk: Any, counts: Any, low: Any
            ) -> Any:  # pragma: no cover - compiled
    """uint32 zigzag residuals of the symbols and the low-bit stream (the caller checked the
    bit lengths and the stream's size against ``counts``; ``low`` padded with 5 zero bytes;
    base, kk: :func:`_symbol_tables`)."""
    start = np.zeros(33, np.int64)
    bit = 0
    for w in range(33):
        start[w] = bit
        bit += counts[w] * w
    n = symbols.shape[0]
    out = np.empty(n, np.uint32)
    for i in range(n):
        s = symbols[i]
        v = base[s]
        k = kk[s]
        if k:
            p = start[k]
            start[k] = p + k
            at = p >> 3
            win = ((np.int64(low[at]) << 32) | (np.int64(low[at + 1]) << 24)
                   | (np.int64(low[at + 2]) << 16) | (np.int64(low[at + 3]) << 8)
                   | np.int64(low[at + 4]))
            v |= (win >> (40 - (p & 7) - k)) & ((np.int64(1) << k) - 1)
        out[i] = np.uint32(v & 0xFFFFFFFF)
    return out


def _bitsum(z: Any, table: Any) -> Any:  # pragma: no cover - compiled
    """Sum of the bit lengths (int64) of uint32 values; ``table``: bit lengths of 0..65535."""
    total = np.int64(0)
    for i in range(z.shape[0]):
        v = np.int64(z[i])
        hi = v >> 16
        total += np.int64(table[hi]) + 16 if hi else np.int64(table[v])
    return total


def _grid(x: Any, g: Any, z: Any, valid: Any, predictor: int, ref: Any, decode: bool, h: int,
          w: int, c: int) -> int:  # pragma: no cover - compiled
    """Prediction of an unsigned grid (H, W, C flattened; valid likewise, or None: every pixel
    valid; predictors 0..4: none, left, up, planar, the reference grid ``ref``), in row-major
    order; an invalid pixel holds its own prediction, and g (like x, written) is the grid the
    predictions read. Encoding (``decode`` False): the zigzag residuals of the valid pixels of
    x go to z (uint32). Decoding: g is written from the residuals z (x is not read). Returns
    the number of valid pixels."""
    bits = g.itemsize * 8
    mask = (np.int64(1) << bits) - 1
    half = np.int64(1) << (bits - 1)
    row = w * c
    j = 0
    for r in range(h):
        base = r * row
        for i in range(base, base + row):
            p = np.int64(0)
            if predictor == 1:
                if i - base >= c:
                    p = np.int64(g[i - c])
            elif predictor == 2:
                if r > 0:
                    p = np.int64(g[i - row])
            elif predictor == 3:
                if i - base >= c:
                    p += np.int64(g[i - c])
                    if r > 0:
                        p -= np.int64(g[i - row - c])
                if r > 0:
                    p += np.int64(g[i - row])
            elif predictor == 4:
                p = np.int64(ref[i])
            if valid is None or valid[i]:
                if decode:
                    zz = np.int64(z[j])
                    p += (zz >> 1) ^ -(zz & 1)
                else:
                    d = (np.int64(x[i]) - p) & mask
                    if d >= half:
                        d -= mask + 1
                    z[j] = np.uint32(((d << 1) ^ (d >> 63)) & mask)
                    p = np.int64(x[i])
                j += 1
            g[i] = p & mask
    return j


def _load() -> Any:
    fns = [numba_jit(fn, boundscheck=False) for fn in (_symbols, _pack_low, _low_counts,
                                                       _unpack, _grid, _bitsum)]
    if fns[0] is None:
        return None
    from lidarscan._codec_bits import ResidualCoder, bitlen_table
    symbols, pack_low, low_counts, unpack, grid, bitsum = fns

    def flat(a: Any) -> Any:
        return None if a is None else np.ascontiguousarray(a).reshape(-1)

    def residuals_of(x: Any, valid: Any, predictor: int, ref: Any) -> Any:
        # ref None: any array of x's type (only the REF predictor reads it)
        z = np.empty(x.size, np.uint32)
        flat_x = flat(x)
        n = grid(flat_x, np.empty_like(flat_x), z, flat(valid), predictor,
                 flat(x if ref is None else ref), False, *x.shape)
        return z[:n]

    def unresiduals_of(z: Any, valid: Any, predictor: int, ref: Any, out: Any) -> Any:
        g = out.reshape(-1)
        grid(g, g, z, flat(valid), predictor, flat(out if ref is None else ref), True,
             *out.shape)
        return out

    def low_counts_of(symbols_: Any, extra: int) -> Any:
        return low_counts(symbols_, _symbol_tables(extra)[1])

    def unpack_of(symbols_: Any, extra: int, counts: Any, low: Any) -> Any:
        return unpack(symbols_, *_symbol_tables(extra), counts,
                      np.concatenate([low, np.zeros(5, np.uint8)]))

    def costs_of(x: Any, valid: Any, ref: Any) -> Any:
        out = np.full(5, -1, np.int64)
        flat_x, flat_valid, flat_ref = flat(x), flat(valid), flat(x if ref is None else ref)
        for predictor in range(5 if ref is not None else 4):
            z = np.empty(x.size, np.uint32)
            n = grid(flat_x, np.empty_like(flat_x), z, flat_valid, predictor, flat_ref, False,
                     *x.shape)
            out[predictor] = bitsum(z[:n], bitlen_table())
        return out

    return ResidualCoder("numba", symbols, pack_low, low_counts_of, unpack_of, residuals_of,
                         unresiduals_of, costs_of)


_COMPILED = LoadOnce(_load)


def coder() -> Any:
    """The compiled :class:`lidarscan.codec.ResidualCoder`, or None without numba. Callers go
    through :func:`converters._kernels.select` (``"codec"``), which honours
    ``LIDARSCAN_NUMBA``."""
    return _COMPILED.get()
