"""converters.sources.velodyne against a per-point reference of the velodyne_pointcloud formula.

``_rawdata_point`` follows the point computation of ros-drivers/velodyne ``rawdata.cpp`` as
described in prior-art.md (b) (re-derived here, math only): distance = raw * resolution, plus
dist_correction when > 0; rot = rotation - rot_correction (clockwise azimuth); xy = d cos(vert) -
vo sin(vert); x = xy sin(rot) - ho cos(rot); y = xy cos(rot) + ho sin(rot); z = d sin(vert) +
vo cos(vert); ROS point = (y, -x, z).
"""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import lidarscan
from converters.sources import velodyne
from lidarscan import geometry
from lidarscan.errors import DecodeError, ValidationError


def _rawdata_point(laser: dict[str, float], raw: int, rotation_deg: float, resolution: float
                   ) -> tuple[float, float, float] | None:
    distance = raw * resolution
    if distance <= 1e-6:
        return None
    distance += laser["dist_correction"]
    rot = math.radians(rotation_deg) - laser["rot_correction"]
    vert = laser["vert_correction"]
    vo, ho = laser["vert_offset_correction"], laser["horiz_offset_correction"]
    xy = distance * math.cos(vert) - vo * math.sin(vert)
    x = xy * math.sin(rot) - ho * math.cos(rot)
    y = xy * math.cos(rot) + ho * math.sin(rot)
    z = distance * math.sin(vert) + vo * math.cos(vert)
    return y, -x, z


def _random_calibration(seed: int, lasers: int) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    elevations = rng.uniform(-0.5, 0.5, lasers)
    ids = rng.permutation(lasers)
    return {
        "num_lasers": lasers,
        "distance_resolution": float(rng.choice([0.002, 0.001, 0.004])),
        "lasers": [{"laser_id": int(ids[k]), "vert_correction": float(elevations[k]),
                    "rot_correction": float(rng.uniform(-0.2, 0.2)),
                    "dist_correction": float(rng.uniform(-0.1, 1.5)),
                    "vert_offset_correction": float(rng.uniform(-0.05, 0.05)),
                    "horiz_offset_correction": float(rng.uniform(-0.05, 0.05)),
                    "dist_correction_x": 0.0, "dist_correction_y": 0.0,
                    "focal_distance": 0.0, "focal_slope": 0.0}
                   for k in range(lasers)],
    }


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), lasers=st.integers(1, 16), columns=st.integers(1, 12))
def test_projection_matches_rawdata_formula(seed: int, lasers: int, columns: int) -> None:
    calib = _random_calibration(seed, lasers)
    rng = np.random.default_rng(seed + 1)
    distances = rng.integers(0, 60000, (columns, lasers)).astype(np.uint16)
    distances[rng.random((columns, lasers)) < 0.2] = 0
    rotations = np.round(rng.uniform(0, 360, columns), 2)    # packets: hundredths of a degree
    info = velodyne.info_from_calibration(calib, columns=columns, stamp_ns=9, as_dataclass=True)
    lidarscan.validate_info(info)
    scan = velodyne.scan_from_firings(calib, info, distances, rotations, stamp_ns=10,
                                      as_dataclass=True)
    lidarscan.validate(scan, info)
    rows = velodyne.laser_ids_by_row(calib)
    by_id = {laser["laser_id"]: laser for laser in calib["lasers"]}
    expected = np.full((lasers, columns, 3), np.nan)
    for u, laser_id in enumerate(rows):
        for c in range(columns):
            point = _rawdata_point(by_id[int(laser_id)], int(distances[c, laser_id]),
                                   float(rotations[c]), calib["distance_resolution"])
            if point is not None:
                expected[u, c] = point
    valid = ~np.isnan(expected).any(-1)
    # the model in float64 (ranges from the raw values, not the float32 decoding) is the
    # driver's formula
    metres = np.where(distances.T[rows] > 0, distances.T[rows] * calib["distance_resolution"],
                      np.inf)
    exact = geometry.exact_xyz(info, metres, column_azimuth_angles=scan.column_azimuth_angles)
    np.testing.assert_array_equal(np.isnan(exact).any(-1), ~valid)
    assert np.all(np.abs(exact[valid] - expected[valid]) < 1e-6)
    points = lidarscan.make_projector(info).project(scan, info)
    np.testing.assert_array_equal(np.isnan(points).any(-1), ~valid)
    assert np.all(np.abs(points[valid] - expected[valid]) < 1e-4)   # float32 tables, <= 130 m


def test_rows_sorted_ring_numbers_and_vlp16_timing() -> None:
    info = velodyne.info_from_calibration(velodyne.VLP16_CALIBRATION, columns=1808,
                                          as_dataclass=True)
    lidarscan.validate_info(info)
    assert (info.height, info.width, info.vendor, info.model) == (16, 1808, "Velodyne", "VLP-16")
    np.testing.assert_allclose(np.rad2deg(info.vertical_angles), np.arange(15, -16, -2),
                               atol=1e-12)
    np.testing.assert_array_equal(info.beam_ids, np.arange(15, -1, -1))   # ring 0 = lowest
    rows = velodyne.laser_ids_by_row(velodyne.VLP16_CALIBRATION)
    np.testing.assert_array_equal(rows, [15, 13, 11, 9, 7, 5, 3, 1, 14, 12, 10, 8, 6, 4, 2, 0])
    np.testing.assert_array_equal(info.beam_time_offsets, rows * 2304)
    assert info.column_time_increment == 55296
    assert info.range_multiplier == 0.002
    np.testing.assert_allclose(info.horizontal_angles, -2 * np.pi * np.arange(1808) / 1808)
    assert not np.any(info.beam_origins) and not np.any(info.beam_range_offsets)


def test_vlp16_nominal_angles() -> None:
    elevations = [math.degrees(laser["vert_correction"])
                  for laser in velodyne.VLP16_CALIBRATION["lasers"]]
    np.testing.assert_allclose(elevations, [-15, 1, -13, 3, -11, 5, -9, 7, -7, 9, -5, 11, -3, 13,
                                            -1, 15], atol=1e-12)


def test_rpm_folds_intra_sequence_rotation_into_beam_azimuth() -> None:
    """With rpm, laser u's azimuth is the sequence azimuth advanced by omega * t_u (clockwise)."""
    rpm = 600.0
    info = velodyne.info_from_calibration(velodyne.VLP16_CALIBRATION, columns=4, rpm=rpm,
                                          as_dataclass=True)
    rows = velodyne.laser_ids_by_row(velodyne.VLP16_CALIBRATION)
    rotations = np.array([0.0, 10.0, 180.0, 359.5])
    distances = np.full((4, 16), 5000, np.uint16)
    scan = velodyne.scan_from_firings(velodyne.VLP16_CALIBRATION, info, distances, rotations,
                                      stamp_ns=0, as_dataclass=True)
    points = geometry.exact_xyz(info, np.full((16, 4), 10.0),
                                column_azimuth_angles=scan.column_azimuth_angles)
    deg_per_ns = rpm * 360.0 / 60.0 * 1e-9
    for u, laser_id in enumerate(rows):
        laser = velodyne.VLP16_CALIBRATION["lasers"][int(laser_id)]
        for c in range(4):
            rotation = rotations[c] + deg_per_ns * 2304 * int(laser_id)
            expected = _rawdata_point(laser, 5000, rotation, 0.002)
            np.testing.assert_allclose(points[u, c], expected, atol=1e-9)


def test_yaml_file_and_distance_resolution(tmp_path: Path) -> None:
    yaml = pytest.importorskip("yaml")
    calib = _random_calibration(5, 32)
    path = tmp_path / "calib.yaml"
    path.write_text(yaml.safe_dump(calib, default_flow_style=None))
    from_file = velodyne.info_from_calibration(path, columns=10, as_dataclass=True)
    from_dict = velodyne.info_from_calibration(calib, columns=10, as_dataclass=True)
    assert geometry.info_key(from_file) == geometry.info_key(from_dict)
    assert from_dict.range_multiplier == calib["distance_resolution"]
    assert from_dict.column_time_increment == 0 and not np.any(from_dict.beam_time_offsets)
    # in the ros-drivers flow style, as the shipped VLP16.yaml
    text = "lasers:\n" + "".join(
        f"- {{dist_correction: 0.0, laser_id: {laser['laser_id']}, rot_correction: 0.0, "
        f"vert_correction: {laser['vert_correction']!r}, vert_offset_correction: 0.0, "
        "horiz_offset_correction: 0.0}\n"
        for laser in velodyne.VLP16_CALIBRATION["lasers"]) + "num_lasers: 16\n"
    (tmp_path / "vlp16.yaml").write_text(text)
    info = velodyne.info_from_calibration(tmp_path / "vlp16.yaml", columns=3, as_dataclass=True)
    np.testing.assert_allclose(np.rad2deg(info.vertical_angles), np.arange(15, -16, -2),
                               atol=1e-12)


def test_rclpy_message_output() -> None:
    info = velodyne.info_from_calibration(velodyne.VLP16_CALIBRATION, columns=8)
    assert type(info).__module__.startswith("lidarscan_msgs")
    scan = velodyne.scan_from_firings(velodyne.VLP16_CALIBRATION, info,
                                      np.ones((8, 16), np.uint16), np.arange(8) * 0.2,
                                      stamp_ns=5, intensities=np.full((8, 16), 7, np.uint8))
    lidarscan.validate(scan, info)
    assert lidarscan.channel_names(scan) == ["range", "intensity"]
    np.testing.assert_allclose(np.asarray(scan.column_azimuth_angles),
                               -np.deg2rad(np.arange(8) * 0.2))


@pytest.mark.parametrize("mutate, error", [
    (lambda c: c.pop("lasers"), DecodeError),
    (lambda c: c["lasers"][0].pop("vert_correction"), DecodeError),
    (lambda c: c["lasers"][0].pop("laser_id"), DecodeError),
    (lambda c: c["lasers"][0].update(laser_id=3), ValidationError),
    (lambda c: c.update(num_lasers=17), ValidationError),
    (lambda c: c["lasers"][1].update(rot_correction=float("nan")), ValidationError),
    (lambda c: c.update(distance_resolution=0.0), ValidationError),
    # vendor / hand-made files: non-numbers are project errors naming the key, never a bare
    # ValueError / TypeError, and whole numbers are not truncated
    (lambda c: c["lasers"][0].update(laser_id="a"), DecodeError),
    (lambda c: c["lasers"][0].update(laser_id=None), DecodeError),
    (lambda c: c["lasers"][0].update(laser_id=1.5), DecodeError),
    (lambda c: c["lasers"][0].update(laser_id=True), DecodeError),
    (lambda c: c.update(num_lasers="sixteen"), DecodeError),
    (lambda c: c.update(distance_resolution="2mm"), ValidationError),
    (lambda c: c.update(distance_resolution=None), ValidationError),
    # an elevation table in degrees: no beam points past a pole
    (lambda c: [las.update(vert_correction=math.degrees(las["vert_correction"]))
                for las in c["lasers"]], ValidationError),
])
def test_bad_calibration(mutate: Any, error: type) -> None:
    calib = copy.deepcopy(velodyne.VLP16_CALIBRATION)
    mutate(calib)
    with pytest.raises(error, match="calibration"):
        velodyne.info_from_calibration(calib, columns=4)


def test_minimal_and_shuffled_calibration_files(tmp_path: Path) -> None:
    """What vendors and ros-drivers ship: only laser_id and vert_correction (no offsets, focal
    or two-point keys, no num_lasers), lasers listed out of order, ids written as 3.0: the same
    info as the complete file (missing optional keys are 0)."""
    full = velodyne.info_from_calibration(velodyne.VLP16_CALIBRATION, columns=8,
                                          as_dataclass=True)
    lasers = [{"laser_id": float(las["laser_id"]), "vert_correction": las["vert_correction"]}
              for las in velodyne.VLP16_CALIBRATION["lasers"]]
    text = "lasers:\n" + "".join(
        f"- {{laser_id: {las['laser_id']}, vert_correction: {las['vert_correction']!r}}}\n"
        for las in lasers[::-1])
    (tmp_path / "min.yaml").write_text(text)
    info = velodyne.info_from_calibration(tmp_path / "min.yaml", columns=8, as_dataclass=True)
    for name in ("vertical_angles", "beam_azimuth_offsets", "beam_origins", "beam_ids",
                 "beam_range_offsets", "beam_time_offsets"):
        np.testing.assert_array_equal(getattr(info, name), getattr(full, name), err_msg=name)


def test_bad_arguments(tmp_path: Path) -> None:
    with pytest.raises(ValidationError):
        velodyne.info_from_calibration(velodyne.VLP16_CALIBRATION, columns=0)
    with pytest.raises(ValidationError):
        velodyne.info_from_calibration(velodyne.VLP16_CALIBRATION, columns=4,
                                       horizontal_angles=[0.0, 1.0])
    with pytest.raises(DecodeError):
        velodyne.info_from_calibration(tmp_path / "missing.yaml", columns=4)
    info = velodyne.info_from_calibration(velodyne.VLP16_CALIBRATION, columns=4)
    with pytest.raises(ValidationError):
        velodyne.scan_from_firings(velodyne.VLP16_CALIBRATION, info, np.ones((16, 4), np.uint16),
                                   np.zeros(4), stamp_ns=0)
    assert velodyne.VLP16_CALIBRATION["lasers"][0]["laser_id"] == 0  # constant not mutated
