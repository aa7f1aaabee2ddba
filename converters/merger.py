"""Merge N LaserScans (2D lidars and LidarScan slices) into one scan in an output frame.

**Geometry.** Ray ``i`` of an input is at ``angle_min + i * angle_increment`` in the input frame
(float64 of the float32 fields; ``angle_max`` is ignored, so negative increments and inconsistent
headers work). Its endpoint ``r * (cos, sin, 0)`` is moved into the output frame by the input's
``extrinsics`` (full 3D: tilted and upside-down mounts work), optionally composed with the motion
between the scan's stamp and the output stamp. Each endpoint is binned by *its own* azimuth in the
output frame, so rays of an offset sensor that cross each other land where they should
(occlusion), and fusion is the per-bin minimum of the planar range. Mixed resolutions need no
special case: every ray lands in exactly one bin (minimum when down-sampling, no duplicated rays
when up-sampling: finer output bins without a ray get ``fill``). Grid, binning, REP 117 classes,
precedence (finite > -Inf > +Inf > NaN > empty) and ties (first input in configuration order,
then first ray) are those of :mod:`converters.slices.spec`.

**Input classes.** A finite range below the scan's own ``range_min`` (e.g. 0.0, which Hokuyo and
other drivers use for "no valid echo") and any range ``<= 0`` are invalid (NaN class); above ``min(scan.range_max,
input.range_max)`` it means nothing within trusted range (+Inf class); below ``input.range_min``
(a user filter, e.g. the robot's own body) it is dropped. ``scan.range_max <= 0`` or NaN means no
upper limit. Rays outside the input's angle window (input frame, CCW from ``angle_min`` to
``angle_max``, inclusive, wrapping across +-pi allowed) are dropped. A 3D-mounted input may have a
height band (output frame) with the slice rules.

**Synchronisation** (:meth:`LaserScanMerger.push`). Each input has a bounded queue sorted by
stamp (int ns). Pass 1: the pivot is the newest of the queue heads; every input picks its queued
scan nearest to the pivot (ties: the older); if every pick is within ``slop_ns`` of the pivot
(inclusive) the set matches. Pass 2 consumes, for each input, its pick and everything older. When
a set does not match, scans older than ``pivot - slop_ns`` can never match any more and are
dropped, nothing else is consumed. When several sets are complete at once (a burst, or when an
input has just been declared dead) the newest is merged and the older ones are dropped
(``stats["dropped_backlog"]``), so output latency never builds up. A scan not newer than its input's last consumed scan
(late/out of order) or with a stamp already queued (duplicate) is dropped. Policies: ``"wait"``
requires every input; ``"timeout"`` leaves out inputs that are *dead*: whose newest stamp is older
than ``clock - timeout_ns`` (``clock`` = the newest stamp pushed to the merger, i.e. data time, so
replays behave like live runs). A scan is fused at most once, and only with scans within the slop,
so stale data is never fused. The output stamp is the newest (``reference="newest"``) or oldest
stamp of the fused set, exact in ns. ``time_increment`` is 0 and ``scan_time`` the largest input
``scan_time``. Scans are validated when pushed (header, frame): a malformed scan raises before
it touches any queue. A scan whose ``header.frame_id`` is not the output frame needs the input's
``extrinsics`` (identity is never assumed across frames).

**Clock jumps backwards** (``jump_back_ns``, default 1 s; None = never). Each input is judged on
its *own* stamps: a scan older than the newest scan queued from that input by more than
``jump_back_ns`` is held as a suspected jump and dropped (``stats["dropped_late"]``,
:attr:`LaserScanMerger.last_drop` says why). If the next scan of that input is such a scan too,
and newer than the held one, the input's clock was reset (a recording played in a loop, a sensor
or simulator restarting): its time is reset (``stats["time_resets"]``, :attr:`last_reset`): its
queue and last consumed stamp are cleared and the confirming scan starts its new timeline. Scans
of the other inputs stamped more than ``jump_back_ns`` after the new stamp belong to the
timeline that was left: they are dropped from the queues (``stats["dropped_jump"]``) and those
inputs' liveness restarts at the new stamp (as if never seen: policy ``"timeout"`` waits for
them for their timeout, then leaves them out until they jump back too or publish again), and the
merger's clock becomes the newest liveness stamp, so fusion resumes on the new timeline as soon as
the inputs have jumped, never mixing scans across the jump. One stale, zero-stamped or replayed
scan, or any number of them that do not rise, therefore never resets anything (a zero stamp,
i.e. unset, is never evidence of a jump); an input merely
lagging behind the others is never a jump (its own stamps do not go back). Odometry follows the
same rule on its own stamps (``stats["odometry_resets"]``: the pose history restarts;
``stats["dropped_odometry"]``).

**Motion compensation** (:meth:`LaserScanMerger.push_odometry`). Odometry gives the pose
``T(t)`` of the output frame in a fixed frame. A scan taken at ``t_i`` is moved by
``T(t_ref)^-1 T(t_i)`` (in 2D: ``p' = R(-dtheta) p - R(-theta_ref) dt`` with
``dtheta = theta_ref - theta_i``, ``dt = t_ref - t_i`` positions: correct at any heading). Poses
are interpolated linearly (position) and by slerp along the shortest arc (orientation); outside
the queued window the nearest pose is held (clamp), but only up to ``odom_max_gap_ns``; a gap
between samples larger than that, or no odometry, leaves the scan uncompensated (counted in
``stats["uncompensated"]``). One odometry pose per scan (no per-ray deskew by odometry).

**Moving mounts.** An input's ``extrinsics`` may move: a :class:`converters.TransformTrack`
(stamped poses, interpolated: linear translation, slerp rotation) or any callable ``stamp_ns ->
4x4``. The mount's pose is looked up at each ray's own time: ray ``i`` of a scan was measured at
``stamp + i * time_increment`` (sensor_msgs/LaserScan's definition; negative increments work;
``time_increment`` 0 or not finite, or ``MergerInput.deskew`` false: every ray at the stamp), so
a sensor on a pan unit turning during its sweep is de-skewed ray by ray. (The slices of
``to_laserscan`` do not follow that convention: their ray ``i`` is not measured at ``stamp + i *
time_increment``; give such an input ``deskew=False``.) A callable is called once per distinct
ray time and its result checked (rigid 4x4); a track computes them in one batch. A pose that
cannot be found (outside the track's span, :class:`converters.shared.transforms.OutOfSpanError`, or any
:class:`~converters.shared.transforms.TransformLookupError` the callable raises) never falls back to
another pose: :meth:`LaserScanMerger.merge` raises it; in :meth:`LaserScanMerger.push` that scan
is left out of the fused set and counted (``stats["dropped_no_pose"]``,
:attr:`LaserScanMerger.last_no_pose` says why); the others are merged without it (nothing is
output when no scan is left).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from converters import _kernels

from converters.slices import spec as _grid

from converters.shared import options
from converters.slices.spec import AngleGrid, OutputOptions
from converters._kernels.slices_numba import Bands, Rays
from converters.shared.frames import check_extrinsics, check_frame, check_poses
from converters.shared.transforms import (TransformLookupError, TransformTrack, _quat_to_matrix,
                                   interpolate_poses, quaternion_from_matrix)
from lidarscan.errors import ConfigError, ValidationError
from lidarscan.scan import as_array
from lidarscan.stamps import to_ns

__all__ = ["LaserScanMerger", "MergerInput", "Pose", "interpolate_pose"]

_NO_KEYS = np.zeros(0, np.int32)    # tie key = ray index + the input's base


@dataclass(frozen=True)
class MergerInput:
    """Settings of one merger input (transport settings such as QoS belong to the node).

    Attributes:
        extrinsics: 4x4 pose of the input's frame in the output frame. None = identity, allowed
            only for an input whose scans are in the output frame: a scan in another frame
            without extrinsics is refused (ValidationError naming the input and both frames).
            A moving mount: a :class:`converters.TransformTrack` or a callable
            ``stamp_ns (int) -> 4x4``, looked up at each ray's time (module docstring).
        range_min, range_max: user range filter on the input's own ranges, metres (see the
            module docstring for what happens below/above).
        angle_min, angle_max: angle window in the input frame, radians, inclusive, CCW from
            ``angle_min`` to ``angle_max`` (``angle_max < angle_min`` wraps across +-pi); both
            None = all rays.
        min_height, max_height: inclusive height band in the output frame for 3D-mounted inputs.
        timeout_ns: how long the input may stay silent before policy ``"timeout"`` merges without
            it (None = the merger's ``timeout_ns``).
        frame_id: if set, scans must carry this ``header.frame_id``.
        deskew: with moving extrinsics, look the pose up per ray at
            ``stamp + i * time_increment`` (false: one pose at the scan's stamp).
    """

    extrinsics: Any = None
    range_min: float = 0.0
    range_max: float = math.inf
    angle_min: float | None = None
    angle_max: float | None = None
    min_height: float = -math.inf
    max_height: float = math.inf
    timeout_ns: int | None = None
    frame_id: str | None = None
    deskew: bool = True


@dataclass(frozen=True)
class Pose:
    """A pose at a stamp: position (3,) metres and unit quaternion (x, y, z, w)."""

    stamp_ns: int
    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float]

    def matrix(self) -> np.ndarray[Any, np.dtype[np.float64]]:
        """4x4 float64 homogeneous transform."""
        out = np.eye(4)
        out[:3, :3] = _quat_to_matrix(np.asarray(self.orientation, np.float64))[0]
        out[:3, 3] = self.position
        return out


def interpolate_pose(stamps: list[int], poses: list[Pose], t: int, max_gap_ns: int
                     ) -> Pose | None:
    """Pose at ``t`` from sorted samples: exact sample, lerp + shortest-arc slerp between two
    (:func:`converters.shared.transforms.interpolate_poses`),
    the nearest one held outside the window; None if the bracketing gap (or the distance to the
    nearest sample outside the window) exceeds ``max_gap_ns`` or there are no samples."""
    if not stamps:
        return None
    i = bisect.bisect_left(stamps, t)
    if i < len(stamps) and stamps[i] == t:
        return poses[i]
    if i == 0:
        return poses[0] if stamps[0] - t <= max_gap_ns else None
    if i == len(stamps):
        return poses[-1] if t - stamps[-1] <= max_gap_ns else None
    t0, t1 = stamps[i - 1], stamps[i]
    if t1 - t0 > max_gap_ns:
        return None
    m = interpolate_poses(poses[i - 1].matrix(), poses[i].matrix(), [(t - t0) / (t1 - t0)])[0]
    return Pose(t, tuple(float(v) for v in m[:3, 3]),  # type: ignore[arg-type]
                quaternion_from_matrix(m))


@dataclass
class _ScanIn:
    stamp: int
    frame_id: str
    angle_min: float
    increment: float
    ranges: np.ndarray[Any, Any]
    intensities: np.ndarray[Any, Any] | None
    range_min: float
    range_max: float
    scan_time: float
    time_increment: float


def _read_scan(scan: Any, name: str) -> _ScanIn:
    ranges = np.ascontiguousarray(as_array(scan.ranges, np.float32).reshape(-1), np.float32)
    inten = as_array(scan.intensities, np.float32).reshape(-1)
    intensities = inten.astype(np.float32, copy=False) if inten.size == ranges.size else None
    amin = float(scan.angle_min)
    inc = float(scan.angle_increment)
    if not math.isfinite(amin):
        raise ValidationError(f"{name}.angle_min", amin, "a finite angle")
    if ranges.size > 1 and not (math.isfinite(inc) and inc != 0.0):
        raise ValidationError(f"{name}.angle_increment", inc,
                              "a finite non-zero increment for a scan of several rays")
    rmin = float(scan.range_min)
    rmax = float(scan.range_max)
    rmin = rmin if math.isfinite(rmin) and rmin > 0 else 0.0
    rmax = rmax if rmax > 0 else math.inf         # 0 / NaN: unknown
    if rmin > rmax:
        raise ValidationError(f"{name}.range_min", rmin, f"<= range_max ({rmax})")
    scan_time = float(scan.scan_time)
    time_inc = float(getattr(scan, "time_increment", 0.0))
    return _ScanIn(to_ns(scan.header.stamp, field=f"{name}.header.stamp"),
                   scan.header.frame_id, amin, inc, ranges, intensities, rmin, rmax,
                   scan_time if math.isfinite(scan_time) else 0.0,
                   time_inc if math.isfinite(time_inc) else 0.0)


class _InputState:
    """Configuration and caches of one input."""

    def __init__(self, name: str, cfg: MergerInput, index: int) -> None:
        self.name = name
        self.cfg = cfg
        self.index = index
        options.merger_input(name, cfg)
        if not isinstance(cfg.deskew, bool):
            raise ConfigError(f"inputs[{name!r}].deskew", cfg.deskew, "True or False")
        #: a moving mount: TransformTrack or callable stamp_ns -> 4x4 (else None)
        self.moving: Any = None
        if callable(cfg.extrinsics):
            self.moving = cfg.extrinsics
            self.extrinsics = np.eye(4)
        else:
            self.extrinsics = check_extrinsics(cfg.extrinsics, f"inputs[{name!r}].extrinsics")
        self.window: tuple[float, float] | None = None
        if cfg.angle_min is not None:
            a, b = float(cfg.angle_min), float(cfg.angle_max)  # type: ignore[arg-type]
            if b - a < 2.0 * math.pi:
                self.window = (a, (b - a) % (2.0 * math.pi))
        self._geom: dict[tuple[float, float, int], tuple[Any, Any, Any]] = {}
        self._rays_key: Any = None
        self._rays: Any = None
        self.kernel_bands: Bands | None = None
        self.queue: list[tuple[int, Any]] = []
        self.consumed = -(1 << 63)
        self.last_seen: int | None = None
        self.newest: int | None = None    # newest queued stamp on the input's own timeline
        self.pending: int | None = None   # stamp of an unconfirmed jump back

    def geometry(self, amin: float, inc: float, n: int) -> tuple[Any, Any, Any]:
        """cos, sin of the ray angles and the window mask (cached per header)."""
        key = (amin, inc, n)
        geom = self._geom.get(key)
        if geom is None:
            theta = amin + np.arange(n) * inc
            keep = None
            if self.window is not None:
                start, width = self.window
                rel = (theta - start) % (2.0 * math.pi)
                keep = rel <= width
            geom = (np.cos(theta), np.sin(theta), keep)
            if len(self._geom) > 8:
                self._geom.clear()
            self._geom[key] = geom
        return geom

    def poses(self, sc: _ScanIn) -> np.ndarray[Any, Any]:
        """The mount's pose(s) for a scan: (4, 4), or (n, 4, 4) one per ray when it moves
        during the sweep (ray ``i`` at ``stamp + i * time_increment``).

        Raises:
            TransformLookupError: a pose the track (or callable) does not know.
            ValidationError: the callable returned something that is not a rigid 4x4.
        """
        if self.moving is None:
            return self.extrinsics
        n = sc.ranges.size
        if self.cfg.deskew and sc.time_increment != 0.0 and n > 1:
            times = sc.stamp + np.round(np.arange(n) * (sc.time_increment * 1e9)).astype(np.int64)
        else:
            times = np.array([sc.stamp], np.int64)
        if isinstance(self.moving, TransformTrack):
            mats = self.moving.lookup_many(times)
        else:
            unique, inverse = np.unique(times, return_inverse=True)
            field = f"inputs[{self.name!r}].extrinsics(stamp_ns)"
            mats = check_poses([self.moving(int(t)) for t in unique], field)[inverse]
        return mats[0] if len(mats) == 1 else mats

    def rays(self, matrix: np.ndarray[Any, Any], amin: float, inc: float, n: int,
             grid: AngleGrid, options: OutputOptions, near: float, static: bool) -> _Rays:
        """Rays of a scan header in the output frame, cached while transform and header stay.

        ``matrix``: (4, 4), or (n, 4, 4) one transform per ray (a mount moving during the
        sweep). ``static``: the transform will be reused (no motion compensation, a rigid
        mount), so the far-field tables are worth computing; otherwise every point gets atan2.
        """
        key = (matrix.tobytes(), amin, inc, n, near, static)
        if key == self._rays_key:
            return self._rays  # type: ignore[no-any-return]
        c, s, keep = self.geometry(amin, inc, n)
        m = matrix if matrix.ndim == 3 else matrix[None]
        d = np.empty((n, 3))
        for i in range(3):
            d[:, i] = m[:, i, 0] * c + m[:, i, 1] * s
        o = np.empty((n, 3))
        o[:] = m[:, :3, 3]
        if static:
            bin_far, r_thr = _grid.far_field(d, o, grid)
        else:
            bin_far = grid.bins(np.arctan2(d[:, 1], d[:, 0]))
            bin_far[(d[:, 0] == 0) & (d[:, 1] == 0)] = -1
            r_thr = np.full(n, np.inf)
        q_far, q_near = _grid.qualify(d, o, self.cfg.min_height, self.cfg.max_height,
                                      options.range_min, options.range_max, near)
        rays = _Rays(d, o, keep, bin_far, r_thr, q_far, q_near)
        self._rays, self._rays_key = rays, key
        return rays


class _Rays:
    """One input's rays in the output frame (numpy and compiled-kernel layouts)."""

    def __init__(self, d: np.ndarray[Any, Any], o: np.ndarray[Any, Any],
                 keep: np.ndarray[Any, Any] | None, bin_far: np.ndarray[Any, Any],
                 r_thr: np.ndarray[Any, Any], q_far: np.ndarray[Any, Any],
                 q_near: np.ndarray[Any, Any]) -> None:
        self.d, self.o, self.keep = d, o, keep
        self.bin_far, self.r_thr, self.q_far, self.q_near = bin_far, r_thr, q_far, q_near
        self.k_keep = np.zeros(0, np.uint8) if keep is None else keep.astype(np.uint8)
        ok = bin_far >= 0
        columns = (np.ascontiguousarray(a[:, k]) for a in (d, o) for k in range(3))
        #: the rays as the compiled kernels take them (tie keys: ray index + the input's base)
        self.kernel_rays = Rays(
            *columns, keys=_NO_KEYS,
            qual=((q_far & ok).astype(np.uint8) | ((q_near & ok).astype(np.uint8) << 1)
                  )[None, :],
            bin_far=bin_far.astype(np.int32)[None, :], r_thr=_grid.round_up_f32(r_thr)[None, :])


class LaserScanMerger:
    """N named LaserScan inputs fused into one LaserScan (see the module docstring).

    Args:
        inputs: name -> :class:`MergerInput`; the order is the tie order (first wins).
        frame_id: output frame.
        angle_min, angle_max, angle_increment: output grid (default full circle at 0.25 deg).
        range_min, range_max: inclusive planar limits in the output frame.
        use_inf, inf_epsilon, fill: output values (:class:`converters.slices.spec.OutputOptions`).
        intensities: publish intensities (0 where the winner had none) or an empty field.
        slop_ns: synchronisation tolerance, inclusive.
        policy: ``"wait"`` (all inputs needed) or ``"timeout"`` (dead inputs left out).
        timeout_ns: default silence after which an input is dead (policy ``"timeout"``).
        reference: output stamp ``"newest"`` or ``"oldest"`` of the fused set.
        queue_size: scans kept per input.
        motion_compensation: use pushed odometry to move scans to the output stamp.
        odom_queue_size, odom_max_gap_ns: odometry samples kept; largest gap bridged.
        jump_back_ns: an input (or the odometry) whose stamps go back by more than this, two
            scans in a row, had its clock reset (see the module docstring); None = never.
        backend: ``"auto"`` (the numba kernels when installed), ``"numba"``, ``"numpy"``
            (:func:`converters._kernels.select`).

    Raises:
        ConfigError: bad options.
    """

    def __init__(self, inputs: Mapping[str, MergerInput], *, frame_id: str = "base_link",
                 angle_min: float = -math.pi, angle_max: float = math.pi,
                 angle_increment: float = math.radians(0.25), range_min: float = 0.0,
                 range_max: float = math.inf, use_inf: bool = True, inf_epsilon: float = 1.0,
                 fill: float | None = None, intensities: bool = True,
                 slop_ns: int = 50_000_000, policy: str = "wait",
                 timeout_ns: int = 1_000_000_000, reference: str = "newest",
                 queue_size: int = 10, motion_compensation: bool = True,
                 odom_queue_size: int = 200, odom_max_gap_ns: int = 250_000_000,
                 jump_back_ns: int | None = 1_000_000_000, backend: str = "auto") -> None:
        options.merger_options({
            "frame_id": frame_id, "angle_min": angle_min, "angle_max": angle_max,
            "angle_increment": angle_increment, "range_min": range_min, "range_max": range_max,
            "use_inf": use_inf, "inf_epsilon": inf_epsilon, "fill": fill,
            "intensities": intensities, "slop_ns": slop_ns, "policy": policy,
            "timeout_ns": timeout_ns, "reference": reference, "queue_size": queue_size,
            "motion_compensation": motion_compensation, "odom_queue_size": odom_queue_size,
            "odom_max_gap_ns": odom_max_gap_ns, "jump_back_ns": jump_back_ns,
            "backend": backend})
        self._kernel = _kernels.select("merger", backend=backend).numba
        if not isinstance(inputs, Mapping) or not inputs:
            raise ConfigError("inputs", inputs, "a non-empty dict of name -> MergerInput")
        self.frame_id = frame_id
        self._inputs: dict[str, _InputState] = {}
        for i, (name, cfg) in enumerate(inputs.items()):
            if not isinstance(name, str) or not name:
                raise ConfigError("inputs", name, "non-empty str input names")
            if not isinstance(cfg, MergerInput):
                raise ConfigError(f"inputs[{name!r}]", cfg, "a MergerInput")
            self._inputs[name] = _InputState(name, cfg, i)
            if cfg.frame_id is not None:
                check_frame(f"inputs[{name!r}].frame_id", cfg.frame_id, frame_id,
                            cfg.extrinsics is not None, ConfigError)
        self.grid = AngleGrid.create(angle_min, angle_max, angle_increment)
        self.options = OutputOptions.create(range_min, range_max, use_inf, inf_epsilon, fill)
        self.intensities = bool(intensities)
        self.jump_back_ns = None if jump_back_ns is None else int(jump_back_ns)
        self.slop_ns, self.timeout_ns = int(slop_ns), int(timeout_ns)
        self.policy, self.reference = policy, reference
        self.queue_size = int(queue_size)
        self.motion_compensation = bool(motion_compensation)
        self.odom_queue_size, self.odom_max_gap_ns = int(odom_queue_size), int(odom_max_gap_ns)
        self._odom_t: list[int] = []
        self._odom: list[Pose] = []
        self._odom_pending: int | None = None
        self._clock: int | None = None
        self.last_inputs: tuple[str, ...] = ()
        #: why the last pushed scan was not queued (None: it was queued)
        self.last_drop: str | None = None
        #: why the last scan left out for want of a moving mount's pose was (None: never)
        self.last_no_pose: str | None = None
        #: (input, its newest stamp before, new stamp) if the last push reset an input's time
        self.last_reset: tuple[str, int, int] | None = None
        self.stats = {"merged": 0, "partial": 0, "dropped_late": 0, "dropped_duplicate": 0,
                      "dropped_overflow": 0, "dropped_unmatched": 0, "dropped_backlog": 0,
                      "dropped_jump": 0, "time_resets": 0, "odometry_resets": 0,
                      "dropped_odometry": 0, "uncompensated": 0, "dropped_no_pose": 0}

    @property
    def input_names(self) -> tuple[str, ...]:
        """Configured inputs in tie order."""
        return tuple(self._inputs)

    # ----------------------------------------------------------------------------- odometry
    def push_odometry(self, odom: Any) -> None:
        """Add a ``nav_msgs/Odometry`` (rclpy or dataclass): pose of the output frame in a
        fixed frame at ``header.stamp``.

        Raises:
            ValidationError: a zero or non-finite quaternion or position, or a
                ``child_frame_id`` that is set and differs from the output frame.
        """
        child = getattr(odom, "child_frame_id", "") or ""
        if child and child != self.frame_id:
            raise ValidationError("Odometry.child_frame_id", child,
                                  f"{self.frame_id!r} (the merger's output frame) or empty")
        stamp = to_ns(odom.header.stamp, field="Odometry.header.stamp")
        pose = odom.pose.pose
        p = (float(pose.position.x), float(pose.position.y), float(pose.position.z))
        q = np.array([pose.orientation.x, pose.orientation.y, pose.orientation.z,
                      pose.orientation.w], float)
        norm = float(np.linalg.norm(q))
        if not (np.all(np.isfinite(p)) and math.isfinite(norm) and norm > 1e-9):
            raise ValidationError("Odometry.pose.pose", (p, q.tolist()),
                                  "a finite position and a non-zero quaternion")
        q /= norm
        jump = self.jump_back_ns
        if jump is not None and self._odom_t and stamp < self._odom_t[-1] - jump:
            if self._odom_pending is None or stamp <= self._odom_pending:
                self._odom_pending = stamp   # wait for a second sample to confirm the jump
                self.stats["dropped_odometry"] += 1
                return
            self._odom_t.clear()             # the odometry's clock was reset: new history
            self._odom.clear()
            self.stats["odometry_resets"] += 1
        self._odom_pending = None
        i = bisect.bisect_left(self._odom_t, stamp)
        sample = Pose(stamp, p, tuple(float(v) for v in q))  # type: ignore[arg-type]
        if i < len(self._odom_t) and self._odom_t[i] == stamp:
            self._odom[i] = sample
        else:
            self._odom_t.insert(i, stamp)
            self._odom.insert(i, sample)
        while len(self._odom_t) > self.odom_queue_size:
            self._odom_t.pop(0)
            self._odom.pop(0)

    def pose_at(self, stamp_ns: int) -> Pose | None:
        """Interpolated odometry pose at ``stamp_ns`` (see :func:`interpolate_pose`)."""
        return interpolate_pose(self._odom_t, self._odom, int(stamp_ns), self.odom_max_gap_ns)

    # ------------------------------------------------------------------------------- merging
    def merge(self, scans: Mapping[str, Any]) -> Any:
        """Fuse scans taken together (no synchronisation, no queues).

        Args:
            scans: input name -> LaserScan (rclpy or dataclass; arrays may be array.array,
                numpy or lists). A subset of the inputs is allowed.

        Returns:
            rclpy ``sensor_msgs.msg.LaserScan`` in ``frame_id`` stamped with the reference stamp.

        Raises:
            ConfigError: an unknown input name.
            ValidationError: no scan, or a scan with a bad header / wrong frame.
            TransformLookupError: a moving mount's pose is unknown at a ray's time
                (:class:`converters.shared.transforms.OutOfSpanError` outside a track's span).
        """
        for name in scans:
            if name not in self._inputs:
                raise ConfigError("scans", name, f"one of the inputs {list(self._inputs)}")
        states = [s for s in self._inputs.values() if s.name in scans]
        if not states:
            raise ValidationError("scans", dict(scans), "at least one input scan")
        read = [self._read(s, scans[s.name]) for s in states]
        return self._fuse(states, read, [s.poses(sc) for s, sc in zip(states, read)])

    def _read(self, state: _InputState, scan: Any) -> _ScanIn:
        """Header and arrays of one input's scan, validated (frame included: the configured
        frame, and without extrinsics the output frame)."""
        sc = _read_scan(scan, state.name)
        if state.cfg.frame_id is not None and sc.frame_id != state.cfg.frame_id:
            raise ValidationError(f"{state.name}.header.frame_id", sc.frame_id,
                                  f"{state.cfg.frame_id!r} (MergerInput.frame_id)")
        check_frame(f"{state.name}.header.frame_id", sc.frame_id, self.frame_id,
                    state.cfg.extrinsics is not None)
        return sc

    def _fuse(self, states: list[_InputState], read: list[_ScanIn],
              mounts: list[np.ndarray[Any, Any]]) -> Any:
        """Fuse validated scans (one per state, in tie order) with their mounts' poses."""
        stamps = [sc.stamp for sc in read]
        ref = max(stamps) if self.reference == "newest" else min(stamps)
        ref_inv = None
        if self.motion_compensation and self._odom_t:
            pose = self.pose_at(ref)
            ref_inv = None if pose is None else np.linalg.inv(pose.matrix())
        best = np.full(self.grid.size, _grid.EMPTY, np.int64)
        bins_l, codes_l, keys_l, ints_l = [], [], [], []
        base = 0
        compensate = self.motion_compensation and bool(self._odom_t)
        for s, sc, matrix in zip(states, read, mounts):
            if compensate and sc.stamp != ref:
                pose = self.pose_at(sc.stamp)
                if pose is None or ref_inv is None:
                    self.stats["uncompensated"] += 1
                else:
                    matrix = ref_inv @ pose.matrix() @ matrix
            n = sc.ranges.size
            if n:
                rays = s.rays(matrix, sc.angle_min, sc.increment, n, self.grid, self.options,
                              sc.range_min, static=not compensate and s.moving is None)
                if self._kernel is not None:
                    self._input_kernel(self._kernel, s, sc, rays, base, best)
                else:
                    bins, codes, keys = self._input_codes(s, sc, rays)
                    bins_l.append(bins)
                    codes_l.append(codes)
                    keys_l.append(keys + base)
            ints_l.append(sc.intensities if sc.intensities is not None
                          else np.zeros(n, np.float32))
            base += n
        if bins_l:
            best = _grid.reduce_min(self.grid.size, np.concatenate(bins_l),
                                    np.concatenate(codes_l), np.concatenate(keys_l))
        ranges, winners = _grid.decode(best, self.options, self._kernel)
        intensities = None
        if self.intensities:
            intensities = np.zeros(self.grid.size, np.float32)
            hit = winners >= 0
            if hit.any():
                intensities[hit] = np.concatenate(ints_l)[winners[hit]]
        self.last_inputs = tuple(s.name for s in states)
        return _grid.make_laserscan(stamp_ns=ref, frame_id=self.frame_id, grid=self.grid,
                                    ranges=ranges, intensities=intensities,
                                    options=self.options,
                                    scan_time=max(sc.scan_time for sc in read),
                                    time_increment=0.0)

    def _limits(self, s: _InputState, sc: _ScanIn) -> tuple[float, float, float]:
        """(invalid below, +Inf above, dropped below) for finite ranges of this input."""
        return sc.range_min, min(sc.range_max, float(s.cfg.range_max)), float(s.cfg.range_min)

    def _input_kernel(self, kernel: Any, s: _InputState, sc: _ScanIn, rays: _Rays, base: int,
                      best: np.ndarray[Any, Any]) -> None:
        bands = s.kernel_bands
        if bands is None:      # the input as one slice: its height band, the output's limits
            bands = s.kernel_bands = Bands.create(
                [(float(s.cfg.min_height), float(s.cfg.max_height), self.options, 0)],
                [self.grid])
        kernel.fuse(sc.ranges, rays.kernel_rays, bands, best, keep=rays.k_keep,
                    limits=np.array(self._limits(s, sc)), key_base=base)

    def _input_codes(self, s: _InputState, sc: _ScanIn, rays: _Rays
                     ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any], np.ndarray[Any, Any]]:
        """numpy path: (bins, codes, ray indices) of one input."""
        invalid_below, inf_above, drop_below = self._limits(s, sc)
        r = sc.ranges.astype(np.float64)
        with np.errstate(invalid="ignore"):
            finite = np.isfinite(r)
            invalid = finite & ((r <= 0) | (r < invalid_below))
            over = finite & (r > inf_above) & ~invalid
            point = finite & ~invalid & ~over & (r >= drop_below)
            special = ~finite | invalid | over
        if rays.keep is not None:
            point &= rays.keep
            special &= rays.keep
        pidx = np.flatnonzero(point)
        sel, pbins, pcodes = _grid.point_codes(
            r[pidx], rays.d[pidx], rays.o[pidx], s.cfg.min_height, s.cfg.max_height,
            self.options.range_min, self.options.range_max, self.grid,
            rays.bin_far[pidx], rays.r_thr[pidx])
        pkeys = pidx[sel]
        sidx = np.flatnonzero(special)
        if not sidx.size:
            return pbins, pcodes, pkeys
        values = r[sidx]
        values[invalid[sidx]] = np.nan
        values[over[sidx]] = np.inf
        scodes = _grid.special_codes(values, rays.q_far[sidx], rays.q_near[sidx])
        ok = (scodes >= 0) & (rays.bin_far[sidx] >= 0)
        return (np.concatenate([pbins, rays.bin_far[sidx][ok]]),
                np.concatenate([pcodes, scodes[ok]]),
                np.concatenate([pkeys, sidx[ok]]))

    # ---------------------------------------------------------------------------- streaming
    def push(self, name: str, scan: Any) -> Any:
        """Queue one scan; return the merged scan if a set now matches, else None (also when
        every scan of the set lacked its moving mount's pose: ``stats["dropped_no_pose"]``).

        The scan is validated here (header, frame), so a malformed scan is rejected before it
        touches any queue. Why a scan was not queued is in :attr:`last_drop` (None: queued).

        Raises:
            ConfigError: unknown input name.
            ValidationError: the scan's header cannot be read or is inconsistent.
        """
        state = self._inputs.get(name)
        if state is None:
            raise ConfigError("name", name, f"one of the inputs {list(self._inputs)}")
        sc = self._read(state, scan)
        stamp = sc.stamp
        self.last_drop = None
        self.last_reset = None
        jump = self.jump_back_ns
        if jump is not None and state.newest is not None and stamp < state.newest - jump:
            if stamp == 0:                   # unset stamp: no evidence of any time
                self._drop(state, "dropped_late", "zero (unset) stamp")
                return None
            if state.pending is None or stamp <= state.pending:
                state.pending = stamp        # one scan is no evidence: wait for a second one
                self._drop(state, "dropped_late", f"{(state.newest - stamp) / 1e9:.3f} s "
                           "older than the input's newest scan (a jump back is taken "
                           "only after a second scan in a row confirms it)")
                return None
            self._time_reset(state, stamp)
        state.pending = None
        if self._clock is None or stamp > self._clock:
            self._clock = stamp
        for other in self._inputs.values():    # "never seen" counts from the first scan
            if other.last_seen is None:
                other.last_seen = stamp
        state.last_seen = max(state.last_seen, stamp)  # type: ignore[type-var]
        if stamp <= state.consumed:
            self._drop(state, "dropped_late", "not newer than the input's last "
                       "consumed scan")
            return None
        queue = state.queue
        if queue and stamp > queue[-1][0]:
            queue.append((stamp, sc))
        else:
            i = bisect.bisect_left(queue, stamp, key=lambda item: item[0])
            if i < len(queue) and queue[i][0] == stamp:
                self._drop(state, "dropped_duplicate", "stamp already queued")
                return None
            queue.insert(i, (stamp, sc))
        if state.newest is None or stamp > state.newest:
            state.newest = stamp
        while len(queue) > self.queue_size:
            queue.pop(0)
            self.stats["dropped_overflow"] += 1
        return self._match()

    def _drop(self, state: _InputState, reason: str, why: str) -> None:
        """Count a scan that is not queued and say why (:attr:`last_drop`)."""
        self.stats[reason] += 1
        self.last_drop = f"input {state.name!r}: scan {reason.removeprefix('dropped_')}: {why}"

    def _time_reset(self, state: _InputState, stamp: int) -> None:
        """Input ``state`` jumped back to ``stamp`` (confirmed): start its new timeline."""
        jump = int(self.jump_back_ns)  # type: ignore[arg-type]
        old = state.newest
        dropped = len(state.queue)
        state.queue.clear()
        state.consumed = -(1 << 63)
        state.newest = None
        state.last_seen = stamp
        horizon = stamp + jump        # later stamps belong to the timeline that was left
        for other in self._inputs.values():
            if other is state:
                continue
            if other.last_seen is not None and other.last_seen > horizon:
                other.last_seen = stamp  # its liveness restarts on the new timeline
            keep = [item for item in other.queue if item[0] <= horizon]
            dropped += len(other.queue) - len(keep)
            other.queue[:] = keep
        seen = [s.last_seen for s in self._inputs.values() if s.last_seen is not None]
        self._clock = max(seen) if seen else stamp
        self.stats["time_resets"] += 1
        self.stats["dropped_jump"] += dropped
        self.last_reset = (state.name, int(old), stamp)  # type: ignore[arg-type]

    def _alive(self, state: _InputState) -> bool:
        if self.policy == "wait":
            return True
        timeout = state.cfg.timeout_ns if state.cfg.timeout_ns is not None else self.timeout_ns
        return state.last_seen is not None and self._clock is not None \
            and state.last_seen >= self._clock - int(timeout)

    def _match(self) -> Any:
        """Consume every complete set; merge the newest, count older ones as backlog."""
        found: dict[str, _ScanIn] | None = None
        partial = False
        while True:
            matched = self._match_once()
            if matched is None:
                break
            if found is not None:
                self.stats["dropped_backlog"] += 1
            found, partial = matched
        if found is None:
            return None
        states, read, mounts = [], [], []
        for s in self._inputs.values():
            if s.name not in found:
                continue
            try:
                mounts.append(s.poses(found[s.name]))
            except TransformLookupError as err:   # no pose: this scan is left out, counted
                self.stats["dropped_no_pose"] += 1
                self.last_no_pose = f"input {s.name!r}: scan left out of the fusion: {err}"
                partial = True
                continue
            states.append(s)
            read.append(found[s.name])
        if not states:
            return None
        self.stats["merged"] += 1
        self.stats["partial"] += int(partial)
        return self._fuse(states, read, mounts)

    def _match_once(self) -> tuple[dict[str, _ScanIn], bool] | None:
        while True:
            required = [s for s in self._inputs.values() if self._alive(s)]
            if not required:
                return None
            heads = [s.queue[0][0] for s in required if s.queue]
            if not heads:
                return None
            pivot = max(heads)
            if len(heads) == len(required):
                picks: list[int] = []
                for s in required:
                    stamps = [t for t, _ in s.queue]
                    j = bisect.bisect_left(stamps, pivot)
                    cands = [k for k in (j - 1, j) if 0 <= k < len(stamps)]
                    picks.append(min(cands, key=lambda k: (abs(stamps[k] - pivot), stamps[k])))
                if all(abs(s.queue[k][0] - pivot) <= self.slop_ns
                       for s, k in zip(required, picks)):
                    scans = {}
                    for s, k in zip(required, picks):
                        stamp, scan = s.queue[k]
                        self.stats["dropped_unmatched"] += k
                        del s.queue[:k + 1]
                        s.consumed = stamp
                        scans[s.name] = scan
                    return scans, len(required) < len(self._inputs)
            dropped = 0
            for s in self._inputs.values():
                while s.queue and s.queue[0][0] < pivot - self.slop_ns:
                    s.queue.pop(0)
                    dropped += 1
            self.stats["dropped_unmatched"] += dropped
            if not dropped:
                return None
