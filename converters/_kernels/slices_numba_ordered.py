"""numba kernels of the slices on one shared grid: bin-ordered and row-ordered.

Split from :mod:`converters._kernels.slices_numba` (which compiles them in
:func:`~converters._kernels.slices_numba.kernels` and drives them through its ``Compiled``
class); the conventions are that module's. The kernels call each other through the module
globals ``_J_*`` of this module, set by ``kernels()`` before the kernels that use them are
compiled (numba resolves a global dispatcher at compile time).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from converters.slices.spec import CODE_NAN, CODE_NEG_INF, CODE_POS_INF, EMPTY

_J_NEAR: Any = None      # compiled helpers, set by slices_numba.kernels()
_J_BIN: Any = None
_J_VALUE: Any = None
_J_ROW: Any = None
_J_DECODE_SLICES: Any = None

# ------------------------------------------------- bin-ordered kernel (slices, one shared grid)
#
# Per LidarInfo version the pixel tables are permuted once into the order of the far-field bins
# (``src[j]`` = pixel at position ``j``; ``bin_start[b]:bin_start[b+1]`` = the positions of bin
# ``b``; pixels without a far-field bin at the end). Per scan, bin by bin: the ranges of the bin
# are gathered once (shared by all slices), one branch-free loop the compiler vectorises gives
# every position its code (``code << 32 | key``) and its slice bits (height band for points,
# the precomputed +Inf/NaN/-Inf qualifiers otherwise), and a running minimum per slice over the
# bin's positions replaces the scatter; only points closer than their far-field threshold (rare
# for a sensor on the target's z axis) take a scalar path with atan2. The per-pixel thresholds
# are read only for runs of bins whose smallest positive range is below the run's largest
# threshold (``bin_thr``), so a centred sensor does not stream them at all. Used when all slices
# share one grid and their planar range limits (so a point's class is decided once).


def _sorted_fuse(r: Any, src: Any, keys: Any, dz: Any, oz: Any, dx: Any, dy: Any, ox: Any,
                 oy: Any, r_thr: Any, qf: Any, qn: Any, zmin: Any, zmax: Any, n_slices: Any,
                 lim_lo: Any, lim_hi: Any, bin_start: Any, bin_thr: Any, max_width: Any,
                 offset: Any, g_min: Any, g_inc: Any, g_size: Any, g_full: Any,
                 best: Any) -> None:  # pragma: no cover - compiled
    """Fuse one scan into ``best`` for slices ``0 .. n_slices-1`` on one grid.

    Args:
        r: (n,) float32 ranges in pixel order.
        src, keys: (n,) int32 pixel and tie key of each position (bin order).
        dz, oz, dx, dy, ox, oy, r_thr: (n,) float32 ray tables and far-field threshold, bin order.
        qf, qn: (n,) bit s: slice s may report +Inf/NaN (qf) or -Inf (qn), bin order.
        zmin, zmax: bands padded to a multiple of four slices with empty ones (inf, -inf).
        lim_lo, lim_hi: the shared planar range limits.
        bin_start: (size + 2,) int64 position of each bin's first pixel (last: the pixels
            without a far-field bin, only their near points can contribute).
        bin_thr: (size + 1,) float32 the largest ``r_thr`` of each bin's pixels: a run of
            bins whose smallest positive range reaches it has no near point, and its
            ``r_thr`` values are not read at all (less memory traffic).
        max_width: positions per chunk of whole bins (>= the largest bin; scratch size).
        offset: (n_slices,) int64 first element of each slice in ``best``.
        g_min, g_inc, g_size, g_full: the grid.
        best: reduction array, updated in place.
    """
    empty = np.int64(EMPTY)
    chunk = max_width
    rp = np.empty(chunk, np.float32)
    no_thr = np.zeros(chunk, np.float32)          # stands for r_thr when no point is near
    cm = np.empty(chunk, np.int64)
    mm = np.empty(chunk, np.int64)
    n_blocks = zmin.shape[0] // 4
    b_end = 0
    while b_end < g_size + 1:
        # a run of whole bins, at most ``chunk`` positions (at least one bin)
        b_first = b_end
        j0 = bin_start[b_first]
        b_end = b_first + 1
        while b_end < g_size + 1 and bin_start[b_end + 1] - j0 <= chunk:
            b_end += 1
        j1 = bin_start[b_end]
        w = j1 - j0
        if w == 0:
            continue
        vsrc = src[j0:j1]
        lowest = np.float32(np.inf)         # smallest positive range of the run
        for k in range(w):
            rv = r[vsrc[k]]
            rp[k] = rv
            lowest = min(lowest, rv if rv > 0.0 else np.float32(np.inf))   # branch-free
        thr_max = bin_thr[b_first]
        for b in range(b_first + 1, b_end):
            thr_max = max(thr_max, bin_thr[b])
        vthr = r_thr[j0:j1] if lowest < thr_max else no_thr[:w]
        vkeys, vqf, vqn = keys[j0:j1], qf[j0:j1], qn[j0:j1]
        vdz, voz, vdx, vdy, vox, voy = (dz[j0:j1], oz[j0:j1], dx[j0:j1], dy[j0:j1],
                                        ox[j0:j1], oy[j0:j1])
        for blk in range(n_blocks):
            s0 = 4 * blk
            lo0, hi0 = zmin[s0], zmax[s0]
            lo1, hi1 = zmin[s0 + 1], zmax[s0 + 1]
            lo2, hi2 = zmin[s0 + 2], zmax[s0 + 2]
            lo3, hi3 = zmin[s0 + 3], zmax[s0 + 3]
            count = np.int64(0)
            for k in range(w):
                rv = rp[k]
                z = np.float64(rv) * vdz[k] + voz[k]
                point = (rv > 0.0) & (rv < np.inf)
                near = point & (rv < vthr[k])
                count += np.int64(near)
                value = _J_VALUE(rv, vdx[k], vdy[k], vox[k], voy[k], vkeys[k], lim_lo, lim_hi)
                cm[k] = empty if near else value
                m = np.int64((z >= lo0) & (z <= hi0))
                m |= np.int64((z >= lo1) & (z <= hi1)) << 1
                m |= np.int64((z >= lo2) & (z <= hi2)) << 2
                m |= np.int64((z >= lo3) & (z <= hi3)) << 3
                # both qualifiers loaded, one picked arithmetically: a conditional load would
                # keep the compiler from vectorising this loop (about 1.5x slower)
                sel = np.int64(rv == -np.inf)
                q = (np.int64(vqn[k]) * sel) | (np.int64(vqf[k]) * (1 - sel))
                mm[k] = m if point else (q >> s0) & 15
            for b in range(b_first, min(b_end, g_size)):
                vm = mm[bin_start[b] - j0:bin_start[b + 1] - j0]
                vc = cm[bin_start[b] - j0:bin_start[b + 1] - j0]
                r0 = empty
                r1 = empty
                r2 = empty
                r3 = empty
                for k in range(vm.shape[0]):
                    m = vm[k]
                    v = vc[k]
                    r0 = min(r0, v if m & 1 else empty)
                    r1 = min(r1, v if m & 2 else empty)
                    r2 = min(r2, v if m & 4 else empty)
                    r3 = min(r3, v if m & 8 else empty)
                for t, run in enumerate((r0, r1, r2, r3)):
                    if s0 + t < n_slices:
                        jj = offset[s0 + t] + b
                        best[jj] = min(best[jj], run)
            if count == 0:
                continue
            # points closer than their far-field threshold: exact bin from atan2
            for k in range(w):
                rv = rp[k]
                if not ((rv > 0.0) & (rv < np.inf) & (rv < vthr[k]) & (mm[k] != 0)):
                    continue
                _J_NEAR(rv, vdx[k], vdy[k], vox[k], voy[k], vkeys[k], mm[k], s0, n_slices,
                        lim_lo, lim_hi, g_min, g_inc, g_size, g_full, offset, best)


def _value(rv: Any, dx: Any, dy: Any, ox: Any, oy: Any, key: Any, lim_lo: Any,
           lim_hi: Any) -> Any:  # pragma: no cover - compiled
    """``code << 32 | key`` of one range on its ray (module docstring): the float32 bits of
    the planar range of a point (or -Inf / +Inf outside the planar limits), the class code of a
    non-point. Branch-free, inlined into the kernels' vectorised loops."""
    rd = np.float64(rv)
    x = rd * dx + ox
    y = rd * dy + oy
    rho = math.sqrt(x * x + y * y)
    point = (rv > 0.0) & (rv < np.inf)
    code = np.int64(np.float32(rho).view(np.int32))
    code = np.int64(CODE_NEG_INF) if rho < lim_lo else code
    code = np.int64(CODE_POS_INF) if rho > lim_hi else code
    special = np.int64(CODE_NAN)
    special = np.int64(CODE_POS_INF) if rv == np.inf else special
    special = np.int64(CODE_NEG_INF) if rv == -np.inf else special
    return ((code if point else special) << 32) | np.int64(key)


def _angle_bin(theta: Any, g_min: Any, g_inc: Any, g_size: Any,
               g_full: Any) -> Any:  # pragma: no cover - compiled
    """The bin of angle ``theta`` (radians, float64) on a grid (the rule of
    :meth:`converters.slices.spec.AngleGrid`: nearest bin, half-bin to the lower index; a full
    circle wraps, a sector's angle is taken modulo 2*pi around it), or -1 outside a sector.
    The one binning step of the numba kernels (inlined into them)."""
    d = theta - g_min
    if g_full:
        k = np.int64(math.ceil(d / g_inc - 0.5))
        if k < 0 or k >= g_size:          # (a modulo only when needed: slow)
            k %= g_size
        return k
    two_pi = 2.0 * math.pi
    d = d - two_pi * math.floor((d + 0.5 * g_inc) / two_pi)
    k = np.int64(math.ceil(d / g_inc - 0.5))
    return k if 0 <= k < g_size else np.int64(-1)


def _near_point(rv: Any, dx: Any, dy: Any, ox: Any, oy: Any, key: Any, m: Any, s0: Any,
                n_slices: Any, lim_lo: Any, lim_hi: Any, g_min: Any, g_inc: Any, g_size: Any,
                g_full: Any, offset: Any, best: Any) -> None:  # pragma: no cover - compiled
    """One point closer than its far-field threshold (range ``rv``, ray ``dx, dy, ox, oy``):
    its exact bin from atan2, then its value into slices ``s0 + t`` for the bits t of ``m``
    (shared by the bin-ordered and row-ordered kernels)."""
    rd = np.float64(rv)
    x = rd * dx + ox
    y = rd * dy + oy
    rho = math.sqrt(x * x + y * y)
    code = np.int64(np.float32(rho).view(np.int32))
    if rho < lim_lo:
        code = np.int64(CODE_NEG_INF)
    elif rho > lim_hi:
        code = np.int64(CODE_POS_INF)
    bn = _J_BIN(math.atan2(y, x), g_min, g_inc, g_size, g_full)
    if bn < 0:
        return
    value = (code << 32) | np.int64(key)
    for t in range(4):
        if (m >> t) & 1 and s0 + t < n_slices:
            jj = offset[s0 + t] + bn
            best[jj] = min(best[jj], value)


def _row_fuse(r: Any, src: Any, keys: Any, dx: Any, dy: Any, ox: Any, oy: Any, r_thr: Any,
              qf: Any, qn: Any, q_rows: Any, lo: Any, hi: Any, n_slices: Any, lim_lo: Any,
              lim_hi: Any, height: Any, bin_thr: Any, offset: Any, g_min: Any, g_inc: Any,
              g_size: Any, g_full: Any, best: Any) -> None:  # pragma: no cover - compiled
    """:func:`_sorted_fuse` for the row-ordered layout: bin ``b`` is positions
    ``b*H .. b*H + H - 1`` and position ``k`` of a bin is row ``k``.

    Args:
        r: (n,) float32 ranges in pixel order.
        src, keys: (n,) uint32 pixel and tie key of each position (bin order).
        dx, dy, ox, oy, r_thr: (n,) float32 ray tables and far-field threshold, bin order.
        qf, qn: bit s: slice s may report +Inf/NaN (qf) or -Inf (qn); (H,) per row when
            ``q_rows`` (the same for every bin), else (n,) in bin order.
        lo, hi: (S, H) float32 per band (padded to a multiple of four with empty ones) and row,
            from :func:`band_intervals_f32`: a range ``rv`` of row ``k`` is a point inside band
            ``s`` iff ``lo[s, k] <= rv <= hi[s, k]`` (false for every non-point).
        n_slices, lim_lo, lim_hi, bin_thr, offset, g_*, best: as in :func:`_sorted_fuse`.

    Per bin: one gather of its H ranges; one vectorised loop giving every position its value
    ``code << 32 | key`` (``EMPTY`` for a point closer than its far-field threshold: those take
    the atan2 path) and, for non-points, the qualifier bits of their class; then per block of
    four slices one vectorised loop of four running minima (a position takes part in slice s
    iff it is inside the band interval or a qualified non-point).
    """
    empty = np.int64(EMPTY)
    rows = height
    rp = np.empty(rows, np.float32)
    cv = np.empty(rows, np.int64)             # value of each position
    qx = np.empty(rows, np.int32)             # qualifier bits of non-points (0 for points)
    n_blocks = lo.shape[0] // 4
    q_step = 0 if q_rows else rows
    # Tables are read at index offsets (j0 + k): array views created per bin cost reference
    # counting calls that showed up as ~20 % of the time.
    for b in range(g_size):
        j0 = b * rows
        q0 = b * q_step
        lowest = np.float32(np.inf)           # smallest positive range of the bin
        for k in range(rows):
            rv = r[src[j0 + k]]
            rp[k] = rv
            lowest = min(lowest, rv if rv > 0.0 else np.float32(np.inf))   # branch-free
        for k in range(rows):
            rv = rp[k]
            point = (rv > 0.0) & (rv < np.inf)
            cv[k] = _J_VALUE(rv, dx[j0 + k], dy[j0 + k], ox[j0 + k], oy[j0 + k], keys[j0 + k],
                             lim_lo, lim_hi)
            # both qualifiers loaded, one picked arithmetically (keeps the loop vectorised)
            sel = np.int64(rv == -np.inf)
            q = (np.int64(qn[q0 + k]) * sel) | (np.int64(qf[q0 + k]) * (1 - sel))
            qx[k] = np.int32(0 if point else q)
        count = np.int64(0)
        if lowest < bin_thr[b]:
            # some point may be closer than its far-field threshold (rare for a centred
            # sensor): such points leave the minima and take the atan2 path below
            for k in range(rows):
                rv = rp[k]
                near = (rv > 0.0) & (rv < np.inf) & (rv < r_thr[j0 + k])
                count += np.int64(near)
                cv[k] = empty if near else cv[k]
        for blk in range(n_blocks):
            s0 = 4 * blk
            r0 = empty
            r1 = empty
            r2 = empty
            r3 = empty
            for k in range(rows):
                rv = rp[k]
                v = cv[k]
                q = qx[k] >> s0
                r0 = min(r0, v if (((rv >= lo[s0, k]) & (rv <= hi[s0, k]))
                                   | ((q & 1) != 0)) else empty)
                r1 = min(r1, v if (((rv >= lo[s0 + 1, k]) & (rv <= hi[s0 + 1, k]))
                                   | ((q & 2) != 0)) else empty)
                r2 = min(r2, v if (((rv >= lo[s0 + 2, k]) & (rv <= hi[s0 + 2, k]))
                                   | ((q & 4) != 0)) else empty)
                r3 = min(r3, v if (((rv >= lo[s0 + 3, k]) & (rv <= hi[s0 + 3, k]))
                                   | ((q & 8) != 0)) else empty)
            # (padded slices s >= n_slices have empty bands and no qualifier bits)
            if s0 < n_slices:
                best[offset[s0] + b] = min(best[offset[s0] + b], r0)
            if s0 + 1 < n_slices:
                best[offset[s0 + 1] + b] = min(best[offset[s0 + 1] + b], r1)
            if s0 + 2 < n_slices:
                best[offset[s0 + 2] + b] = min(best[offset[s0 + 2] + b], r2)
            if s0 + 3 < n_slices:
                best[offset[s0 + 3] + b] = min(best[offset[s0 + 3] + b], r3)
            if count == 0:
                continue
            # points closer than their far-field threshold: exact bin from atan2
            for k in range(rows):
                rv = rp[k]
                if not ((rv > 0.0) & (rv < np.inf) & (rv < r_thr[j0 + k])):
                    continue
                m = 0
                for t in range(4):
                    if (rv >= lo[s0 + t, k]) & (rv <= hi[s0 + t, k]):
                        m |= 1 << t
                if m != 0:
                    _J_NEAR(rv, dx[j0 + k], dy[j0 + k], ox[j0 + k], oy[j0 + k], keys[j0 + k],
                            m, s0, n_slices, lim_lo, lim_hi, g_min, g_inc, g_size, g_full,
                            offset, best)


def _row_convert(r: Any, src: Any, keys: Any, dx: Any, dy: Any, ox: Any, oy: Any, r_thr: Any,
                 qf: Any, qn: Any, q_rows: Any, lo: Any, hi: Any, n_slices: Any, lim_lo: Any,
                 lim_hi: Any, height: Any, bin_thr: Any, offset: Any, g_min: Any, g_inc: Any,
                 g_size: Any, g_full: Any, total: Any, size: Any, inf_value: Any,
                 fill_value: Any, intensity: Any, key_to_pos: Any, want_ints: Any,
                 h_start: Any, h_below: Any, h_no_return: Any, h_slice_start: Any,
                 h_slice: Any, h_pixel: Any, h_bin: Any, h_value: Any, h_dz: Any,
                 h_oz: Any) -> Any:  # pragma: no cover - compiled
    """:func:`_row_fuse` into a fresh reduction array of ``total`` elements, the hole edges
    (``h_*``: the arrays of :class:`converters.slices.holes.HolePlan`, empty without holes; the rule
    of :func:`converters.slices.holes.hole_hits`), then :func:`_decode_slices`, in one compiled call
    (one dispatch less per scan).

    Returns:
        (ranges, ints): float32 of all slices back to back (ints empty unless ``want_ints``).
    """
    best = np.full(total, np.int64(EMPTY), np.int64)
    _J_ROW(r, src, keys, dx, dy, ox, oy, r_thr, qf, qn, q_rows, lo, hi, n_slices, lim_lo, lim_hi,
           height, bin_thr, offset, g_min, g_inc, g_size, g_full, best)
    hits = np.empty(h_pixel.shape[0], np.int32)
    for g in range(h_start.shape[0] - 1):
        below = h_below[g]
        no_return = h_no_return[g]
        n_hits = 0
        for e in range(h_start[g], h_start[g + 1]):      # branch-free: hits are rare
            rv = np.float64(r[h_pixel[e]])
            z = rv * np.float64(h_dz[e]) + np.float64(h_oz[e])
            hits[n_hits] = e
            n_hits += ((rv > 0.0) & (rv < np.inf) & (z <= below)) | (no_return
                                                                    & (rv == np.inf))
        for k in range(h_slice_start[g], h_slice_start[g + 1]):
            base = offset[h_slice[k]]
            for j in range(n_hits):
                e = hits[j]
                t = base + h_bin[e]
                best[t] = min(best[t], h_value[e])
    ranges = np.empty(total, np.float32)
    ints = np.empty(total if want_ints else 0, np.float32)
    _J_DECODE_SLICES(best, offset, size, inf_value, fill_value, intensity, key_to_pos, ranges,
                     ints)
    return ranges, ints

