"""Optional compiled (numba) path of :mod:`converters.cloud_slices`: unstructured cloud ->
several LaserScan slices in one pass over the points.

One kernel, ``fuse_points``, doing exactly what ``converters.cloud_slices._fuse_numpy`` does
(the reference): per point (x, y, z read as float64 from the cloud's own float32 / float64
fields, native byte order), its target-frame z first (``m``: rotation row-major then
translation, evaluated in the same order as the reference; from z alone for an upright
target), dropped unless it lies in the hull of the bands; only a kept point has its x, y
read and transformed and its finiteness checked (the reference's order gives the same set,
:func:`_fill`). Kept points are buffered in chunks of ``_CHUNK``; per chunk: the bin of every
point once per distinct grid (one vectorised loop), its planar range and float32 code once,
then band by band the points inside the band (branch-free compaction) and the minimum of
``code << 32 | point index`` in the reduction array.

Binning without libm's ``atan2`` for almost every point: an odd polynomial of ``atan`` on
``[0, 1]`` (8 terms, error below 4e-8 rad, checked by a test) after the octant reduction
(arithmetic blends, no branches, so the loop vectorises) gives the azimuth within ``EPS`` =
1e-7 rad. The bin is a monotone function of the azimuth, so when the approximate azimuth is
more than ``2 * EPS`` from every bin edge (and, for sectors, from the wrap point) the bin is
the one of the exact ``atan2``; the other points (about ``4e-7 / increment`` of them: 7e-5 at
2*pi/1024) and points at the origin take ``math.atan2``. Results therefore equal the reference
except for points within an ulp of a bin edge, where numpy's SIMD ``arctan2`` and libm's may
differ in the last bit (as for the structured slices).

Chosen by :func:`converters._kernels.select` (``"cloud_slices"``), which reads the switches.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from converters._grid import CODE_NEG_INF, CODE_POS_INF
from converters._kernels._loader import LoadOnce

__all__ = ["ATAN_COEFFS", "EPS", "atan2_approx", "kernel"]

#: atan(u) ~= u * sum(c_j * u**(2j)) on 0 <= u <= 1 (least squares on Chebyshev nodes,
#: reweighted towards minimax)
ATAN_COEFFS = (0.9999993356986212, -0.33329861034289326, 0.19946567288244435,
               -0.13908634232863948, 0.09642203544865086, -0.05591235776154396,
               0.021862952643013092, -0.00405456031490202)
#: bound on |atan2_approx - atan2| in radians (polynomial error 3.7e-8 plus rounding; a test
#: checks the polynomial against it)
EPS = 1e-7
_TWO_PI = 2.0 * math.pi
_F32_MAX = float(np.finfo(np.float32).max)


def atan2_approx(y: float, x: float) -> float:  # pragma: no cover - compiled (also plain)
    """atan2(y, x) within :data:`EPS` for finite (x, y) not both 0; range [-pi, pi].

    Octant fix-ups are arithmetic blends, not branches or selects (the octant of a cloud's
    points is unpredictable; the compiler turned selects into mispredicted branches here)."""
    ax, ay = abs(x), abs(y)
    z = min(ax, ay) / max(ax, ay)
    u2 = z * z
    c = ATAN_COEFFS
    p = c[7]
    p = p * u2 + c[6]
    p = p * u2 + c[5]
    p = p * u2 + c[4]
    p = p * u2 + c[3]
    p = p * u2 + c[2]
    p = p * u2 + c[1]
    p = p * u2 + c[0]
    a = z * p
    a = a + np.float64(ay > ax) * (0.5 * math.pi - 2.0 * a)
    a = a + np.float64(x < 0.0) * (math.pi - 2.0 * a)
    return math.copysign(a, y)


def _bin_exact(theta: float, amin: float, inc: float, size: int,
               full: bool) -> int:  # pragma: no cover - compiled
    """:meth:`converters._grid.AngleGrid.bins` of one angle (-1 outside a sector)."""
    d = theta - amin
    if not full:
        half = 0.5 * inc
        d = d - _TWO_PI * math.floor((d + half) / _TWO_PI)
    k = int(math.ceil(d / inc - 0.5))
    if full:
        return k % size
    return k if 0 <= k < size else -1


def _approx_bins(px: Any, py: Any, count: int, amin: float, inc: float, inv: float,
                 size: int, full: bool, out: Any) -> None:  # pragma: no cover - compiled
    """``out[j]`` = the bin of the exact ``atan2(py[j], px[j])`` for ``j < count`` (-1 outside a
    sector), or -2 where the approximate angle is within 2 * EPS of a bin edge or of a sector's
    wrap point, or the point is at the origin (then the caller takes ``math.atan2``).

    Straight-line loops (no calls, no branches) so that the compiler vectorises them (``np.ceil``
    and ``np.floor`` stay in float64: numba's ``math.ceil`` returns an int64, and a float64 to
    int64 conversion does not vectorise without AVX-512)."""
    fsize = float(size)
    if full:
        for j in range(count):
            e = (atan2_approx(py[j], px[j]) - amin) * inv - 0.5   # bin edges: integer e
            kf = np.ceil(e)
            edge = kf - e                                          # NaN at the origin
            safe = (min(edge, 1.0 - edge) * inc > 2.0 * EPS) & (abs(e) < 1e9)
            kf = kf - fsize if kf >= fsize else kf
            kf = kf + fsize if kf < 0.0 else kf
            safe = safe & (kf >= 0.0) & (kf < fsize)
            out[j] = np.int32(kf if safe else -2.0)
        return
    half = 0.5 * inc
    inv_2pi = 1.0 / _TWO_PI
    for j in range(count):
        d = atan2_approx(py[j], px[j]) - amin
        w = (d + half) * inv_2pi
        fw = np.floor(w)
        wrap_far = min(w - fw, fw + 1.0 - w) * _TWO_PI > 2.0 * EPS
        e = (d - _TWO_PI * fw) * inv - 0.5
        kf = np.ceil(e)
        edge = kf - e
        safe = (min(edge, 1.0 - edge) * inc > 2.0 * EPS) & (abs(e) < 1e9) & wrap_far
        kf = kf if (kf >= 0.0) & (kf < fsize) else -1.0
        out[j] = np.int32(kf if safe else -2.0)


def _flush(bx: Any, by: Any, bz: Any, bi: Any, bk: Any, brho: Any, bbits: Any, bsel: Any,
           count: int,
           zlo: Any, zhi: Any, rlo: Any, rhi: Any, sgrid: Any, soff: Any, gmin: Any, ginc: Any,
           ginv: Any,
           gsize: Any, gfull: Any, best: Any) -> None:  # pragma: no cover - compiled
    """Fuse ``count`` buffered points (target-frame x, y, z and cloud index) into ``best``:
    bins per grid and planar ranges first, then band by band: the points inside the band
    (a branch-free compaction into ``bsel``), then their minima (``brho``, ``bbits``,
    ``bsel``: scratch)."""
    n_s = zlo.shape[0]
    for g in range(gmin.shape[0]):
        _approx_bins(bx, by, count, gmin[g], ginc[g], ginv[g], gsize[g], gfull[g], bk[g])
    for j in range(count):                       # vectorised: planar range
        brho[j] = math.sqrt(bx[j] * bx[j] + by[j] * by[j])
    for j in range(count):                       # its float32 bits; beyond float32: +Inf
        rho = brho[j]
        bbits[j] = CODE_POS_INF if rho > _F32_MAX else np.int64(np.float32(rho).view(np.int32))
    for s in range(n_s):
        lo, hi, rl, rh, off = zlo[s], zhi[s], rlo[s], rhi[s], soff[s]
        g = sgrid[s]
        n_in = 0
        for j in range(count):                   # branch-free: the points inside the band
            pz = bz[j]
            bsel[n_in] = j
            n_in += (pz >= lo) & (pz <= hi)
        for q in range(n_in):
            j = bsel[q]
            b = np.int64(bk[g, j])
            if b == -2:                                  # rare: near a bin edge
                b = _bin_exact(math.atan2(by[j], bx[j]), gmin[g], ginc[g], gsize[g], gfull[g])
                bk[g, j] = b
            if b < 0:
                continue
            rho = brho[j]
            code = CODE_NEG_INF if rho < rl else bbits[j]
            code = CODE_POS_INF if rho > rh else code
            v = (code << 32) | bi[j]
            t = off + b
            best[t] = min(best[t], v)


def _push(bx: Any, by: Any, bz: Any, bi: Any, c: int, i: int, x: float, y: float, z: float,
          pz: float, m: Any) -> int:  # pragma: no cover - compiled (inlined)
    """Buffer point ``i`` (cloud x, y, z; target z ``pz``) at ``c`` in the target frame;
    returns ``c + 1``."""
    bx[c] = m[0] * x + m[1] * y + m[2] * z + m[9]
    by[c] = m[3] * x + m[4] * y + m[5] * z + m[10]
    bz[c] = pz
    bi[c] = i
    return c + 1


def _fill(xs: Any, ys: Any, zs: Any, m: Any, zall_lo: float, zall_hi: float, start: int,
          bx: Any, by: Any, bz: Any, bi: Any) -> tuple[int, int]:  # pragma: no cover - compiled
    """Buffer the points from ``start`` on whose target-frame z lies in the hull of the bands
    (target-frame x, y, z and cloud index) until the buffer is full; returns (points
    buffered, index to resume from).

    The height comes first: a point outside the hull is dropped before its x, y are read or
    its finiteness tested. Exact: a finite z implies finite coordinates (a non-finite one
    makes its term NaN or infinite, as does 0 * inf); only an infinite z in an infinite
    band needs the test. Upright (``m[6] == m[7] == 0``): z from the cloud's z alone (the
    reference's ``0*x + 0*y`` adds only zeros for finite x, y; a non-finite x or y is tested
    before the point is kept)."""
    n = xs.shape[0]
    size = bx.shape[0]
    c = 0
    i = start
    if m[6] == 0.0 and m[7] == 0.0:
        m8 = m[8]
        m11 = m[11]
        while i < n:
            z = float(zs[i])
            pz = m8 * z + m11
            if pz >= zall_lo and pz <= zall_hi:
                x = float(xs[i])
                y = float(ys[i])
                if math.isfinite(x) and math.isfinite(y) and math.isfinite(z):
                    c = _push(bx, by, bz, bi, c, i, x, y, z, pz, m)
                    if c == size:
                        return c, i + 1
            i += 1
        return c, i
    while i < n:
        x = float(xs[i])
        y = float(ys[i])
        z = float(zs[i])
        pz = m[6] * x + m[7] * y + m[8] * z + m[11]
        if pz >= zall_lo and pz <= zall_hi and (
                math.isfinite(pz) or (math.isfinite(x) and math.isfinite(y)
                                      and math.isfinite(z))):
            c = _push(bx, by, bz, bi, c, i, x, y, z, pz, m)
            if c == size:
                return c, i + 1
        i += 1
    return c, i


_CHUNK = 2048      # points buffered between the scan of the cloud and the fusion (L1-sized)


def _fuse_points(xs: Any, ys: Any, zs: Any, m: Any, zlo: Any, zhi: Any, rlo: Any, rhi: Any,
                 sgrid: Any, soff: Any, gmin: Any, ginc: Any, ginv: Any, gsize: Any,
                 gfull: Any, zall_lo: float, zall_hi: float,
                 best: Any) -> None:  # pragma: no cover - compiled
    """See the module docstring; ``best``: (total bins,) int64 reduction array updated in
    place. Points inside the hull of the bands are buffered in chunks (:func:`_fill`); each
    chunk's bins are computed in one vectorised loop per grid, then fused into every band it
    falls in."""
    bx = np.empty(_CHUNK)
    by = np.empty(_CHUNK)
    bz = np.empty(_CHUNK)
    bi = np.empty(_CHUNK, np.int64)
    bk = np.empty((gmin.shape[0], _CHUNK), np.int32)
    brho = np.empty(_CHUNK)
    bbits = np.empty(_CHUNK, np.int64)
    bsel = np.empty(_CHUNK, np.int64)
    i = 0
    while i < xs.shape[0]:
        c, i = _fill(xs, ys, zs, m, zall_lo, zall_hi, i, bx, by, bz, bi)
        if c:
            _flush(bx, by, bz, bi, bk, brho, bbits, bsel, c, zlo, zhi, rlo, rhi, sgrid, soff, gmin,
                   ginc, ginv, gsize, gfull, best)


def _load() -> Any:
    try:
        import numba
    except ImportError:
        return None
    global atan2_approx, _bin_exact, _push, _approx_bins, _flush, _fill
    # called by the kernel, so compiled first; numba resolves globals at compile time
    inline = numba.njit(nogil=True, error_model="numpy", inline="always")
    atan2_approx = inline(atan2_approx)
    _bin_exact = inline(_bin_exact)
    _push = inline(_push)
    jit = numba.njit(nogil=True, error_model="numpy", boundscheck=False)
    _approx_bins = jit(_approx_bins)
    _flush = jit(_flush)
    _fill = jit(_fill)
    return numba.njit(cache=True, nogil=True, error_model="numpy",
                      boundscheck=False)(_fuse_points)


_COMPILED = LoadOnce(_load)


def kernel() -> Any:
    """The compiled ``fuse_points`` (arguments of ``_fuse_points``), or None without numba.
    Callers go through :func:`converters._kernels.select`, which honours ``LIDARSCAN_NUMBA``."""
    return _COMPILED.get()
