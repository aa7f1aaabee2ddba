"""Firings of a dual-return cloud whose first echoes share their block pair's azimuth, and the
per-pixel azimuths that place such points.

ROS 2's ``velodyne_pointcloud`` (ros-drivers/velodyne, branches ``ros2`` and ``humble-devel``,
``RawData::unpack_vlp16``) interpolates each laser's azimuth from the gap to the NEXT BLOCK. In a
VLP-16 dual-return packet the two blocks of a pair (last echo, strongest echo of the same two
firing sequences) carry one azimuth, so the gap of a pair's first block is 0: all its points
(both firing sequences, every laser) sit at the pair's azimuth, while the second block's points
get the true firing azimuths. Per beam, in cloud order, a pair is four slots::

    slot 0: first echo,  firing 2k      azimuth X_k
    slot 1: first echo,  firing 2k + 1  azimuth X_k           (the same value, to float32)
    slot 2: second echo, firing 2k      azimuth X_k + e_u      (e_u: the beam's firing delay)
    slot 3: second echo, firing 2k + 1  azimuth X_k + 1 + e_u  (in firing steps; X_{k+1} = X_k + 2)

No per-column + per-beam azimuth holds both echoes (the first echoes lie up to 1.6 firing steps
from their firing's direction), so such a grid needs the per-pixel azimuth channels
(``azimuth``, ``azimuth2``; ``msgs/README.md``). :func:`block_pair_columns` numbers the firings
from the cloud order and the azimuths alone (the driver's ``time`` of a dual packet does not
give them: it uses its single-return table); each beam's points take strictly increasing slots,
so no two points of a beam ever share a pixel. :func:`pixel_thetas` gives each pixel the
azimuth of its own point.

Angles in radians (REP 103, counter-clockwise about +z), ranges in metres.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from converters.sources.clouds.grid import _Fit, _fit_geometry, _Grid, _ring_grid, _wrap
from lidarscan.errors import ConversionError

#: consecutive points of one beam closer than this in azimuth (rad) share an azimuth value: the
#: driver's float32 points of one 0.01 deg azimuth differ by ~1e-7 rad
SAME_AZIMUTH = 2e-5
#: matches of a point to two slots this close (firing steps) go to the earlier slot
SLOT_MARGIN = 0.08
#: least share of a cloud's points in runs of one azimuth for the block-pair layout
MIN_RUN_SHARE = 0.05


def _next_slot(k: int, j: int, delta: float, offsets: tuple[float, ...]
               ) -> tuple[int, int, float]:
    """The slot after (k, j) whose predicted azimuth matches the point's, ``delta`` firing
    steps after its pair's azimuth X_k: the earliest slot within ``SLOT_MARGIN`` of the best
    match (azimuths are rounded to 0.01 deg and pairs are 39 or 40 such units apart). A pair's
    second echoes may also sit at X_k (the last pair of a packet: the driver reuses the
    previous, zero, gap). Returns (pair, slot, the point's offset from its pair's azimuth)."""
    cands = []
    for jn in range(4):
        lowest = k + (1 if jn <= j else 0)
        for off in ((offsets[jn], 0.0) if jn >= 2 else (offsets[jn],)):
            kn = max(lowest, k + int(np.rint((delta - off) / 2)))
            cands.append((abs(delta - 2 * (kn - k) - off), kn, jn, off))
    best = min(c[0] for c in cands)
    _, kn, jn, off = min((c for c in cands if c[0] <= best + SLOT_MARGIN),
                         key=lambda c: (c[1], c[2], c[0]))
    return kn, jn, off


def block_pair_columns(psi: np.ndarray[Any, Any], rows: np.ndarray[Any, Any], height: int
                       ) -> np.ndarray[Any, Any] | None:
    """Firing (column) of every point of a block-pair dual-return cloud, or None when the cloud
    does not have that layout (too few runs of one azimuth in a beam).

    Args:
        psi: (N,) float64 azimuth of each point (rad), cloud order.
        rows: (N,) int64 row (beam) of each point.
        height: number of rows.

    Returns:
        (N,) int64 columns >= 0 (two points of one beam share a column only as the first and
        second echo of one firing), or None.
    """
    n = psi.size
    order = np.lexsort((np.arange(n), rows))
    rr, pp = rows[order], psi[order]
    same = rr[1:] == rr[:-1]
    d = _wrap(np.diff(pp))
    flat = same & (np.abs(d) < SAME_AZIMUTH)
    if np.count_nonzero(flat) < MIN_RUN_SHARE * n:
        return None
    # runs of one azimuth (a pair's first echoes): their starts, per beam in order
    start = np.flatnonzero(np.concatenate([flat, [False]]) & ~np.concatenate([[False], flat]))
    ds = _wrap(np.diff(pp[start]))
    ds = ds[rr[start][1:] == rr[start][:-1]]
    if ds.size < 8:
        return None
    sign = 1.0 if np.median(ds) > 0 else -1.0
    mag = np.abs(ds)
    med = float(np.median(mag))
    pair = mag[(mag > 0.7 * med) & (mag < 1.3 * med)]
    step = float(pair.mean()) / 2 if pair.size else med / 2        # one firing, rad
    if not step > 0:
        return None
    k_all = np.zeros(n, np.int64)
    j_all = np.zeros(n, np.int64)
    bounds = np.searchsorted(rr, np.arange(height + 1))
    for u in range(height):
        lo, hi = int(bounds[u]), int(bounds[u + 1])
        if hi <= lo:
            continue
        run = flat[lo:hi - 1]                    # within one beam: `same` holds throughout
        x = np.cumsum(np.concatenate([[0.0], sign * d[lo:hi - 1] / step]))
        e = _beam_delay(x, run)
        offsets = (0.0, 0.0, e, 1.0 + e)
        k, j = np.zeros(hi - lo, np.int64), np.zeros(hi - lo, np.int64)
        base = x[0]                              # the azimuth of the current pair
        runs = np.concatenate([run, [False]])
        for i in range(1, hi - lo):
            k[i], j[i], off = _next_slot(int(k[i - 1]), int(j[i - 1]), x[i] - base, offsets)
            if runs[i] and j[i] >= 2 and k[i] > k[i - 1]:
                j[i], off = 0, 0.0        # a run of one azimuth in a new pair: its first echoes
            base = x[i] - off
        k_all[order[lo:hi]] = k
        j_all[order[lo:hi]] = j
    k_all += _beam_pair_offsets(k_all, rows, height)
    k_all -= k_all.min()
    _lone_first_echoes(k_all, j_all, rows, order)
    return 2 * k_all + (j_all % 2)


def _lone_first_echoes(k: np.ndarray[Any, Any], j: np.ndarray[Any, Any],
                       rows: np.ndarray[Any, Any], order: np.ndarray[Any, Any]) -> None:
    """Set the firing of each lone first echo (the only one of its beam in its pair, at the
    pair's azimuth: slot 0 or 1 alike) from the cloud order: a pair's first firing sequence
    (every beam) is published before its second, so a lone echo after another beam's sure
    slot-1 echo of the pair is in slot 1, one before a sure slot-0 echo in slot 0. In place."""
    kk, jj, rr = k[order], j[order], rows[order]
    same = (rr[1:] == rr[:-1]) & (kk[1:] == kk[:-1])
    sure_a = np.zeros(k.size, bool)
    sure_b = np.zeros(k.size, bool)
    pair01 = same & (jj[:-1] == 0) & (jj[1:] == 1)
    sure_a[order[:-1][pair01]] = True
    sure_b[order[1:][pair01]] = True
    lone = (j <= 1) & ~sure_a & ~sure_b
    if not lone.any() or not sure_a.any():
        return
    idx = np.arange(k.size)
    size = int(k.max()) + 1
    first_b = np.full(size, k.size, np.int64)
    np.minimum.at(first_b, k[sure_b], idx[sure_b])
    last_a = np.full(size, -1, np.int64)
    np.maximum.at(last_a, k[sure_a], idx[sure_a])
    sel = np.flatnonzero(lone)
    after_b = first_b[k[sel]] < sel
    before_a = last_a[k[sel]] > sel
    j[sel[after_b]] = 1
    j[sel[~after_b & before_a]] = 0


def _beam_delay(x: np.ndarray[Any, Any], flat: np.ndarray[Any, Any]) -> float:
    """A beam's firing delay e (firing steps): the step from the end of a run of one azimuth
    to the next point, modulo 1 (0 when most such steps are whole)."""
    run_end = np.flatnonzero(np.concatenate([[False], flat]) & ~np.concatenate([flat, [False]]))
    nxt = run_end + 1
    ok = nxt < x.size
    if not ok.any():
        return 0.0
    delta = x[nxt[ok]] - x[run_end[ok]]
    frac = np.mod(delta + 0.1, 1.0) - 0.1
    off = frac[(frac > 0.02) & (frac < 0.8)]
    if off.size < 0.25 * frac.size:
        return 0.0
    return float(np.median(off))


def _beam_pair_offsets(k: np.ndarray[Any, Any], rows: np.ndarray[Any, Any], height: int
                       ) -> np.ndarray[Any, Any]:
    """(N,) pair number offset of each point's beam against the beam with most points: the
    median difference to that beam's pair at the same place in cloud order (a pair's points of
    every beam are contiguous in the cloud)."""
    counts = np.bincount(rows, minlength=height)
    ref = int(np.argmax(counts))
    in_ref = np.flatnonzero(rows == ref)
    idx = np.arange(rows.size)
    prev = np.clip(np.searchsorted(in_ref, idx, "right") - 1, 0, in_ref.size - 1)
    nxt = np.clip(np.searchsorted(in_ref, idx, "left"), 0, in_ref.size - 1)
    agree = k[in_ref[prev]] == k[in_ref[nxt]]
    vote = k[in_ref[prev]] - k
    offset = np.zeros(height, np.int64)
    for u in range(height):
        sel = (rows == u) & agree
        if sel.any():
            offset[u] = int(np.rint(np.median(vote[sel])))
    return offset[rows]


def pixel_thetas(points: np.ndarray[Any, Any], valid: np.ndarray[Any, Any],
                 origins: np.ndarray[Any, Any], phi: np.ndarray[Any, Any]
                 ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """Per-pixel azimuth and range that put every pixel exactly on its own point.

    Args:
        points: (H, G, 3) float64 grid points (NaN where not valid).
        valid: (H, G) bool.
        origins: (H, 3) beam origins (o_x = 0), metres.
        phi: (H,) beam elevations, rad.

    Returns:
        (theta (H, G) float64 rad, NaN where not valid; rho (H, G) metres along the beam).
    """
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    rxy = np.hypot(x, y)
    oy, oz = origins[:, 1][:, None], origins[:, 2][:, None]
    with np.errstate(invalid="ignore"):
        ratio = np.clip(oy / np.maximum(rxy, 1e-9), -1, 1)
        theta = np.arctan2(y, x) - np.arcsin(ratio)
        xr = np.sqrt(np.maximum(rxy**2 - oy**2, 0.0))
    rho = xr * np.cos(phi)[:, None] + (z - oz) * np.sin(phi)[:, None]
    theta = np.where(valid, _wrap(theta), np.nan)
    rho = np.where(valid, rho, np.nan)
    return theta, rho


#: a block-pair grid holds a cloud when this share of its points lies within
#: ``MAX_FIRINGS_OFF`` firing steps of its pixel's column + beam azimuth
MIN_NEAR_SHARE, MAX_FIRINGS_OFF = 0.98, 2.0


def block_pair_fit(grid: _Grid, fit: _Fit) -> tuple[_Fit, np.ndarray[Any, Any]] | None:
    """The fit of a block-pair grid with every pixel on its own point: (the fit with ranges
    along each point's own direction, (H, G) per-pixel azimuths in rad, the column + beam
    azimuth where a pixel has no point), or None when the grid is not a beam x firing
    structure (more than 2 % of the points farther than 2 firings from their pixel's column +
    beam azimuth)."""
    theta, rho = pixel_thetas(grid.points, grid.valid, fit.origins, fit.phi)
    model = fit.alpha[grid.cidx] + fit.beta[:, None]
    valid = grid.valid
    if not valid.any():
        return None
    step = float(np.median(np.abs(_wrap(np.diff(fit.alpha))))) if fit.alpha.size > 1 else 0.0
    off = np.abs(_wrap(theta[valid] - model[valid]))
    if not step > 0 or np.mean(off <= MAX_FIRINGS_OFF * step) < MIN_NEAR_SHARE:
        return None
    return (dataclasses.replace(fit, rho=rho), np.where(valid, theta, _wrap(model)))


def block_pair_grid(pts: np.ndarray[Any, Any], names: Sequence[str], time_name: str | None,
                    header_ns: int, range_name: str | None, range_scale: float
                    ) -> tuple[_Grid, _Fit, np.ndarray[Any, Any]] | None:
    """A ring cloud as a block-pair dual-return grid: (grid, fit, (H, G) per-pixel azimuths),
    or None when the cloud does not have that layout. Times, if any, time the columns by their
    first echoes (as for any cloud whose times do not give the firings)."""
    try:
        grid = _ring_grid(pts, names, time_name, header_ns, range_name, range_scale,
                          columns=block_pair_columns)
        if grid.returns != 2:
            return None
        fit = _fit_geometry(grid.points, grid.valid, grid.cidx, grid.width, grid.known_range)
    except ConversionError:
        return None
    placed = block_pair_fit(grid, fit)
    if placed is None:
        return None
    return grid, placed[0], placed[1]
