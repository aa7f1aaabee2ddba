"""Stamped pose tracks: the pose of a moving mount looked up at any time inside its history.

A :class:`TransformTrack` holds poses ``T(t)`` of one frame in another (4x4 float64,
``p_parent = T(t) @ p_child``, REP 103 axes, metres) at int64 ns stamps, e.g. a laser on a pan
unit seen from ``base_link``. :meth:`TransformTrack.lookup` interpolates between the two nearest
samples as tf2 does: linear translation, spherical-linear (shortest-arc) rotation, written as
``R(t) = R0 exp(u log(R0^T R1))`` with the rotation helpers of :mod:`converters.deskew` (this is
slerp: same rotation, numerically). At a sample's own stamp the sample is returned exactly.

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
import threading
from typing import Any

import numpy as np

from converters.deskew import _matrix_to_rotvec, _so3_exp_and_v, pose_matrix
from lidarscan.errors import ConfigError, ConversionError

__all__ = ["OutOfSpanError", "TransformLookupError", "TransformTrack"]


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
            ConfigError: not a rigid transform, or bad numbers
                (:func:`converters.deskew.pose_matrix`).
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
            delta = np.stack([_matrix_to_rotvec(a[:3, :3].T @ b[:3, :3])
                              for a, b in zip(p0, p1)])          # shortest arc, |delta| <= pi
            rot, _ = _so3_exp_and_v(u[:, None] * delta[inverse])
            a, b = p0[inverse], p1[inverse]
            block = np.zeros((between.size, 4, 4))
            block[:, :3, :3] = a[:, :3, :3] @ rot
            block[:, :3, 3] = a[:, :3, 3] + u[:, None] * (b[:, :3, 3] - a[:, :3, 3])
            block[:, 3, 3] = 1.0
            out[between] = block
        return out
