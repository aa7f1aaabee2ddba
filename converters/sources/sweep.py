"""Tilting / nodding 2D laser: a sweep of LaserScans + joint angles -> one LidarScan.

Each LaserScan becomes one row (the PR2 "dense laser" idea); its rays are the columns. Geometry,
for scan k with joint angle q (radians, right-handed about ``axis``) and ray i at angle
``a_i = angle_min + i * angle_increment`` in the laser's scan plane::

    P = R_axis(q) * (laser_offset + r * (cos a_i, sin a_i, 0))

``laser_offset`` is the laser's origin relative to the tilt axis, in the tilting (joint) frame,
i.e. the frame that coincides with the output frame at q = 0. The output frame is the joint's
fixed parent frame.

The LidarInfo carries the exact direction of every pixel in ``pixel_azimuth_angles`` /
``pixel_altitude_angles``; ``horizontal_angles`` and ``beam_azimuth_offsets`` are zero so each
row's ``beam_origins`` entry is used as is (``R_axis(q) * laser_offset``). With one joint angle
per scan the projection is exact. With (start, end) pairs the angle is interpolated linearly
over the rays (ray 0 at start, ray N-1 at end); directions stay exact, the origin uses the
scan's mid angle (error <= |laser_offset perpendicular to the axis| * |end - start| / 2).

``vertical_angles[u]`` is the elevation of row u's central ray (positive up); with ``sort`` the
rows are ordered by it, highest first (ties keep input order). The joint angles themselves are
recorded in ``vendor_metadata`` (JSON). Ranges follow REP 117: +Inf, -Inf and NaN are kept; a
finite value that is 0, negative, below ``range_min`` or above ``range_max`` (inclusive interval;
range_max <= 0 means no upper limit) becomes NaN.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from lidarscan.errors import ValidationError
from lidarscan.scan import _as_array, make_info, make_scan
from lidarscan.stamps import to_ns

__all__ = ["from_laserscan_sweep", "rotation_matrix"]

_EPS = 1e-9
_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0),
         "-x": (-1.0, 0.0, 0.0), "-y": (0.0, -1.0, 0.0), "-z": (0.0, 0.0, -1.0)}


def _unit_axis(axis: str | Sequence[float] | np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    if isinstance(axis, str):
        if axis.lower() not in _AXES:
            raise ValidationError("axis", axis, f"one of {sorted(_AXES)} or a 3-vector")
        return np.asarray(_AXES[axis.lower()])
    vec = np.asarray(axis, dtype=np.float64).reshape(-1)
    norm = float(np.linalg.norm(vec)) if vec.size == 3 else 0.0
    if vec.size != 3 or not math.isfinite(norm) or norm == 0.0:
        raise ValidationError("axis", list(vec), "a non-zero finite 3-vector or 'x'/'y'/'z'")
    return vec / norm


def rotation_matrix(axis: str | Sequence[float] | np.ndarray[Any, Any], angle: Any
                    ) -> np.ndarray[Any, Any]:
    """Right-handed rotation(s) by ``angle`` (radians, scalar or array) about ``axis``.

    Returns:
        (..., 3, 3) float64 (Rodrigues' formula).
    """
    k = _unit_axis(axis)
    q = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(q)[..., None, None], np.sin(q)[..., None, None]
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    result: np.ndarray[Any, Any] = c * np.eye(3) + s * cross + (1.0 - c) * np.outer(k, k)
    return result


def _joint_table(joint_angles: Any, count: int, rays: int) -> np.ndarray[Any, Any]:
    """(K, N) joint angle of every ray from K angles or K (start, end) pairs."""
    q = np.asarray(joint_angles, dtype=np.float64)
    if q.shape == (count,):
        table = np.repeat(q[:, None], rays, axis=1)
    elif q.shape == (count, 2):
        frac = np.arange(rays) / (rays - 1) if rays > 1 else np.zeros(1)
        table = q[:, :1] + (q[:, 1:] - q[:, :1]) * frac[None, :]
    else:
        raise ValidationError("joint_angles", f"shape {q.shape}",
                              f"({count},) angles or ({count}, 2) (start, end) pairs in radians")
    if not np.all(np.isfinite(q)):
        raise ValidationError("joint_angles", q[~np.isfinite(q)][:3].tolist(), "finite radians")
    return table


def _scan_arrays(scans: Sequence[Any]) -> tuple[int, float, float, list[np.ndarray[Any, Any]],
                                                list[np.ndarray[Any, Any]] | None]:
    first = scans[0]
    rays = len(_as_array(first.ranges, np.float32))
    angle_min, increment = float(first.angle_min), float(first.angle_increment)
    if rays == 0:
        raise ValidationError("scans[0].ranges", "length 0", "at least one ray")
    if not (math.isfinite(angle_min) and math.isfinite(increment)) or (rays > 1 and
                                                                       increment == 0.0):
        raise ValidationError("scans[0].angle_increment", increment,
                              "a finite, non-zero increment (finite angle_min)")
    if abs(angle_min) > 4 * math.pi or abs(increment) * max(rays - 1, 0) > 4 * math.pi:
        raise ValidationError("scans[0].angle_increment", increment,
                              f"rays spanning at most 4*pi from angle_min (|angle_min| <= 4*pi); "
                              f"{rays} rays from {angle_min} rad")
    ranges, intensities = [], []
    for k, scan in enumerate(scans):
        r = np.asarray(_as_array(scan.ranges, np.float32), dtype=np.float32)
        if r.size != rays:
            raise ValidationError(f"scans[{k}].ranges", f"length {r.size}",
                                  f"length {rays} (as scans[0])")
        if abs(float(scan.angle_min) - angle_min) > _EPS:
            raise ValidationError(f"scans[{k}].angle_min", float(scan.angle_min),
                                  f"{angle_min} (as scans[0], within {_EPS})")
        if abs(float(scan.angle_increment) - increment) > _EPS:
            raise ValidationError(f"scans[{k}].angle_increment", float(scan.angle_increment),
                                  f"{increment} (as scans[0], within {_EPS})")
        ranges.append(r)
        inten = np.asarray(_as_array(scan.intensities, np.float32), dtype=np.float32)
        if inten.size not in (0, rays):
            raise ValidationError(f"scans[{k}].intensities", f"length {inten.size}",
                                  f"length 0 or {rays}")
        intensities.append(inten)
    sizes = {i.size for i in intensities}
    if len(sizes) > 1:
        raise ValidationError("scans[*].intensities", sorted(sizes),
                              "intensities in every scan or in none")
    return rays, angle_min, increment, ranges, (intensities if rays in sizes else None)


def _clean_ranges(r: np.ndarray[Any, Any], range_min: float, range_max: float
                  ) -> np.ndarray[Any, Any]:
    out = r.copy()
    finite = np.isfinite(out)
    bad = finite & ((out <= 0) | (out < range_min))
    if range_max > 0:
        bad |= finite & (out > range_max)
    out[bad] = np.nan
    return out


def from_laserscan_sweep(scans: Sequence[Any], joint_angles: Any, *,
                         axis: str | Sequence[float] = "y",
                         laser_offset: Sequence[float] = (0.0, 0.0, 0.0),
                         stamp_ns: int | None = None, frame_id: str | None = None,
                         sort: bool = True, as_dataclass: bool = False) -> tuple[Any, Any]:
    """One LidarScan (+ its LidarInfo) from the LaserScans of a tilting-laser sweep.

    Args:
        scans: K ``sensor_msgs/LaserScan`` (rclpy or dataclass) with equal ray count N,
            angle_min and angle_increment (within 1e-9 rad).
        joint_angles: K joint angles in radians (one per scan), or K (start, end) pairs
            interpolated linearly from the first to the last ray.
        axis: tilt axis in the output frame: "x", "y", "z" (or "-x", ...) or a 3-vector;
            rotation is right-handed (about +y a positive angle tilts the forward ray down).
        laser_offset: laser origin relative to the tilt axis, metres, in the tilting frame.
        stamp_ns: header.stamp of scan and info (the info's version key); default the earliest
            scan stamp.
        frame_id: frame of the points (the joint's fixed parent); default scans[0]'s frame_id.
        sort: order rows by elevation, highest first (else keep the input order).
        as_dataclass: return lidarscan dataclasses instead of rclpy messages.

    Returns:
        (LidarScan, LidarInfo): H = K rows, W = N columns; channels ``range`` (float32 m,
        REP 117, see the module docstring) and ``intensity`` (float32) when every scan has
        intensities. ``beam_time_offsets[u]`` = stamp of row u's scan - header.stamp (ns),
        ``column_time_increment`` = round(time_increment * 1e9) (for a negative time_increment
        the scan carries explicit negative ``column_time_offsets`` instead).

    Raises:
        ValidationError: empty input, mismatched rays/angles/intensities, bad joint angles,
            axis or offset.
    """
    scans = list(scans)
    if not scans:
        raise ValidationError("scans", 0, "at least one LaserScan")
    count = len(scans)
    rays, angle_min, increment, ranges, intensities = _scan_arrays(scans)
    q_table = _joint_table(joint_angles, count, rays)                   # (K, N)
    q_mid = 0.5 * (q_table[:, 0] + q_table[:, -1])                      # (K,)
    k_axis = _unit_axis(axis)
    offset = np.asarray(laser_offset, dtype=np.float64).reshape(-1)
    if offset.size != 3 or not np.all(np.isfinite(offset)):
        raise ValidationError("laser_offset", list(offset), "a finite (x, y, z) in metres")

    a = angle_min + increment * np.arange(rays, dtype=np.float64)
    u = np.stack([np.cos(a), np.sin(a), np.zeros(rays)], -1)           # (N, 3)
    d = np.einsum("knij,nj->kni", rotation_matrix(k_axis, q_table), u)   # (K, N, 3)
    pix_az = np.arctan2(d[..., 1], d[..., 0])
    pix_alt = np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1]))
    origins = rotation_matrix(k_axis, q_mid) @ offset                   # (K, 3)

    a_mid = angle_min + increment * (rays - 1) / 2.0
    centre = rotation_matrix(k_axis, q_mid) @ np.array([math.cos(a_mid), math.sin(a_mid), 0.0])
    elevation = np.arctan2(centre[:, 2], np.hypot(centre[:, 0], centre[:, 1]))
    order = np.argsort(-elevation, kind="stable") if sort else np.arange(count)

    stamps = np.array([to_ns(s.header.stamp, field=f"scans[{k}].header.stamp")
                       for k, s in enumerate(scans)], dtype=np.int64)
    header_ns = int(stamps.min()) if stamp_ns is None else int(stamp_ns)
    time_increment = float(scans[0].time_increment)
    if not math.isfinite(time_increment):
        raise ValidationError("scans[0].time_increment", time_increment, "finite seconds")
    column_ns = round(time_increment * 1e9)
    column_offsets = None
    if column_ns < 0:
        column_offsets = np.arange(rays, dtype=np.int64) * column_ns
        column_ns = 0

    range_min = max(float(s.range_min) for s in scans)
    positive_max = [float(s.range_max) for s in scans if float(s.range_max) > 0]
    range_max = min(positive_max) if positive_max else 0.0
    if not (math.isfinite(range_min) and math.isfinite(range_max)):
        raise ValidationError("scans[*].range_min/range_max", (range_min, range_max),
                              "finite limits")
    range_min = max(range_min, 0.0)

    metadata = {
        "source": "laserscan_sweep",
        "axis": k_axis.tolist(),
        "laser_offset": offset.tolist(),
        "scan_index": order.tolist(),
        "joint_angles": [[float(q_table[k, 0]), float(q_table[k, -1])] for k in order],
    }
    info = make_info(
        stamp_ns=header_ns,
        frame_id=scans[0].header.frame_id if frame_id is None else frame_id,
        vertical_angles=elevation[order],
        horizontal_angles=np.zeros(rays),
        beam_azimuth_offsets=np.zeros(count),
        pixel_azimuth_angles=pix_az[order].reshape(-1),
        pixel_altitude_angles=pix_alt[order].reshape(-1),
        beam_origins=origins[order].reshape(-1),
        beam_time_offsets=stamps[order] - header_ns,
        column_time_increment=column_ns,
        beam_ids=order.astype(np.uint16) if count <= 65536 else np.zeros(0, np.uint16),
        range_min=range_min, range_max=range_max,
        vendor_metadata=json.dumps(metadata),
        as_dataclass=as_dataclass)
    channels = {"range": np.stack([_clean_ranges(ranges[k], range_min, range_max)
                                   for k in order])}
    if intensities is not None:
        channels["intensity"] = np.stack([intensities[k] for k in order])
    scan = make_scan(info, channels, header_ns, column_time_offsets=column_offsets,
                     as_dataclass=as_dataclass)
    return scan, info
