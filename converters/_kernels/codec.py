"""Optional compiled (numba) path of :mod:`lidarscan.codec`: the residual bit-length coding.

The format's version 2 residual coding (methods PREDICT2 and QUANT2, spec in the header of
:mod:`lidarscan.codec`) turns zigzag residuals into one symbol byte per value plus a bit stream
of low bits grouped by their width. Its numpy reference (:mod:`lidarscan._codec_bits`, the test
oracle) makes one pass per bit width; the kernels here make one pass over the values and must
give the same bytes (integer arithmetic only: bit-identical by construction, and tested so).

Three kernels, the same arguments as the reference functions they replace:

* ``symbols(z, table)``: (symbols with extra 1, k with extra 1, symbols with extra 2, k with
  extra 2) of uint32 zigzag residuals, ``table`` the uint8 bit length of 0 .. 65535;
* ``pack_low(z, k)``: the low-bit stream (uint8) of the values ``z`` with ``k`` low bits each;
* ``low_counts(symbols, extra)`` and ``unpack(symbols, extra, counts, low)``: the inverse.

:func:`coder` bundles them as a :class:`lidarscan.codec.ResidualCoder`, the object
``compress_scan`` / ``decompress_scan`` take (``coder=``); it is chosen by
:func:`converters._kernels.select` (``"codec"``), which reads the switches. The core package
never imports this module (layering): converters-level entry points pass the coder.
"""

from __future__ import annotations

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
    out = np.zeros((bit + 7) // 8, np.uint8)
    for i in range(z.shape[0]):
        rem = np.int64(k[i])
        if rem == 0:
            continue
        p = start[rem]
        start[rem] = p + rem
        v = np.int64(z[i])
        while rem > 0:
            off = p & 7
            take = 8 - off if 8 - off < rem else rem
            bits = (v >> (rem - take)) & ((1 << take) - 1)
            out[p >> 3] |= np.uint8(bits << (8 - off - take))
            p += take
            rem -= take
    return out


def _low_counts(symbols: Any, extra: int) -> Any:  # pragma: no cover - compiled
    """Number of values per low-bit width 0 .. 32 (int64) of the symbols."""
    counts = np.zeros(33, np.int64)
    for i in range(symbols.shape[0]):
        b = np.int64(symbols[i]) >> extra
        below = b - 1 if b > 0 else 0
        e = below if below < extra else extra
        k = below - e
        if k > 32:
            k = 32
        counts[k] += 1
    return counts


def _unpack(symbols: Any, extra: int, counts: Any, low: Any) -> Any:  # pragma: no cover
    """uint32 zigzag residuals of the symbols and the low-bit stream (the caller checked the
    bit lengths and the stream's size against ``counts``)."""
    start = np.zeros(33, np.int64)
    bit = 0
    for w in range(33):
        start[w] = bit
        bit += counts[w] * w
    n = symbols.shape[0]
    out = np.empty(n, np.uint32)
    for i in range(n):
        s = np.int64(symbols[i])
        b = s >> extra
        below = b - 1 if b > 0 else 0
        e = below if below < extra else extra
        k = below - e
        v = np.int64(0)
        if b > 0:
            v = (np.int64(1) << below) | ((s & ((1 << e) - 1)) << k)
        if k:
            p = start[k]
            start[k] = p + k
            rem = k
            acc = np.int64(0)
            while rem > 0:
                off = p & 7
                take = 8 - off if 8 - off < rem else rem
                byte = np.int64(low[p >> 3])
                acc = (acc << take) | ((byte >> (8 - off - take)) & ((1 << take) - 1))
                p += take
                rem -= take
            v |= acc
        out[i] = np.uint32(v & 0xFFFFFFFF)
    return out


def _load() -> Any:
    fns = [numba_jit(fn, boundscheck=False) for fn in (_symbols, _pack_low, _low_counts,
                                                       _unpack)]
    if fns[0] is None:
        return None
    from lidarscan.codec import ResidualCoder
    return ResidualCoder("numba", *fns)


_COMPILED = LoadOnce(_load)


def coder() -> Any:
    """The compiled :class:`lidarscan.codec.ResidualCoder`, or None without numba. Callers go
    through :func:`converters._kernels.select` (``"codec"``), which honours
    ``LIDARSCAN_NUMBA``."""
    return _COMPILED.get()
