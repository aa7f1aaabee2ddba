"""Motion compensation (converters.shared.deskew) against slow references written from the definitions.

* constant velocity: a loop over points with the closed-form SE(3) exponential written out with
  ``math``, and, independently of any closed form, a numerical integration of the body twist;
* odometry pair: quaternion slerp + linear translation written out per point;
* to_pointcloud2(motion=...): every pixel moved with its own time to the cloud's stamp.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

import lidarscan
from converters.shared import deskew
from lidarscan.errors import ConfigError, ValidationError

# ----------------------------------------------------------------------------- references

def _mat(rows: list[list[float]]) -> np.ndarray:
    return np.array(rows, dtype=float)


def cv_transform_loop(linear: list[float], angular: list[float], dt: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """exp(dt * xi^) for a body twist, written out (Rodrigues + left Jacobian)."""
    wx, wy, wz = (a * dt for a in angular)
    theta = math.sqrt(wx * wx + wy * wy + wz * wz)
    k = _mat([[0, -wz, wy], [wz, 0, -wx], [-wy, wx, 0]])
    k2 = k @ k
    if theta < 1e-9:
        rot = np.eye(3) + k + k2 / 2
        v = np.eye(3) + k / 2 + k2 / 6
    else:
        rot = np.eye(3) + math.sin(theta) / theta * k + (1 - math.cos(theta)) / theta**2 * k2
        v = (np.eye(3) + (1 - math.cos(theta)) / theta**2 * k
             + (theta - math.sin(theta)) / theta**3 * k2)
    return rot, v @ np.array([a * dt for a in linear])


def cv_transform_integrated(linear: list[float], angular: list[float], dt: float,
                            steps: int = 20000) -> tuple[np.ndarray, np.ndarray]:
    """The same pose by integrating dR = R w^ dt, dp = R v dt (midpoint rule)."""
    h = dt / steps
    w = np.array(angular)
    k = _mat([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    small = np.eye(3) + k * h + (k @ k) * h * h / 2 + (k @ k @ k) * h**3 / 6
    rot, pos = np.eye(3), np.zeros(3)
    for _ in range(steps):
        nxt = rot @ small
        pos = pos + 0.5 * (rot + nxt) @ np.array(linear) * h
        rot = nxt
    return rot, pos


def quat_to_mat(q: list[float]) -> np.ndarray:
    x, y, z, w = q
    return _mat([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def slerp(q0: list[float], q1: list[float], s: float) -> list[float]:
    dot = sum(a * b for a, b in zip(q0, q1))
    if dot < 0:
        q1, dot = [-c for c in q1], -dot
    omega = math.acos(min(1.0, dot))
    if omega < 1e-12:
        return list(q0)
    a = math.sin((1 - s) * omega) / math.sin(omega)
    b = math.sin(s * omega) / math.sin(omega)
    q = [a * c0 + b * c1 for c0, c1 in zip(q0, q1)]
    norm = math.sqrt(sum(c * c for c in q))
    return [c / norm for c in q]


def pair_pose_loop(t: int, t0: int, p0: tuple, t1: int, p1: tuple) -> np.ndarray:
    s = (t - t0) / (t1 - t0)
    matrix = np.eye(4)
    matrix[:3, :3] = quat_to_mat(slerp(list(p0[1]), list(p1[1]), s))
    matrix[:3, 3] = [a + s * (b - a) for a, b in zip(p0[0], p1[0])]
    return matrix


def unit(q: list[float]) -> list[float]:
    n = math.sqrt(sum(c * c for c in q))
    return [c / n for c in q]


# ---------------------------------------------------------------------------------- tests

LIN, ANG = [2.0, -0.5, 0.3], [0.2, -0.4, 1.5]


def test_constant_velocity_matches_closed_form_loop_and_integration() -> None:
    rng = np.random.default_rng(1)
    pts = rng.uniform(-20, 20, (200, 3))
    times = rng.integers(-60_000_000, 60_000_000, 200) + 10**9
    got = deskew.deskew_points(pts, times, deskew.ConstantVelocity(LIN, ANG), 10**9)
    for p, t, g in zip(pts, times, got):
        rot, trans = cv_transform_loop(LIN, ANG, (int(t) - 10**9) * 1e-9)
        np.testing.assert_allclose(g, rot @ p + trans, atol=2e-5)
    for dt in (0.1, -0.05):
        rot, trans = deskew.relative_transforms((LIN, ANG), [int(dt * 1e9)], 0)
        rot_i, trans_i = cv_transform_integrated(LIN, ANG, dt)
        np.testing.assert_allclose(rot[0], rot_i, atol=1e-9)
        np.testing.assert_allclose(trans[0], trans_i, atol=1e-9)


def test_constant_velocity_simple_cases() -> None:
    pts = np.array([[1.0, 2.0, 3.0], [np.nan, 0, 0]])
    zero = deskew.deskew_points(pts, [5, 9], {"linear": (0, 0, 0), "angular": (0, 0, 0)}, 0)
    np.testing.assert_array_equal(zero[0], np.float32(pts[0]))
    assert np.isnan(zero[1]).all()
    moved = deskew.deskew_points(pts[:1], [500_000_000], ((1.0, 0, 0), (0, 0, 0)), 0)
    np.testing.assert_allclose(moved[0], [1.5, 2, 3], atol=1e-6)     # moved forward 0.5 m
    turned = deskew.deskew_points(np.array([[1.0, 0, 0]]), [10**9], ((0, 0, 0),
                                                                    (0, 0, np.pi / 2)), 0)
    np.testing.assert_allclose(turned[0], [0, 1, 0], atol=1e-6)       # CCW quarter turn
    ref = deskew.ConstantVelocity((1.0, 0, 0), (0, 0, 0), reference_ns=10**9)
    np.testing.assert_allclose(deskew.deskew_points(pts[:1], [10**9], ref, 0)[0], pts[0],
                               atol=1e-6)


def test_odometry_pair_matches_slerp_loop() -> None:
    rng = np.random.default_rng(2)
    t0, t1 = 1_000_000_000, 1_100_000_000
    p0 = ((1.0, 2.0, 0.5), unit([0.1, -0.2, 0.3, 0.9]))
    p1 = ((1.8, 2.3, 0.4), unit([0.15, -0.1, 0.5, 0.8]))
    pair = deskew.OdometryPair(t0, p0, t1, p1)
    pts = rng.uniform(-30, 30, (100, 3))
    times = rng.integers(t0 - 20_000_000, t1 + 20_000_000, 100)       # incl. extrapolation
    ref = t0 + 37_000_000
    got = deskew.deskew_points(pts, times, pair, ref)
    t_ref_inv = np.linalg.inv(pair_pose_loop(ref, t0, p0, t1, p1))
    for p, t, g in zip(pts, times, got):
        expect = t_ref_inv @ pair_pose_loop(int(t), t0, p0, t1, p1) @ np.append(p, 1.0)
        np.testing.assert_allclose(g, expect[:3], atol=5e-5)
    # stamps exactly on the samples; matrix poses; the antipodal quaternion is the same pose
    as_matrix = deskew.OdometryPair(t0, deskew.pose_matrix(p0), t1,
                                    (p1[0], [-c for c in p1[1]]))
    np.testing.assert_allclose(deskew.deskew_points(pts, times, as_matrix, ref), got, atol=5e-5)
    on = deskew.relative_transforms(pair, [t1], t0)
    rel = np.linalg.inv(deskew.pose_matrix(p0)) @ deskew.pose_matrix(p1)
    np.testing.assert_allclose(on[0][0], rel[:3, :3], atol=1e-12)
    np.testing.assert_allclose(on[1][0], rel[:3, 3], atol=1e-12)


def test_motion_forms_and_errors() -> None:
    assert isinstance(deskew.as_motion(((1, 2, 3), (0, 0, 1))), deskew.ConstantVelocity)
    pair = deskew.as_motion(((0, np.eye(4)), (10, np.eye(4))))
    assert isinstance(pair, deskew.OdometryPair)
    for bad in ("fast", {"speed": 1}, ((1, 2), (0, 0, 1)), 3.0):
        with pytest.raises(ConfigError):
            deskew.as_motion(bad)
    with pytest.raises(ConfigError):
        deskew.OdometryPair(5, np.eye(4), 5, np.eye(4))
    with pytest.raises(ConfigError):
        deskew.pose_matrix(np.diag([2.0, 1, 1, 1]))
    with pytest.raises(ConfigError):
        deskew.pose_matrix(((0, 0, 0), (0, 0, 0, 0)))
    with pytest.raises(ValidationError):
        deskew.deskew_points(np.zeros((3, 3)), [1, 2], ((0, 0, 0), (0, 0, 0)), 0)


@pytest.fixture
def scan_info() -> tuple[Any, Any]:
    rng = np.random.default_rng(9)
    height, width = 3, 16
    info = lidarscan.make_info(
        stamp_ns=1, frame_id="lidar", vertical_angles=np.radians([5.0, 0.0, -5.0]),
        horizontal_angles=2 * np.pi * (1 - np.arange(width) / width),
        beam_origins=rng.normal(0, 0.01, 9), pixel_shift_by_row=[2, 1, 0],
        beam_time_offsets=[0, 1000, 2000], column_time_increment=6_250_000)
    ranges = rng.uniform(1, 30, (height, width)).astype(np.float32)
    ranges[1, 5] = np.inf
    scan = lidarscan.make_scan(info, {"range": ranges}, 2_000_000_000)
    return info, scan


@pytest.mark.parametrize("preset", [None, "ouster", "velodyne"])
def test_to_pointcloud2_deskews_every_pixel_with_its_time(scan_info: tuple[Any, Any],
                                                          preset: str | None) -> None:
    from converters.pointcloud2.converter import read_points, to_pointcloud2
    info, scan = scan_info
    proj = lidarscan.make_projector(info)
    motion = deskew.ConstantVelocity(LIN, ANG)
    cloud = to_pointcloud2(scan, info, preset=preset, organized=True, destagger=True,
                           motion=motion)
    header = lidarscan.to_ns(cloud.header.stamp)
    pts = read_points(cloud)
    xyz = np.stack([pts[n] for n in "xyz"], -1)
    raw = proj.destagger(proj.project(scan, info))
    times = proj.destagger(proj.pixel_times(scan)) + 2_000_000_000
    if preset == "velodyne":                                   # firings x lasers, ring order
        xyz = xyz.transpose(1, 0, 2)[::-1]
    for u in range(3):
        for v in range(16):
            if np.isnan(raw[u, v, 0]):
                assert np.isnan(xyz[u, v]).all()
                continue
            rot, trans = cv_transform_loop(LIN, ANG, (int(times[u, v]) - header) * 1e-9)
            np.testing.assert_allclose(xyz[u, v], rot @ raw[u, v] + trans, atol=2e-5)
    if preset == "velodyne":                        # the reference is the last pixel's time
        assert header == int(times.max())


def test_zero_motion_is_identity(scan_info: tuple[Any, Any]) -> None:
    from converters.pointcloud2.converter import to_pointcloud2
    info, scan = scan_info
    from converters.pointcloud2.converter import PointCloud2Converter
    still = to_pointcloud2(scan, info, motion=((0, 0, 0), (0, 0, 0)))
    # deskew works on the projector's r * D + O, like the numpy path (the compiled kernel's
    # factored form is a few float32 ulps away)
    plain = PointCloud2Converter(info, kernel=False).convert(scan)
    assert bytes(still.data) == bytes(plain.data)
