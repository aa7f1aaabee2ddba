"""Velodyne calibration (ros-drivers/velodyne YAML) -> LidarInfo, and decoded firings -> LidarScan.

Conventions: see :mod:`converters.sources.velodyne` (the beam-model mapping, rows sorted by elevation,
row 0 the highest, column azimuth ``-radians(packet azimuth)``).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from lidarscan.errors import DecodeError, ValidationError
from lidarscan.scan import make_info, make_scan

#: VLP-16 time between two lasers of a firing sequence, and between two sequences (ns).
VLP16_FIRING_NS = 2304
VLP16_CYCLE_NS = 55296

#: Nominal VLP-16 calibration (public datasheet angles): laser k points at k - 15 degrees for
#: even k and k degrees for odd k (-15, +1, -13, +3, ..., -1, +15); no other corrections.
VLP16_CALIBRATION: dict[str, Any] = {
    "num_lasers": 16,
    "distance_resolution": 0.002,
    "lasers": [
        {"laser_id": k, "rot_correction": 0.0,
         "vert_correction": math.radians(k - 15 if k % 2 == 0 else k),
         "dist_correction": 0.0, "dist_correction_x": 0.0, "dist_correction_y": 0.0,
         "vert_offset_correction": 0.0, "horiz_offset_correction": 0.0,
         "focal_distance": 0.0, "focal_slope": 0.0, "min_intensity": 0, "max_intensity": 255}
        for k in range(16)
    ],
}

#: VLP-32C laser table of the user manual (the same for every unit): elevation and azimuth
#: offset (clockwise, as the manual lists it) of laser k, degrees. ``rot_correction`` is the
#: negated offset (the ros-drivers convention), e.g. laser 0: -25 deg, +1.4 deg.
_VLP32C_ELEVATION_DEG = (
    -25.0, -1.0, -1.667, -15.639, -11.31, 0.0, -0.667, -8.843, -7.254, 0.333, -0.333, -6.148,
    -5.333, 1.333, 0.667, -4.0, -4.667, 1.667, 1.0, -3.667, -3.333, 3.333, 2.333, -2.667, -3.0,
    7.0, 4.667, -2.333, -2.0, 15.0, 10.333, -1.333)
_VLP32C_AZIMUTH_OFFSET_DEG = (
    1.4, -4.2, 1.4, -1.4, 1.4, -1.4, 4.2, -1.4, 1.4, -4.2, 1.4, -1.4, 4.2, -1.4, 4.2, -1.4, 1.4,
    -4.2, 1.4, -4.2, 4.2, -1.4, 1.4, -1.4, 1.4, -1.4, 1.4, -4.2, 4.2, -1.4, 1.4, -1.4)

#: Nominal VLP-32C calibration (the manual's table above; no distance or offset corrections).
VLP32C_CALIBRATION: dict[str, Any] = {
    "num_lasers": 32,
    "distance_resolution": 0.004,
    "lasers": [
        {"laser_id": k, "vert_correction": math.radians(e), "rot_correction": -math.radians(a),
         "dist_correction": 0.0, "vert_offset_correction": 0.0, "horiz_offset_correction": 0.0}
        for k, (e, a) in enumerate(zip(_VLP32C_ELEVATION_DEG, _VLP32C_AZIMUTH_OFFSET_DEG))
    ],
}

_DEFAULT_RANGE = (0.9, 130.0)  # velodyne_pointcloud's default min_range / max_range (m)


def load_calibration(calib: Mapping[str, Any] | str | os.PathLike[str]) -> dict[str, Any]:
    """The calibration as a dict: a mapping is returned as a shallow copy, a path is read as YAML.

    Raises:
        DecodeError: unreadable file, invalid YAML, or no ``lasers`` list.
    """
    if isinstance(calib, Mapping):
        data: Any = dict(calib)
    else:
        import yaml
        from lidarscan import _yaml

        path = Path(os.fspath(calib))
        try:
            data = _yaml.safe_load(path.read_text(encoding="utf-8"))
        except OSError as err:
            raise DecodeError("calibration", str(path), "a readable velodyne calibration YAML "
                              "file or a mapping") from err
        except yaml.YAMLError as err:
            raise DecodeError("calibration", str(path), f"valid YAML ({err})") from err
    if not isinstance(data, dict) or not isinstance(data.get("lasers"), list) \
            or not data["lasers"]:
        raise DecodeError("calibration.lasers", None if not isinstance(data, dict)
                          else data.get("lasers"), "a non-empty list of per-laser dicts")
    return data


def _whole(value: Any, field: str, expected: str) -> int:
    """``value`` as an int when it is a whole number (YAML may give 3 or 3.0), else a
    DecodeError naming ``field`` (no silent truncation of 1.5, no bool, no string)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)) \
            or not math.isfinite(float(value)) or float(value) != int(value):
        raise DecodeError(field, value, expected)
    return int(value)


def _laser_values(data: Mapping[str, Any]) -> dict[str, np.ndarray[Any, Any]]:
    """Per-laser arrays in laser_id order (laser_id must be a permutation of 0..L-1)."""
    lasers = data["lasers"]
    count = len(lasers)
    declared = data.get("num_lasers")
    if declared is not None and _whole(declared, "calibration.num_lasers",
                                       "a whole number of lasers") != count:
        raise ValidationError("calibration.num_lasers", declared,
                              f"{count} (the length of calibration.lasers)")
    ids = []
    for i, laser in enumerate(lasers):
        if not isinstance(laser, Mapping) or "laser_id" not in laser:
            raise DecodeError(f"calibration.lasers[{i}].laser_id", None, "a laser_id")
        ids.append(_whole(laser["laser_id"], f"calibration.lasers[{i}].laser_id",
                          f"a whole number in 0..{count - 1}"))
    if sorted(ids) != list(range(count)):
        raise ValidationError("calibration.lasers[*].laser_id", sorted(ids),
                              f"each of 0..{count - 1} exactly once")
    by_id = {int(laser["laser_id"]): laser for laser in lasers}
    out: dict[str, np.ndarray[Any, Any]] = {}
    for key, required in (("vert_correction", True), ("rot_correction", False),
                          ("dist_correction", False), ("vert_offset_correction", False),
                          ("horiz_offset_correction", False)):
        values = []
        for k in range(count):
            if key not in by_id[k] and required:
                raise DecodeError(f"calibration.lasers[laser_id={k}].{key}", None,
                                  "a number (radians/metres)")
            values.append(by_id[k].get(key, 0.0))
        try:
            arr = np.asarray(values, dtype=np.float64)
        except (TypeError, ValueError) as err:
            raise DecodeError(f"calibration.lasers[*].{key}", values[:4], "numbers") from err
        if not np.all(np.isfinite(arr)):
            raise ValidationError(f"calibration.lasers[*].{key}", arr.tolist()[:4],
                                  "finite numbers")
        out[key] = arr
    steep = np.flatnonzero(np.abs(out["vert_correction"]) > math.pi / 2)
    if steep.size:                       # e.g. a table in degrees: no beam points past a pole
        k = int(steep[0])
        raise ValidationError(f"calibration.lasers[laser_id={k}].vert_correction",
                              float(out["vert_correction"][k]),
                              "an elevation in radians within [-pi/2, pi/2] (the ros-drivers "
                              "format is in radians; degrees?)")
    return out


def laser_ids_by_row(calib: Mapping[str, Any] | str | os.PathLike[str]) -> np.ndarray[Any, Any]:
    """(H,) int64 laser_id of each row: sorted by elevation, highest first (ties by laser_id)."""
    return _row_order(_laser_values(load_calibration(calib)))


def _row_order(values: Mapping[str, np.ndarray[Any, Any]]) -> np.ndarray[Any, Any]:
    elevation = values["vert_correction"]
    return np.lexsort((np.arange(elevation.size), -elevation)).astype(np.int64)


def info_from_calibration(calib: Mapping[str, Any] | str | os.PathLike[str], *, columns: int,
                          stamp_ns: int = 0, frame_id: str = "velodyne",
                          horizontal_angles: Any = None, rpm: float | None = None,
                          beam_time_offsets: Any = None, column_time_increment: int | None = None,
                          range_min: float | None = None, range_max: float | None = None,
                          model: str = "", distance_resolution: float | None = None,
                          beam_ids: str = "ring", as_dataclass: bool = False) -> Any:
    """LidarInfo of a Velodyne-style sensor from its calibration (see the module docstring).

    Args:
        calib: ros-drivers/velodyne calibration: a mapping or the path of its YAML file.
        columns: W, the number of firing sequences (columns) per scan.
        stamp_ns: header.stamp (version key), int ns.
        frame_id: header.frame_id (the driver's fixed frame of the sensor).
        horizontal_angles: (W,) nominal column azimuths in radians; default ``-2*pi*c/W``
            (rotation 0 at column 0, sweeping clockwise). Scans normally carry the measured ones.
        rpm: rotation speed; when given, ``beta_u`` also holds ``-2*pi*rpm/60 * t_u`` (the
            azimuth swept until laser u fires). Default None: no intra-sequence rotation.
        beam_time_offsets: (L,) ns per laser_id; default the VLP-16 table for 16 lasers
            (2304 ns * laser_id), else zeros.
        column_time_increment: ns between columns; default 55296 for 16 lasers, else 0.
        range_min, range_max: valid interval (m); default 0.9 / 130 (velodyne_pointcloud).
        model: free-text model name (default "VLP-16" for 16 lasers).
        distance_resolution: metres per raw distance unit, overriding the calibration's
            ``distance_resolution`` (the packet decoder passes the model's unit from the manual).
        beam_ids: "ring" (default: Velodyne ring numbers, 0 = lowest beam) or "laser_id" (the
            vendor's laser number, the position of the laser in a firing sequence).
        as_dataclass: return :class:`lidarscan.types.LidarInfo` instead of the rclpy message.

    Returns:
        LidarInfo with rows sorted by elevation (row 0 highest), ``beam_ids`` = Velodyne ring
        numbers (0 = lowest beam), ``range_multiplier`` = distance_resolution for raw integer
        distances.

    Raises:
        DecodeError / ValidationError: malformed calibration or arguments.
    """
    data = load_calibration(calib)
    values = _laser_values(data)
    count = values["vert_correction"].size
    if int(columns) <= 0:
        raise ValidationError("columns", columns, "a positive number of columns")
    width = int(columns)
    order = _row_order(values)                     # laser_id of each row
    height = order.size

    if beam_time_offsets is None:
        per_laser = (np.arange(count, dtype=np.int64) * VLP16_FIRING_NS if count == 16
                     else np.zeros(count, np.int64))
    else:
        per_laser = np.asarray(beam_time_offsets)
        if per_laser.shape != (count,) or per_laser.dtype.kind not in "iu":
            raise ValidationError("beam_time_offsets", f"{per_laser.dtype} {per_laser.shape}",
                                  f"({count},) integer ns per laser_id")
        per_laser = per_laser.astype(np.int64)
    if column_time_increment is None:
        column_time_increment = VLP16_CYCLE_NS if count == 16 else 0

    phi = values["vert_correction"][order]
    beta = values["rot_correction"][order].copy()
    if rpm is not None:
        if not math.isfinite(float(rpm)):
            raise ValidationError("rpm", rpm, "a finite rotation speed (rev/min)")
        omega = 2.0 * math.pi * float(rpm) / 60.0
        beta -= omega * per_laser[order] * 1e-9
    vert = values["vert_offset_correction"][order]
    horiz = values["horiz_offset_correction"][order]
    origins = np.stack([-vert * np.sin(phi), horiz, vert * np.cos(phi)], -1)

    if horizontal_angles is None:
        alpha = -2.0 * np.pi * np.arange(width, dtype=np.float64) / width
    else:
        alpha = np.asarray(horizontal_angles, dtype=np.float64).reshape(-1)
        if alpha.size != width:
            raise ValidationError("horizontal_angles", f"length {alpha.size}",
                                  f"length {width} (columns)")
    resolution = (data.get("distance_resolution", 0.002) if distance_resolution is None
                  else distance_resolution)
    if isinstance(resolution, (bool, np.bool_)) \
            or not isinstance(resolution, (int, float, np.number)) \
            or not resolution > 0 or not math.isfinite(resolution):
        raise ValidationError("calibration.distance_resolution", resolution, "> 0 metres")
    resolution = float(resolution)
    if beam_ids == "ring":
        ids = (height - 1 - np.arange(height)).astype(np.uint16)
    elif beam_ids == "laser_id":
        ids = order.astype(np.uint16)
    else:
        raise ValidationError("beam_ids", beam_ids, '"ring" or "laser_id"')
    lo, hi = _DEFAULT_RANGE
    return make_info(
        stamp_ns=stamp_ns, frame_id=frame_id,
        vertical_angles=phi, horizontal_angles=alpha,
        beam_azimuth_offsets=beta,
        beam_origins=origins.reshape(-1),
        beam_range_offsets=values["dist_correction"][order],
        beam_time_offsets=per_laser[order],
        column_time_increment=int(column_time_increment),
        beam_ids=ids,
        range_multiplier=resolution, range_offset=0.0,
        range_min=lo if range_min is None else range_min,
        range_max=hi if range_max is None else range_max,
        vendor="Velodyne", model=model or ("VLP-16" if count == 16 else ""),
        as_dataclass=as_dataclass)


def scan_from_firings(calib: Mapping[str, Any] | str | os.PathLike[str], info: Any,
                      distances: Any, rotations_deg: Any, *, stamp_ns: int,
                      intensities: Any = None, column_time_offsets: Any = None,
                      as_dataclass: bool = False) -> Any:
    """LidarScan from decoded firing sequences (one column each).

    Args:
        calib: the calibration ``info`` was built from (for the laser_id -> row order).
        info: from :func:`info_from_calibration` with ``columns`` = W.
        distances: (W, L) raw distances in laser_id order (uint16 units of distance_resolution,
            0 = no return), as in the packets.
        rotations_deg: (W,) packet azimuth of each sequence in degrees (clockwise), stored as
            ``column_azimuth_angles = -radians(rotation)``.
        stamp_ns: time of column 0 (int ns).
        intensities: optional (W, L) uint8 in laser_id order.
        column_time_offsets: optional (W,) int ns relative to ``stamp_ns``.
        as_dataclass: return :class:`lidarscan.types.LidarScan` instead of the rclpy message.

    Returns:
        LidarScan with a UINT16 ``range`` channel (decoded by ``info.range_multiplier``) and an
        optional UINT8 ``intensity``.
    """
    order = laser_ids_by_row(calib)
    height, width = int(info.height), int(info.width)
    raw = np.asarray(distances)
    if raw.shape != (width, order.size) or order.size != height:
        raise ValidationError("distances.shape", raw.shape,
                              f"({width}, {height}) (columns, lasers)")
    if raw.dtype.kind not in "iu" or (raw.size and (raw.min() < 0 or raw.max() > 65535)):
        raise ValidationError("distances", str(raw.dtype), "raw uint16 distance units")
    rot = np.asarray(rotations_deg, dtype=np.float64).reshape(-1)
    if rot.size != width:
        raise ValidationError("rotations_deg", f"length {rot.size}", f"length {width}")
    channels = {"range": np.ascontiguousarray(raw.T[order]).astype(np.uint16)}
    if intensities is not None:
        inten = np.asarray(intensities)
        if inten.shape != raw.shape:
            raise ValidationError("intensities.shape", inten.shape, f"{raw.shape}")
        channels["intensity"] = np.ascontiguousarray(inten.T[order]).astype(np.uint8)
    return make_scan(info, channels, stamp_ns, column_azimuth_angles=-np.deg2rad(rot),
                     column_time_offsets=column_time_offsets, as_dataclass=as_dataclass)
