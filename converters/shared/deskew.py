"""Motion compensation (deskew) of lidar points measured at different times.

A spinning lidar measures its columns over a whole revolution (~100 ms); if the sensor moves
meanwhile, every column sees the world from another pose. Deskewing moves each point, measured at
time ``t`` in the sensor frame *at time t*, into the sensor frame at one reference time ``t_ref``::

    p_ref = T_ref^-1 T(t) p          (T(t): pose of the sensor frame at time t)

Two motion models (both give T_ref^-1 T(t) directly):

* :class:`ConstantVelocity` -- a body twist (linear m/s, angular rad/s, expressed in the sensor
  frame, i.e. the frame of the points) held constant: ``T_ref^-1 T(t) = exp((t - t_ref) xi^)``,
  the SE(3) exponential (rotation by Rodrigues, translation ``V(omega dt) v dt``).
* :class:`OdometryPair` -- two poses of the sensor frame in any fixed frame with their stamps:
  ``T(t)`` is interpolated (and linearly extrapolated outside the pair) with a linear translation
  and a spherical-linear (shortest-arc) rotation, the convention of ``tf2`` / laser_geometry.

Times are int64 nanoseconds; transforms are computed in float64 once per distinct time and applied
in float64, results stored as float32. NaN points stay NaN.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from converters.shared.transforms import _so3_exp_and_v, interpolate_poses, pose_matrix
from lidarscan.errors import ConfigError, ValidationError

__all__ = [
    "ConstantVelocity",
    "Motion",
    "OdometryPair",
    "as_motion",
    "deskew_points",
    "pose_matrix",
    "relative_transforms",
]


@dataclasses.dataclass(frozen=True)
class ConstantVelocity:
    """Constant body twist of the sensor frame.

    Attributes:
        linear: (3,) m/s, velocity of the sensor frame's origin expressed in the sensor frame.
        angular: (3,) rad/s, angular velocity expressed in the sensor frame (REP 103, CCW).
        reference_ns: absolute time (int ns) whose pose the points are moved to; None: the
            caller's default (for :func:`converters.pointcloud2.converter.to_pointcloud2`, the output
            cloud's header stamp).
    """

    linear: Any
    angular: Any
    reference_ns: int | None = None

    def __post_init__(self) -> None:
        for name in ("linear", "angular"):
            arr = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1)
            if arr.shape != (3,) or not np.all(np.isfinite(arr)):
                raise ConfigError(f"ConstantVelocity.{name}", getattr(self, name),
                                  "three finite numbers")
            object.__setattr__(self, name, arr)


@dataclasses.dataclass(frozen=True)
class OdometryPair:
    """Two stamped poses of the sensor frame in a fixed frame (e.g. odom).

    Attributes:
        stamp0_ns, stamp1_ns: int ns, different.
        pose0, pose1: 4x4 homogeneous matrices (fixed <- sensor), or (xyz, quaternion xyzw).
        reference_ns: as in :class:`ConstantVelocity`.
    """

    stamp0_ns: int
    pose0: Any
    stamp1_ns: int
    pose1: Any
    reference_ns: int | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "pose0", pose_matrix(self.pose0, "OdometryPair.pose0"))
        object.__setattr__(self, "pose1", pose_matrix(self.pose1, "OdometryPair.pose1"))
        if int(self.stamp0_ns) == int(self.stamp1_ns):
            raise ConfigError("OdometryPair.stamp1_ns", int(self.stamp1_ns),
                              f"a stamp different from stamp0_ns ({int(self.stamp0_ns)})")


Motion = ConstantVelocity | OdometryPair


def as_motion(motion: Any) -> Motion:
    """Normalise the accepted motion forms to :class:`ConstantVelocity` / :class:`OdometryPair`.

    Accepted: those classes; a mapping ``{"linear": (3,), "angular": (3,)}``; a pair
    ``(linear (3,), angular (3,))``; a pair of stamped poses ``((t0_ns, pose0), (t1_ns, pose1))``.

    Raises:
        ConfigError: anything else.
    """
    if isinstance(motion, (ConstantVelocity, OdometryPair)):
        return motion
    if isinstance(motion, Mapping):
        if set(motion) <= {"linear", "angular", "reference_ns"} and "linear" in motion:
            return ConstantVelocity(motion["linear"], motion.get("angular", (0, 0, 0)),
                                    motion.get("reference_ns"))
        raise ConfigError("motion", sorted(motion), 'keys "linear", "angular"[, "reference_ns"]')
    if isinstance(motion, Sequence) and len(motion) == 2:
        first, second = motion
        if (isinstance(first, Sequence) and len(first) == 2 and isinstance(first[0], (int, np.integer))
                and isinstance(second, Sequence) and len(second) == 2):
            return OdometryPair(int(first[0]), first[1], int(second[0]), second[1])
        return ConstantVelocity(first, second)
    raise ConfigError("motion", type(motion).__name__,
                      "ConstantVelocity, OdometryPair, {'linear', 'angular'}, (linear, angular) "
                      "or ((t0_ns, pose0), (t1_ns, pose1))")


# ------------------------------------------------------------------------------ transforms

def relative_transforms(motion: Any, times_ns: Any, reference_ns: int
                        ) -> tuple[np.ndarray[Any, np.dtype[np.float64]],
                                   np.ndarray[Any, np.dtype[np.float64]]]:
    """Transforms ``T_ref^-1 T(t)`` for each time.

    Args:
        motion: anything :func:`as_motion` accepts.
        times_ns: (N,) absolute int ns.
        reference_ns: absolute int ns of the reference pose (``motion.reference_ns`` wins when
            set).

    Returns:
        (R, t): (N, 3, 3) and (N, 3) float64; a point p measured at time t maps to R p + t.
    """
    motion = as_motion(motion)
    if motion.reference_ns is not None:
        reference_ns = int(motion.reference_ns)
    times = np.asarray(times_ns, dtype=np.int64).reshape(-1)
    dt = (times - np.int64(reference_ns)).astype(np.float64) * 1e-9           # seconds
    if isinstance(motion, ConstantVelocity):
        rot, v = _so3_exp_and_v(dt[:, None] * motion.angular[None, :])
        trans = np.einsum("nij,nj->ni", v, dt[:, None] * motion.linear[None, :])
        return rot, trans
    # odometry pair: interpolate T(t) and T(t_ref), then T_ref^-1 T(t)
    rot_t, trans_t = _interpolate(motion, times)
    rot_r, trans_r = _interpolate(motion, np.array([reference_ns], dtype=np.int64))
    rot_r_inv = rot_r[0].T
    rot = np.einsum("ij,njk->nik", rot_r_inv, rot_t)
    trans = (trans_t - trans_r[0]) @ rot_r_inv.T
    return rot, trans


def _interpolate(motion: OdometryPair, times: np.ndarray[Any, Any]
                 ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """Pose at each time: :func:`converters.shared.transforms.interpolate_poses` of the pair
    (lerp translation, shortest-arc slerp rotation), extrapolated along the same motion."""
    t0, t1 = int(motion.stamp0_ns), int(motion.stamp1_ns)
    s = (times - np.int64(t0)).astype(np.float64) / float(t1 - t0)
    poses = interpolate_poses(motion.pose0, motion.pose1, s)
    return poses[:, :3, :3], poses[:, :3, 3]


def deskew_points(points: Any, times_ns: Any, motion: Any, reference_ns: int
                  ) -> np.ndarray[Any, np.dtype[np.float32]]:
    """Move points measured at different times into the sensor frame at ``reference_ns``.

    Args:
        points: (..., 3) float, metres, each in the sensor frame at its own time; NaN allowed.
        times_ns: (...) absolute int ns of each point (same leading shape as ``points``).
        motion: anything :func:`as_motion` accepts.
        reference_ns: int ns of the target pose (``motion.reference_ns`` wins when set).

    Returns:
        New (..., 3) float32 array (the input is never modified).

    Raises:
        ValidationError: shapes do not match.
    """
    pts = np.asarray(points)
    times = np.asarray(times_ns, dtype=np.int64)
    if pts.shape[-1:] != (3,) or pts.shape[:-1] != times.shape:
        raise ValidationError("points.shape", pts.shape, f"{times.shape + (3,)} (times shape + 3)")
    unique, inverse = np.unique(times.reshape(-1), return_inverse=True)
    rot, trans = relative_transforms(motion, unique, reference_ns)
    flat = pts.reshape(-1, 3).astype(np.float64)
    r = rot[inverse]
    out = np.einsum("nij,nj->ni", r, flat) + trans[inverse]
    return np.asarray(out, dtype=np.float32).reshape(pts.shape)
