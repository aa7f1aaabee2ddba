"""``lidarscan-merger``: N LaserScan inputs (+ optional odometry) -> one merged LaserScan.

Wraps :class:`converters.merger.LaserScanMerger` (read its docstring for the grid, fusion,
synchronisation and motion-compensation rules). Each input is a LaserScan topic with its own QoS:
a 2D lidar, or a slice published by ``lidarscan-converter``.

Input extrinsics (``frame_id <- input frame``) come from TF (``/tf_static``, ``/tf``, the newest
transform; mounts are assumed rigid) when available, else from ``inputs.NAME.extrinsics``, else
identity when the input's frame is the output frame. A scan whose pose is unknown is dropped with a
log line. When a mount changes (a new ``/tf_static``) the merger is rebuilt (its queues restart;
the recent odometry is replayed).

**Moving inputs** (``inputs.NAME.moving: true``, e.g. a laser on a pan unit or an arm): the
input's pose ``frame_id <- scan frame`` is a :class:`converters.TransformTrack` filled from
``/tf``: each time a dynamic transform of the chain between the two frames arrives, the chained
transform at that stamp is added (static edges from ``/tf_static`` compose in; see
:meth:`converters.edge.nodes.tf.TransformBuffer.samples` for chains with several moving joints). The
merger looks the pose up at each ray's time (``stamp + i * time_increment``, de-skew; off with
``inputs.NAME.deskew: false``) and never extrapolates. Since ``/tf`` usually arrives a little
after a sweep ends, a moving input's scan waits until the track covers its whole sweep, for at
most ``tf_wait`` seconds of data time (the newest stamp seen on any input or on the track); then
it is merged anyway and, if a pose is still missing, left out of the fusion and counted
(``dropped_no_pose`` in the diagnostics). ``tf_tolerance`` holds the newest pose that long after
it (0 = strict, as tf2). A moving input needs ``use_tf``; its ``extrinsics`` parameter is not
used. The input's frame is its scans' ``header.frame_id``. Its chain must contain a ``/tf``
(dynamic) edge: a mount known only from ``/tf_static`` gives no poses (every scan counted in
``dropped_no_pose``); leave ``moving`` false for it.

Parameters (defaults in brackets; ``config/merger.yaml`` is a complete example):

* ``input_names`` [[]] (required): names of the inputs, in tie order (first wins ties); per NAME:
  ``inputs.NAME.topic`` [NAME], ``inputs.NAME.qos`` [``sensor_data``],
  ``inputs.NAME.extrinsics`` [[]] (6, 7 or 16 numbers, see :func:`params.parse_extrinsics`),
  ``inputs.NAME.range_min`` [0.0], ``inputs.NAME.range_max`` [inf] (user range filter),
  ``inputs.NAME.angle_min`` / ``angle_max`` (optional window, input frame, radians),
  ``inputs.NAME.min_height`` [-inf] / ``max_height`` [inf] (band in the output frame),
  ``inputs.NAME.timeout`` (optional, seconds; default ``timeout``),
  ``inputs.NAME.moving`` [false] (pose from ``/tf`` at every ray's time, see above),
  ``inputs.NAME.deskew`` [true] (a moving input's pose per ray, not one per scan);
* ``frame_id`` [``base_link``]: output frame; ``output_topic`` [``scan_merged``];
  ``output_qos`` [``sensor_data``];
* output grid: ``angle_min`` [-pi], ``angle_max`` [pi], ``angle_increment`` [0.25 deg in
  radians], ``range_min`` [0.0], ``range_max`` [inf], ``use_inf`` [true], ``inf_epsilon`` [1.0],
  ``intensities`` [true];
* synchronisation: ``slop`` [0.05] s, ``policy`` [``timeout``] (``wait``: every input needed;
  ``timeout``: inputs silent for longer than ``timeout`` [1.0] s are left out, so a dead sensor
  never blocks the output and stale data is never fused), ``reference`` [``newest``],
  ``queue_size`` [10];
* odometry: ``odometry_topic`` [""] ("" = none), ``odometry_qos`` [``reliable``],
  ``motion_compensation`` [true], ``odom_max_gap`` [0.25] s;
* ``use_tf`` [true]: read ``/tf`` and ``/tf_static`` for the mounts;
* moving inputs: ``tf_wait`` [0.1] s (how long a scan waits for ``/tf`` to cover its sweep),
  ``tf_tolerance`` [0.0] s (newest pose held that long; 0 = never beyond the newest);
* ``jump_back`` [1.0] s: an input whose *own* stamps go back by more than this, two scans in a
  row, had its clock reset (a looping recording, a simulator reset): that input starts a new
  timeline (its queue dropped, one log line) instead of every later scan being dropped as late
  (the odometry likewise). One stale or zero-stamped scan, or an input lagging behind the
  others, is never taken as a jump (it is dropped as late or merged as usual). 0 = never. The
  policy is :class:`converters.merger.LaserScanMerger`'s (``jump_back_ns``).

* ``allow_unknown_parameters`` [false]: an undeclared parameter (a typo) stops the node at
  start-up unless true.

``lidarscan-merger --help`` prints every parameter (one table, :func:`_specs`). Topics, QoS,
``input_names``, ``frame_id``, ``use_tf``, ``odometry_topic``, the inputs' extrinsics,
``moving``, ``tf_wait`` and ``tf_tolerance`` are read-only; the grid, limits, bands, windows,
``deskew`` and timing (slop, policy, timeouts, queue_size, jump_back, odometry options) may be
changed while running: a change is checked by its rule and by building
:class:`converters.merger.LaserScanMerger` with it (refused with the reason otherwise), then the
merger is rebuilt (queues restart). ``/diagnostics`` (1 Hz): output and per-input rates, drops,
silence and latency.

Behaviour: nothing is merged while nobody subscribes to the output (incoming scans are counted and
dropped); a malformed scan is dropped with one log line (rate-limited) and counted; Ctrl-C exits
cleanly.
"""

from __future__ import annotations

import functools
import math
import sys
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import numpy as np

from converters.edge.nodes.common import Guard, entry_points, kernels_status
from converters.edge.nodes.tf import extend_track
from lidarscan.errors import ConfigError, ConversionError, LidarScanError

__all__ = ["MergerCore", "main"]


class MergerCore:
    """The node's logic without rclpy: per-input mounts, (re)building the merger, pushing.

    Args:
        inputs: name -> keyword options of :class:`converters.merger.MergerInput` except
            ``extrinsics`` (order = tie order).
        fallback_extrinsics: name -> 4x4 used when ``resolve`` knows no transform (or None).
        resolve: ``(output frame, input frame) -> 4x4 | None`` (e.g. a TF lookup); None = none.
        tf_version: ``() -> int`` that changes when the transforms may have changed.
        jump_back_ns: :class:`converters.merger.LaserScanMerger`'s ``jump_back_ns``: an input
            whose own stamps go back by more than this, two scans in a row, starts a new
            timeline (a recording restarted, a simulator reset). None = never.
        on_event: called with one line per notable event (an input's time reset).
        moving: names of moving inputs (pose per ray from a :class:`converters.TransformTrack`
            filled by ``tf_samples``; see the module docstring).
        tf_samples: ``(output frame, input frame, after_ns) -> [(stamp_ns, 4x4), ...]``
            (:meth:`converters.edge.nodes.tf.TransformBuffer.samples`); required with ``moving``.
        tf_wait_ns: how long (data time) a moving input's scan waits for its poses.
        tf_tolerance_ns: the tracks' ``tolerance_ns`` (newest pose held that long).
        **output_options: keyword options of :class:`converters.merger.LaserScanMerger`
            (``frame_id`` included).
    """

    def __init__(self, inputs: Mapping[str, Mapping[str, Any]], *,
                 fallback_extrinsics: Mapping[str, Any] | None = None,
                 resolve: Callable[[str, str], Any] | None = None,
                 tf_version: Callable[[], int] | None = None,
                 jump_back_ns: int | None = 1_000_000_000,
                 on_event: Callable[[str], None] | None = None,
                 moving: Iterable[str] = (),
                 tf_samples: Callable[[str, str, int | None], Any] | None = None,
                 tf_wait_ns: int = 100_000_000, tf_tolerance_ns: int = 0,
                 **output_options: Any) -> None:
        from converters.shared.transforms import TransformTrack

        if not inputs:
            raise ConfigError("input_names", [], "at least one input")
        moving = list(moving)
        for name in moving:
            if name not in inputs:
                raise ConfigError("moving", name, f"one of the inputs {list(inputs)}")
        if moving and tf_samples is None:
            raise ConfigError(f"inputs.{moving[0]}.moving", True,
                              "use_tf true: a moving input's poses come from /tf")
        self.inputs = {name: dict(opts) for name, opts in inputs.items()}
        self.fallback = dict(fallback_extrinsics or {})
        self.resolve = resolve
        self.tf_version = tf_version or (lambda: 0)
        self.output_options = dict(output_options)
        self.frame_id = str(self.output_options.get("frame_id", "base_link"))
        # mounts known without a scan (fallback parameters) are used from the start
        self.extrinsics: dict[str, Any] = {
            n: None if self.fallback.get(n) is None else np.asarray(self.fallback[n], np.float64)
            for n in inputs}
        #: moving inputs: name -> TransformTrack (the merger's extrinsics for that input)
        self.tracks = {n: TransformTrack(name=f"{self.frame_id} <- input {n}",
                                         tolerance_ns=int(tf_tolerance_ns)) for n in moving}
        self.extrinsics.update(self.tracks)
        self.tf_samples = tf_samples
        self.tf_wait_ns = int(tf_wait_ns)
        self.frames: dict[str, str] = {}          # a moving input's frame (from its scans)
        self._waiting: dict[str, deque[Any]] = {n: deque() for n in moving}
        self._data_clock: int | None = None
        self._versions: dict[str, int | None] = {n: None for n in inputs}
        depth = int(self.output_options.get("queue_size", 10))
        self._recent: dict[str, deque[Any]] = {n: deque(maxlen=depth) for n in inputs}
        self._odometry: deque[Any] = deque(maxlen=200)
        self.last_output_ns: int | None = None
        self.jump_back_ns = jump_back_ns
        self.on_event = on_event or (lambda line: None)
        self.resets = 0
        self.merger: Any = None
        self.rebuilds = 0
        self._build()  # validates the options now (bad parameters fail at start)

    def _build(self) -> None:
        from converters.merger import LaserScanMerger, MergerInput

        configs = {}
        for name, opts in self.inputs.items():
            configs[name] = MergerInput(extrinsics=self.extrinsics[name], **opts)
        self.merger = LaserScanMerger(configs, jump_back_ns=self.jump_back_ns,
                                      **self.output_options)
        for odom in self._odometry:
            self.merger.push_odometry(odom)
        self.rebuilds += 1

    def _mount(self, name: str, frame: str) -> np.ndarray[Any, Any]:
        """output_frame <- frame: TF, else the fallback parameter, else identity if equal."""
        if self.resolve is not None:
            found = self.resolve(self.frame_id, frame)
            if found is not None:
                return np.asarray(found, dtype=np.float64)
        if self.fallback.get(name) is not None:
            return np.asarray(self.fallback[name], dtype=np.float64)
        if frame.lstrip("/") == self.frame_id.lstrip("/"):
            return np.eye(4)
        raise ConversionError(f"inputs.{name}", frame,
                              f"a transform {self.frame_id} <- {frame} on /tf or /tf_static, "
                              f"or the parameter inputs.{name}.extrinsics")

    def push(self, name: str, scan: Any) -> list[Any]:
        """Queue one LaserScan of input ``name``; returns the merged scans now ready (usually
        none or one).

        When the input's mount changes (first scan, new TF), the merger is rebuilt and the
        recent scans of every input are replayed into it; only outputs newer than the last one
        returned are returned, so nothing is emitted twice. Late, duplicate and jump-back scans
        are handled by the merger (:attr:`LaserScanMerger.last_drop`); a confirmed time reset
        of an input (``jump_back_ns``) is counted in :attr:`resets` and reported to
        ``on_event``.

        A moving input's scan waits (:meth:`update_tracks` releases it) until its track covers
        the sweep or ``tf_wait_ns`` has passed.

        Raises:
            LidarScanError: unknown input, malformed scan, or no pose for its frame.
        """
        from lidarscan.stamps import to_ns

        if name not in self.inputs:
            raise ConfigError("input", name, f"one of {list(self.inputs)}")
        stamp = to_ns(scan.header.stamp, field=f"{name}.header.stamp")
        self._tick(stamp)
        if name in self.tracks:
            frame = str(scan.header.frame_id).lstrip("/")
            if self.frames.get(name) != frame:       # first scan, or the frame changed
                self.frames[name] = frame
                self.tracks[name].clear()
                self._fill(name)
            self._waiting[name].append(scan)
            return self._release()
        return self._release() + self._push(name, scan)

    def _push(self, name: str, scan: Any) -> list[Any]:
        """:meth:`push` without the wait for a moving input's poses."""
        from lidarscan.stamps import to_ns

        version = self.tf_version()
        rebuilt = False
        if name not in self.tracks and (self.resolve is not None and
                                        self._versions[name] != version or
                                        self.extrinsics[name] is None):
            matrix = self._mount(name, str(scan.header.frame_id))
            self._versions[name] = version
            current = self.extrinsics[name]
            if current is None or not np.allclose(current, matrix, atol=1e-9):
                self.extrinsics[name] = matrix
                self._build()
                rebuilt = True
        if not rebuilt:
            merged = self.merger.push(name, scan)
            if self.merger.last_reset is not None:
                self._on_reset(*self.merger.last_reset)
            if self.merger.last_drop is None:
                self._recent[name].append(scan)
            if merged is None:
                return []
            self.last_output_ns = to_ns(merged.header.stamp)
            return [merged]
        self._recent[name].append(scan)
        replay = sorted(((to_ns(s.header.stamp), order, n, s)
                         for order, (n, queue) in enumerate(self._recent.items())
                         for s in queue), key=lambda item: (item[0], item[1]))
        out = []
        for _, _, n, s in replay:
            merged = self.merger.push(n, s)
            if merged is None:
                continue
            out_ns = to_ns(merged.header.stamp)
            if self.last_output_ns is None or out_ns > self.last_output_ns:  # not sent before
                self.last_output_ns = out_ns
                out.append(merged)
        return out

    def _tick(self, stamp: int) -> None:
        if self._data_clock is None or stamp > self._data_clock:
            self._data_clock = stamp

    def _fill(self, name: str) -> None:
        """Extend a moving input's track with the chained /tf samples newer than it holds."""
        frame = self.frames.get(name)
        if frame is None or self.tf_samples is None:
            return
        extend_track(self.tracks[name], self.tf_samples, self.frame_id, frame, self._tick)

    def update_tracks(self, cleared: bool = False) -> list[Any]:
        """New /tf arrived (``cleared``: its time jumped back and the buffer was cleared):
        extend the tracks, then release the waiting scans now covered (or waited long enough).
        Returns the merged scans now ready."""
        if cleared:
            self._data_clock = None              # a new timeline: wait afresh
        for name, track in self.tracks.items():
            if cleared:
                track.clear()
            self._fill(name)
        return self._release()

    def _release(self) -> list[Any]:
        """Push every waiting scan whose sweep the track covers, that can never be covered
        (older than the track), or that waited ``tf_wait_ns`` (oldest first per input)."""
        from lidarscan.stamps import to_ns

        out: list[Any] = []
        depth = int(self.output_options.get("queue_size", 10))
        for name, queue in self._waiting.items():
            track = self.tracks[name]
            while queue:
                scan = queue[0]
                stamp = to_ns(scan.header.stamp)
                end = stamp
                n = len(scan.ranges)
                inc = float(scan.time_increment)
                if self.inputs[name].get("deskew", True) and n > 1 and math.isfinite(inc):
                    end = stamp + round((n - 1) * inc * 1e9)
                lo, hi = min(stamp, end), max(stamp, end)
                span = track.span
                ready = span is not None and (
                    lo < span[0] or hi <= span[1] + track.tolerance_ns)
                waited = self._data_clock is not None and self._data_clock - hi > self.tf_wait_ns
                if not (ready or waited or len(queue) > depth):
                    break
                queue.popleft()
                out += self._push(name, scan)
        return out

    def reconfigure(self, inputs: Mapping[str, Mapping[str, Any]], *,
                    jump_back_ns: int | None, **output_options: Any) -> None:
        """New input and output options (same input names and output frame): the merger is
        rebuilt (queues restart, recent odometry replayed), mounts are kept. Validate first by
        building a throwaway :class:`MergerCore` with the same options.

        Raises:
            LidarScanError: options the merger refuses (nothing is changed then).
        """
        if list(inputs) != list(self.inputs):
            raise ConfigError("input_names", list(inputs), f"the inputs of the start "
                              f"{list(self.inputs)}")
        old = (self.inputs, self.output_options, self.jump_back_ns)
        self.inputs = {name: dict(opts) for name, opts in inputs.items()}
        self.output_options = {**dict(output_options), "frame_id": self.frame_id}
        self.jump_back_ns = jump_back_ns
        try:
            self._build()
        except LidarScanError:
            self.inputs, self.output_options, self.jump_back_ns = old
            raise
        depth = int(self.output_options.get("queue_size", 10))
        self._recent = {n: deque(q, maxlen=depth) for n, q in self._recent.items()}
        self.last_output_ns = None

    def _on_reset(self, name: str, old_ns: int, new_ns: int) -> None:
        """Input ``name`` jumped back to ``new_ns``: forget what the merger forgot."""
        from lidarscan.stamps import to_ns

        self.resets += 1
        self.on_event(f"input {name}: time jumped back {(old_ns - new_ns) / 1e9:.3f} s (2 scans "
                      "in a row): new timeline, its queued scans dropped")
        horizon = new_ns + int(self.jump_back_ns or 0)
        self._data_clock = new_ns
        self._recent[name].clear()
        for queue in self._recent.values():
            keep = [s for s in queue if to_ns(s.header.stamp) <= horizon]
            queue.clear()
            queue.extend(keep)
        self.last_output_ns = None

    def push_odometry(self, odom: Any) -> None:
        """Add an odometry sample (kept for replay after a rebuild).

        Raises:
            LidarScanError: malformed odometry.
        """
        self.merger.push_odometry(odom)
        self._odometry.append(odom)


# ------------------------------------------------------------------------------ parameters

def _specs() -> tuple[tuple[Any, ...], tuple[Any, ...]]:
    """(node parameters, per-input templates ``inputs.NAME.*``), from one table."""
    from converters.edge.nodes.params import QOS_NAMES, ParamSpec as S

    node = (
        S("input_names", (), "input names, in tie order (first wins equal ranges); required",
          kind="str_list", read_only=True),
        S("frame_id", "base_link", "output frame", read_only=True),
        S("output_topic", "scan_merged", "merged sensor_msgs/LaserScan topic", read_only=True),
        S("output_qos", "sensor_data", "QoS of the output", choices=QOS_NAMES, read_only=True),
        S("angle_min", -math.pi, "first bin, radians"),
        S("angle_max", math.pi, "last bin, radians"),
        S("angle_increment", math.radians(0.25), "bin width, radians", low=0.0),
        S("range_min", 0.0, "planar range min, metres", low=0.0),
        S("range_max", math.inf, "planar range max, metres", low=0.0),
        S("use_inf", True, "publish +Inf for no return (else range_max + inf_epsilon)"),
        S("inf_epsilon", 1.0, "see use_inf, metres", low=0.0),
        S("intensities", True, "publish intensities"),
        S("slop", 0.05, "scans within this many seconds of each other are fused", low=0.0),
        S("policy", "timeout", "timeout: inputs silent for longer than timeout are left out; "
          "wait: every input needed", choices=("timeout", "wait")),
        S("timeout", 1.0, "seconds of silence before an input counts as dead", low=0.0),
        S("reference", "newest", "output stamp: the newest or oldest of the fused set",
          choices=("newest", "oldest")),
        S("queue_size", 10, "scans queued per input", low=1, high=10_000),
        S("motion_compensation", True, "move scans to the output stamp by odometry"),
        S("odom_max_gap", 0.25, "largest odometry gap bridged, seconds", low=0.0),
        S("odometry_topic", "", "nav_msgs/Odometry topic ('' = none)", read_only=True),
        S("odometry_qos", "reliable", "QoS of the odometry", choices=QOS_NAMES,
          read_only=True),
        S("use_tf", True, "read /tf and /tf_static for the mounts", read_only=True),
        S("tf_wait", 0.1, "seconds (data time) a moving input's scan waits for /tf to cover "
          "its sweep", low=0.0, read_only=True),
        S("tf_tolerance", 0.0, "seconds a moving input's newest /tf pose is held (0 = never "
          "beyond it, as tf2)", low=0.0, read_only=True),
        S("jump_back", 1.0, "an input whose stamps go back by more than this (s), 2 scans in "
          "a row, starts a new timeline (0 = never)", low=0.0),
        S("allow_unknown_parameters", False, "start even with parameters this node does not "
          "know (a typo is otherwise an error)", read_only=True),
    )
    per_input = (
        S("inputs.NAME.topic", "", "input NAME: LaserScan topic ('' = NAME)", read_only=True),
        S("inputs.NAME.qos", "sensor_data", "input NAME: QoS", choices=QOS_NAMES,
          read_only=True),
        S("inputs.NAME.extrinsics", (), "input NAME: frame_id <- input frame when TF has none "
          "(6, 7 or 16 numbers)", kind="float_list", read_only=True),
        S("inputs.NAME.range_min", 0.0, "input NAME: user range filter min, metres", low=0.0),
        S("inputs.NAME.range_max", math.inf, "input NAME: user range filter max, metres",
          low=0.0),
        S("inputs.NAME.min_height", -math.inf, "input NAME: band min in the output frame, "
          "metres"),
        S("inputs.NAME.max_height", math.inf, "input NAME: band max, metres"),
        S("inputs.NAME.angle_min", None, "input NAME: window start, input frame, radians "
          "(optional)", kind="float"),
        S("inputs.NAME.angle_max", None, "input NAME: window end, radians (optional)",
          kind="float"),
        S("inputs.NAME.timeout", None, "input NAME: seconds (optional; default timeout)",
          kind="float", low=0.0),
        S("inputs.NAME.moving", False, "input NAME: its mount moves: pose from /tf at every "
          "ray's time", read_only=True),
        S("inputs.NAME.deskew", True, "input NAME (moving): one pose per ray at stamp + i * "
          "time_increment (false: one per scan)"),
    )
    return node, per_input


TOPICS = (("inputs.NAME.topic", "in  sensor_msgs/LaserScan", "one per input"),
          ("odometry_topic", "in  nav_msgs/Odometry", "optional"),
          ("/tf, /tf_static", "in  tf2_msgs/TFMessage", "when use_tf"),
          ("scan_merged", "out sensor_msgs/LaserScan", "output_topic, output_qos"),
          ("/diagnostics", "out diagnostic_msgs/DiagnosticArray", "1 Hz"))


def usage() -> str:
    """``lidarscan-merger --help``."""
    from converters.edge.nodes.params import help_text

    node, per_input = _specs()
    return help_text("lidarscan-merger", __doc__.split("\n\n")[0], TOPICS, node,
                     {"per input (for each NAME in input_names):": per_input},
                     "config/merger.yaml")


def settings(values: Mapping[str, Any]) -> dict[str, Any]:
    """:class:`MergerCore` arguments from checked parameter values: ``inputs``,
    ``fallback_extrinsics``, ``jump_back_ns``, ``options`` (LaserScanMerger's), ``topics``
    (name -> (topic, qos)), ``moving`` (names) and ``tf`` (``tf_wait_ns``,
    ``tf_tolerance_ns``).

    Raises:
        ConfigError: no or duplicate input names, bad extrinsics.
    """
    from converters.edge.nodes.params import parse_extrinsics

    names = [str(n) for n in values["input_names"]]
    if not names:
        raise ConfigError("input_names", [], "at least one input name")
    if len(set(names)) != len(names):
        raise ConfigError("input_names", names, "unique names")
    inputs: dict[str, dict[str, Any]] = {}
    fallback: dict[str, Any] = {}
    topics: dict[str, tuple[str, str]] = {}
    for n in names:
        p = f"inputs.{n}."
        cfg = {k: values[p + k] for k in ("range_min", "range_max", "min_height", "max_height",
                                          "deskew")}
        for key in ("angle_min", "angle_max"):
            if values.get(p + key) is not None:
                cfg[key] = values[p + key]
        if values.get(p + "timeout") is not None:
            cfg["timeout_ns"] = round(values[p + "timeout"] * 1e9)
        inputs[n] = cfg
        extr = values[p + "extrinsics"]
        fallback[n] = parse_extrinsics(extr, p + "extrinsics") if extr else None
        topics[n] = (values[p + "topic"] or n, values[p + "qos"])
    options = {k: values[k] for k in ("frame_id", "angle_min", "angle_max", "angle_increment",
                                      "range_min", "range_max", "use_inf", "inf_epsilon",
                                      "intensities", "policy", "reference", "queue_size",
                                      "motion_compensation")}
    options.update(slop_ns=round(values["slop"] * 1e9),
                   timeout_ns=round(values["timeout"] * 1e9),
                   odom_max_gap_ns=round(values["odom_max_gap"] * 1e9))
    jump = values["jump_back"]
    return {"inputs": inputs, "fallback_extrinsics": fallback, "options": options,
            "jump_back_ns": round(jump * 1e9) if jump > 0 else None, "topics": topics,
            "moving": [n for n in names if values[f"inputs.{n}.moving"]],
            "tf": {"tf_wait_ns": round(values["tf_wait"] * 1e9),
                   "tf_tolerance_ns": round(values["tf_tolerance"] * 1e9)}}


# ------------------------------------------------------------------------------------ node

@functools.cache
def _node_class() -> type:
    from rclpy.node import Node

    from converters.edge.nodes import params as P
    from converters.edge.nodes.common import (
        ERROR,
        WARN,
        Diagnostics,
        LatencyWindow,
        LogLimiter,
        RateMeter,
        Status,
    )
    from converters.edge.nodes.tf import TfListener, TransformBuffer, TransformLookupError

    class MergerNode(Node):
        """The rclpy node around :class:`MergerCore` (see the module docstring)."""

        def __init__(self, name: str = "lidarscan_merger", **kwargs: Any) -> None:
            super().__init__(name, **kwargs)
            self._log = LogLimiter(self.get_logger().warning)
            node_specs, per_input = _specs()
            values = P.declare_specs(self, node_specs)
            input_specs = [t.for_name(str(n)) for n in values["input_names"] for t in per_input]
            values.update(P.declare_specs(self, input_specs))
            P.refuse_unknown(self, values["allow_unknown_parameters"])
            config = settings(values)
            topics = config["topics"]
            frame_id = values["frame_id"]

            self.tf_buffer = TransformBuffer()

            def resolve(target: str, source: str) -> Any:
                try:
                    return self.tf_buffer.lookup(target, source)
                except TransformLookupError:
                    return None

            self.core = MergerCore(config["inputs"],
                                   fallback_extrinsics=config["fallback_extrinsics"],
                                   resolve=resolve if values["use_tf"] else None,
                                   tf_version=lambda: self.tf_buffer.version,
                                   jump_back_ns=config["jump_back_ns"],
                                   on_event=lambda line: self._log(line, "reset"),
                                   moving=config["moving"],
                                   tf_samples=self.tf_buffer.samples if values["use_tf"]
                                   else None, **config["tf"], **config["options"])
            self.guard = P.ParameterGuard(
                self, {s.name: s for s in (*node_specs, *input_specs)}, values,
                self._validate, self._apply)
            self.stats = {"received": 0, "bad": 0, "idle": 0, "published": 0, "odometry": 0,
                          "bad_odometry": 0}
            self.input_stats = {n: {"received": 0, "bad": 0} for n in topics}
            self._last_seen: dict[str, float] = {}

            from sensor_msgs.msg import LaserScan

            output_topic = values["output_topic"]
            self.pub = self.create_publisher(LaserScan, output_topic,
                                             P.qos_profile(values["output_qos"]))
            odom_topic = values["odometry_topic"]
            self._rates = RateMeter()
            self._latency = LatencyWindow()
            self._status = (Status, WARN, ERROR)
            self.diagnostics = Diagnostics(self, self._diagnose)
            self.get_logger().info(
                f"merging {', '.join(f'{n} ({self.resolve_topic_name(t)})' for n, (t, _) in topics.items())}"
                f" -> '{self.resolve_topic_name(output_topic)}' in '{frame_id}', policy "
                f"{values['policy']}" + (f", odometry '{odom_topic}'" if odom_topic else ""))
            # ready before listening (converters.edge.nodes.common): the merger's kernels from
            # numba's cache only (numpy while it lacks them), then the subscriptions
            from converters.edge.nodes.common import warm_up
            self.kernels: Any = None
            self.startup = warm_up(self, {"kernels": self._warm}, self.diagnostics,
                                   describe=self._kernels_line)
            self.tf_listener = TfListener(self, self.tf_buffer,
                                          on_error=lambda line: self._log(line, "tf"),
                                          on_message=self._on_tf) \
                if values["use_tf"] else None
            for n, (topic, qos) in topics.items():
                self.create_subscription(LaserScan, topic,
                                         functools.partial(self._on_scan, n),
                                         P.qos_profile(qos), raw=True)
            if odom_topic:
                from nav_msgs.msg import Odometry

                self.create_subscription(Odometry, odom_topic, self._on_odom,
                                         P.qos_profile(values["odometry_qos"]), raw=True)

        def _warm(self, config: dict[str, Any] | None = None) -> dict[str, Any]:
            """Load the merger's kernels (cache only); the options with the backend to use
            (``config``: :func:`settings` of new values; None: rebuild the running merger
            when the backend changes)."""
            from converters.warmup import prepare

            self.kernels = prepare(("merger",))
            options = {**(config or {}).get("options", self.core.output_options),
                       "backend": self.kernels.backend}
            if config is None and self.kernels.backend != "auto":
                self.core.reconfigure(dict(self.core.inputs), jump_back_ns=self.core.jump_back_ns,
                                      **options)
            return options

        def _kernels_line(self) -> tuple[str, dict[str, Any]]:
            """(log line, diagnostics values) of the kernels that run."""
            return kernels_status(self.kernels)

        # ------------------------------------------------------------------ parameters
        def _validate(self, values: dict[str, Any]) -> None:
            """Build LaserScanMerger and its MergerInputs with the candidate values."""
            config = settings(values)
            MergerCore(config["inputs"], jump_back_ns=config["jump_back_ns"],
                       **config["options"])

        def _apply(self, values: dict[str, Any], changed: set[str]) -> None:
            config = settings(values)
            self.core.reconfigure(config["inputs"], jump_back_ns=config["jump_back_ns"],
                                  **self._warm(config))
            self.get_logger().info(f"parameters changed: {', '.join(sorted(changed))} "
                                   "(merger rebuilt, its queues restart)")

        # ----------------------------------------------------------------- diagnostics
        def _diagnose(self) -> list[Any]:
            import time

            Status, WARN, ERROR = self._status
            counters = dict(self.stats)
            for n, st in self.input_stats.items():
                counters[f"{n}.received"] = st["received"]
                counters[f"{n}.bad"] = st["bad"]
            delta, dt = self._rates.update(counters)
            out = Status("output", {**{f"{k}_per_s": round(v / dt, 2) for k, v in delta.items()},
                                    **self.stats, "rebuilds": self.core.rebuilds,
                                    "dropped_no_pose":
                                        self.core.merger.stats["dropped_no_pose"],
                                    "resets": self.core.resets, **self._latency.take()})
            if delta["bad"]:
                out.worse(WARN, f"{delta['bad']} input scan(s) dropped in the last {dt:.1f} s")
            if delta["received"] and not delta["idle"] and not delta["published"]:
                out.worse(ERROR, "inputs arrive but nothing is merged (policy wait with a dead "
                          "input, or no pose for an input frame?)")
            now = time.monotonic()
            silent_after = max(self.core.output_options.get("timeout_ns", 10**9) / 1e9, 1.0)
            statuses = [out]
            for n in self.input_stats:
                seen = self._last_seen.get(n)
                st = Status(f"input {n}", {
                    "received_per_s": round(delta[f"{n}.received"] / dt, 2),
                    "dropped_last_period": delta[f"{n}.bad"],
                    "silent_s": round(now - seen, 2) if seen is not None else "never seen",
                    "mount_known": self.core.extrinsics[n] is not None and
                    (n not in self.core.tracks or len(self.core.tracks[n]) > 0)})
                if seen is None:
                    st.worse(WARN, "no scan received yet")
                elif now - seen > silent_after:
                    st.worse(WARN, f"silent for {now - seen:.1f} s (left out of the fusion)")
                if delta[f"{n}.bad"]:
                    st.worse(WARN, f"{delta[f'{n}.bad']} scan(s) dropped (see the log)")
                statuses.append(st)
            return statuses

        def _on_scan(self, name: str, raw: bytes) -> None:
            import time

            from lidarscan import decode

            self.stats["received"] += 1
            self.input_stats[name]["received"] += 1
            self._last_seen[name] = time.monotonic()
            if self.pub.get_subscription_count() == 0:
                self.stats["idle"] += 1
                return
            def bad(err: Exception) -> None:
                self.stats["bad"] += 1
                self.input_stats[name]["bad"] += 1

            with Guard(self._log, f"input {name}: scan dropped", bad=bad,
                       key=f"bad {name}") as guard:
                scan = decode(raw, "sensor_msgs/msg/LaserScan")
                ready = self.core.push(name, scan)
            if guard.failed:
                return
            self._publish(ready)

        def _publish(self, ready: list[Any]) -> None:
            from lidarscan.stamps import to_ns

            for merged in ready:
                self.pub.publish(merged)
                self.stats["published"] += 1
                self._latency.add(self.get_clock().now().nanoseconds -
                                  to_ns(merged.header.stamp))

        def _on_tf(self, cleared: bool) -> None:
            """New /tf: extend the moving inputs' tracks, publish what they release."""
            if not self.core.tracks:
                return
            with Guard(self._log, "moving input: scan dropped", bad=self._count_bad,
                       key="moving"):
                self._publish(self.core.update_tracks(cleared))

        def _on_odom(self, raw: bytes) -> None:
            from lidarscan import decode

            with Guard(self._log, "odometry dropped", bad=self._count_bad_odometry,
                       key="bad odometry"):
                self.core.push_odometry(decode(raw, "nav_msgs/msg/Odometry"))
                self.stats["odometry"] += 1

        def _count_bad(self, err: Exception) -> None:
            self.stats["bad"] += 1

        def _count_bad_odometry(self, err: Exception) -> None:
            self.stats["bad_odometry"] += 1

    return MergerNode


__getattr__, main = entry_points("MergerNode", _node_class, "lidarscan-merger", usage)


if __name__ == "__main__":
    sys.exit(main())
