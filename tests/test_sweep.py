"""converters.sources.sweep: tilting-laser LaserScans -> LidarScan, against a per-ray loop reference.

Reference: ray i of scan k at angle a = angle_min + i*inc, range r, joint angle q about a unit
axis k (Rodrigues, written with math only): P = R(q) (laser_offset + r (cos a, sin a, 0)).
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import lidarscan
from converters.sources.sweep import from_laserscan_sweep, rotation_matrix
from lidarscan import geometry, types
from lidarscan.errors import ValidationError

LaserScan = types.message_class("sensor_msgs/msg/LaserScan")


def _rotate(axis: tuple[float, float, float], q: float, v: list[float]) -> list[float]:
    kx, ky, kz = axis
    c, s = math.cos(q), math.sin(q)
    dot = kx * v[0] + ky * v[1] + kz * v[2]
    cross = [ky * v[2] - kz * v[1], kz * v[0] - kx * v[2], kx * v[1] - ky * v[0]]
    return [v[i] * c + cross[i] * s + (kx, ky, kz)[i] * dot * (1 - c) for i in range(3)]


def _reference(scan: Any, q: float, axis: tuple[float, float, float],
               offset: tuple[float, float, float], i: int) -> list[float]:
    a = float(scan.angle_min) + i * float(scan.angle_increment)
    r = float(scan.ranges[i])
    return _rotate(axis, q, [offset[0] + r * math.cos(a), offset[1] + r * math.sin(a),
                             offset[2]])


def _scans(seed: int, count: int, rays: int, *, intensities: bool = True,
           stamp0: int = 1_700_000_000, span: float = 4.0) -> list[Any]:
    rng = np.random.default_rng(seed)
    increment = np.float32(span / max(rays - 1, 1))
    angle_min = np.float32(-span / 2)
    out = []
    for k in range(count):
        ranges = rng.uniform(0.05, 30.0, rays).astype(np.float32)
        out.append(LaserScan(
            header=types.Header(types.Time(stamp0, int(rng.integers(0, 10**9))), "laser"),
            angle_min=float(angle_min), angle_max=float(angle_min + (rays - 1) * increment),
            angle_increment=float(increment), time_increment=float(np.float32(1e-4)),
            scan_time=0.025, range_min=0.02, range_max=30.0, ranges=ranges,
            intensities=(rng.uniform(0, 1000, rays).astype(np.float32) if intensities
                         else np.zeros(0, np.float32))))
    return out


AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), count=st.integers(1, 6), rays=st.integers(1, 20),
       axis=st.sampled_from(["x", "y", "z", "vector"]), with_offset=st.booleans())
def test_matches_loop_reference(seed: int, count: int, rays: int, axis: str,
                                with_offset: bool) -> None:
    rng = np.random.default_rng(seed + 1)
    scans = _scans(seed, count, rays)
    q = rng.uniform(-1.2, 1.2, count)
    if axis == "vector":
        vec = rng.normal(size=3)
        axis_arg: Any = vec.tolist()
        unit = tuple((vec / np.linalg.norm(vec)).tolist())
    else:
        axis_arg, unit = axis, AXES[axis]
    offset = tuple(rng.uniform(-0.2, 0.2, 3).tolist()) if with_offset else (0.0, 0.0, 0.0)
    scan, info = from_laserscan_sweep(scans, q, axis=axis_arg, laser_offset=offset,
                                      frame_id="tilt_base", as_dataclass=True)
    lidarscan.validate(scan, info)
    assert (info.height, info.width) == (count, rays)
    assert info.header.frame_id == "tilt_base"
    rows = json.loads(info.vendor_metadata)["scan_index"]
    assert sorted(rows) == list(range(count))
    expected = np.array([[_reference(scans[k], float(q[k]), unit, offset, i)
                          for i in range(rays)] for k in rows])
    ranges = lidarscan.range_m(scan)
    exact = geometry.exact_xyz(info, ranges.astype(np.float64))
    assert np.abs(exact - expected).max() < 1e-6
    points = lidarscan.make_projector(info).project(scan)
    assert np.abs(points - expected).max() < 1e-4
    # rows sorted by elevation of the central ray, highest first
    assert np.all(np.diff(info.vertical_angles) <= 0)
    np.testing.assert_array_equal(lidarscan.channel(scan, "intensity"),
                                  np.stack([scans[k].intensities for k in rows]))


def test_nodding_laser_row_order_and_metadata() -> None:
    """About +y a positive joint angle tilts the forward ray down: row 0 = most negative q."""
    scans = _scans(1, 4, 11)
    q = [0.1, -0.3, 0.4, 0.0]
    _, info = from_laserscan_sweep(scans, q, as_dataclass=True)
    meta = json.loads(info.vendor_metadata)
    assert meta["scan_index"] == [1, 3, 0, 2]
    assert [pair[0] for pair in meta["joint_angles"]] == [-0.3, 0.0, 0.1, 0.4]
    np.testing.assert_allclose(info.vertical_angles, [0.3, 0.0, -0.1, -0.4], atol=1e-12)
    np.testing.assert_array_equal(info.beam_ids, [1, 3, 0, 2])
    assert info.header.frame_id == "laser"
    stamps = np.array([lidarscan.to_ns(s.header.stamp) for s in scans])
    np.testing.assert_array_equal(info.beam_time_offsets, stamps[[1, 3, 0, 2]] - stamps.min())
    unsorted, info_u = from_laserscan_sweep(scans, q, sort=False, as_dataclass=True)
    assert json.loads(info_u.vendor_metadata)["scan_index"] == [0, 1, 2, 3]
    np.testing.assert_array_equal(lidarscan.channel(unsorted, "range")[0], scans[0].ranges)


def test_times() -> None:
    scans = _scans(2, 3, 5)
    stamps = [lidarscan.to_ns(s.header.stamp) for s in scans]
    scan, info = from_laserscan_sweep(scans, [0.0, 0.1, 0.2], sort=False, as_dataclass=True)
    assert lidarscan.to_ns(scan.header.stamp) == min(stamps) == lidarscan.to_ns(info.header.stamp)
    np.testing.assert_array_equal(info.beam_time_offsets, np.array(stamps) - min(stamps))
    assert info.column_time_increment == round(float(np.float32(1e-4)) * 1e9)
    times = lidarscan.make_projector(info).pixel_times(scan)
    for k in range(3):
        for i in range(5):
            assert min(stamps) + times[k, i] == stamps[k] + i * info.column_time_increment
    _, info_e = from_laserscan_sweep(scans, [0.0, 0.1, 0.2], sort=False,
                                     stamp_ns=stamps[1], as_dataclass=True)
    np.testing.assert_array_equal(info_e.beam_time_offsets, np.array(stamps) - stamps[1])
    # negative time_increment: explicit (negative) column offsets
    reverse = [LaserScan(**{**{f: getattr(s, f) for f in s.__dataclass_fields__},
                            "time_increment": -1e-4}) for s in scans]
    scan_r, info_r = from_laserscan_sweep(reverse, [0.0, 0.1, 0.2], as_dataclass=True)
    assert info_r.column_time_increment == 0
    np.testing.assert_array_equal(scan_r.column_time_offsets, np.arange(5) * -100_000)


def test_rep117_range_rule() -> None:
    values = [np.inf, -np.inf, np.nan, 0.0, -1.0, 0.01, 0.02, 5.0, 30.0, 30.5]
    scan_msg = LaserScan(header=types.Header(types.Time(1, 0), "laser"), angle_min=-1.0,
                         angle_max=1.0, angle_increment=0.2, time_increment=0.0, scan_time=0.1,
                         range_min=0.02, range_max=30.0,
                         ranges=np.array(values, np.float32), intensities=np.zeros(0))
    scan, info = from_laserscan_sweep([scan_msg], [0.0], as_dataclass=True)
    out = lidarscan.channel(scan, "range")[0]
    assert out[0] == np.inf and out[1] == -np.inf
    assert np.isnan(out[[2, 3, 4, 5, 9]]).all()
    np.testing.assert_array_equal(out[[6, 7, 8]], np.float32([0.02, 5.0, 30.0]))  # inclusive
    assert lidarscan.channel_names(scan) == ["range"]          # no intensities
    assert (info.range_min, info.range_max) == (pytest.approx(0.02), pytest.approx(30.0))
    assert np.isnan(lidarscan.make_projector(info).project(scan)[0, :6]).all()


def test_interpolated_joint_angles() -> None:
    """(start, end) pairs: exact directions; with no offset the points are exact."""
    scans = _scans(3, 2, 9)
    pairs = [(0.0, 0.2), (-0.5, -0.1)]
    scan, info = from_laserscan_sweep(scans, pairs, sort=False, as_dataclass=True)
    exact = geometry.exact_xyz(info, lidarscan.range_m(scan).astype(np.float64))
    for k in range(2):
        for i in range(9):
            q = pairs[k][0] + (pairs[k][1] - pairs[k][0]) * i / 8
            np.testing.assert_allclose(exact[k, i],
                                       _reference(scans[k], q, AXES["y"], (0, 0, 0), i),
                                       atol=1e-9)
    # with an offset the origin uses the mid angle: bounded error
    offset = (0.1, 0.0, 0.05)
    scan, info = from_laserscan_sweep(scans, pairs, sort=False, laser_offset=offset,
                                      as_dataclass=True)
    exact = geometry.exact_xyz(info, lidarscan.range_m(scan).astype(np.float64))
    bound = math.hypot(0.1, 0.05) * 0.4 / 2 + 1e-9
    for k in range(2):
        for i in range(9):
            q = pairs[k][0] + (pairs[k][1] - pairs[k][0]) * i / 8
            ref = _reference(scans[k], q, AXES["y"], offset, i)
            assert np.linalg.norm(exact[k, i] - ref) <= bound


def test_rclpy_messages_in_and_out() -> None:
    from builtin_interfaces.msg import Time
    from sensor_msgs.msg import LaserScan as RosLaserScan
    msgs = []
    for k in range(3):
        msg = RosLaserScan()
        msg.header.stamp = Time(sec=5, nanosec=k * 1000)
        msg.header.frame_id = "tilt"
        msg.angle_min, msg.angle_increment = -0.5, 0.25
        msg.angle_max = 0.5
        msg.range_min, msg.range_max = 0.1, 10.0
        msg.ranges = [1.0, 2.0, 3.0, 4.0, 5.0]
        msgs.append(msg)
    scan, info = from_laserscan_sweep(msgs, [0.2, 0.0, -0.2])
    assert type(scan).__module__.startswith("lidarscan_msgs")
    lidarscan.validate(scan, info)
    points = lidarscan.make_projector(info).project(scan)
    assert np.isfinite(points).all()


def test_rotation_matrix_is_right_handed() -> None:
    np.testing.assert_allclose(rotation_matrix("z", math.pi / 2) @ [1, 0, 0], [0, 1, 0],
                               atol=1e-15)
    np.testing.assert_allclose(rotation_matrix("y", math.pi / 2) @ [1, 0, 0], [0, 0, -1],
                               atol=1e-15)
    assert rotation_matrix([0, 0, 2], np.zeros(4)).shape == (4, 3, 3)


@pytest.mark.parametrize("change, field", [
    (lambda s: s[1].__setattr__("ranges", np.ones(4, np.float32)), "scans[1].ranges"),
    (lambda s: s[2].__setattr__("angle_min", s[0].angle_min + 1e-6), "scans[2].angle_min"),
    (lambda s: s[1].__setattr__("angle_increment", s[0].angle_increment * 2),
     "scans[1].angle_increment"),
    (lambda s: s[1].__setattr__("intensities", np.ones(3, np.float32)), "scans[1].intensities"),
    (lambda s: s[1].__setattr__("intensities", np.zeros(0, np.float32)),
     "scans[*].intensities"),
])
def test_validation_errors(change: Any, field: str) -> None:
    scans = [_Mutable(s) for s in _scans(4, 3, 6)]
    change(scans)
    with pytest.raises(ValidationError) as err:
        from_laserscan_sweep(scans, [0.0, 0.1, 0.2])
    assert err.value.field == field


def test_argument_errors() -> None:
    scans = _scans(5, 2, 4)
    with pytest.raises(ValidationError):
        from_laserscan_sweep([], [])
    with pytest.raises(ValidationError):
        from_laserscan_sweep(scans, [0.0])
    with pytest.raises(ValidationError):
        from_laserscan_sweep(scans, [0.0, float("nan")])
    with pytest.raises(ValidationError):
        from_laserscan_sweep(scans, [0.0, 0.1], axis="w")
    with pytest.raises(ValidationError):
        from_laserscan_sweep(scans, [0.0, 0.1], axis=[0, 0, 0])
    with pytest.raises(ValidationError):
        from_laserscan_sweep(scans, [0.0, 0.1], laser_offset=(0, 0))


def test_angle_tolerance_accepts_float32_noise() -> None:
    scans = [_Mutable(s) for s in _scans(6, 2, 5)]
    scans[1].angle_min = scans[0].angle_min + 5e-10
    scan, _ = from_laserscan_sweep(scans, [0.0, 0.1], as_dataclass=True)
    assert scan.height == 2


class _Mutable:
    """A LaserScan stand-in whose fields can be changed (duck typing on field names)."""

    def __init__(self, scan: Any) -> None:
        for name in scan.__dataclass_fields__:
            setattr(self, name, getattr(scan, name))
