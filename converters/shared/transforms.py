"""Stamped pose tracks: the pose of a moving mount looked up at any time inside its history.

A :class:`TransformTrack` holds poses ``T(t)`` of one frame in another (4x4 float64,
``p_parent = T(t) @ p_child``, REP 103 axes, metres) at int64 ns stamps, e.g. a laser on a pan
unit seen from ``base_link``. :meth:`TransformTrack.lookup` interpolates between the two nearest
samples as tf2 does: linear translation, spherical-linear (shortest-arc) rotation, written as
``R(t) = R0 exp(u log(R0^T R1))`` (:func:`interpolate_poses`; this is slerp: same rotation,
numerically). At a sample's own stamp the sample is returned exactly.

**One pose interpolation.** :func:`interpolate_poses` is the project's only lerp/slerp of poses:
the tracks here, :class:`converters.shared.deskew.OdometryPair`, the merger's odometry and the nodes'
:class:`converters.edge.nodes.tf.TransformBuffer` all call it. The SO(3) helpers it rests on
(Rodrigues, log map, quaternion <-> matrix) and :func:`pose_matrix` live here too.

**Span.** A lookup before the oldest sample, or after the newest one, raises
:class:`OutOfSpanError` (naming the stamp and the span): a track never extrapolates. The one
exception is ``tolerance_ns`` (default 0, tf2's behaviour): up to that long after the newest
sample the newest pose is *held* (zero-order hold, not extrapolated). Use it when the poses
arrive a little after the data that needs them and a small error is preferred to a drop (the
error is at most the mount's speed times the tolerance). A track with one sample covers that
stamp only (plus the tolerance).

**History.** At most ``max_samples`` samples, and only those within ``max_age_ns`` of the newest
one (tf2's cache length, 10 s by default) are kept; older ones are forgotten (counted in
:attr:`TransformTrack.forgotten`). A sample at a stamp already held replaces it. Adding is
thread-safe.
"""

from __future__ import annotations

import bisect
import math
import threading
from collections.abc import Sequence
from typing import Any

import numpy as np

from lidarscan.errors import ConfigError, ConversionError

__all__ = ["OutOfSpanError", "TransformLookupError", "TransformTrack", "interpolate_poses",
           "pose_matrix", "quaternion_from_matrix", "segment_rotvecs"]


class TransformLookupError(ConversionError):
    """No transform is known for the requested frames or time."""


class OutOfSpanError(TransformLookupError):
    """A lookup outside the span of a :class:`TransformTrack`.

    Attributes:
        stamp_ns: the requested stamp (int ns; the first bad one of a batch).
        span: (oldest, newest) stamps held, int ns, or None when the track is empty.
    """

    def __init__(self, name: str, stamp_ns: int, span: tuple[int, int] | None,
                 tolerance_ns: int = 0) -> None:
        self.stamp_ns = int(stamp_ns)
        self.span = span
        if span is None:
            expected = "a stamp inside the track's span, but the track holds no pose yet"
        else:
            expected = (f"a stamp inside the track's span [{span[0]}, {span[1]}] ns"
                        + (f" (+{tolerance_ns} ns tolerance after the newest pose)"
                           if tolerance_ns else "")
                        + f"; it is {_side(stamp_ns, span)}: no extrapolation")
        super().__init__(f"{name} at stamp_ns", self.stamp_ns, expected)


def _side(stamp: int, span: tuple[int, int]) -> str:
    if stamp < span[0]:
        return f"{span[0] - stamp} ns before the oldest pose"
    return f"{stamp - span[1]} ns after the newest pose"


class TransformTrack:
    """Poses of a moving frame at stamps, interpolated in between (see the module docstring).

    Args:
        max_samples: most samples kept (>= 2).
        max_age_ns: samples older than the newest minus this are forgotten (int ns, > 0).
        tolerance_ns: how long after the newest sample its pose is held (int ns, >= 0).
        name: names the track in error messages (e.g. ``"base_link <- laser"``).

    Raises:
        ConfigError: bad limits.
    """

    def __init__(self, *, max_samples: int = 2000, max_age_ns: int = 10_000_000_000,
                 tolerance_ns: int = 0, name: str = "TransformTrack") -> None:
        for key, value, low in (("max_samples", max_samples, 2), ("max_age_ns", max_age_ns, 1),
                                ("tolerance_ns", tolerance_ns, 0)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
                raise ConfigError(f"TransformTrack.{key}", value, f"an int >= {low}")
        self.max_samples = int(max_samples)
        self.max_age_ns = int(max_age_ns)
        self.tolerance_ns = int(tolerance_ns)
        self.name = str(name)
        self._times: list[int] = []
        self._poses: list[np.ndarray[Any, Any]] = []
        self._array: np.ndarray[Any, Any] | None = None      # cached np.array(self._times)
        self._lock = threading.Lock()
        #: samples forgotten (beyond max_samples / max_age_ns, or too old when added)
        self.forgotten = 0

    def __len__(self) -> int:
        return len(self._times)

    def __call__(self, stamp_ns: int) -> np.ndarray[Any, np.dtype[np.float64]]:
        """Same as :meth:`lookup` (a track is a valid ``stamp_ns -> 4x4`` callable)."""
        return self.lookup(stamp_ns)

    @property
    def span(self) -> tuple[int, int] | None:
        """(oldest, newest) stamp held, int ns; None when empty."""
        with self._lock:
            return (self._times[0], self._times[-1]) if self._times else None

    def add(self, stamp_ns: int, pose: Any, quaternion: Any = None) -> None:
        """Add the pose at ``stamp_ns`` (int ns).

        Args:
            pose: a 4x4 rigid transform, an (xyz, quaternion xyzw) pair, or, with
                ``quaternion``, the translation (3,) metres.
            quaternion: (x, y, z, w), normalised here.

        Raises:
            ConfigError: not a rigid transform, or bad numbers (:func:`pose_matrix`).
        """
        field = f"{self.name}.add({int(stamp_ns)})"
        matrix = pose_matrix(pose if quaternion is None else (pose, quaternion), field).copy()
        stamp = int(stamp_ns)
        with self._lock:
            times = self._times
            if times and stamp < times[-1] - self.max_age_ns:
                self.forgotten += 1
                return
            i = bisect.bisect_left(times, stamp)
            if i < len(times) and times[i] == stamp:
                self._poses[i] = matrix
                return
            times.insert(i, stamp)
            self._poses.insert(i, matrix)
            drop = max(bisect.bisect_left(times, times[-1] - self.max_age_ns),
                       len(times) - self.max_samples)
            if drop > 0:
                del times[:drop]
                del self._poses[:drop]
                self.forgotten += drop
            self._array = None

    def clear(self) -> None:
        """Forget every sample (e.g. after a clock jump backwards)."""
        with self._lock:
            self._times.clear()
            self._poses.clear()
            self._array = None

    def lookup(self, stamp_ns: int) -> np.ndarray[Any, np.dtype[np.float64]]:
        """4x4 float64 pose at ``stamp_ns`` (int ns).

        Raises:
            OutOfSpanError: the stamp is outside the span (plus ``tolerance_ns``).
        """
        return self.lookup_many(np.array([int(stamp_ns)], np.int64))[0]

    def samples(self, first_ns: int, last_ns: int
                ) -> tuple[np.ndarray[Any, np.dtype[np.int64]],
                           np.ndarray[Any, np.dtype[np.float64]]]:
        """The samples that every stamp in ``[first_ns, last_ns]`` is interpolated between (or
        held at), as one consistent snapshot: from the newest sample at or before ``first_ns``
        to the oldest at or after ``last_ns`` (the newest sample when ``last_ns`` is held).
        :meth:`lookup_many` of a stamp in that interval equals :func:`interpolate_poses`
        between the two samples around it (the sample itself at its own stamp).

        Returns:
            (times, poses): (K,) int64 ns ascending and (K, 4, 4) float64, K >= 1.

        Raises:
            OutOfSpanError: ``first_ns`` or ``last_ns`` outside the span (plus ``tolerance_ns``).
        """
        first, last = int(first_ns), int(last_ns)
        with self._lock:
            times = self._times
            if not times:
                raise OutOfSpanError(self.name, first, None)
            span = (times[0], times[-1])
            for stamp in (first, last):
                if stamp < span[0] or stamp > span[1] + self.tolerance_ns:
                    raise OutOfSpanError(self.name, stamp, span, self.tolerance_ns)
            i0 = bisect.bisect_right(times, first) - 1
            i1 = min(bisect.bisect_left(times, last), len(times) - 1)
            return (np.array(times[i0:i1 + 1], np.int64),
                    np.stack(self._poses[i0:i1 + 1]))

    def lookup_many(self, stamps_ns: Any) -> np.ndarray[Any, np.dtype[np.float64]]:
        """(N, 4, 4) float64 poses at the (N,) int ns stamps (any order).

        Raises:
            OutOfSpanError: a stamp is outside the span (the first one is named).
        """
        t = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        with self._lock:
            if self._array is None:
                self._array = np.array(self._times, np.int64)
            times = self._array
            poses = self._poses
            if not len(times):
                if t.size:
                    raise OutOfSpanError(self.name, int(t[0]), None)
                return np.zeros((0, 4, 4))
            newest = int(times[-1])
            bad = (t < times[0]) | (t > newest + self.tolerance_ns)
            if bad.any():
                raise OutOfSpanError(self.name, int(t[np.argmax(bad)]),
                                     (int(times[0]), newest), self.tolerance_ns)
            out = np.empty((t.size, 4, 4))
            right = np.searchsorted(times, t, side="right")   # first sample after t
            knot = times[right - 1] == t
            held = t > newest
            for j in np.flatnonzero(knot | held):               # exact samples, held newest
                out[j] = poses[right[j] - 1]
            between = np.flatnonzero(~(knot | held))
            if between.size:
                k1 = right[between]
                k0 = k1 - 1
                t0, t1 = times[k0], times[k1]
                u = (t[between] - t0).astype(np.float64) / (t1 - t0).astype(np.float64)
                segments, inverse = np.unique(k0, return_inverse=True)
                p0 = np.stack([poses[k] for k in segments])
                p1 = np.stack([poses[k + 1] for k in segments])
        if between.size:
            out[between] = interpolate_poses(p0, p1, u, inverse)
        return out


# ------------------------------------------------------------------------------ interpolation

def interpolate_poses(p0: Any, p1: Any, u: Any, segment: Any = None
                      ) -> np.ndarray[Any, np.dtype[np.float64]]:
    """Poses between two rigid transforms: linear translation, shortest-arc slerp rotation.

    ``T(u) = [R0 exp(u log(R0^T R1)), t0 + u (t1 - t0)]``: ``u = 0`` gives ``p0``'s rotation
    and translation, ``u = 1`` ``p1``'s; ``u`` outside [0, 1] extrapolates along the same
    motion (callers that must not extrapolate check their span first). Two rotations exactly
    pi apart have no unique shortest arc: one of the two is taken.

    Args:
        p0, p1: (K, 4, 4) or (4, 4) float64 rigid transforms (segment starts and ends).
        u: (N,) float64 fractions.
        segment: (N,) int indices into the K pairs (None: every u on pair 0).

    Returns:
        (N, 4, 4) float64.
    """
    a0 = np.asarray(p0, dtype=np.float64).reshape(-1, 4, 4)
    a1 = np.asarray(p1, dtype=np.float64).reshape(-1, 4, 4)
    frac = np.asarray(u, dtype=np.float64).reshape(-1)
    index = np.zeros(frac.size, np.intp) if segment is None else np.asarray(segment)
    delta = segment_rotvecs(a0, a1)
    rot, _ = _so3_exp_and_v(frac[:, None] * delta[index])
    a, b = a0[index], a1[index]
    out = np.zeros((frac.size, 4, 4))
    out[:, :3, :3] = a[:, :3, :3] @ rot
    out[:, :3, 3] = a[:, :3, 3] + frac[:, None] * (b[:, :3, 3] - a[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


def segment_rotvecs(p0: Any, p1: Any) -> np.ndarray[Any, np.dtype[np.float64]]:
    """(K, 3) float64 rotation vectors ``log(R0^T R1)`` (shortest arc, norm <= pi) of K pairs of
    (K, 4, 4) rigid transforms: the rotation :func:`interpolate_poses` scales by ``u``."""
    a0 = np.asarray(p0, np.float64).reshape(-1, 4, 4)
    a1 = np.asarray(p1, np.float64).reshape(-1, 4, 4)
    return np.stack([_matrix_to_rotvec(a[:3, :3].T @ b[:3, :3]) for a, b in zip(a0, a1)])


def quaternion_from_matrix(matrix: Any) -> tuple[float, float, float, float]:
    """(x, y, z, w) unit quaternion (w >= 0) of the rotation of a 4x4 or 3x3 matrix."""
    m = np.asarray(matrix, dtype=np.float64)[:3, :3]
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4)
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = (s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s)
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = ((m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = ((m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s)
    norm = math.sqrt(sum(v * v for v in q))
    x, y, z, w = (v / norm for v in q)
    return (-x, -y, -z, -w) if w < 0 else (x, y, z, w)


def pose_matrix(pose: Any, field: str = "pose") -> np.ndarray[Any, np.dtype[np.float64]]:
    """4x4 float64 rigid transform from a 4x4 matrix or an (xyz, quaternion xyzw) pair.

    Raises:
        ConfigError: not a rigid transform / not 3 + 4 finite numbers / zero quaternion.
    """
    if isinstance(pose, np.ndarray) and pose.shape == (4, 4) or (
            isinstance(pose, Sequence) and len(pose) == 4):
        matrix = np.asarray(pose, dtype=np.float64)
        if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
            raise ConfigError(field, pose, "a finite 4x4 matrix")
        rot = matrix[:3, :3]
        if not (np.allclose(matrix[3], [0, 0, 0, 1], atol=1e-9)
                and np.allclose(rot @ rot.T, np.eye(3), atol=1e-6) and np.linalg.det(rot) > 0):
            raise ConfigError(field, matrix.round(6).tolist(), "a rigid transform")
        return matrix
    try:
        xyz, quat = pose
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1)
        quat = np.asarray(quat, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ConfigError(field, pose, "a 4x4 matrix or (xyz, quaternion xyzw)") from None
    norm = float(np.linalg.norm(quat)) if quat.shape == (4,) else 0.0
    if xyz.shape != (3,) or not np.all(np.isfinite(xyz)) or not np.isfinite(norm) or norm == 0:
        raise ConfigError(field, pose, "(xyz: 3 finite numbers, quaternion xyzw: 4, non-zero)")
    matrix = np.eye(4)
    matrix[:3, :3] = _quat_to_matrix(quat / norm)[0]
    matrix[:3, 3] = xyz
    return matrix



# ------------------------------------------------------------------------------ rotations

def _hat(w: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """(N, 3) -> (N, 3, 3) skew-symmetric matrices."""
    out = np.zeros(w.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def _so3_exp_and_v(phi: np.ndarray[Any, Any]) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """Rodrigues: rotation vectors (N, 3) -> R (N, 3, 3) and the SE(3) left Jacobian V (N, 3, 3)."""
    theta = np.linalg.norm(phi, axis=-1)
    small = theta < 1e-6
    safe = np.where(small, 1.0, theta)
    # Taylor series below 1e-6 rad: exact to double precision there
    a = np.where(small, 1 - theta**2 / 6, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24, (1 - np.cos(safe)) / safe**2)
    c = np.where(small, 1 / 6 - theta**2 / 120, (safe - np.sin(safe)) / safe**3)
    k = _hat(phi)
    k2 = k @ k
    eye = np.eye(3)
    rot = eye + a[:, None, None] * k + b[:, None, None] * k2
    v = eye + b[:, None, None] * k + c[:, None, None] * k2
    return rot, v


def _quat_to_matrix(q: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """Unit quaternions (N, 4) xyzw -> (N, 3, 3)."""
    q = np.atleast_2d(q)
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def _matrix_to_rotvec(rot: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """One 3x3 rotation -> rotation vector (3,) (log map, robust near 0 and pi)."""
    cos_t = np.clip((np.trace(rot) - 1) / 2, -1.0, 1.0)
    theta = float(np.arccos(cos_t))
    if theta < 1e-7:
        return np.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]]) / 2
    if np.pi - theta < 1e-4:
        # near pi: axis from the symmetric part
        sym = (rot + np.eye(3)) / 2
        axis = sym[int(np.argmax(np.diag(sym)))]
        axis = axis / np.linalg.norm(axis)
        sign = np.sign(np.dot(axis, [rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0],
                                     rot[1, 0] - rot[0, 1]])) or 1.0
        return np.asarray(sign * theta * axis, dtype=np.float64)
    vec = np.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]])
    return np.asarray(theta / (2 * np.sin(theta)) * vec, dtype=np.float64)
