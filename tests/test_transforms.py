"""One pose interpolation (converters.shared.transforms.interpolate_poses) behind every user: the
TransformTrack, OdometryPair de-skew, the nodes' TransformBuffer and the merger's odometry.

Oracle: quaternion slerp written out with its sine formula and a plain lerp of the translation
(tests/test_moving_mounts.py's ``ref_slerp``), extrapolated by the same formula for fractions
outside [0, 1].
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from converters.shared import deskew

from converters.shared import transforms
from converters.merger import Pose, interpolate_pose
from converters.edge.nodes.tf import (TransformBuffer, matrix_from_quaternion, quaternion_from_matrix,
                                 slerp)
from converters.shared.transforms import TransformTrack, interpolate_poses
from lidarscan.errors import ConfigError
from test_moving_mounts import ref_slerp

unit_quaternions = st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4).filter(
    lambda q: sum(v * v for v in q) > 0.01)
translations = st.lists(st.floats(-50.0, 50.0), min_size=3, max_size=3)


def ref_pose(q0: Any, p0: Any, q1: Any, p1: Any, u: float) -> np.ndarray:
    """Loop oracle: lerp + sine-formula slerp (the short way round)."""
    p = np.asarray(p0, float) + u * (np.asarray(p1, float) - np.asarray(p0, float))
    return matrix_from_quaternion(ref_slerp(q0, q1, u), p)


@settings(max_examples=60, deadline=None)
@given(q0=unit_quaternions, q1=unit_quaternions, p0=translations, p1=translations,
       u=st.floats(-0.5, 1.5))
def test_interpolate_poses_is_lerp_and_slerp(q0: list[float], q1: list[float], p0: list[float],
                                             p1: list[float], u: float) -> None:
    a, b = matrix_from_quaternion(q0, p0), matrix_from_quaternion(q1, p1)
    # rotations (nearly) pi apart have two shortest arcs: the oracle may take the other one
    dot = abs(float(np.dot(quaternion_from_matrix(a), quaternion_from_matrix(b))))
    if dot < 1e-3:
        return
    got = interpolate_poses(a, b, [u])[0]
    np.testing.assert_allclose(got, ref_pose(q0, p0, q1, p1, u), atol=1e-9)
    np.testing.assert_allclose(got[:3, :3] @ got[:3, :3].T, np.eye(3), atol=1e-12)


def test_knots_are_exact_and_segments_index_their_pairs() -> None:
    rng = np.random.default_rng(8)
    poses = [matrix_from_quaternion(rng.normal(size=4), rng.normal(size=3)) for _ in range(4)]
    at0 = interpolate_poses(poses[0], poses[1], [0.0])[0]
    np.testing.assert_array_equal(at0, poses[0])
    np.testing.assert_allclose(interpolate_poses(poses[0], poses[1], [1.0])[0], poses[1],
                               atol=1e-12)
    u = rng.uniform(0, 1, 9)
    seg = np.array([0, 1, 2, 2, 1, 0, 0, 2, 1])
    batch = interpolate_poses(np.stack(poses[:3]), np.stack(poses[1:]), u, seg)
    for k in range(9):
        one = interpolate_poses(poses[seg[k]], poses[seg[k] + 1], [u[k]])[0]
        np.testing.assert_allclose(batch[k], one, atol=1e-15)


def test_every_user_gives_the_same_pose() -> None:
    """Track, TransformBuffer, OdometryPair and the merger's odometry agree to round-off on
    the same two samples (they are one implementation)."""
    rng = np.random.default_rng(9)
    q0, q1 = rng.normal(size=4), rng.normal(size=4)
    p0, p1 = rng.normal(size=3), rng.normal(size=3)
    a, b = matrix_from_quaternion(q0, p0), matrix_from_quaternion(q1, p1)
    t0, t1 = 1_000, 2_000
    track = TransformTrack()
    track.add(t0, a)
    track.add(t1, b)
    buffer = TransformBuffer()
    buffer.set_transform("odom", "base", a, t0)
    buffer.set_transform("odom", "base", b, t1)
    pair = deskew.OdometryPair(t0, a, t1, b)
    poses = [Pose(t0, tuple(p0), quaternion_from_matrix(a)),  # type: ignore[arg-type]
             Pose(t1, tuple(p1), quaternion_from_matrix(b))]  # type: ignore[arg-type]
    for t in (1_000, 1_001, 1_250, 1_500, 1_999, 2_000):
        want = interpolate_poses(a, b, [(t - t0) / (t1 - t0)])[0]
        np.testing.assert_allclose(track.lookup(t), want, atol=1e-12)
        np.testing.assert_allclose(buffer.lookup("odom", "base", t), want, atol=1e-12)
        rot, trans = deskew.relative_transforms(pair, [t], t0)       # a^-1 T(t)
        np.testing.assert_allclose(a @ np.block([[rot[0], trans[0][:, None]], [0, 0, 0, 1]]),
                                   want, atol=1e-12)
        mid = interpolate_pose([t0, t1], poses, t, 10_000)
        assert mid is not None
        np.testing.assert_allclose(mid.matrix(), want, atol=1e-12)


def test_tf_slerp_is_the_shared_slerp() -> None:
    """Also where the old copy switched to a normalised lerp (dot > 0.9995: 0.05 rad)."""
    a = matrix_from_quaternion((0.1, 0.2, 0.3, 0.9))
    q0 = quaternion_from_matrix(a)
    q1 = quaternion_from_matrix(a @ matrix_from_quaternion((0, 0, math.sin(0.025),
                                                              math.cos(0.025))))
    for f in (0.0, 0.3, 0.5, 1.0):
        got = np.array(slerp(q0, q1, f))
        want = np.array(ref_slerp(q0, q1, f))
        assert min(np.abs(got - want).max(), np.abs(got + want).max()) < 1e-12


def test_helpers_moved_with_their_old_names() -> None:
    """pose_matrix stays importable from converters.shared.deskew (moved to converters.shared.transforms)."""
    assert deskew.pose_matrix is transforms.pose_matrix
    with pytest.raises(ConfigError):
        transforms.pose_matrix(np.diag([2.0, 1, 1, 1]))
    assert math.isclose(float(np.linalg.det(transforms.pose_matrix(((0, 0, 0),
                                                                    (0, 0, 1, 1)))[:3, :3])), 1.0)
