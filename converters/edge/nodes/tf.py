"""A minimal TF buffer (tf2 is not in the ROS 2 PyPI wheels): store, chain, interpolate.

:class:`TransformBuffer` is plain Python + numpy (no rclpy): it keeps the transform tree of
``/tf_static`` and ``/tf`` (every frame has one parent, as in tf2), composes the chain between
two frames through their common ancestor, and looks a transform up at a time:

* static transforms hold at every time;
* dynamic transforms are kept per edge for ``cache_ns`` (default 10 s) and at most
  ``max_per_edge`` samples; a lookup between two samples interpolates (linear translation,
  spherical-linear rotation: :func:`converters.shared.transforms.interpolate_poses`); a lookup
  outside the samples is allowed up to ``tolerance_ns``
  beyond the newest/oldest one (the nearest sample is used) and fails beyond that;
* ``time_ns=None`` asks for the newest transform of each edge (tf2's "time 0");
* :meth:`TransformBuffer.samples` gives the chained transform at every stored stamp of the
  chain's dynamic edges, to fill a :class:`converters.shared.transforms.TransformTrack` (a moving
  mount). With one moving joint in the chain the composite samples are exact; with several,
  each is composed from the other joints' interpolated (or, within ``tolerance_ns`` of their
  ends, nearest) samples, and between two composite samples the track interpolates the
  composite as one rigid motion.

:class:`TfListener` attaches a buffer to an rclpy node: ``/tf_static`` (reliable,
transient-local, so late joiners get it) and ``/tf``, subscribed raw and decoded by
:func:`lidarscan.decode`, so a malformed message is counted and logged, never fatal. It needs the
``tf2_msgs`` type (built from ``third_party/tf2_msgs`` by ``make tf2msgs``); without it the
listener stays inactive and nodes fall back to their extrinsics parameters. ``on_message`` is
called after each ``/tf`` message is stored (e.g. to extend moving mounts' tracks).

Conventions: a transform ``parent -> child`` (TransformStamped ``header.frame_id`` = parent,
``child_frame_id`` = child) is the 4x4 matrix that maps points of the child frame into the
parent frame; ``lookup(target, source)`` returns ``target_from_source``.
"""

from __future__ import annotations

import bisect
import math
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from converters.shared.transforms import TransformLookupError, interpolate_poses, quaternion_from_matrix
from lidarscan.errors import ValidationError
from lidarscan.stamps import to_ns

__all__ = [
    "TfListener",
    "TransformBuffer",
    "TransformLookupError",
    "matrix_from_quaternion",
    "matrix_from_transform_msg",
    "matrix_from_xyz_rpy",
    "quaternion_from_matrix",
    "slerp",
]


def matrix_from_quaternion(q: Any, translation: Any = (0.0, 0.0, 0.0)
                           ) -> np.ndarray[Any, np.dtype[np.float64]]:
    """4x4 from a quaternion (x, y, z, w) (normalised here) and a translation.

    Raises:
        ValidationError: a zero or non-finite quaternion or translation.
    """
    x, y, z, w = (float(v) for v in q)
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if not math.isfinite(norm) or norm < 1e-9:
        raise ValidationError("rotation", (x, y, z, w), "a finite, non-zero quaternion")
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    t = np.asarray(translation, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(t)):
        raise ValidationError("translation", t.tolist(), "finite metres")
    m = np.eye(4)
    m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    m[:3, 3] = t
    return m


def matrix_from_xyz_rpy(x: float = 0.0, y: float = 0.0, z: float = 0.0, roll: float = 0.0,
                        pitch: float = 0.0, yaw: float = 0.0
                        ) -> np.ndarray[Any, np.dtype[np.float64]]:
    """4x4 from a translation (m) and roll/pitch/yaw (rad): R = Rz(yaw) Ry(pitch) Rx(roll)
    (fixed axes x, y, z, as tf2's ``setRPY``)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    m = np.eye(4)
    m[:3, :3] = [[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                 [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                 [-sp, cp * sr, cp * cr]]
    m[:3, 3] = (x, y, z)
    return m


def slerp(q0: Any, q1: Any, fraction: float) -> tuple[float, float, float, float]:
    """Spherical-linear interpolation of unit quaternions (x, y, z, w), the short way round
    (:func:`converters.shared.transforms.interpolate_poses`; the result has ``w >= 0``)."""
    pose = interpolate_poses(matrix_from_quaternion(q0), matrix_from_quaternion(q1),
                             [float(fraction)])[0]
    return quaternion_from_matrix(pose)


def matrix_from_transform_msg(transform: Any) -> np.ndarray[Any, np.dtype[np.float64]]:
    """4x4 of a ``geometry_msgs/Transform`` (rclpy or dataclass)."""
    t, r = transform.translation, transform.rotation
    return matrix_from_quaternion((r.x, r.y, r.z, r.w), (t.x, t.y, t.z))


class _Edge:
    """Samples of one parent -> child transform: sorted times, translations, quaternions."""

    __slots__ = ("parent", "static", "times", "values")

    def __init__(self, parent: str, static: bool) -> None:
        self.parent = parent
        self.static = static
        self.times: list[int] = []
        self.values: list[tuple[np.ndarray[Any, Any], tuple[float, float, float, float]]] = []


def extend_track(track: Any, tf_samples: Callable[[str, str, int | None], Any],
                 target_frame: str, frame: str, tick: Callable[[int], None]) -> None:
    """Add to ``track`` (a :class:`converters.TransformTrack` of ``frame`` in
    ``target_frame``) the chained /tf samples newer than it holds (``tf_samples``, e.g.
    :meth:`TransformBuffer.samples`), calling ``tick(stamp_ns)`` after each one added."""
    span = track.span
    for stamp, matrix in tf_samples(target_frame, frame, None if span is None else span[1]):
        track.add(stamp, matrix)
        tick(stamp)


class TransformBuffer:
    """Transform tree with time-interpolated lookups (thread-safe).

    Args:
        cache_ns: how long dynamic samples are kept, measured back from the newest sample of
            the same edge (int ns).
        max_per_edge: hard bound on samples kept per edge (memory bound).
        tolerance_ns: how far a lookup may lie outside an edge's samples (nearest sample used).
    """

    def __init__(self, *, cache_ns: int = 10_000_000_000, max_per_edge: int = 2000,
                 tolerance_ns: int = 100_000_000) -> None:
        self.cache_ns = int(cache_ns)
        self.max_per_edge = int(max_per_edge)
        self.tolerance_ns = int(tolerance_ns)
        self._edges: dict[str, _Edge] = {}  # child -> edge to its parent
        self._lock = threading.Lock()
        self.version = 0  # bumped on every change of a static edge or of the tree's shape

    # ---------------------------------------------------------------------------- input
    def set_transform(self, parent: str, child: str, matrix: Any, stamp_ns: int = 0, *,
                      static: bool = False) -> None:
        """Add one sample of ``parent_from_child`` (4x4).

        Raises:
            ValidationError: empty or equal frame names, a matrix that is not a finite 4x4.
        """
        parent, child = _strip(parent), _strip(child)
        if not parent or not child or parent == child:
            raise ValidationError("frames", (parent, child), "two different, non-empty names")
        m = np.asarray(matrix, dtype=np.float64).reshape(4, 4)
        if not np.all(np.isfinite(m)):
            raise ValidationError("transform", m.tolist(), "finite values")
        self._add(parent, child, m[:3, 3].copy(), quaternion_from_matrix(m), int(stamp_ns), static)

    def add_message(self, message: Any, *, static: bool = False) -> int:
        """Add every TransformStamped of a ``tf2_msgs/TFMessage``; returns how many were used.

        Raises:
            ValidationError: the first malformed transform (the ones before it are kept).
        """
        used = 0
        for item in message.transforms:
            t, r = item.transform.translation, item.transform.rotation
            quat = (float(r.x), float(r.y), float(r.z), float(r.w))
            norm = math.sqrt(sum(v * v for v in quat))
            if not math.isfinite(norm) or norm < 1e-9:
                raise ValidationError(f"transform {item.header.frame_id}->{item.child_frame_id}"
                                      ".rotation", quat, "a finite, non-zero quaternion")
            trans = np.array([float(t.x), float(t.y), float(t.z)])
            if not np.all(np.isfinite(trans)):
                raise ValidationError(f"transform {item.header.frame_id}->{item.child_frame_id}"
                                      ".translation", trans.tolist(), "finite metres")
            parent, child = _strip(item.header.frame_id), _strip(item.child_frame_id)
            if not parent or not child or parent == child:
                raise ValidationError("transform frames", (parent, child),
                                      "two different, non-empty frame names")
            self._add(parent, child, trans, tuple(v / norm for v in quat),  # type: ignore[arg-type]
                      to_ns(item.header.stamp), static)
            used += 1
        return used

    def _add(self, parent: str, child: str, trans: np.ndarray[Any, Any],
             quat: tuple[float, float, float, float], stamp: int, static: bool) -> None:
        with self._lock:
            edge = self._edges.get(child)
            if edge is None or edge.parent != parent or edge.static != static:
                edge = _Edge(parent, static)
                self._edges[child] = edge
                self.version += 1
            if static:
                edge.times, edge.values = [stamp], [(trans, quat)]
                self.version += 1
                return
            i = bisect.bisect_left(edge.times, stamp)
            if i < len(edge.times) and edge.times[i] == stamp:
                edge.values[i] = (trans, quat)
            else:
                edge.times.insert(i, stamp)
                edge.values.insert(i, (trans, quat))
            newest = edge.times[-1]
            drop = bisect.bisect_left(edge.times, newest - self.cache_ns)
            drop = max(drop, len(edge.times) - self.max_per_edge)
            if drop > 0:
                del edge.times[:drop]
                del edge.values[:drop]

    def clear(self, *, static: bool = False) -> None:
        """Forget the dynamic transforms (e.g. after a clock jump backwards), and the static
        ones too when ``static`` is true."""
        with self._lock:
            for child in [c for c, e in self._edges.items() if static or not e.static]:
                del self._edges[child]
            self.version += 1

    # --------------------------------------------------------------------------- lookup
    def frames(self) -> list[str]:
        """Every frame name known."""
        with self._lock:
            names = set(self._edges)
            names.update(e.parent for e in self._edges.values())
        return sorted(names)

    def can_transform(self, target: str, source: str, time_ns: int | None = None) -> bool:
        """Whether :meth:`lookup` would succeed."""
        try:
            self.lookup(target, source, time_ns)
        except TransformLookupError:
            return False
        return True

    def is_static(self, target: str, source: str) -> bool:
        """True when every edge between the two frames is static (a fixed mount)."""
        target, source = _strip(target), _strip(source)
        with self._lock:
            up_s, up_t = self._path(source), self._path(target)
            common = next((f for f in up_s if f in up_t), None)
            if common is None:
                return False
            chain = up_s[:up_s.index(common)] + up_t[:up_t.index(common)]
            return all(self._edges[f].static for f in chain)

    def samples(self, target: str, source: str, after_ns: int | None = None
                ) -> list[tuple[int, np.ndarray[Any, np.dtype[np.float64]]]]:
        """``(stamp, target_from_source)`` at every stamp held by a dynamic edge of the chain
        (newer than ``after_ns``), oldest first; stamps where the chain cannot be composed
        (another edge has no sample near) are left out. Empty when the frames are not
        connected or the chain is all static."""
        target, source = _strip(target), _strip(source)
        with self._lock:
            up_s, up_t = self._path(source), self._path(target)
            common = next((f for f in up_s if f in up_t), None)
            if common is None or target == source:
                return []
            chain = up_s[:up_s.index(common)] + up_t[:up_t.index(common)]
            stamps = sorted({t for f in chain if not self._edges[f].static
                             for t in self._edges[f].times
                             if after_ns is None or t > after_ns})
        out = []
        for stamp in stamps:
            try:
                out.append((stamp, self.lookup(target, source, stamp)))
            except TransformLookupError:
                continue
        return out

    def lookup(self, target: str, source: str, time_ns: int | None = None
               ) -> np.ndarray[Any, np.dtype[np.float64]]:
        """``target_from_source`` (4x4 float64) at ``time_ns`` (``None``: newest samples).

        Raises:
            TransformLookupError: the frames are not connected, or a dynamic edge has no
                sample within ``tolerance_ns`` of the time.
        """
        target, source = _strip(target), _strip(source)
        if target == source:
            return np.eye(4)
        with self._lock:
            up_s, up_t = self._path(source), self._path(target)
            common = next((f for f in up_s if f in up_t), None)
            if common is None:
                raise TransformLookupError(
                    f"transform {target} <- {source}", None,
                    f"frames connected in the TF tree (known: {sorted(self._known())})")
            root_from_source = np.eye(4)
            for frame in up_s[:up_s.index(common)]:
                root_from_source = self._at(frame, time_ns) @ root_from_source
            root_from_target = np.eye(4)
            for frame in up_t[:up_t.index(common)]:
                root_from_target = self._at(frame, time_ns) @ root_from_target
        return np.linalg.inv(root_from_target) @ root_from_source

    def _known(self) -> set[str]:
        names = set(self._edges)
        names.update(e.parent for e in self._edges.values())
        return names

    def _path(self, frame: str) -> list[str]:
        """frame, its parent, ..., the root (stops on a cycle)."""
        path = [frame]
        while frame in self._edges:
            frame = self._edges[frame].parent
            if frame in path:
                break
            path.append(frame)
        return path

    def _at(self, child: str, time_ns: int | None) -> np.ndarray[Any, Any]:
        edge = self._edges[child]
        if edge.static or time_ns is None:
            trans, quat = edge.values[-1]
            return matrix_from_quaternion(quat, trans)
        times = edge.times
        i = bisect.bisect_left(times, time_ns)
        if i < len(times) and times[i] == time_ns:
            trans, quat = edge.values[i]
            return matrix_from_quaternion(quat, trans)
        if i == 0 or i == len(times):
            nearest = 0 if i == 0 else len(times) - 1
            if abs(times[nearest] - time_ns) > self.tolerance_ns:
                side = "before the oldest" if i == 0 else "after the newest"
                raise TransformLookupError(
                    f"transform {edge.parent} -> {child} at {time_ns} ns", time_ns,
                    f"a time within {self.tolerance_ns} ns of the samples [{times[0]}, "
                    f"{times[-1]}] (requested time is {side})")
            trans, quat = edge.values[nearest]
            return matrix_from_quaternion(quat, trans)
        t0, t1 = times[i - 1], times[i]
        (p0, q0), (p1, q1) = edge.values[i - 1], edge.values[i]
        return interpolate_poses(matrix_from_quaternion(q0, p0), matrix_from_quaternion(q1, p1),
                                 [(time_ns - t0) / (t1 - t0)])[0]


def _strip(frame: str) -> str:
    """tf2 ignores a leading slash (ROS 1 habit)."""
    return str(frame).lstrip("/")


class TfListener:
    """Feeds a :class:`TransformBuffer` from ``/tf`` and ``/tf_static`` of an rclpy node.

    Args:
        node: the rclpy node that owns the subscriptions.
        buffer: the buffer to fill.
        on_error: called with one line when a TF message is malformed (default: node logger).
        on_message: called after each ``/tf`` message is stored, with True when the dynamic
            transforms were just cleared (``/tf`` time jumped back).
        tf_topic, tf_static_topic: topic names.

    Attributes:
        active: False when the tf2_msgs type is unavailable (nothing subscribed).
        received, bad: message counters.
    """

    def __init__(self, node: Any, buffer: TransformBuffer, *,
                 on_error: Callable[[str], None] | None = None,
                 on_message: Callable[[bool], None] | None = None, tf_topic: str = "/tf",
                 tf_static_topic: str = "/tf_static") -> None:
        self.buffer = buffer
        self.received = 0
        self.bad = 0
        self._node = node
        self._on_error = on_error or (lambda line: node.get_logger().warning(line))
        self._on_message = on_message
        self._last_stamp: int | None = None
        try:
            from tf2_msgs.msg import TFMessage
        except ImportError:
            self.active = False
            node.get_logger().warning(
                "tf2_msgs is not installed (run `make tf2msgs`): /tf and /tf_static are not "
                "read; extrinsics come from parameters only")
            return
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

        static_qos = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST,
                                reliability=ReliabilityPolicy.RELIABLE,
                                durability=DurabilityPolicy.TRANSIENT_LOCAL)
        dynamic_qos = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST,
                                 reliability=ReliabilityPolicy.RELIABLE,
                                 durability=DurabilityPolicy.VOLATILE)
        self.active = True
        self._subs = [
            node.create_subscription(TFMessage, tf_static_topic,
                                     lambda raw: self._on_raw(raw, True), static_qos, raw=True),
            node.create_subscription(TFMessage, tf_topic,
                                     lambda raw: self._on_raw(raw, False), dynamic_qos, raw=True),
        ]

    def _on_raw(self, raw: bytes, static: bool) -> None:
        from lidarscan import decode
        from lidarscan.errors import LidarScanError

        self.received += 1
        cleared = False
        try:
            message = decode(raw, "tf2_msgs/msg/TFMessage")
            if not static:
                stamps = [to_ns(t.header.stamp) for t in message.transforms]
                newest = max(stamps, default=None)
                if newest is not None and self._last_stamp is not None and \
                        newest < self._last_stamp - 1_000_000_000:
                    self._on_error(f"/tf time jumped back {(self._last_stamp - newest) / 1e9:.3f}"
                                   " s (recording restarted?): dynamic transforms cleared")
                    self.buffer.clear()
                    self._last_stamp = None
                    cleared = True
                if newest is not None:
                    self._last_stamp = max(newest, self._last_stamp or newest)
            self.buffer.add_message(message, static=static)
        except LidarScanError as err:
            self.bad += 1
            self._on_error(f"bad {'/tf_static' if static else '/tf'} message ignored: {err}")
        if not static and self._on_message is not None:
            self._on_message(cleared)
