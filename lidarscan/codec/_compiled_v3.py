"""Optional compiled (numba) path of :mod:`lidarscan.codec._v3`: the XPREDICT fit and prediction.

Format version 3's method XPREDICT (spec in the header of :mod:`lidarscan.codec._v3`, which
holds the numpy reference and test oracle) predicts an integer block (Ouster reflectivity) from
a signal and a range block with integer tables; the residual grid is then coded as a PREDICT2
payload by the v2 coder. The kernels here give the same values as the reference, bit for bit:

* :func:`_residual` computes the prediction P of each pixel (integer arithmetic on the tables,
  64-bit wrapping products, and exact IEEE float32 words of the range and of the linear value)
  row by row into a small row buffer and, in the same pass, either the rolled residual
  ``roll(f - P)`` (encoding) or the restored block ``roll(d, -1) + P`` (decoding), so no
  full-size temporary (bins, linear values, prediction, residual before the roll) is made.
* :func:`_fit` fits the tables on the encoder's column subsample in one pass over the pixels
  and per-key medians by selection (a counting sort by key, then a three-way quickselect per
  key: the median of a multiset does not depend on the order, so the result equals the
  reference's sort), with the same float64 operations in the same order as the reference.

The float32 word of a value comes from one LLVM bitcast (:func:`_make_f32_bits`). Integer
values of at most 2**33 convert to float32 with one rounding in numpy and numba alike.

:func:`kernels` returns the pair ``(xfit, xpredict)`` that :func:`lidarscan.codec._compiled.coder`
puts into its :class:`lidarscan.codec._bits.ResidualCoder` (fields ``xfit`` and ``xpredict``,
documented there); nothing else imports this module.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lidarscan._backends import LoadOnce, numba_jit

#: the IEEE-754 word (int64, 0 .. 2**32 - 1) of a float32 value, an LLVM bitcast set by
#: :func:`_load` before any kernel compiles
_f32_bits: Any = None


def _make_f32_bits() -> Any:
    """The numba intrinsic ``f32_bits(x float32) -> int64``: the value's IEEE-754 word."""
    from llvmlite import ir
    from numba.core import types
    from numba.extending import intrinsic

    @intrinsic  # type: ignore[misc]
    def f32_bits(typingctx: Any, x: Any) -> Any:
        if x != types.float32:
            return None

        def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
            word = builder.bitcast(args[0], ir.IntType(32))
            return builder.zext(word, ir.IntType(64))
        return types.int64(x), codegen
    return f32_bits


def _row_prediction(sr: Any, rr: Any, gain: Any, row_gain: int, bin0: int, knee: int,
                    ubin0: int, comp: Any, top: int, p: Any) -> None:  # pragma: no cover
    """p (int64, one row) = the prediction P of the row's pixels from the signal row sr and
    the range row rr (native), ``row_gain`` the row's gain; branch-free."""
    ng = np.int64(gain.shape[0]) - 1
    nc = np.int64(comp.shape[0]) - 1
    for c in range(sr.shape[0]):
        word = _f32_bits(np.float32(rr[c]))
        ok = (word >= 1) & (word < 0x7F800000)  # 0 < r < +Inf (not +-0, negative or NaN)
        rb = min(max((word >> 18) - bin0, np.int64(0)), ng)
        u = np.int64(gain[np.uint64(rb)]) * row_gain * max(np.int64(sr[c]), np.int64(0))
        u = max((u + (np.int64(1) << 30)) >> 31, np.int64(0))  # int64, wrapping
        kb = min(max((_f32_bits(np.float32(u)) >> 20) - ubin0, np.int64(0)), nc)
        v = np.int64(comp[np.uint64(kb)]) if u >= knee else u
        p[c] = min(v, top) if ok else np.int64(0)


def _residual(x: Any, s: Any, r: Any, gain: Any, row_gain: Any, bin0: int, knee: int,
              ubin0: int, comp: Any, shifts: Any, sign: int, out: Any
              ) -> None:  # pragma: no cover - compiled
    """sign 1 (encoding): out = the residual ``(x - P) mod 2**bits`` rolled right by the row
    shifts (x: the target block); sign -1 (decoding): out = ``(x rolled back + P) mod
    2**bits`` (x: the rolled residual). x, out (H, W) unsigned of one type, s, r (H, W)
    native, shifts int64[H]."""
    h, w = s.shape
    mask = (np.int64(1) << (out.itemsize * 8)) - 1
    p = np.empty(w, np.int64)
    for y in range(h):
        _row_prediction(s[y], r[y], gain, np.int64(row_gain[y]), bin0, knee, ubin0, comp,
                        mask, p)
        k = shifts[y] % w if w else 0
        m = w - k
        xr, outr = x[y], out[y]
        if sign > 0:  # out[(c + k) mod W] = x[c] - P[c]; views indexed from 0
            head, xt, pt = outr[k:], xr[m:], p[m:]
            for c in range(m):
                head[c] = (np.int64(xr[c]) - p[c]) & mask
            for c in range(k):
                outr[c] = (np.int64(xt[c]) - pt[c]) & mask
        else:  # out[c] = x[(c + k) mod W] + P[c]
            xs, ot, pt = xr[k:], outr[m:], p[m:]
            for c in range(m):
                outr[c] = (np.int64(xs[c]) + p[c]) & mask
            for c in range(k):
                ot[c] = (np.int64(xr[c]) + pt[c]) & mask


def _select(a: Any, k: int) -> float:  # pragma: no cover - compiled
    """The k-th smallest value of the float64 array a (reordered: every value after index k
    is then >= it); three-way partitions (many equal values are common)."""
    lo, hi = 0, a.shape[0] - 1
    while lo < hi:
        x, y, z = a[lo], a[(lo + hi) // 2], a[hi]
        pivot = max(min(x, y), min(max(x, y), z))  # median of three
        lt, i, gt = lo, lo, hi
        while i <= gt:
            v = a[i]
            if v < pivot:
                a[i], a[lt] = a[lt], v
                lt += 1
                i += 1
            elif v > pivot:
                a[i], a[gt] = a[gt], v
                gt -= 1
            else:
                i += 1
        if k < lt:
            hi = lt - 1
        elif k > gt:
            lo = gt + 1
        else:
            return pivot
    return a[k]


def _medians(keys: Any, values: Any, n: int) -> Any:  # pragma: no cover - compiled
    """``lidarscan.codec._v3._medians``: the median of ``values`` per key 0 .. n-1 (the mean
    of the two middle values of an even count), a key without values taking the nearest
    key's median (the lower on a tie), all 1.0 without values."""
    out = np.ones(n, np.float64)
    m = keys.shape[0]
    if m == 0:
        return out
    start = np.zeros(n + 1, np.int64)
    for i in range(m):
        start[keys[i] + 1] += 1
    for k in range(n):
        start[k + 1] += start[k]
    fill = start[:n].copy()
    grouped = np.empty(m, np.float64)
    for i in range(m):
        g = keys[i]
        grouped[fill[g]] = values[i]
        fill[g] += 1
    have = np.zeros(n, np.bool_)
    for k in range(n):
        a, b = start[k], start[k + 1]
        if b > a:
            seg = grouped[a:b]
            count = b - a
            lo = (count - 1) // 2
            low = _select(seg, lo)
            high = low if count // 2 == lo else seg[lo + 1:].min()
            out[k] = 0.5 * (low + high)
            have[k] = True
    picked = out.copy()
    below = -1
    for k in range(n):  # nearest key with values: the lower one on a tie
        if have[k]:
            below = k
            continue
        above = k + 1
        while above < n and not have[above]:
            above += 1
        if below >= 0 and (above >= n or k - below <= above - k):
            picked[k] = out[below]
        else:
            picked[k] = out[above]
    return picked


def _fit(f: Any, s: Any, r: Any, step: int, knee: int) -> Any:  # pragma: no cover - compiled
    """``lidarscan.codec._v3.fit``'s tables on every step-th column: (found, bin0, gain
    uint32, row_gain uint16, ubin0, comp uint16); found False when no pixel has a range and a
    positive signal."""
    h = f.shape[0]
    nw = (f.shape[1] + step - 1) // step
    m = h * nw
    bins = np.empty(m, np.int64)
    sig = np.empty(m, np.int64)
    fv = np.empty(m, np.int64)
    valid = np.empty(m, np.bool_)
    lo_bin, hi_bin = np.int64(1) << 40, -(np.int64(1) << 40)
    for y in range(h):
        for j in range(nw):
            i = y * nw + j
            word = _f32_bits(np.float32(r[y, j * step]))
            ok = (word >= 1) & (word < 0x7F800000)
            b = word >> 18
            sv = np.int64(s[y, j * step])
            bins[i], sig[i], fv[i], valid[i] = b, sv, np.int64(f[y, j * step]), ok
            if ok and sv > 0:
                lo_bin = min(lo_bin, b)
                hi_bin = max(hi_bin, b)
    empty16 = np.zeros(1, np.uint16)
    if lo_bin > hi_bin:
        return False, 0, np.zeros(1, np.uint32), empty16, 0, empty16
    n = hi_bin - lo_bin + 1
    keys = np.empty(m, np.int64)
    rows = np.empty(m, np.int64)
    ratio = np.empty(m, np.float64)
    nl = 0
    for i in range(m):
        if valid[i] and sig[i] > 0 and fv[i] < knee:
            keys[nl] = bins[i] - lo_bin
            rows[nl] = i // nw
            ratio[nl] = np.float64(fv[i]) / np.float64(sig[i])
            nl += 1
    keys, rows, ratio = keys[:nl], rows[:nl], ratio[:nl]
    gain = _medians(keys, ratio, n)
    scaled = np.empty(nl, np.float64)
    for i in range(nl):
        scaled[i] = ratio[i] / max(gain[keys[i]], 1e-9)
    row_gain = _medians(rows, scaled, h)
    for y in range(h):
        row_gain[y] = min(max(row_gain[y], 0.5), 1.99)
    for i in range(nl):
        scaled[i] = ratio[i] / row_gain[rows[i]]
    gain = _medians(keys, scaled, n)
    gain_q = np.empty(n, np.uint32)
    for k in range(n):
        gain_q[k] = np.uint32(min(max(np.rint(gain[k] * 65536.0), 0.0), 16777215.0))
    row_q = np.empty(h, np.uint16)
    for y in range(h):
        row_q[y] = np.uint16(np.rint(row_gain[y] * 32768.0))
    ukeys = np.empty(m, np.int64)
    uvals = np.empty(m, np.float64)
    nh = 0
    lo_u, hi_u = np.int64(1) << 40, -(np.int64(1) << 40)
    for i in range(m):  # the linear value u with these tables, as the prediction
        if not (valid[i] and sig[i] > 0):
            continue
        rb = min(max(bins[i] - lo_bin, np.int64(0)), n - 1)
        u = np.int64(gain_q[rb]) * np.int64(row_q[i // nw]) * sig[i]
        u = max((u + (np.int64(1) << 30)) >> 31, np.int64(0))
        if u >= knee:
            ub = _f32_bits(np.float32(u)) >> 20
            ukeys[nh], uvals[nh] = ub, np.float64(fv[i])
            lo_u = min(lo_u, ub)
            hi_u = max(hi_u, ub)
            nh += 1
    if nh == 0:
        return True, lo_bin, gain_q, row_q, 0, empty16
    ukeys = ukeys[:nh] - lo_u
    comp = _medians(ukeys, uvals[:nh], hi_u - lo_u + 1)
    comp_q = np.empty(comp.shape[0], np.uint16)
    for k in range(comp.shape[0]):
        comp_q[k] = np.uint16(min(max(np.rint(comp[k]), 0.0), 65535.0))
    return True, lo_bin, gain_q, row_q, lo_u, comp_q


def _load() -> Any:
    global _f32_bits, _row_prediction, _select, _medians
    try:
        _f32_bits = _make_f32_bits()
    except ImportError:
        return None
    _row_prediction = numba_jit(_row_prediction, boundscheck=False)
    _select = numba_jit(_select, boundscheck=False)
    _medians = numba_jit(_medians, boundscheck=False)
    residual = numba_jit(_residual, boundscheck=False)
    fit_tables = numba_jit(_fit, boundscheck=False)
    from lidarscan.codec._v3 import _KNEE, XParams, fit_step

    def native(a: Any, keep: tuple[str, ...] = ("u1", "u2", "u4"), other: Any = None) -> Any:
        """a C-contiguous, aligned, native-order (a copy if needed), read-only view; a dtype
        not in ``keep`` converted to ``other`` (same values: a signed signal to int64, an
        integer range other than uint32 to float32, as the kernels convert it): the kernels
        compile once per kept dtype, not per writeable flag or rare dtype"""
        dtype = a.dtype.newbyteorder("=")
        if a.dtype.str[1:] not in keep and other is not None:
            dtype = np.dtype(other)
        view = np.require(a, dtype, ("C", "A")).view()
        view.flags.writeable = False
        return view

    def sources(s: Any, r: Any) -> tuple[Any, Any]:
        return native(s, other=np.int64), native(r, ("f4", "u4"), np.float32)

    def xfit(f: Any, s: Any, r: Any, signal: tuple[int, int], rng: tuple[int, int],
             knee: int = _KNEE) -> Any:
        found, bin0, gain, row_gain, ubin0, comp = fit_tables(
            native(f), *sources(s, r), fit_step(f.size), knee)
        if not found:
            return None
        return XParams(signal[0], signal[1], rng[0], rng[1], bin0, gain, row_gain, knee, ubin0,
                       comp)

    def xpredict(x: Any, s: Any, r: Any, p: Any, shifts: Any, sign: int) -> Any:
        h, w = s.shape
        x = native(x).reshape(h, w)
        out = np.empty((h, w), x.dtype)
        rows = np.zeros(h, np.int64) if shifts is None else np.asarray(shifts, np.int64)
        residual(x, *sources(s, r), p.gain, p.row_gain, p.bin0, p.knee, p.ubin0, p.comp, rows,
                 sign, out)
        return out

    return xfit, xpredict


_COMPILED = LoadOnce(_load)


def kernels() -> Any:
    """``(xfit, xpredict)``, the compiled fields of :class:`lidarscan.codec._bits.ResidualCoder`
    (arguments documented there), or None without numba."""
    return _COMPILED.get()
