"""Optional compiled (numba) path of :mod:`lidarscan.codec`: prediction and residual coding.

The format's version 2 residual coding (methods PREDICT2 and QUANT2, spec in the header of
:mod:`lidarscan.codec`) predicts every pixel of a channel grid, turns the zigzag residuals into
one symbol byte per value plus a bit stream of low bits grouped by their width; float32
channels go through an int32 grid first. Its numpy reference (:mod:`lidarscan.codec._bits`,
the test oracle) makes one pass per predictor step and per bit width; the kernels here make
one pass over the values and give the same bytes (integer arithmetic, and the same float64
products and float32 roundings for the float grid: bit-identical by construction, and tested
so): the predictor costs of all candidates in one pass (without a mask: a vectorised loop per
row; with one: branch-free, the fill values to the left carried in registers), residuals with
one loop per predictor when no pixel is masked (branch-free when one is), symbols of both
symbol splits in one branch-free (vectorised) pass, the low-bit packing, the float32 grid
(quantisation and its inverse), the destaggering roll, and on decoding a branch-free
unpacking into residuals followed by one loop per predictor. Bit lengths come from two small
LLVM intrinsics (:func:`_make_bitlen`: an exact float64 exponent where the loop vectorises,
count-leading-zeros where it does not); the wrappers' own large temporaries are reused per
thread (:func:`_scratch`). Loops that must vectorise (or merely run without a branch per
access) index row views from 0 or use unsigned indices: a signed index numba cannot prove
non-negative (``x[i - c]``) gets a negative-index wraparound check, which keeps a loop scalar.

:func:`coder` bundles them, with format version 3's fit and prediction
(:mod:`lidarscan.codec._compiled_v3`), as a :class:`lidarscan.codec.ResidualCoder` (the fields
and their arguments are documented there): the default coder of ``compress_scan`` /
``decompress_scan`` when numba is installed, chosen by :func:`lidarscan.codec.residual_coder`,
which honours the switch ``LIDARSCAN_NUMBA`` (:mod:`lidarscan._backends`). Importing this
module imports no numba: :func:`coder` compiles the kernels (or loads them from numba's
on-disk cache) at its first call.

The grid kernels take flattened C-order arrays plus the shape (H, W, C); the wrappers in
:func:`_load` flatten, pad the low-bit stream by 5 bytes (the 40-bit read window) and stand in
x for an absent reference grid (only predictor 4 reads it).
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

from lidarscan._backends import LoadOnce, numba_jit

_SCRATCH = threading.local()


def _scratch(name: str, n: int, dtype: Any) -> Any:
    """This thread's work array ``name`` of n values of ``dtype`` (contents undefined), kept
    and reused from call to call: a fresh megabyte-sized array costs a page fault per 4 KiB
    page at its first writes, a large part of a kernel's time. Only for a wrapper's own
    temporaries, never for what it returns."""
    pool = getattr(_SCRATCH, "pool", None)
    if pool is None:
        pool = _SCRATCH.pool = {}
    key = (name, np.dtype(dtype).str)
    got = pool.get(key)
    if got is None or got.size < n:
        got = pool[key] = np.empty(max(n, 1), dtype)
    return got[:n]


#: bit length of an integer below 2**32 (0 for 0), two LLVM intrinsics (:func:`_make_bitlen`)
#: set by :func:`_load` before any kernel compiles: ``_bitlen`` for vectorised loops,
#: ``_clzlen`` (count leading zeros) for scalar ones
_bitlen: Any = None
_clzlen: Any = None


def _make_bitlen() -> tuple[Any, Any]:
    """The numba intrinsics ``(bitlen, clzlen)(x) -> int64`` of an integer 0 <= x < 2**32.
    bitlen is branch-free and vectorisable (AVX2 has no vector count-leading-zeros): the
    float64 2**52 + x (its bit pattern: 2**52's exponent ORed with x) minus 2**52 is x exactly;
    its biased exponent minus 1022 is the bit length of x >= 1 (0 for x = 0, clamped). clzlen
    is 64 - ctlz(x), one instruction in a scalar loop."""
    from llvmlite import ir
    from numba.core import types
    from numba.extending import intrinsic

    i64, f64 = ir.IntType(64), ir.DoubleType()

    def of_int64(body: Any) -> Any:
        """An intrinsic ``f(x) -> int64`` of any integer x, computed by ``body(builder,
        x as i64)``."""
        @intrinsic  # type: ignore[misc]
        def fn(typingctx: Any, x: Any) -> Any:
            if not isinstance(x, types.Integer):
                return None

            def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
                return body(builder, context.cast(builder, args[0], signature.args[0],
                                                  types.int64))
            return types.int64(x), codegen
        return fn

    def bitlen(builder: Any, v: Any) -> Any:
        f = builder.bitcast(builder.or_(v, ir.Constant(i64, 0x4330000000000000)), f64)
        f = builder.fsub(f, ir.Constant(f64, 4503599627370496.0))
        e = builder.sub(builder.lshr(builder.bitcast(f, i64), ir.Constant(i64, 52)),
                        ir.Constant(i64, 1022))
        zero = ir.Constant(i64, 0)
        return builder.select(builder.icmp_signed("<", e, zero), zero, e)

    def clzlen(builder: Any, v: Any) -> Any:
        clz = builder.ctlz(v, ir.Constant(ir.IntType(1), 0))
        return builder.sub(ir.Constant(i64, 64), clz)

    return of_int64(bitlen), of_int64(clzlen)


def _zbits(d: Any, mask: Any, half: Any) -> Any:  # pragma: no cover - compiled
    """Bit length of zigzag(d) for a difference d of values of a grid of ``mask``'s width
    (wrapping: d is reduced to that width's signed range first); vectorisable."""
    d = ((d & mask) ^ half) - half
    return _bitlen(((d << 1) ^ (d >> 63)) & mask)


def _zbits_scalar(d: Any, mask: Any, half: Any) -> Any:  # pragma: no cover - compiled
    """:func:`_zbits` for scalar loops (count leading zeros)."""
    d = ((d & mask) ^ half) - half
    return _clzlen(((d << 1) ^ (d >> 63)) & mask)


def _symbols(z: Any) -> Any:  # pragma: no cover - compiled
    """z (n,) uint32 -> (sym1, k1, sym2, k2) (n,) uint8 each and the low-bit totals (bits1,
    bits2) (see the reference), branch-free (vectorised): bit length b, bm = b - 1 bits below
    the leading one (0 for z = 0), k2 = bm - min(bm, 2) low bits and the e2 = min(bm, 2) top
    bits of extra 2; extra 1 keeps one top bit less when bm >= 2 ("wide")."""
    n = z.shape[0]
    sym1 = np.empty(n, np.uint8)
    k1 = np.empty(n, np.uint8)
    sym2 = np.empty(n, np.uint8)
    k2 = np.empty(n, np.uint8)
    bits1 = bits2 = np.int64(0)
    for i in range(n):
        v = np.int64(z[i])
        b = _bitlen(v)
        bm = max(b - 1, 0)
        kk2 = max(bm - 2, 0)
        top2 = (v >> kk2) & ((np.int64(1) << (bm - kk2)) - 1)
        wide = np.int64(bm >= 2)
        sym1[i] = np.uint8(((b << 1) | (top2 >> wide)) & 0xFF)
        k1[i] = np.uint8(kk2 + wide)
        sym2[i] = np.uint8(((b << 2) | top2) & 0xFF)
        k2[i] = np.uint8(kk2)
        bits1 += kk2 + wide
        bits2 += kk2
    return sym1, k1, sym2, k2, bits1, bits2


def _pack_low(z: Any, k: Any) -> Any:  # pragma: no cover - compiled
    """The low-bit stream: values grouped by k ascending (value order inside a group), each
    value's k low bits most significant first, packed MSB first, zero padded. One 64-bit
    accumulator per group, flushed 4 bytes at a time into the group's bytes (ORed: a group's
    first and last byte may hold bits of its neighbours)."""
    counts = np.zeros(33, np.int64)
    for i in range(k.shape[0]):
        counts[k[i]] += 1
    pos = np.zeros(33, np.int64)
    nb = np.zeros(33, np.int64)
    acc = np.zeros(33, np.uint64)
    bit = 0
    for w in range(33):
        pos[w] = bit >> 3
        nb[w] = bit & 7
        bit += counts[w] * w
    nbytes = (bit + 7) // 8
    out = np.zeros(nbytes + 8, np.uint8)
    for i in range(z.shape[0]):
        g = k[i]  # unsigned indices (g, p): no negative-index wraparound checks
        w = np.int64(g)
        n = nb[g] + w
        a = (acc[g] << np.uint64(w)) | np.uint64(np.int64(z[i]) & ((np.int64(1) << w) - 1))
        if n >= 32:
            n -= 32
            top = a >> np.uint64(n)
            p = np.uint64(pos[g])
            out[p] |= np.uint8((top >> np.uint64(24)) & np.uint64(0xFF))
            out[p + np.uint64(1)] |= np.uint8((top >> np.uint64(16)) & np.uint64(0xFF))
            out[p + np.uint64(2)] |= np.uint8((top >> np.uint64(8)) & np.uint64(0xFF))
            out[p + np.uint64(3)] |= np.uint8(top & np.uint64(0xFF))
            pos[g] = p + np.uint64(4)
            a &= (np.uint64(1) << np.uint64(n)) - np.uint64(1)
        acc[g] = a
        nb[g] = n
    for w in range(1, 33):  # the rest of each group, left-aligned in its last bytes
        n = nb[w]
        a = acc[w]
        p = pos[w]
        while n >= 8:
            n -= 8
            out[p] |= np.uint8((a >> np.uint64(n)) & np.uint64(0xFF))
            p += 1
        if n:
            out[p] |= np.uint8((a << np.uint64(8 - n)) & np.uint64(0xFF))
    return out[:nbytes]


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


def _grid(x: Any, g: Any, z: Any, valid: Any, predictor: int, ref: Any, h: int, w: int, c: int
          ) -> int:  # pragma: no cover - compiled
    """The zigzag residuals (uint32, to z: n values of room) of the valid pixels of an
    unsigned grid x (H, W, C flattened; valid likewise; predictors 0..4: none, left, up,
    planar, the reference grid ``ref``), in row-major order; an invalid pixel holds its own
    prediction, and g (like x, written) is the grid the predictions read. Branch-free: the
    prediction is a1 * left + a2 * up - a3 * up-left + a4 * ref with the predictor's 0/1
    coefficients; per row and count index the left and up-left fill values are carried in
    registers (the left predictor with C = 1 has a loop of its own that neither reads nor
    writes g). With C = 1 the residuals are written compacted as they come; else every
    pixel's goes to its own index and the row's valid ones are moved forward after the row
    (in place: the write index never passes the read index). Returns the number of valid
    pixels."""
    bits = g.itemsize * 8
    mask = (np.int64(1) << bits) - 1
    half = np.int64(1) << (bits - 1)
    a1 = np.int64(predictor == 1 or predictor == 3)
    a2 = np.int64(predictor == 2 or predictor == 3)
    a3 = np.int64(predictor == 3)
    a4 = np.int64(predictor == 4)
    one = c == 1
    row = w * c
    j = 0
    if predictor == 1 and one:  # left, one value per cell: only the fill value is carried
        for r in range(h):
            f = np.int64(0)
            xr, vr = x[r * w:r * w + w], valid[r * w:r * w + w]  # indexed from 0: no wraparound
            for t in range(w):
                v = np.int64(xr[t])
                d = (((v - f) & mask) ^ half) - half
                z[j] = np.uint32(((d << 1) ^ (d >> 63)) & mask)
                ok = vr[t]
                j += np.int64(ok)
                f = v if ok else f
        return j
    for r in range(h):
        base = r * row
        for kx in range(c):
            f = corner = np.int64(0)  # the left neighbour's fill value, the up-left one's
            for t in range(w):  # a unit-step loop: faster than a range with a variable step
                i = base + kx + t * c
                up = np.int64(g[i - row]) if r > 0 else np.int64(0)
                p = (a1 * f + a2 * up - a3 * corner + a4 * np.int64(ref[i])) & mask
                corner = up
                v = np.int64(x[i])
                d = (((v - p) & mask) ^ half) - half
                z[j if one else i] = np.uint32(((d << 1) ^ (d >> 63)) & mask)
                ok = valid[i]
                j += np.int64(ok)
                f = v if ok else p
                g[i] = f
        if not one:
            j -= np.int64(valid[base:base + row].sum())
            for i in range(base, base + row):
                z[j] = z[i]
                j += np.int64(valid[i])
    return j


def _unpack_grid(symbols: Any, sbase: Any, kk: Any, counts: Any, low: Any, valid: Any,
                 d: Any) -> int:  # pragma: no cover - compiled
    """The signed residuals d (int64, one per pixel, 0 at invalid ones) from the symbols and
    the low-bit stream (``low`` padded with 5 zero bytes; sbase, kk: ``symbol_tables``),
    branch-free. Returns the symbols used."""
    start = np.zeros(33, np.int64)
    bit = 0
    for k in range(33):
        start[k] = bit
        bit += counts[k] * k
    j = 0
    for i in range(d.shape[0]):
        if valid is None or valid[i]:
            s = symbols[j]
            k = kk[s]
            ku = np.uint64(k)  # unsigned indices (ku, at): no negative-index wraparound
            q = start[ku]  # k = 0 reads a window and keeps none of it
            start[ku] = q + k
            at = np.uint64(q >> 3)
            win = ((np.int64(low[at]) << 32) | (np.int64(low[at + np.uint64(1)]) << 24)
                   | (np.int64(low[at + np.uint64(2)]) << 16)
                   | (np.int64(low[at + np.uint64(3)]) << 8) | np.int64(low[at + np.uint64(4)]))
            zz = sbase[s] | ((win >> (40 - (q & 7) - k)) & ((np.int64(1) << k) - 1))
            d[i] = (zz >> 1) ^ -(zz & 1)
            j += 1
        else:
            d[i] = 0
    return j


def _unpredict(d: Any, g: Any, predictor: int, ref: Any, h: int, w: int, c: int
               ) -> None:  # pragma: no cover - compiled
    """g (unsigned, flattened (H, W, C)) from the signed residuals d of every pixel (0 at
    masked ones: they hold their prediction), one loop per predictor, wrapping."""
    mask = (np.int64(1) << (g.itemsize * 8)) - 1
    row = w * c
    n = h * row
    if predictor == 0:
        for i in range(n):
            g[i] = d[i] & mask
    elif predictor == 4:
        for i in range(n):
            g[i] = (np.int64(ref[i]) + d[i]) & mask
    elif predictor == 2:
        for i in range(min(row, n)):
            g[i] = d[i] & mask
        for r in range(1, h):  # row views indexed from 0: no negative-index wraparound
            base = r * row
            dr, gr, gu = d[base:base + row], g[base:base + row], g[base - row:base]
            for t in range(row):
                gr[t] = (np.int64(gu[t]) + dr[t]) & mask
    else:
        for r in range(h):
            base = r * row
            dr, gr = d[base:base + row], g[base:base + row]
            gu = g[base - row:base] if r > 0 else gr  # read only when r > 0
            planar = predictor == 3 and r > 0
            for k in range(c):  # one running sum per count index along the row
                acc = np.int64(0)
                for t in range(w):
                    i = np.uint64(k + t * c)  # unsigned: no wraparound checks
                    acc += dr[i]
                    if planar:
                        gr[i] = (acc + np.int64(gu[i])) & mask
                    else:
                        gr[i] = acc & mask


def _quantise(v: Any, step: float, q: Any, exc: Any) -> int:  # pragma: no cover - compiled
    """q = rint(v / step) (int32; 0 where it does not fit or the value is an exception) and
    the exception flags (float32(float64(q) * step) does not have v's bits) of float32 v, as
    ``lidarscan.codec._quantise``. Returns the number of exceptions."""
    n_exc = 0
    bits = v.view(np.uint32)
    for i in range(v.shape[0]):  # branch-free
        vi = v[i]
        qf = np.rint(np.float64(vi) / step)
        qi = np.int32(qf if abs(qf) < 2147483648.0 else 0.0)
        back = np.float32(np.float64(qi) * step)
        # back is finite and a zero of it is +0.0: equal bits unless v is -0.0
        bad = (back != vi) | ((back == 0) & (bits[i] != 0))
        exc[i] = bad
        q[i] = np.int32(0) if bad else qi
        n_exc += np.int64(bad)
    return n_exc


def _dequantise(q: Any, step: float, out: Any) -> None:  # pragma: no cover - compiled
    """out (float32) = float32(float64(q) * step) of the int32 grid q."""
    for i in range(q.shape[0]):
        out[i] = np.float32(np.float64(q[i]) * step)


def _costs(x: Any, valid: Any, ref: Any, nref: int, h: int, w: int, c: int,
           g2: Any, g3: Any) -> Any:  # pragma: no cover - compiled
    """The sums of the residuals' bit lengths under predictors 0 .. 3 (and 4 when ``nref``)
    of the valid pixels, in one pass (int64[5], -1 for REF without a reference). A masked
    pixel holds each predictor's own prediction: the left and planar fill values to the left
    are carried in registers (per row and count index), the up and planar ones of the row
    above read g2, g3 (int64 like x, written: the fill grids). Branch-free. Without a mask:
    :func:`_costs_plain`."""
    bits = x.itemsize * 8
    mask = (np.int64(1) << bits) - 1
    half = np.int64(1) << (bits - 1)
    row = w * c
    s0 = s1 = s2 = s3 = s4 = np.int64(0)
    for r in range(h):
        base = r * row
        # row views, indexed by an unsigned index: no negative-index wraparound checks
        xr, vr, rr = x[base:base + row], valid[base:base + row], ref[base:base + row]
        g2r, g3r = g2[base:base + row], g3[base:base + row]
        g2u = g2[base - row:base] if r > 0 else g2r  # read only when r > 0
        g3u = g3[base - row:base] if r > 0 else g3r
        for kx in range(c):
            f1 = f3 = corner = np.int64(0)
            for t in range(w):  # a unit-step loop: faster than a range with a variable step
                i = np.uint64(kx + t * c)
                up2 = np.int64(g2u[i]) if r > 0 else np.int64(0)
                up3 = np.int64(g3u[i]) if r > 0 else np.int64(0)
                p3 = (f3 + up3 - corner) & mask
                corner = up3
                v = np.int64(xr[i])
                ok = vr[i]
                on = np.int64(ok)
                s0 += on * _zbits_scalar(v, mask, half)
                s1 += on * _zbits_scalar(v - f1, mask, half)
                s2 += on * _zbits_scalar(v - up2, mask, half)
                s3 += on * _zbits_scalar(v - p3, mask, half)
                if nref:
                    s4 += on * _zbits_scalar(v - np.int64(rr[i]), mask, half)
                f1 = v if ok else f1
                g2r[i] = v if ok else up2
                f3 = v if ok else p3
                g3r[i] = f3
    out = np.empty(5, np.int64)
    out[0], out[1], out[2], out[3], out[4] = s0, s1, s2, s3, s4 if nref else -1
    return out


def _costs_plain(x: Any, ref: Any, nref: int, h: int, w: int, c: int
                 ) -> Any:  # pragma: no cover - compiled
    """:func:`_costs` without a mask (every pixel valid; predictions read x itself); the loop
    over a row's inner pixels has no branch (vectorised: it indexes views of the row from 0,
    so that numba's negative-index wraparound, which stops vectorisation, is provably never
    taken)."""
    bits = x.itemsize * 8
    mask = (np.int64(1) << bits) - 1
    half = np.int64(1) << (bits - 1)
    row = w * c
    m = row - c  # the cells with a left neighbour, from index c of the row
    s0 = s1 = s2 = s3 = s4 = np.int64(0)
    for r in range(h):
        base = r * row
        xr = x[base:base + row]
        up = x[base - row:base] if r > 0 else xr  # read only when r > 0
        for k in range(min(c, row)):  # first cell: no left neighbour
            v = np.int64(xr[k])
            u = np.int64(up[k]) if r > 0 else np.int64(0)
            s0 += _zbits(v, mask, half)
            s1 += _zbits(v, mask, half)
            s2 += _zbits(v - u, mask, half)
            s3 += _zbits(v - u, mask, half)
            if nref:
                s4 += _zbits(v - np.int64(ref[base + k]), mask, half)
        cur, left = xr[c:], xr[:m]
        if r == 0:
            for t in range(m):
                v = np.int64(cur[t])
                lv = np.int64(left[t])
                s0 += _zbits(v, mask, half)
                s1 += _zbits(v - lv, mask, half)
                s2 += _zbits(v, mask, half)
                s3 += _zbits(v - lv, mask, half)
        else:
            above, corner = up[c:], up[:m]
            for t in range(m):
                v = np.int64(cur[t])
                lv = np.int64(left[t])
                u = np.int64(above[t])
                s0 += _zbits(v, mask, half)
                s1 += _zbits(v - lv, mask, half)
                s2 += _zbits(v - u, mask, half)
                s3 += _zbits(v - lv - u + np.int64(corner[t]), mask, half)
        if nref:
            rr = ref[base + c:base + row]
            for t in range(m):
                s4 += _zbits(np.int64(cur[t]) - np.int64(rr[t]), mask, half)
    out = np.empty(5, np.int64)
    out[0], out[1], out[2], out[3], out[4] = s0, s1, s2, s3, s4 if nref else -1
    return out


def _residuals_plain(x: Any, z: Any, predictor: int, ref: Any, h: int, w: int, c: int
                     ) -> None:  # pragma: no cover - compiled
    """:func:`_grid` encoding without a mask, one loop per predictor (the predictions read x
    itself): z = zigzag residuals (uint32) of every pixel. The row loops index views of the
    row from 0 (vectorised, as in :func:`_costs_plain`)."""
    bits = x.itemsize * 8
    mask = (np.int64(1) << bits) - 1
    half = np.int64(1) << (bits - 1)
    row = w * c
    n = h * row
    m = row - c
    if predictor == 0:
        for i in range(n):
            d = ((np.int64(x[i]) & mask) ^ half) - half
            z[i] = np.uint32(((d << 1) ^ (d >> 63)) & mask)
    elif predictor == 4:
        for i in range(n):
            d = (((np.int64(x[i]) - np.int64(ref[i])) & mask) ^ half) - half
            z[i] = np.uint32(((d << 1) ^ (d >> 63)) & mask)
    else:
        for r in range(h):
            base = r * row
            xr = x[base:base + row]
            zr = z[base:base + row]
            up = x[base - row:base] if r > 0 else xr  # read only when r > 0
            for k in range(min(c, row)):
                d = np.int64(xr[k])
                if predictor >= 2 and r > 0:
                    d -= np.int64(up[k])
                d = ((d & mask) ^ half) - half
                zr[k] = np.uint32(((d << 1) ^ (d >> 63)) & mask)
            cur, left, out = xr[c:], xr[:m], zr[c:]
            if predictor == 1 or (predictor == 3 and r == 0):
                for t in range(m):
                    d = (((np.int64(cur[t]) - np.int64(left[t])) & mask) ^ half) - half
                    out[t] = np.uint32(((d << 1) ^ (d >> 63)) & mask)
            elif predictor == 2:
                if r == 0:
                    for t in range(m):
                        d = ((np.int64(cur[t]) & mask) ^ half) - half
                        out[t] = np.uint32(((d << 1) ^ (d >> 63)) & mask)
                else:
                    above = up[c:]
                    for t in range(m):
                        d = (((np.int64(cur[t]) - np.int64(above[t])) & mask) ^ half) - half
                        out[t] = np.uint32(((d << 1) ^ (d >> 63)) & mask)
            else:
                above, corner = up[c:], up[:m]
                for t in range(m):
                    d = (np.int64(cur[t]) - np.int64(left[t]) - np.int64(above[t])
                         + np.int64(corner[t]))
                    d = ((d & mask) ^ half) - half
                    out[t] = np.uint32(((d << 1) ^ (d >> 63)) & mask)


def _roll_rows(x: Any, shifts: Any, sign: int, c: int, out: Any
               ) -> None:  # pragma: no cover - compiled
    """Row r of x (H, W * C: rows of W cells of C values) rotated right by sign * shifts[r]
    cells into out (as ``lidarscan.codec._bits.roll``)."""
    h, n = x.shape
    cells = n // c
    for r in range(h):
        k = ((sign * shifts[r]) % cells) * c if cells else 0
        src, dst = x[r], out[r]
        head, tail = dst[k:], src[n - k:]  # views indexed from 0: vectorised copies
        for i in range(n - k):
            head[i] = src[i]
        for i in range(k):
            dst[i] = tail[i]


def _load() -> Any:
    global _bitlen, _clzlen, _zbits, _zbits_scalar
    try:
        _bitlen, _clzlen = _make_bitlen()
    except ImportError:
        return None
    _zbits = numba_jit(_zbits, inline="always")
    _zbits_scalar = numba_jit(_zbits_scalar, inline="always")
    fns = [numba_jit(fn, boundscheck=False) for fn in (
        _symbols, _pack_low, _low_counts, _grid, _costs, _costs_plain, _unpack_grid, _quantise,
        _dequantise, _residuals_plain, _roll_rows, _unpredict)]
    from lidarscan.codec._bits import ResidualCoder, roll, symbol_tables
    (symbols, pack_low, low_counts, grid, costs, costs_plain, unpack_grid, quantise,
     dequantise, residuals_plain, roll_rows, unpredict) = fns

    def flat(a: Any) -> Any:
        return None if a is None else np.ascontiguousarray(a).reshape(-1)

    def residuals_of(x: Any, valid: Any, predictor: int, ref: Any) -> Any:
        # ref None: any array of x's type (only the REF predictor reads it)
        z = np.empty(x.size, np.uint32)
        flat_x = flat(x)
        if valid is None:
            residuals_plain(flat_x, z, predictor, flat(x if ref is None else ref), *x.shape)
            return z
        n = grid(flat_x, _scratch("fill", x.size, x.dtype), z, flat(valid), predictor,
                 flat(x if ref is None else ref), *x.shape)
        return z[:n]

    def low_counts_of(symbols_: Any, extra: int) -> Any:
        return low_counts(symbols_, symbol_tables(extra)[1])

    def costs_of(x: Any, valid: Any, ref: Any) -> Any:
        flat_x = flat(x)
        flat_ref = flat(x if ref is None else ref)
        nref = 0 if ref is None else 1
        if valid is None:
            return costs_plain(flat_x, flat_ref, nref, *x.shape)
        return costs(flat_x, flat(valid), flat_ref, nref, *x.shape,
                     _scratch("up fill", x.size, np.int64),
                     _scratch("planar fill", x.size, np.int64))

    def decode_of(symbols_: Any, extra: int, counts: Any, low: Any, valid: Any,
                  predictor: int, ref: Any, out: Any) -> Any:
        padded = _scratch("low bits", low.size + 5, np.uint8)
        padded[:low.size] = low
        padded[low.size:] = 0
        d = _scratch("residuals", out.size, np.int64)
        unpack_grid(symbols_, *symbol_tables(extra), counts, padded, flat(valid), d)
        unpredict(d, out.reshape(-1), predictor, flat(out if ref is None else ref), *out.shape)
        return out

    def quantise_of(v: Any, step: float) -> Any:
        q = np.empty(v.size, np.int32)
        exc = np.empty(v.size, np.bool_)
        quantise(v, step, q, exc)
        return q, exc

    def dequantise_of(q: Any, step: float) -> Any:
        out = np.empty(q.size, np.float32)
        dequantise(q, step, out)
        return out

    def roll_of(x: Any, shifts: Any, sign: int) -> Any:
        if shifts is None or not x.dtype.isnative or x.ndim != 3:
            return roll(x, shifts, sign)
        out = np.empty(x.shape, x.dtype)
        roll_rows(np.ascontiguousarray(x).reshape(x.shape[0], -1), shifts, sign, x.shape[2],
                  out.reshape(x.shape[0], -1))
        return out

    def symbols_of(z: Any, table: Any) -> Any:  # table: the reference's, not needed
        return symbols(np.ascontiguousarray(z, np.uint32))

    from lidarscan.codec import _compiled_v3
    return ResidualCoder("numba", symbols_of, pack_low, low_counts_of, residuals_of, costs_of,
                         decode_of, quantise_of, dequantise_of, roll_of,
                         *(_compiled_v3.kernels() or ()))


_COMPILED = LoadOnce(_load)


def coder() -> Any:
    """The compiled :class:`lidarscan.codec.ResidualCoder`, or None without numba. Callers go
    through :func:`lidarscan.codec.residual_coder`, which honours ``LIDARSCAN_NUMBA``."""
    return _COMPILED.get()
