"""PointCloud2 -> LidarScan + estimated LidarInfo, and the error of such an estimate.

:func:`from_pointcloud2` estimates the geometry of the beam model from the points themselves:
organized clouds (rows = beams, e.g. ouster-ros H x W destaggered) and ring-tagged clouds
(velodyne with ring + time, Hesai / RoboSense with ring + timestamp; organized velodyne clouds
too). The model fitted, in the cloud's frame (spin axis = z, identity lidar_to_sensor)::

    theta(u, c) = alpha_c + beta_u       P = Rz(theta) (0, o_y[u], o_z[u]) + rho * d(theta, phi_u)

The along-beam offset is gauge-free (``o_x = 0``: rho is measured from where the beam line
crosses the spin axis) unless the cloud has a range field (ouster-ros ``range`` mm), whose values
are kept and the full offset fitted. Column order / stagger come from per-point times (the time of
each destaggered pixel reveals its measurement column); without times the cloud's own column order
is used (exact for organized clouds, whose destaggered columns still fit ``alpha_v + beta'_u``).
:func:`estimation_error` re-projects the estimate and compares it with the cloud's points.

Driver clouds (unorganized, points in the driver's order, no-return pixels omitted): rows are the
values of the beam number field (``ring``: velodyne_pointcloud, Hesai ROS driver, RoboSense;
``channel``: Nebula), columns the firings, found from the time field (``time`` f32 s relative,
``timestamp`` f64 absolute s, Nebula ``time_stamp`` u32 ns relative, ...) or, without one, from
the cloud's point order: drivers publish firing after firing, so the azimuth step between a
ring's consecutive points counts the firings between them. Two points in one pixel (same ring,
same firing: dual return) become ``range`` and ``range2`` (and ``intensity``/``intensity2``...)
in cloud order; Nebula's ``distance`` is used as the range along the beam when it fits. With a
known LidarInfo (``info=``, e.g. from the calibration file) any cloud, xyz only too, is placed by
that geometry instead of estimating one. A cloud the model does not hold (more than 2 % of the
points left without a pixel, or a median re-projection error above 2 cm, e.g. a Livox rosette) is
refused with an error saying what was tried, never returned with points silently lost.

What is achievable (tests/test_pointcloud2.py): ouster-ros clouds of the REAL Ouster frames in
tests/data re-project to <= 0.03 mm (float32 rounding; OS-2-128 0.015 mm max with the range
field, 0.03 mm from xyz alone; OS-0-32 0.005 mm), times exactly; a noise-free VLP-16-like ring
cloud to 0.006 mm, times to 4 ns (f32 relative) or ~0.27 us (f64 absolute seconds: that is the
float64 resolution of an epoch time). Real Velodyne output is bounded by the driver itself:
velodyne_pointcloud rounds every laser's interpolated azimuth to 0.01 deg, a per-point pattern a
per-column + per-beam model cannot hold, so expect up to ~1.3e-4 rad x range (simulated VLP-16:
7.6 mm max at 60 m, 1.5 mm RMS). Very sparse clouds (most columns with < 2 points, e.g. second
returns) are fitted with evenly spaced column azimuths.

"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from converters.cloud_layout import read_points
from lidarscan.datatypes import datatype_of
from lidarscan.errors import ConfigError, ConversionError, InfoMismatchError, ValidationError
from lidarscan.scan import as_array, make_info, make_scan
from lidarscan.stamps import to_ns

__all__ = ["ReprojectionError", "estimation_error", "from_pointcloud2"]

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
        ring = (ring[..., 0] if ring.ndim == 3 else ring).astype(np.int64)
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
               stamp_ns: int, range_name: str | None, range_scale: float) -> _Grid:
    """Unorganized (or ring-mixed) cloud -> grid of rings x firings, up to two returns a pixel.

    Columns come from the per-point times when the cloud has them, else from the cloud's own
    point order and each ring's azimuth steps (:func:`_order_times`). Points sharing a pixel
    (same ring, same firing: dual return) become the pixel's first and second return in cloud
    order; a third is dropped and counted.
    """
    ring_name = _ring_name(names) or "ring"
    flat = pts.reshape(-1)
    xyz = np.stack([_field_f64(flat[None, :], n)[0] for n in "xyz"], -1)
    ok = np.all(np.isfinite(xyz), -1) & np.any(xyz != 0, -1)
    flat, xyz = flat[ok], xyz[ok]
    ring = flat[ring_name]
    ring = (ring[:, 0] if ring.ndim == 2 else ring).astype(np.int64)
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
    if t_abs is not None and np.ptp(t_abs) > 0:
        cols, beam_times = _columns_from_times(t_abs, rows, height)
    time_cols = cols is not None
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
        tf, rf, cf = t_abs[keep], rows[keep], cols[keep]
        beam = beam_times.astype(np.float64)
        for _ in range(2):
            col = _interp_missing(_median_by(cf, tf - beam[rf], width))
            beam = np.nan_to_num(_median_by(rf, tf - col[cf], height))
            beam -= beam.min()
        beam_times = np.rint(beam).astype(np.int64)
        column_times = _column_times(tf - beam_times[rf], cf, width)
    elif t_abs is not None and np.ptp(t_abs) > 0:
        column_times = _column_times(t_abs[keep], cols[keep], width)
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
                 per_scan_azimuths=True, dropped=dropped, returns=returns)


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


def _column_times(t_col: np.ndarray[Any, Any], cols: np.ndarray[Any, Any], width: int
                  ) -> np.ndarray[Any, Any]:
    """Absolute ns of each column: median over its points, interpolated where empty."""
    med = _median_by(cols, t_col.astype(np.float64), width)
    return np.asarray(np.rint(_interp_missing(med)), dtype=np.int64)


# ----------------------------------------------------------------------------- public API

def from_pointcloud2(cloud: Any, *, layout: str = "auto", time_field: str | None = None,
                     range_field: str | None = "auto", range_scale: float | None = None,
                     stamp_ns: int | None = None, frame_id: str | None = None,
                     info: Any = None, as_dataclass: bool = False) -> tuple[Any, Any]:
    """PointCloud2 from a lidar driver -> (LidarScan, estimated LidarInfo).

    Args:
        cloud: ``sensor_msgs/PointCloud2`` (rclpy message or dataclass); any byte order, float32
            or float64 x/y/z, padding, row padding. Never modified.
        layout: "organized" (rows = beams, e.g. ouster-ros H x W), "ring" (group points by their
            ``ring`` / ``channel`` field; velodyne / Hesai / RoboSense / Nebula, organized or
            not) or "auto" (organized when height > 1 and each row holds one ring, else ring).
        time_field: per-point time field; default the first of t, time, timestamp,
            time_stamp, offset_time. Integer fields are ns, float fields s; values > 1e6 s
            (or > 1e15 ns) are absolute, smaller ones relative to the header stamp.
        range_field: field with ranges along the beam ("auto": ``range`` if present; None:
            ignore). Its values become the scan's ranges when they fit the geometry.
        range_scale: metres per unit of the range field; default 0.001 for integer fields
            (ouster-ros millimetres), 1 for float fields.
        stamp_ns: the info's stamp (version key); default the scan's stamp.
        frame_id: frame of scan and info; default the cloud's.
        info: a known LidarInfo of the sensor (e.g. from its calibration file): every point is
            then placed by this geometry (row by elevation, column by azimuth, range along its
            beam; a second point in a pixel is its second return) and the scan refers to this
            info, which is returned as is. Works for xyz-only clouds.
        as_dataclass: return :mod:`lidarscan.types` dataclasses instead of rclpy messages.

    Returns:
        (scan, info): ``range`` float32 metres (+Inf where the cloud has no point) first, then
        every other scalar field of the cloud as a channel of its own datatype (time, ring, range
        and x/y/z excluded); with two points in a pixel (dual return) also ``range2`` and each
        field's second-return channel (``intensity2``, ...). Organized clouds keep their column
        order (``is_destaggered`` true with the estimated ``pixel_shift_by_row`` when times
        reveal a stagger); ring clouds are in firing order with per-scan
        ``column_azimuth_angles``. ``beam_ids`` = ring values.

    Raises:
        ConversionError: no x/y/z, too few points, a layout that cannot be inferred, or a cloud
            the beam model does not hold (more than ``MAX_LOST_SHARE`` of the points without a
            pixel or a median re-projection error above ``MAX_MEDIAN_ERROR_M``; e.g. a Livox
            rosette): the message says what was tried.
        ConfigError: bad option values.
    """
    if layout not in ("auto", "organized", "ring"):
        raise ConfigError("layout", layout, '"auto", "organized" or "ring"')
    pts = read_points(cloud)
    names = list(pts.dtype.names or ())
    for axis in "xyz":
        if axis not in names:
            raise ConversionError("fields", names, "x, y and z fields")
    if pts.size == 0:
        raise ConversionError("cloud", f"{pts.shape[0]}x{pts.shape[1]} points",
                              "a cloud with points to estimate a geometry from")
    header_ns = to_ns(cloud.header.stamp, field="cloud.header.stamp")
    time_name = _pick_time_field(names, time_field)
    if info is not None:
        return _import_with_info(cloud, pts, names, info, time_name, header_ns, frame_id,
                                 as_dataclass)
    range_name: str | None = None
    if range_field == "auto":
        range_name = next((n for n in _RANGE_FIELDS if n in names), None)
    elif range_field is not None:
        if range_field not in names:
            raise ConfigError("range_field", range_field, f"one of the cloud's fields {names}")
        range_name = range_field
    scale = 1.0
    if range_name is not None:
        kind = pts.dtype[range_name].base.kind
        scale = float(range_scale) if range_scale is not None else (0.001 if kind in "iu"
                                                                     else 1.0)
    ring_name = _ring_name(names)
    chosen = layout
    if layout == "auto":
        chosen = "ring" if ring_name is not None else "organized"
        if chosen == "ring" and pts.shape[0] > 1:
            ring = pts[ring_name]
            ring = ring[..., 0] if ring.ndim == 3 else ring
            if np.all(ring == ring[:, :1]) and np.unique(ring[:, 0]).size == pts.shape[0]:
                chosen = "organized"
        if chosen == "organized" and pts.shape[0] < 2:
            raise ConversionError(
                "cloud", f"1 x {pts.shape[1]} points with fields {names}",
                "a beam structure: tried an organized cloud (height > 1, rows = beams) and a "
                f"beam number field ({', '.join(_RING_FIELDS)}); this cloud has neither. A "
                "cloud without beams (e.g. a Livox non-repetitive pattern) has no LidarScan grid: "
                "keep it as sensor_msgs/PointCloud2 (non-grid sensors, msgs/README.md), or pass "
                "info= with the sensor's LidarInfo to place each point by its geometry")
    if chosen == "ring" and ring_name is None:
        raise ConversionError("fields", names,
                              f"a beam number field ({', '.join(_RING_FIELDS)}) for "
                              'layout="ring"')
    build = _organized_grid if chosen == "organized" else _ring_grid
    grid = build(pts, names, time_name, header_ns, range_name, scale)
    fit = _fit_geometry(grid.points, grid.valid, grid.cidx, grid.width, grid.known_range)
    _check_fit(grid, fit, chosen, ring_name, time_name)
    return _assemble(cloud, grid, fit, header_ns, stamp_ns, frame_id, as_dataclass)


#: A beam model that leaves more than this share of points out, or re-projects the median point
#: farther than this (m), is not the cloud's structure: from_pointcloud2 refuses it.
MAX_LOST_SHARE, MAX_MEDIAN_ERROR_M = 0.02, 0.02


def _check_fit(grid: _Grid, fit: _Fit, layout: str, ring_name: str | None,
               time_name: str | None) -> None:
    """Raise instead of returning a scan that silently loses points or misplaces them."""
    u, g = np.nonzero(grid.valid)
    points = u.size + grid.dropped
    theta = fit.alpha[grid.cidx[u, g]] + fit.beta[u]
    ct, st = np.cos(theta), np.sin(theta)
    o = fit.origins[u]
    rho = fit.rho[u, g]
    cp, sp = np.cos(fit.phi[u]), np.sin(fit.phi[u])
    model = np.stack([ct * o[:, 0] - st * o[:, 1] + rho * cp * ct,
                      st * o[:, 0] + ct * o[:, 1] + rho * cp * st,
                      o[:, 2] + rho * sp], -1)
    err = np.linalg.norm(model - grid.points[u, g], axis=-1)
    err = np.where(np.isfinite(err), err, np.inf)
    median = float(np.median(err)) if err.size else 0.0
    if grid.dropped <= MAX_LOST_SHARE * points and median <= MAX_MEDIAN_ERROR_M:
        return
    if layout == "organized":
        tried = "rows as beams (organized cloud), columns in cloud order"
    else:
        tried = (f"rows from the {ring_name!r} field, columns (firings) from "
                 + (f"the {time_name!r} times" if grid.column_times is not None
                    else "the point order and azimuth steps"))
    raise ConversionError(
        "cloud", f"{grid.dropped} of {points} points without a pixel, median re-projection "
                 f"error {median:.3g} m on a {grid.points.shape[0]} x {grid.width} grid",
        f"a beam x firing structure (tried: {tried}). A cloud without one (e.g. a Livox "
        "non-repetitive pattern) has no LidarScan grid: keep it as sensor_msgs/PointCloud2 "
        "(non-grid sensors, msgs/README.md), or pass info= with the sensor's LidarInfo")


def _assemble(cloud: Any, grid: _Grid, fit: _Fit, header_ns: int, info_stamp: int | None,
              frame_id: str | None, as_dataclass: bool) -> tuple[Any, Any]:
    width = grid.width
    order = np.argsort(-fit.phi, kind="stable")           # rows top -> bottom

    def rows(a: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        return a[order]
    col_offsets = None
    increment = 0
    scan_stamp = header_ns
    if grid.column_times is not None:
        scan_stamp = int(grid.column_times[0])
        col_offsets = grid.column_times - np.int64(scan_stamp)
        if width > 1:
            increment = round(float(np.median(np.diff(col_offsets))))
            increment = max(increment, 0)
    frame = frame_id if frame_id is not None else cloud.header.frame_id
    shifts = rows(grid.shifts)
    info = make_info(
        stamp_ns=scan_stamp if info_stamp is None else int(info_stamp), frame_id=frame,
        vertical_angles=rows(fit.phi), horizontal_angles=fit.alpha,
        beam_azimuth_offsets=rows(fit.beta), beam_origins=rows(fit.origins).reshape(-1),
        pixel_shift_by_row=shifts if np.any(shifts) else [],
        beam_time_offsets=rows(grid.beam_times) if np.any(grid.beam_times) else [],
        column_time_increment=increment,
        beam_ids=rows(np.asarray(grid.beam_ids)).astype(np.uint16),
        model="estimated from sensor_msgs/PointCloud2",
        as_dataclass=as_dataclass)
    rng = np.where(grid.valid, fit.rho, np.inf).astype(np.float32)
    channels: dict[str, Any] = {}
    for k in range(grid.returns):              # grid columns: return 1, then return 2
        channels["range" + ("2" if k else "")] = rows(rng[:, k * width:(k + 1) * width])
    for name, img in grid.channels.items():
        if name == "range":
            continue
        try:
            datatype_of(img.dtype)
        except ValidationError:
            continue
        img = np.ascontiguousarray(img).astype(img.dtype.newbyteorder("="))
        for k in range(grid.returns):
            channels[name + ("2" if k else "")] = rows(img[:, k * width:(k + 1) * width])
    scan = make_scan(info, channels, scan_stamp, frame_id=frame,
                     is_destaggered=bool(np.any(shifts)),
                     column_time_offsets=col_offsets,
                     column_azimuth_angles=fit.alpha if grid.per_scan_azimuths else None,
                     as_dataclass=as_dataclass)
    return scan, info


# ------------------------------------------------------------------- cloud + known LidarInfo

def _pixel_ranks(pix: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """Rank of every point among the points of its pixel, in cloud order (0 = first return)."""
    o = np.argsort(pix, kind="stable")
    ps = pix[o]
    starts = np.flatnonzero(np.concatenate([[True], ps[1:] != ps[:-1]]))
    run = np.arange(ps.size) - np.repeat(starts, np.diff(np.concatenate([starts, [ps.size]])))
    rank = np.empty(ps.size, np.int64)
    rank[o] = run
    return rank


def _nearest_angle(values: np.ndarray[Any, Any], table: np.ndarray[Any, Any]
                   ) -> np.ndarray[Any, Any]:
    """Index of the table angle nearest to each value (radians, on the circle)."""
    tab = np.mod(table, 2 * np.pi)
    order = np.argsort(tab, kind="stable")
    ext = np.concatenate([tab[order[-1:]] - 2 * np.pi, tab[order], tab[order[:1]] + 2 * np.pi])
    ext_idx = np.concatenate([order[-1:], order, order[:1]])
    v = np.mod(values, 2 * np.pi)
    k = np.clip(np.searchsorted(ext, v), 1, ext.size - 1)
    left = (v - ext[k - 1]) <= (ext[k] - v)
    return np.asarray(ext_idx[np.where(left, k - 1, k)], dtype=np.int64)


def _import_with_info(cloud: Any, pts: np.ndarray[Any, Any], names: Sequence[str], info: Any,
                      time_name: str | None, header_ns: int, frame_id: str | None,
                      as_dataclass: bool) -> tuple[Any, Any]:
    """Place every point of a cloud by a known beam model (see :func:`from_pointcloud2`).

    Row: the beam whose elevation line (from its origin) passes nearest to the point, among
    the five beams nearest in plain elevation; column: the measurement column whose azimuth
    (``horizontal_angles``) is nearest to the point's ``theta - beam_azimuth_offsets[u]``. The
    scan's ``column_azimuth_angles`` are the mean measured azimuths of its columns (the info's
    where a column has no point), so points re-project where they were.
    """
    height, width = int(info.height), int(info.width)
    if len(as_array(info.pixel_azimuth_angles, np.float64)):
        raise ConversionError("info.pixel_azimuth_angles", "per-pixel directions",
                              "a beam model with one elevation per row and one azimuth per "
                              "column to place points by")
    phi = as_array(info.vertical_angles, np.float64)
    alpha_nom = as_array(info.horizontal_angles, np.float64)
    beta = as_array(info.beam_azimuth_offsets, np.float64)
    beta = beta if beta.size else np.zeros(height)
    orig = as_array(info.beam_origins, np.float64)
    orig = orig.reshape(height, 3) if orig.size else np.zeros((height, 3))
    delta = as_array(info.beam_range_offsets, np.float64)
    delta = delta if delta.size else np.zeros(height)
    flat = pts.reshape(-1)
    xyz = np.stack([_field_f64(flat[None, :], n)[0] for n in "xyz"], -1)
    ok = np.all(np.isfinite(xyz), -1) & np.any(xyz != 0, -1)
    flat, xyz = flat[ok], xyz[ok]
    if xyz.shape[0] == 0:
        raise ConversionError("cloud", "0 finite points", "points to place")
    transform = as_array(info.lidar_to_sensor_transform, np.float64).reshape(4, 4)
    if np.any(transform) and not np.allclose(transform, np.eye(4)):
        xyz = (xyz - transform[:3, 3]) @ transform[:3, :3]     # sensor -> beam-model frame
    rxy = np.hypot(xyz[:, 0], xyz[:, 1])
    psi = np.arctan2(xyz[:, 1], xyz[:, 0])
    asc = np.argsort(phi, kind="stable")
    near = np.searchsorted(phi[asc], np.arctan2(xyz[:, 2], rxy))
    best_err = np.full(xyz.shape[0], np.inf)
    row = np.zeros(xyz.shape[0], np.int64)
    for off in range(-3, 3):
        u = asc[np.clip(near + off, 0, height - 1)]
        a = np.sqrt(np.maximum(rxy**2 - orig[u, 1] ** 2, 0.0))
        e = np.abs(np.arctan2(xyz[:, 2] - orig[u, 2], a - orig[u, 0]) - phi[u])
        better = e < best_err
        row[better], best_err[better] = u[better], e[better]
    o = orig[row]
    a = np.sqrt(np.maximum(rxy**2 - o[:, 1] ** 2, 0.0))
    rho = np.hypot(a - o[:, 0], xyz[:, 2] - o[:, 2]) - delta[row]
    theta = psi - np.arctan2(o[:, 1], a)
    alpha = theta - beta[row]
    col = _nearest_angle(alpha, alpha_nom)
    pix = row * width + col
    rank = _pixel_ranks(pix)
    returns = 2 if np.any(rank == 1) else 1
    keep = rank < returns
    if np.count_nonzero(~keep) > 0.02 * keep.size:
        raise ConversionError("cloud", f"{np.count_nonzero(~keep)} of {keep.size} points in "
                              "pixels that already hold two returns",
                              "a cloud of the sensor this LidarInfo describes (same beams and "
                              "columns per turn)")
    cnt = np.bincount(col, minlength=width).astype(np.float64)
    meas = alpha_nom + _group_mean(col, _wrap(alpha - alpha_nom[col]), width, cnt)
    column_az = np.where(cnt > 0, meas, alpha_nom)
    channels: dict[str, Any] = {}
    for k in range(returns):
        sel = keep & (rank == k)
        img = np.full(height * width, np.inf, np.float32)
        img[pix[sel]] = rho[sel]
        channels["range" + ("2" if k else "")] = img.reshape(height, width)
    skip = set(_SKIP) | set(_RANGE_FIELDS) | {time_name}
    for n in names:
        if n in skip or flat[n].ndim != 1:
            continue
        src = flat[n]
        try:
            datatype_of(src.dtype)
        except ValidationError:
            continue
        for k in range(returns):
            sel = keep & (rank == k)
            img = np.zeros(height * width, src.dtype.newbyteorder("="))
            img[pix[sel]] = src[sel]
            channels[n + ("2" if k else "")] = img.reshape(height, width)
    stamp = header_ns
    col_offsets = None
    if time_name is not None:
        t_abs = _time_ns(flat[None, :], time_name, header_ns)[0]
        bt = as_array(info.beam_time_offsets, np.int64)
        bt = bt if bt.size else np.zeros(height, np.int64)
        col_t = _column_times(t_abs - bt[row], col, width)
        stamp = int(col_t[0])
        col_offsets = col_t - np.int64(stamp)
    scan = make_scan(info, channels, stamp,
                     frame_id=frame_id if frame_id is not None else cloud.header.frame_id,
                     column_time_offsets=col_offsets, column_azimuth_angles=column_az,
                     as_dataclass=as_dataclass)
    return scan, info


@dataclasses.dataclass(frozen=True)
class ReprojectionError:
    """How well a (scan, info) pair reproduces a cloud's points.

    Attributes:
        points: finite points in the cloud.
        matched: of those, points whose pixel re-projects to a point.
        max_m, rms_m, median_m, p99_m: largest, RMS, median and 99th-percentile distance
            (metres) between the cloud's xyz and the re-projected pixel (over matched points;
            with two returns, the nearer of the pixel's two points).
        max_time_ns: largest |cloud time - pixel time| (None without a time field).
    """

    points: int
    matched: int
    max_m: float
    rms_m: float
    max_time_ns: int | None
    median_m: float = 0.0
    p99_m: float = 0.0


def estimation_error(cloud: Any, scan: Any, info: Any, *, time_field: str | None = None
                     ) -> ReprojectionError:
    """Re-project ``scan`` with ``info`` and compare with the cloud's points.

    Points are matched to pixels like :func:`from_pointcloud2` arranges them: organized clouds of
    the scan's size pixel by pixel (rows through ``info.beam_ids`` = ring / source row), other
    clouds by ring and time (or azimuth when there is no time field, or when its times are
    shared by several firings).
    """
    from lidarscan.geometry import make_projector as _mk
    from lidarscan.scan import channel_names

    proj = _mk(info)
    xyz_returns = [proj.project(scan, info, ch).astype(np.float64)
                   for ch in ("range", "range2") if ch in channel_names(scan)]
    xyz_scan = xyz_returns[0]
    stamp = to_ns(scan.header.stamp)
    times = proj.pixel_times(scan) + np.int64(stamp)
    pts = read_points(cloud)
    names = list(pts.dtype.names or ())
    time_name = _pick_time_field(names, time_field)
    header_ns = to_ns(cloud.header.stamp)
    ids = as_array(info.beam_ids, np.uint16).astype(np.int64)
    height, width = int(info.height), int(info.width)
    if ids.size == 0:
        ids = np.arange(height)
    row_of_id = {int(v): i for i, v in enumerate(ids)}
    xyz = np.stack([_field_f64(pts, n) for n in "xyz"], -1)
    ok = np.all(np.isfinite(xyz), -1) & np.any(xyz != 0, -1)
    t_abs = _time_ns(pts, time_name, header_ns) if time_name else None
    ring_name = _ring_name(names)
    ring_all = _ring_rows(pts, ring_name) if ring_name is not None else None
    if pts.shape == (height, width) and (ring_all is None
                                         or np.all(ring_all == ring_all[:, :1])):
        ring = ring_all[:, 0] if ring_all is not None else np.arange(height)
        rows = np.array([row_of_id.get(int(r), -1) for r in ring])
        if np.any(rows < 0):
            raise InfoMismatchError("LidarInfo.beam_ids", ids.tolist(), "the cloud's rings")
        u = np.broadcast_to(rows[:, None], pts.shape)[ok]
        c = np.broadcast_to(np.arange(width)[None, :], pts.shape)[ok]
    else:
        if ring_all is None:
            raise ConversionError("fields", names, "a beam number field "
                                  f"({', '.join(_RING_FIELDS)}) to match points to rows")
        ring = ring_all[ok]
        u = np.array([row_of_id.get(int(r), -1) for r in ring], dtype=np.int64)
        if np.any(u < 0):
            raise InfoMismatchError("LidarInfo.beam_ids", ids.tolist(), "the cloud's rings")
        t_ok = t_abs[ok] if t_abs is not None else None
        if t_ok is not None and np.unique(np.stack([u, t_ok]), axis=1).shape[1] >= 0.4 * u.size:
            c = _nearest_time_column(times, u, t_ok)
        else:
            c = _nearest_azimuth_column(xyz_scan, u, xyz[ok])
    dist = np.stack([np.linalg.norm(xyz[ok] - x[u, c], axis=-1) for x in xyz_returns])
    dist = np.where(np.isfinite(dist), dist, np.inf).min(axis=0)
    matched = np.isfinite(dist)
    diff = dist[matched]
    max_t = None
    if t_abs is not None:
        max_t = int(np.abs(t_abs[ok] - times[u, c]).max(initial=0))
    return ReprojectionError(points=int(ok.sum()), matched=int(matched.sum()),
                             max_m=float(diff.max(initial=0.0)),
                             rms_m=float(np.sqrt(np.mean(diff**2))) if diff.size else 0.0,
                             max_time_ns=max_t,
                             median_m=float(np.median(diff)) if diff.size else 0.0,
                             p99_m=float(np.quantile(diff, 0.99)) if diff.size else 0.0)


def _ring_rows(pts: np.ndarray[Any, Any], name: str) -> np.ndarray[Any, Any]:
    ring = pts[name]
    return (ring[..., 0] if ring.ndim == 3 else ring).astype(np.int64)


def _nearest_time_column(times: np.ndarray[Any, Any], u: np.ndarray[Any, Any],
                         t: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """Column whose pixel time in row u is nearest to t (pixel times increase along a row)."""
    out = np.empty(u.size, np.int64)
    for row in np.unique(u):
        sel = u == row
        line = times[row]
        k = np.clip(np.searchsorted(line, t[sel]), 1, line.size - 1)
        left = np.abs(t[sel] - line[k - 1]) <= np.abs(line[k] - t[sel])
        out[sel] = np.where(left, k - 1, k)
    return out


def _nearest_azimuth_column(xyz_scan: np.ndarray[Any, Any], u: np.ndarray[Any, Any],
                            p: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """Column whose re-projected direction in row u is nearest in azimuth to the point."""
    out = np.empty(u.size, np.int64)
    psi = np.arctan2(p[:, 1], p[:, 0])
    for row in np.unique(u):
        sel = np.flatnonzero(u == row)
        line = np.arctan2(xyz_scan[row, :, 1], xyz_scan[row, :, 0])
        known = np.isfinite(line)
        cols = np.flatnonzero(known)
        diff = np.abs(_wrap(psi[sel, None] - line[None, cols]))
        out[sel] = cols[np.argmin(diff, axis=1)]
    return out
