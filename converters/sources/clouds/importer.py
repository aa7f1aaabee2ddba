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
ring's consecutive points counts the firings between them. Times that do not give the firings
(a grid they make does not hold the points: velodyne_pointcloud stamps a VLP-16 dual-return
packet with its single-return table, a firing's second echo two firings after its first, the
packet's offsets overrunning the next packet) leave the columns to the point order and time
them by their first returns; negative times (a cloud stamped after its last firing) and jittery
packet stamps are taken as they are. ROS 2's velodyne_pointcloud also gives a VLP-16
dual-return block pair's first echoes no interpolation (``unpack_vlp16`` takes the gap to the
next block, which in a dual packet has the same azimuth): they sit at the pair's azimuth, up to
1.6 firings from their firing. No column + beam azimuth holds them, so such a cloud (runs of one
azimuth in a ring; :mod:`converters.sources.clouds.block_pairs`) gets its firings from the
cloud order and each return a per-pixel azimuth channel (``azimuth``, ``azimuth2``, float32
rad, msgs/README.md) with every point's own azimuth. Two points in one pixel (same ring,
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
float64 resolution of an epoch time); VLP-16 dual-return clouds made by velodyne_pointcloud's
rules from real echoes (tests/test_velodyne_pointcloud_dual.py, organized and not): 100 % of
the points within 2 mm, with and without ``time``; the echoes of ~2 % of the firings land in a
neighbouring firing of their pair (a lone first echo at its pair's azimuth fits either). Real
Velodyne output is bounded by the driver itself: velodyne_pointcloud rounds every laser's
interpolated azimuth to 0.01 deg, a per-point pattern a per-column + per-beam model cannot
hold, so expect up to ~1.3e-4 rad x range (simulated VLP-16: 7.6 mm max at 60 m, 1.5 mm RMS). Very sparse clouds (most columns with < 2 points, e.g. second
returns) are fitted with evenly spaced column azimuths.

The grid (rows, columns, returns, times) and the beam model fit live in
:mod:`converters.sources.clouds.grid`; this module is the API, the checks and the assembly of the scan.

"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from converters.shared.cloud_layout import read_points
from converters.sources.clouds.block_pairs import block_pair_grid
from converters.sources.clouds.grid import (
    _RANGE_FIELDS,
    _RING_FIELDS,
    _SKIP,
    _column_times,
    _field_f64,
    _Fit,
    _fit_geometry,
    _Grid,
    _group_mean,
    _organized_grid,
    _pick_time_field,
    _pixel_ranks,
    _ring_grid,
    _ring_name,
    _time_ns,
    _wrap,
)
from lidarscan.datatypes import datatype_of
from lidarscan.errors import ConfigError, ConversionError, InfoMismatchError, ValidationError
from lidarscan.scan import as_array, make_info, make_scan, return_channel, return_channels
from lidarscan.stamps import to_ns

__all__ = ["ReprojectionError", "estimation_error", "from_pointcloud2"]

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
        ``column_azimuth_angles`` (and float32 ``azimuth``/``azimuth2`` per-pixel azimuths for
        dual-return block pairs whose first echoes share one azimuth). ``beam_ids`` = ring
        values.

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
    fits = _fits(grid, fit)
    if chosen == "ring" and grid.time_columns and not fits:
        # times that are not the firings' (velodyne_pointcloud's single-return table on
        # dual-return packets stamps a firing's second echo two firings later): the point order
        # gives the firings, the times then only their times
        grid = _ring_grid(pts, names, time_name, header_ns, range_name, scale,
                          time_columns=False)
        fit = _fit_geometry(grid.points, grid.valid, grid.cidx, grid.width, grid.known_range)
        fits = _fits(grid, fit)
    theta = None
    if chosen == "ring" and not fits:
        # velodyne_pointcloud's dual-return VLP-16 clouds: a block pair's first echoes share
        # one azimuth; every pixel then carries its own point's azimuth
        paired = block_pair_grid(pts, names, time_name, header_ns, range_name, scale)
        if paired is not None and _fits(paired[0], paired[1], paired[2]):
            (grid, fit, theta), fits = paired, True
    if not fits:
        _refuse_fit(grid, fit, chosen, ring_name, time_name)
    return _assemble(cloud, grid, fit, header_ns, stamp_ns, frame_id, as_dataclass, theta)


#: A beam model that leaves more than this share of points out, or re-projects the median point
#: farther than this (m), is not the cloud's structure: from_pointcloud2 refuses it.
MAX_LOST_SHARE, MAX_MEDIAN_ERROR_M = 0.02, 0.02


def _fit_figures(grid: _Grid, fit: _Fit, pixel_theta: Any = None) -> tuple[int, float]:
    """(points of the cloud, median re-projection error in metres) of a grid and its fit
    (with per-pixel azimuths ``pixel_theta`` (H, G) rad instead of column + beam, if given)."""
    u, g = np.nonzero(grid.valid)
    points = u.size + grid.dropped
    theta = (fit.alpha[grid.cidx[u, g]] + fit.beta[u] if pixel_theta is None
             else pixel_theta[u, g])
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
    return points, median


def _fits(grid: _Grid, fit: _Fit, pixel_theta: Any = None) -> bool:
    """The grid holds the cloud: at most MAX_LOST_SHARE of its points without a pixel and a
    median re-projection error of at most MAX_MEDIAN_ERROR_M."""
    points, median = _fit_figures(grid, fit, pixel_theta)
    return grid.dropped <= MAX_LOST_SHARE * points and median <= MAX_MEDIAN_ERROR_M


def _refuse_fit(grid: _Grid, fit: _Fit, layout: str, ring_name: str | None,
                time_name: str | None) -> None:
    """Raise (a grid that :func:`_fits` refused) instead of returning a scan that silently
    loses points or misplaces them: the error names the layouts tried and the figures."""
    points, median = _fit_figures(grid, fit)
    if layout == "organized":
        tried = "rows as beams (organized cloud), columns in cloud order"
    else:
        tried = (f"rows from the {ring_name!r} field, columns (firings) from "
                 + (f"the {time_name!r} times, then " if time_name is not None else "")
                 + "the point order and azimuth steps, then dual-return block pairs whose "
                 "first echoes share one azimuth")
    raise ConversionError(
        "cloud", f"{grid.dropped} of {points} points without a pixel, median re-projection "
                 f"error {median:.3g} m on a {grid.points.shape[0]} x {grid.width} grid",
        f"a beam x firing structure (tried: {tried}). A cloud without one (e.g. a Livox "
        "non-repetitive pattern) has no LidarScan grid: keep it as sensor_msgs/PointCloud2 "
        "(non-grid sensors, msgs/README.md), or pass info= with the sensor's LidarInfo")


def _assemble(cloud: Any, grid: _Grid, fit: _Fit, header_ns: int, info_stamp: int | None,
              frame_id: str | None, as_dataclass: bool, pixel_theta: Any = None
              ) -> tuple[Any, Any]:
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
        seen = grid.valid.reshape(grid.valid.shape[0], -1, width).any(axis=(0, 1))
        increment = _time_increment(col_offsets, seen)
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
        channels[return_channel("range", k + 1)] = rows(rng[:, k * width:(k + 1) * width])
    for name, img in grid.channels.items():
        if name == "range":
            continue
        try:
            datatype_of(img.dtype)
        except ValidationError:
            continue
        img = np.ascontiguousarray(img).astype(img.dtype.newbyteorder("="))
        for k in range(grid.returns):
            channels[return_channel(name, k + 1)] = rows(img[:, k * width:(k + 1) * width])
    if pixel_theta is not None:          # each return's own azimuths (msgs/README.md)
        for k in range(grid.returns):
            channels[return_channel("azimuth", k + 1)] = rows(
                pixel_theta[:, k * width:(k + 1) * width].astype(np.float32))
    scan = make_scan(info, channels, scan_stamp, frame_id=frame,
                     is_destaggered=bool(np.any(shifts)),
                     column_time_offsets=col_offsets,
                     column_azimuth_angles=fit.alpha if grid.per_scan_azimuths else None,
                     as_dataclass=as_dataclass)
    return scan, info


def _time_increment(col_offsets: np.ndarray[Any, Any], seen: np.ndarray[Any, Any]) -> int:
    """Nominal ns between two columns: the median step of the column times, unless the times
    of the columns with points say otherwise (jittery packet stamps, a driver's table that
    runs ahead of the firings, columns of a missing sector sharing one interpolated time): then
    the slope of straight lines through them, one per run of consecutive columns with points
    (a common slope: a time gap between two runs, e.g. a sector the sensor does not send, does
    not bend it). Never negative."""
    if col_offsets.size < 2:
        return 0
    median = float(np.median(np.diff(col_offsets)))
    idx = np.flatnonzero(seen)
    if idx.size < 2:
        return max(round(median), 0)
    run = np.cumsum(np.concatenate([[1], np.diff(idx) != 1]))      # run number of each column
    counts = np.bincount(run).astype(np.float64)
    x = idx.astype(np.float64)
    y = col_offsets[idx].astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        dx = x - (np.bincount(run, x) / np.maximum(counts, 1))[run]
        dy = y - (np.bincount(run, y) / np.maximum(counts, 1))[run]
    if not np.any(dx):
        return max(round(median), 0)
    slope = float(np.sum(dx * dy) / np.sum(dx * dx))
    step = median if abs(median - slope) <= 0.1 * abs(slope) else slope
    return max(round(step), 0)


# ------------------------------------------------------------------- cloud + known LidarInfo

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
        channels[return_channel("range", k + 1)] = img.reshape(height, width)
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
            channels[return_channel(n, k + 1)] = img.reshape(height, width)
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
                   for ch in return_channels("range", channel_names(scan))]
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
