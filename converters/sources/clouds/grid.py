"""The grid and beam model of :func:`converters.sources.clouds.importer.from_pointcloud2`: a cloud's points
arranged on (rows = beams, columns = firings), and the per-row / per-column beam model fitted to
them.

* layouts (:func:`_organized_grid`, :func:`_ring_grid`): an organized cloud keeps its rows and
  columns; a ring-tagged driver cloud gets rows from its beam number field (``ring`` /
  ``channel``) and columns from its time field (:func:`_columns_from_times`) or, without one,
  from the azimuth steps of each ring's consecutive points in cloud order (:func:`_order_times`);
  two points in one pixel are returns of one firing;
* the beam model (:func:`_fit_geometry`), in the cloud's frame (spin axis z)::

      theta(u, c) = alpha_c + beta_u       P = Rz(theta) (0, o_y[u], o_z[u]) + rho * d(theta, phi_u)

  angles in radians, offsets and ranges in metres, times int64 ns (:func:`_time_ns`).

Private to :mod:`converters.sources.clouds.importer` (its docstring states what is achievable and what is
refused); the reference path, numpy only.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from lidarscan.errors import ConfigError, ConversionError

_NS = 1_000_000_000

def _field_f64(points: np.ndarray[Any, Any], name: str) -> np.ndarray[Any, Any]:
    arr = points[name]
    if arr.ndim == 3:
        arr = arr[..., 0]
    return arr.astype(np.float64)


def _time_ns(points: np.ndarray[Any, Any], name: str, stamp_ns: int
             ) -> np.ndarray[Any, np.dtype[np.int64]]:
    """Absolute int64 ns of every point from a time field (see :func:`from_pointcloud2`)."""
    arr = points[name]
    if arr.ndim == 3:
        arr = arr[..., 0]
    if arr.dtype.kind in "iu":
        values = arr.astype(np.int64)
        big = np.abs(values).max(initial=0) > 10**15
        return values if big else values + np.int64(stamp_ns)
    seconds = arr.astype(np.float64)
    finite = seconds[np.isfinite(seconds)]
    peak = float(np.abs(finite).max(initial=0.0))
    if peak > 1e14:                         # absolute ns stored as float (Livox)
        return np.asarray(np.rint(np.nan_to_num(seconds)), dtype=np.int64)
    if peak > 1e6:                          # absolute seconds
        sec = np.floor(np.nan_to_num(seconds))
        frac = np.rint((np.nan_to_num(seconds) - sec) * 1e9)
        return np.asarray(sec, dtype=np.int64) * _NS + np.asarray(frac, dtype=np.int64)
    rel = np.asarray(np.rint(np.nan_to_num(seconds) * 1e9), dtype=np.int64)
    return rel + np.int64(stamp_ns)


# ========================================================================= geometry estimate

def _wrap(a: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    return (a + np.pi) % (2 * np.pi) - np.pi


def _group_mean(index: np.ndarray[Any, Any], values: np.ndarray[Any, Any], size: int,
                counts: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    sums = np.bincount(index, weights=values, minlength=size)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, sums / np.maximum(counts, 1), 0.0)


@dataclasses.dataclass
class _Fit:
    phi: np.ndarray[Any, Any]        # (H,)
    beta: np.ndarray[Any, Any]       # (H,)
    alpha: np.ndarray[Any, Any]      # (W,)
    origins: np.ndarray[Any, Any]    # (H, 3)
    rho: np.ndarray[Any, Any]        # (H, W) metres, NaN where not valid


def _fill_periodic(values: np.ndarray[Any, Any], known: np.ndarray[Any, Any],
                   field: str) -> np.ndarray[Any, Any]:
    """Fill unknown column azimuths by linear interpolation of the unwrapped known ones."""
    width = values.size
    idx = np.flatnonzero(known)
    if idx.size == width:
        return values
    if idx.size < 2:
        raise ConversionError(field, f"{idx.size} columns with points",
                              "at least two columns with valid points")
    unwrapped = np.unwrap(values[idx])
    slope = (unwrapped[-1] - unwrapped[0]) / max(idx[-1] - idx[0], 1)
    ext_idx = np.concatenate([[idx[-1] - width], idx, [idx[0] + width]])
    ext_val = np.concatenate([[unwrapped[-1] - slope * width], unwrapped,
                              [unwrapped[0] + slope * width]])
    out = np.interp(np.arange(width), ext_idx, ext_val)
    out[idx] = unwrapped
    return _wrap(out)


def _linear_fit(alpha: np.ndarray[Any, Any], counts: np.ndarray[Any, Any]
                ) -> np.ndarray[Any, Any]:
    """Column azimuths as a straight line in the column index (count-weighted fit of the
    unwrapped azimuths of the columns that have points)."""
    idx = np.flatnonzero(counts > 0)
    if idx.size < 2:
        return alpha
    unwrapped = np.unwrap(alpha[idx])
    slope, icpt = np.polyfit(idx.astype(np.float64), unwrapped, 1, w=np.sqrt(counts[idx]))
    return np.asarray(icpt + slope * np.arange(alpha.size, dtype=np.float64), dtype=np.float64)


def _fit_geometry(points: np.ndarray[Any, Any], valid: np.ndarray[Any, Any],
                  cidx: np.ndarray[Any, Any], width: int,
                  known_range: np.ndarray[Any, Any] | None, min_spread: float = 0.02) -> _Fit:
    """Fit the per-row / per-column beam model to a grid of points.

    Args:
        points: (H, G, 3) float64 points in the grid.
        valid: (H, G) bool.
        cidx: (H, G) measurement column of every grid pixel (0..width-1).
        width: number of measurement columns.
        known_range: (H, G) ranges along the beam (m) from the cloud, or None.
        min_spread: rows whose points spread less than this (m, standard deviation along the
            beam) take their elevation from the common point of the other rows' beam lines
            (one range fixes no direction).
    """
    height = points.shape[0]
    u_idx, g_idx = np.nonzero(valid)
    if u_idx.size < 3:
        raise ConversionError("cloud", f"{u_idx.size} valid points",
                              "at least 3 finite points to estimate a geometry")
    pts = points[u_idx, g_idx]
    X, Y, Z = pts[:, 0], pts[:, 1], pts[:, 2]
    c = cidx[u_idx, g_idx]
    rxy = np.hypot(X, Y)
    psi = np.arctan2(Y, X)
    cnt_u = np.bincount(u_idx, minlength=height).astype(np.float64)
    cnt_c = np.bincount(c, minlength=width).astype(np.float64)
    # initial column azimuths: circular mean over the rows
    alpha = np.arctan2(np.bincount(c, np.sin(psi), width), np.bincount(c, np.cos(psi), width))
    beta = np.zeros(height)
    oy = np.zeros(height)
    g = 1.0 / np.maximum(rxy, 1e-9)
    # angle model psi = alpha_c + beta_u + asin(o_y[u] / rxy): alternate between the columns
    # (alpha) and, per row, the joint linear regression of psi - alpha on (1, 1/rxy) -> (beta,
    # o_y); the asin curvature (< 1e-7 rad) is carried as a fixed correction.
    sum_g = np.bincount(u_idx, g, height)
    sum_gg = np.bincount(u_idx, g * g, height)
    denom = cnt_u * sum_gg - sum_g**2
    solvable = (cnt_u >= 3) & (denom > 1e-9 * np.maximum(cnt_u * sum_gg, 1e-300))
    # too few points per column to fix every column's azimuth: assume evenly spaced columns
    sparse = float(np.mean(cnt_c >= 2)) < 0.5
    if sparse:
        alpha = _linear_fit(alpha, cnt_c)
    psi = alpha[c] + _wrap(psi - alpha[c])        # one branch: the loop needs no wrapping
    for _ in range(500):
        x_ratio = np.clip(oy[u_idx] * g, -1, 1)
        e = psi - alpha[c] - (np.arcsin(x_ratio) - x_ratio)
        sum_e = np.bincount(u_idx, e, height)
        sum_eg = np.bincount(u_idx, e * g, height)
        with np.errstate(invalid="ignore", divide="ignore"):
            new_oy = np.where(solvable, (cnt_u * sum_eg - sum_g * sum_e) / np.where(
                solvable, denom, 1.0), 0.0)
            new_beta = np.where(cnt_u > 0, (sum_e - new_oy * sum_g) / np.maximum(cnt_u, 1), 0.0)
        x_ratio = np.clip(new_oy[u_idx] * g, -1, 1)
        res = psi - np.arcsin(x_ratio) - new_beta[u_idx] - alpha[c]
        step = _group_mean(c, res, width, cnt_c)
        if sparse:
            step = _linear_fit(alpha + step, cnt_c) - alpha
        alpha = alpha + step
        change = max(np.abs(step).max(initial=0), np.abs(new_beta - beta).max(initial=0),
                     np.abs(new_oy - oy).max(initial=0) * 1e-1)
        beta, oy = new_beta, new_oy
        if change < 1e-14:
            break
    # gauge: mean beam offset 0 over rows with points
    has_row = cnt_u > 0
    shift = float(beta[has_row].mean()) if has_row.any() else 0.0
    beta[has_row] -= shift
    beta[~has_row] = 0.0
    alpha = _wrap(alpha + shift)
    alpha = _fill_periodic(alpha, cnt_c > 0, "cloud columns")
    theta = alpha[c] + beta[u_idx]
    cos_t, sin_t = np.cos(theta), np.sin(theta)
    xr = cos_t * X + sin_t * Y

    # elevation and axis-crossing height per row (total least squares in the (xr, z) plane)
    mx = _group_mean(u_idx, xr, height, cnt_u)
    mz = _group_mean(u_idx, Z, height, cnt_u)
    dx, dz = xr - mx[u_idx], Z - mz[u_idx]
    sxx = _group_mean(u_idx, dx * dx, height, cnt_u)
    szz = _group_mean(u_idx, dz * dz, height, cnt_u)
    sxz = _group_mean(u_idx, dx * dz, height, cnt_u)
    phi = 0.5 * np.arctan2(2 * sxz, sxx - szz)
    spread = np.sqrt(np.maximum(0.5 * (sxx + szz) + np.hypot(0.5 * (sxx - szz), sxz), 0))
    good = (cnt_u >= 3) & (spread >= min_spread)
    oz = mz - mx * np.tan(phi)
    weak = has_row & ~good
    if weak.any():
        # a row whose points all lie at about one range fixes no direction: take the line
        # through its centroid and the point closest to the other rows' lines (the common beam
        # origin of Ouster-like sensors; the spin axis at the median crossing height otherwise)
        x0, z0 = 0.0, float(np.median(oz[good])) if good.any() else 0.0
        if good.sum() >= 2:
            nrm = np.stack([-np.sin(phi[good]), np.cos(phi[good])], -1)          # line normals
            a = nrm.T @ nrm
            b = nrm.T @ np.sum(nrm * np.stack([mx[good], mz[good]], -1), -1)
            reg = 1e-6 * np.trace(a)
            sol = np.linalg.solve(a + reg * np.eye(2), b + reg * np.array([x0, z0]))
            x0, z0 = float(sol[0]), float(sol[1])
        phi[weak] = np.arctan2(mz[weak] - z0, mx[weak] - x0)
        oz[weak] = z0 - x0 * np.tan(phi[weak])
    origins = np.zeros((height, 3))
    origins[:, 1], origins[:, 2] = oy, oz

    rho = np.full(valid.shape, np.nan)
    if known_range is not None:
        k = known_range[u_idx, g_idx]
        cos_p, sin_p = np.cos(phi)[u_idx], np.sin(phi)[u_idx]
        ax = _group_mean(u_idx, xr - k * cos_p, height, cnt_u)
        az = _group_mean(u_idx, Z - k * sin_p, height, cnt_u)
        resid = np.hypot(xr - ax[u_idx] - k * cos_p, Z - az[u_idx] - k * sin_p)
        if np.all(np.isfinite(resid)) and float(np.percentile(resid, 99)) < 1e-3:
            origins[:, 0], origins[:, 2] = ax, az
            rho[u_idx, g_idx] = k
        else:
            known_range = None
    if known_range is None:
        rho[u_idx, g_idx] = xr * np.cos(phi)[u_idx] + (Z - oz[u_idx]) * np.sin(phi)[u_idx]
    # rows without any point: interpolate the elevation by row index
    if not has_row.all():
        rows = np.arange(height)
        phi[~has_row] = np.interp(rows[~has_row], rows[has_row], phi[has_row])
    return _Fit(phi=phi, beta=beta, alpha=alpha, origins=origins, rho=rho)


# --------------------------------------------------------------------------- cloud layouts

_TIME_FIELDS = ("t", "time", "timestamp", "time_stamp", "offset_time")
_RANGE_FIELDS = ("range", "distance")
#: beam number fields: velodyne / Hesai / RoboSense ``ring``, Nebula ``channel``
_RING_FIELDS = ("ring", "channel")
_SKIP = {"x", "y", "z", *_RING_FIELDS}


def _ring_name(names: Sequence[str]) -> str | None:
    return next((n for n in _RING_FIELDS if n in names), None)


def _ring_values(ring: np.ndarray[Any, Any], name: str) -> np.ndarray[Any, Any]:
    """A beam number field's values as int64, refused unless all lie in 0..65535 (the
    ``LidarInfo.beam_ids`` they become are uint16; NaN or a fraction in a float field is
    refused too: such a field holds no beam numbers)."""
    if ring.size and ring.dtype.kind == "f":
        bad = ~np.isfinite(ring) | (ring != np.round(ring))
        if bad.any():
            raise ConversionError(name, f"{np.count_nonzero(bad)} values such as "
                                  f"{ring[bad].flat[0]}", "whole beam numbers from 0 to 65535")
    if ring.size and not (ring.min() >= 0 and ring.max() <= 65535):
        raise ConversionError(name, f"values from {ring.min()} to {ring.max()}",
                              "beam numbers from 0 to 65535")
    return ring.astype(np.int64)


def _pick_time_field(names: Sequence[str], time_field: str | None) -> str | None:
    if time_field is not None:
        if time_field not in names:
            raise ConfigError("time_field", time_field, f"one of the cloud's fields {names}")
        return time_field
    for name in _TIME_FIELDS:
        if name in names:
            return name
    return None


def _median_by(index: np.ndarray[Any, Any], values: np.ndarray[Any, Any], size: int
               ) -> np.ndarray[Any, Any]:
    """Median of ``values`` per group (NaN for empty groups)."""
    out = np.full(size, np.nan)
    if index.size == 0:
        return out
    order = np.lexsort((values, index))
    idx, vals = index[order], values[order]
    starts = np.searchsorted(idx, np.arange(size), "left")
    ends = np.searchsorted(idx, np.arange(size), "right")
    has = ends > starts
    lo = (starts + ends - 1) // 2
    hi = (starts + ends) // 2
    out[has] = 0.5 * (vals[lo[has]] + vals[hi[has]])
    return out


def _interp_missing(values: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    known = np.isfinite(values)
    if known.all() or not known.any():
        return np.asarray(np.nan_to_num(values), dtype=np.float64)
    idx = np.arange(values.size)
    return np.asarray(np.interp(idx, idx[known], values[known]), dtype=np.float64)


def _pixel_ranks(pix: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """Rank of every point among the points of its pixel, in cloud order (0 = first return)."""
    o = np.argsort(pix, kind="stable")
    ps = pix[o]
    starts = np.flatnonzero(np.concatenate([[True], ps[1:] != ps[:-1]]))
    run = np.arange(ps.size) - np.repeat(starts, np.diff(np.concatenate([starts, [ps.size]])))
    rank = np.empty(ps.size, np.int64)
    rank[o] = run
    return rank


@dataclasses.dataclass
class _Grid:
    """Points arranged on (rows = beams, grid columns) plus their bookkeeping."""

    points: np.ndarray[Any, Any]              # (H, G, 3) float64, NaN where no point
    valid: np.ndarray[Any, Any]               # (H, G)
    cidx: np.ndarray[Any, Any]                # (H, G) measurement column
    width: int
    shifts: np.ndarray[Any, Any]              # (H,) pixel shift (grid = destaggered if any)
    beam_ids: np.ndarray[Any, Any]            # (H,) ring / source row
    beam_times: np.ndarray[Any, Any]          # (H,) int64 ns
    column_times: np.ndarray[Any, Any] | None  # (W,) absolute int64 ns, or None
    channels: dict[str, np.ndarray[Any, Any]]  # grid images
    known_range: np.ndarray[Any, Any] | None
    per_scan_azimuths: bool
    dropped: int = 0
    returns: int = 1                           # grid columns = returns x width
    time_columns: bool = False                 # columns (firings) from the time field


def _organized_grid(pts: np.ndarray[Any, Any], names: Sequence[str], time_name: str | None,
                    stamp_ns: int, range_name: str | None, range_scale: float) -> _Grid:
    height, width = pts.shape
    xyz = np.stack([_field_f64(pts, n) for n in "xyz"], -1)
    valid = np.all(np.isfinite(xyz), -1) & np.any(xyz != 0, -1)
    shifts = np.zeros(height, np.int64)
    beam_times = np.zeros(height, np.int64)
    column_times = None
    if time_name is not None:
        t_abs = _time_ns(pts, time_name, stamp_ns)
        if np.ptp(t_abs) > 0:
            # the measurement column 0 of each row is where its times wrap (largest drop)
            drop = t_abs - np.roll(t_abs, 1, axis=1)
            shifts = np.argmin(drop, axis=1).astype(np.int64)
            if not np.any(drop < 0):
                shifts[:] = 0
            cols = np.arange(width)
            src = (cols[None, :] + shifts[:, None]) % width          # grid column of c
            meas = np.take_along_axis(t_abs, src, axis=1).astype(np.float64)
            col = np.median(meas, axis=0)
            beam = np.median(meas - col[None, :], axis=1)
            beam -= beam.min()
            col = np.median(meas - beam[:, None], axis=0)
            beam_times = np.rint(beam).astype(np.int64)
            column_times = np.rint(col).astype(np.int64)
            shifts = shifts % width
            shifts[shifts > width // 2] -= width   # smallest magnitude representation
    cidx = (np.arange(width)[None, :] - shifts[:, None]) % width
    ring_name = _ring_name(names)
    if ring_name is not None:
        ring = pts[ring_name]
        ring = _ring_values(ring[..., 0] if ring.ndim == 3 else ring, ring_name)
        beam_ids = np.array([np.bincount(r - r.min()).argmax() + r.min() for r in ring])
    else:
        beam_ids = np.arange(height)
    known = None
    if range_name is not None:
        known = _field_f64(pts, range_name) * range_scale
        known = np.where(valid & (known > 0), known, np.nan)
        if not np.isfinite(known[valid]).all():
            known = None
    channels = {n: np.array(pts[n]) for n in names
                if n not in _SKIP and n != time_name and n != range_name}
    return _Grid(points=np.where(valid[..., None], xyz, np.nan), valid=valid, cidx=cidx,
                 width=width, shifts=shifts, beam_ids=beam_ids, beam_times=beam_times,
                 column_times=column_times, channels=channels, known_range=known,
                 per_scan_azimuths=False)


#: Largest grid estimated from an unorganized cloud: no spinning lidar has more beams or more
#: columns per turn; the checks keep garbage fields from allocating gigabytes.
MAX_ROWS, MAX_COLUMNS = 1024, 1 << 16


def _check_grid_size(height: int, width: int, points: int, source: str) -> None:
    """Refuse a ring x column grid that no lidar produces, before allocating it."""
    if height > MAX_ROWS or width > MAX_COLUMNS or height * width > 16 * points + 65536:
        raise ConversionError("cloud", f"{height} rings x {width} columns from {points} points",
                              f"at most {MAX_ROWS} rings, {MAX_COLUMNS} columns and a grid not "
                              f"much larger than the cloud (check the cloud's {source})")


def _ring_grid(pts: np.ndarray[Any, Any], names: Sequence[str], time_name: str | None,
               stamp_ns: int, range_name: str | None, range_scale: float, *,
               time_columns: bool = True, columns: Any = None) -> _Grid:
    """Unorganized (or ring-mixed) cloud -> grid of rings x firings, up to two returns a pixel.

    Columns come from the per-point times when the cloud has them (and ``time_columns``), else
    from the cloud's own point order and each ring's azimuth steps (:func:`_order_times`); the
    times then give only the firings' times (their first returns') and the beams' offsets.
    Points sharing a pixel (same ring, same firing: dual return) become the pixel's first and
    second return in cloud order; a third is dropped and counted. ``columns``: a function
    (azimuths (N,) rad, rows (N,), height) -> (N,) columns or None, used instead of the times
    and the azimuth steps (None from it: ConversionError).
    """
    ring_name = _ring_name(names) or "ring"
    flat = pts.reshape(-1)
    xyz = np.stack([_field_f64(flat[None, :], n)[0] for n in "xyz"], -1)
    ok = np.all(np.isfinite(xyz), -1) & np.any(xyz != 0, -1)
    flat, xyz = flat[ok], xyz[ok]
    ring = flat[ring_name]
    ring = _ring_values(ring[:, 0] if ring.ndim == 2 else ring, ring_name)
    rings, row_of = np.unique(ring, return_inverse=True)
    height = rings.size
    _check_grid_size(height, 1, flat.size, f"{ring_name} values")
    if flat.size < 3:
        raise ConversionError("cloud", f"{flat.size} valid points", "at least 3 finite points")
    # rows top -> bottom: order rings by their median elevation
    elev = np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1]))
    med = _median_by(row_of, elev, height)
    order = np.argsort(-med, kind="stable")
    rank = np.empty(height, np.int64)
    rank[order] = np.arange(height)
    rows = rank[row_of]
    beam_ids = rings[order]
    psi = np.arctan2(xyz[:, 1], xyz[:, 0])

    beam_times = np.zeros(height, np.int64)
    column_times = None
    t_abs = _time_ns(flat[None, :], time_name, stamp_ns)[0] if time_name else None
    cols = None
    if columns is not None:
        cols = columns(psi, rows, height)
        if cols is None:
            raise ConversionError("cloud", "no firing layout found by the given rule",
                                  "points in that layout")
    elif time_columns and t_abs is not None and np.ptp(t_abs) > 0:
        cols, beam_times = _columns_from_times(t_abs, rows, height)
    time_cols = cols is not None and columns is None
    if cols is not None:
        # times shared by several firings (a driver stamping per packet or block) put more than
        # two points in a pixel: then the times do not resolve firings, the point order does
        width = int(cols.max()) + 1
        _check_grid_size(height, width, flat.size, "time spacing")
        if np.count_nonzero(_pixel_ranks(rows * width + cols) >= 2) > 0.01 * cols.size:
            cols, time_cols = None, False
    if cols is None:
        beam_times[:] = 0
        cols = _columns_from_times(_order_times(psi, rows, height), rows, height)[0]
        if cols is None:
            raise ConversionError("cloud", "rings without azimuth steps",
                                  "points spread over azimuth (or a time field)")
    width = int(cols.max()) + 1
    _check_grid_size(height, width, flat.size, "time or azimuth spacing")
    pix = rows * width + cols
    # return number of every point: its rank among the points of its pixel, in cloud order
    ret = _pixel_ranks(pix)
    returns = 2 if np.any(ret == 1) else 1
    keep = ret < returns
    dropped = int(np.count_nonzero(~keep))
    gpix = (rows * returns + ret) * width + cols        # grid (H, returns * W), row-major
    gpix = gpix[keep]
    size = height * returns * width
    grid_pts = np.full((size, 3), np.nan)
    grid_pts[gpix] = xyz[keep]
    valid = np.zeros(size, bool)
    valid[gpix] = True
    if time_cols and t_abs is not None:
        beam_times, column_times = _beam_and_column_times(
            t_abs[keep], rows[keep], cols[keep], beam_times, height, width)
    elif t_abs is not None and np.ptp(t_abs) > 0:
        # times that do not resolve the firings (a driver stamping per packet or block, or
        # velodyne_pointcloud's single-return table on dual-return packets, which stamps a
        # firing's second return two firings after its first): a firing's time is its first
        # return's, each beam's offset its median lag inside the firings
        first = keep & (ret == 0)
        beam_times, column_times = _beam_and_column_times(
            t_abs[first], rows[first], cols[first], np.zeros(height, np.int64), height, width)
    known = None
    if range_name is not None:
        k = _field_f64(flat[None, :], range_name)[0] * range_scale
        flat_known = np.full(size, np.nan)
        flat_known[gpix] = k[keep]
        known = flat_known.reshape(height, returns * width)
        if not np.isfinite(flat_known[valid]).all() or np.any(flat_known[valid] <= 0):
            known = None
    channels = {}
    for n in names:
        if n in _SKIP or n == time_name or n == range_name:
            continue
        src = flat[n][keep]
        img = np.zeros((size,) + src.shape[1:], src.dtype)
        img[gpix] = src
        channels[n] = img.reshape((height, returns * width) + src.shape[1:])
    cidx = np.broadcast_to(np.tile(np.arange(width), returns)[None, :],
                           (height, returns * width))
    return _Grid(points=grid_pts.reshape(height, returns * width, 3),
                 valid=valid.reshape(height, returns * width), cidx=cidx, width=width,
                 shifts=np.zeros(height, np.int64), beam_ids=beam_ids, beam_times=beam_times,
                 column_times=column_times, channels=channels, known_range=known,
                 per_scan_azimuths=True, dropped=dropped, returns=returns,
                 time_columns=time_cols)


def _order_times(psi: np.ndarray[Any, Any], rows: np.ndarray[Any, Any], height: int
                 ) -> np.ndarray[Any, np.dtype[np.int64]]:
    """Pseudo-times (firing periods x 1e6) of a cloud without times, from its point order.

    Drivers publish points firing by firing, so each ring's points are in firing order: the
    azimuth step between a ring's consecutive points counts the firings between them (0 for the
    second return of a firing, negative where a driver goes back for the second return's block).
    That numbers each ring's firings up to an offset; the offset of each ring is its median
    position (in firings) against the ring with most points, interpolated by cloud index (or,
    for a cloud sorted ring after ring, the ring's mean azimuth phase).
    """
    n = psi.size
    idx = np.arange(n)
    order = np.lexsort((idx, rows))
    rr, pp = rows[order], psi[order]
    same = rr[1:] == rr[:-1]
    d = _wrap(np.diff(pp))
    absd = np.abs(d[same])
    if absd.size == 0 or not np.any(absd > 0):
        return np.zeros(n, np.int64)
    q0 = float(np.quantile(absd, 0.75))
    moving = absd[absd > 0.3 * q0]
    q = float(np.quantile(moving, 0.2))
    near = moving[(moving > 0.6 * q) & (moving < 1.4 * q)]
    step = float(near.mean()) if near.size else q
    sign = -1.0 if np.median(d[same][absd > 0.3 * q0]) < 0 else 1.0
    steps = np.where(same, np.rint(sign * d / step), 0.0)
    count = np.concatenate([[0.0], np.cumsum(steps)])
    first = np.concatenate([[True], ~same])
    count -= np.repeat(count[first], np.diff(np.concatenate([np.flatnonzero(first), [n]])))
    c = np.empty(n)
    c[order] = count                                     # firing count within each ring
    if np.count_nonzero(np.diff(rows)) < 2 * height:
        # ring after ring (a cloud sorted by ring): align the rings by azimuth instead, each
        # ring's offset the circular mean of (its azimuth in steps - its firing count)
        turn = 2 * np.pi / step
        a = np.mod(sign * psi / step - c, turn) * (2 * np.pi / turn)
        offset = np.arctan2(np.bincount(rows, np.sin(a), height),
                            np.bincount(rows, np.cos(a), height)) * turn / (2 * np.pi)
    else:
        ref = int(np.argmax(np.bincount(rows, minlength=height)))
        in_ref = np.flatnonzero(rows == ref)
        f = np.interp(idx.astype(np.float64), in_ref.astype(np.float64), c[in_ref])
        offset = _median_by(rows, f - c, height)
    offset = np.nan_to_num(offset)
    # where a firing starts: the phase (ring offset mod 1) after which the cloud order has the
    # fewest descents (one a firing at the true start, two when cut inside a firing); phases are
    # then packed into half a period from that start, so the firing split falls there
    phase = np.mod(offset, 1.0)
    start = _firing_start(phase[rows], phase[np.bincount(rows, minlength=height) > 0])
    shifted = np.mod(phase - start, 1.0)
    tau = c + (offset - start - shifted + 0.5 * shifted)[rows]
    return np.asarray(np.rint((tau - tau.min()) * 1e6), dtype=np.int64)


def _firing_start(seq: np.ndarray[Any, Any], candidates: np.ndarray[Any, Any]) -> float:
    """The candidate phase s minimising the descents of ``(seq - s) mod 1`` along ``seq``.

    A consecutive pair (a, b) descends after the shift iff a > b and s is not in (b, a], or
    a < b and s is in (a, b]; counted for all candidates at once with sorted bounds.
    """
    a, b = seq[:-1], seq[1:]
    moving = a != b
    a, b = a[moving], b[moving]
    down = a > b
    cand = np.sort(np.unique(candidates))
    lo_d, hi_d = np.sort(b[down]), np.sort(a[down])          # s in (b, a]: descent removed
    lo_u, hi_u = np.sort(a[~down]), np.sort(b[~down])        # s in (a, b]: descent added

    def inside(lo: np.ndarray[Any, Any], hi: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        return (np.searchsorted(lo, cand, "left") - np.searchsorted(hi, cand, "left"))

    count = down.sum() - inside(lo_d, hi_d) + inside(lo_u, hi_u)
    return float(cand[int(np.argmin(count))]) if cand.size else 0.0


def _columns_from_times(t_abs: np.ndarray[Any, Any], rows: np.ndarray[Any, Any], height: int
                        ) -> tuple[Any, np.ndarray[Any, Any]]:
    """Column index of every point from its time, and each beam's firing offset (ns).

    Firings repeat with a period (median spacing of a beam's consecutive times, refined by the
    mean of the spacings near it); each beam's phase inside the period is its circular mean, and
    a firing starts after the largest gap between the beams' phases. Points are then sorted by
    ``t - beam offset`` and a new column starts at every gap longer than half a period (a gap of
    k periods skips k - 1 empty columns), so slow drifts of the rotation never accumulate.
    """
    order = np.lexsort((t_abs, rows))
    tt, rr = t_abs[order], rows[order]
    d = np.diff(tt)
    d = d[(rr[1:] == rr[:-1]) & (d > 0)].astype(np.float64)
    if d.size == 0:
        return None, np.zeros(height, np.int64)
    period = float(np.median(d))
    near = (d > 0.5 * period) & (d < 1.5 * period)
    if near.any():
        period = float(d[near].mean())
    t0 = int(t_abs.min())
    rel = (t_abs - t0).astype(np.float64)
    ang = 2 * np.pi * np.mod(rel, period) / period
    cnt = np.bincount(rows, minlength=height)
    phase = np.arctan2(np.bincount(rows, np.sin(ang), height),
                       np.bincount(rows, np.cos(ang), height))
    phase = np.mod(phase, 2 * np.pi) * period / (2 * np.pi)           # ns in [0, period)
    used = np.sort(phase[cnt > 0])
    gaps = np.diff(np.concatenate([used, [used[0] + period]]))
    start = used[(int(np.argmax(gaps)) + 1) % used.size]
    beam = np.mod(phase - start, period)
    beam[cnt == 0] = 0.0
    tc = rel - beam[rows]
    o = np.argsort(tc, kind="stable")
    steps = np.diff(tc[o])
    inc = np.where(steps > 0.5 * period, np.maximum(np.rint(steps / period), 1), 0)
    k = np.empty(tc.size, np.int64)
    k[o] = np.concatenate([[0], np.cumsum(inc)]).astype(np.int64)
    return k, np.rint(beam).astype(np.int64)


def _beam_and_column_times(t: np.ndarray[Any, Any], rows: np.ndarray[Any, Any],
                           cols: np.ndarray[Any, Any], beam0: np.ndarray[Any, Any],
                           height: int, width: int
                           ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """Each beam's firing offset (int64 ns, the smallest 0) and each column's absolute time
    (int64 ns) from points' absolute times ``t`` in (``rows``, ``cols``): alternating medians
    (column time = median of t - beam offset, beam offset = median of t - column time), starting
    from the offsets ``beam0``; empty columns interpolated."""
    beam = np.asarray(beam0, np.float64)
    t0 = np.int64(t.min()) if t.size else np.int64(0)
    rel = (t - t0).astype(np.float64)        # float64 of epoch ns would round to 256 ns
    for _ in range(2):
        col = _interp_missing(_median_by(cols, rel - beam[rows], width))
        beam = np.nan_to_num(_median_by(rows, rel - col[cols], height))
        beam -= beam.min() if beam.size else 0.0
    beam_times = np.rint(beam).astype(np.int64)
    return beam_times, _column_times(t - beam_times[rows], cols, width)


def _column_times(t_col: np.ndarray[Any, Any], cols: np.ndarray[Any, Any], width: int
                  ) -> np.ndarray[Any, Any]:
    """Absolute ns of each column: median over its points, interpolated where empty."""
    t0 = np.int64(t_col.min()) if t_col.size else np.int64(0)
    med = _median_by(cols, (t_col - t0).astype(np.float64), width)
    return np.asarray(np.rint(_interp_missing(med)), dtype=np.int64) + t0
