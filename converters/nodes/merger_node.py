"""``lidarscan-merger``: N LaserScan inputs (+ optional odometry) -> one merged LaserScan.

Wraps :class:`converters.merger.LaserScanMerger` (read its docstring for the grid, fusion,
synchronisation and motion-compensation rules). Each input is a LaserScan topic with its own QoS:
a 2D lidar, or a slice published by ``lidarscan-converter``.

Input extrinsics (``frame_id <- input frame``) come from TF (``/tf_static``, ``/tf``, the newest
transform; mounts are assumed rigid) when available, else from ``inputs.NAME.extrinsics``, else
identity when the input's frame is the output frame. A scan whose pose is unknown is dropped with a
log line. When a mount changes (a new ``/tf_static``) the merger is rebuilt (its queues restart;
the recent odometry is replayed).

Parameters (defaults in brackets; ``config/merger.yaml`` is a complete example):

* ``input_names`` [[]] (required): names of the inputs, in tie order (first wins ties); per NAME:
  ``inputs.NAME.topic`` [NAME], ``inputs.NAME.qos`` [``sensor_data``],
  ``inputs.NAME.extrinsics`` [[]] (6, 7 or 16 numbers, see :func:`params.parse_extrinsics`),
  ``inputs.NAME.range_min`` [0.0], ``inputs.NAME.range_max`` [inf] (user range filter),
  ``inputs.NAME.angle_min`` / ``angle_max`` (optional window, input frame, radians),
  ``inputs.NAME.min_height`` [-inf] / ``max_height`` [inf] (band in the output frame),
  ``inputs.NAME.timeout`` (optional, seconds; default ``timeout``);
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
* ``jump_back`` [1.0] s: an input whose *own* stamps go back by more than this, two scans in a
  row, had its clock reset (a looping recording, a simulator reset): that input starts a new
  timeline (its queue dropped, one log line) instead of every later scan being dropped as late
  (the odometry likewise). One stale or zero-stamped scan, or an input lagging behind the
  others, is never taken as a jump (it is dropped as late or merged as usual). 0 = never. The
  policy is :class:`converters.merger.LaserScanMerger`'s (``jump_back_ns``).

Behaviour: nothing is merged while nobody subscribes to the output (incoming scans are counted and
dropped); a malformed scan is dropped with one log line (rate-limited) and counted; Ctrl-C exits
cleanly.
"""

from __future__ import annotations

import functools
import math
import sys
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from converters.nodes.common import entry_points
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
        **output_options: keyword options of :class:`converters.merger.LaserScanMerger`
            (``frame_id`` included).
    """

    def __init__(self, inputs: Mapping[str, Mapping[str, Any]], *,
                 fallback_extrinsics: Mapping[str, Any] | None = None,
                 resolve: Callable[[str, str], Any] | None = None,
                 tf_version: Callable[[], int] | None = None,
                 jump_back_ns: int | None = 1_000_000_000,
                 on_event: Callable[[str], None] | None = None,
                 **output_options: Any) -> None:
        if not inputs:
            raise ConfigError("input_names", [], "at least one input")
        self.inputs = {name: dict(opts) for name, opts in inputs.items()}
        self.fallback = dict(fallback_extrinsics or {})
        self.resolve = resolve
        self.tf_version = tf_version or (lambda: 0)
        self.output_options = dict(output_options)
        self.frame_id = str(self.output_options.get("frame_id", "base_link"))
        # mounts known without a scan (fallback parameters) are used from the start
        self.extrinsics: dict[str, np.ndarray[Any, Any] | None] = {
            n: None if self.fallback.get(n) is None else np.asarray(self.fallback[n], np.float64)
            for n in inputs}
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

        Raises:
            LidarScanError: unknown input, malformed scan, or no pose for its frame.
        """
        from lidarscan.stamps import to_ns

        if name not in self.inputs:
            raise ConfigError("input", name, f"one of {list(self.inputs)}")
        version = self.tf_version()
        rebuilt = False
        if self.resolve is not None and self._versions[name] != version or \
                self.extrinsics[name] is None:
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

    def _on_reset(self, name: str, old_ns: int, new_ns: int) -> None:
        """Input ``name`` jumped back to ``new_ns``: forget what the merger forgot."""
        from lidarscan.stamps import to_ns

        self.resets += 1
        self.on_event(f"input {name}: time jumped back {(old_ns - new_ns) / 1e9:.3f} s (2 scans "
                      "in a row): new timeline, its queued scans dropped")
        horizon = new_ns + int(self.jump_back_ns or 0)
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


# ------------------------------------------------------------------------------------ node

@functools.cache
def _node_class() -> type:
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from converters.nodes import params as P
    from converters.nodes.common import LogLimiter
    from converters.nodes.tf import TfListener, TransformBuffer, TransformLookupError

    class MergerNode(Node):
        """The rclpy node around :class:`MergerCore` (see the module docstring)."""

        def __init__(self, name: str = "lidarscan_merger", **kwargs: Any) -> None:
            super().__init__(name, **kwargs)
            self._log = LogLimiter(self.get_logger().warning)
            def d(n: str, v: Any, doc: str, **kw: Any) -> Any:
                return P.declare(self, n, v, doc, **kw)

            names = [str(n) for n in d("input_names", [], "input names (tie order)",
                                       type_name="string_array")]
            if not names:
                raise ConfigError("input_names", [], "at least one input name")
            if len(set(names)) != len(names):
                raise ConfigError("input_names", names, "unique names")
            frame_id = d("frame_id", "base_link", "output frame")
            output_topic = d("output_topic", "scan_merged", "merged LaserScan topic")
            output_qos = d("output_qos", "sensor_data", f"QoS of the output: {P.QOS_NAMES}")
            options: dict[str, Any] = {
                "frame_id": frame_id,
                "angle_min": float(d("angle_min", -math.pi, "first bin, radians")),
                "angle_max": float(d("angle_max", math.pi, "last bin, radians")),
                "angle_increment": float(d("angle_increment", math.radians(0.25),
                                           "bin width, radians")),
                "range_min": float(d("range_min", 0.0, "planar range min, metres")),
                "range_max": float(d("range_max", math.inf, "planar range max, metres")),
                "use_inf": bool(d("use_inf", True, "publish +Inf (else range_max + eps)")),
                "inf_epsilon": float(d("inf_epsilon", 1.0, "see use_inf, metres")),
                "intensities": bool(d("intensities", True, "publish intensities")),
                "slop_ns": round(float(d("slop", 0.05, "sync tolerance, s")) * 1e9),
                "policy": d("policy", "timeout", "'wait' or 'timeout'"),
                "timeout_ns": round(float(d("timeout", 1.0, "dead input after, s")) * 1e9),
                "reference": d("reference", "newest", "output stamp: 'newest' or 'oldest'"),
                "queue_size": int(d("queue_size", 10, "scans queued per input")),
                "motion_compensation": bool(d("motion_compensation", True,
                                              "move scans to the output stamp by odometry")),
                "odom_max_gap_ns": round(float(d("odom_max_gap", 0.25,
                                                 "largest odometry gap bridged, s")) * 1e9),
            }
            odom_topic = d("odometry_topic", "", "nav_msgs/Odometry topic ('' = none)")
            odom_qos = d("odometry_qos", "reliable", f"QoS of the odometry: {P.QOS_NAMES}")
            use_tf = bool(d("use_tf", True, "read /tf and /tf_static for the mounts"))

            inputs: dict[str, dict[str, Any]] = {}
            fallback: dict[str, Any] = {}
            topics: dict[str, tuple[str, str]] = {}
            for n in names:
                prefix = f"inputs.{n}."
                topic = d(prefix + "topic", n, f"input {n}: LaserScan topic")
                qos = d(prefix + "qos", "sensor_data", f"input {n}: QoS {P.QOS_NAMES}")
                extr = d(prefix + "extrinsics", [], f"input {n}: {frame_id} <- input frame",
                         type_name="double_array")
                cfg: dict[str, Any] = {
                    "range_min": float(d(prefix + "range_min", 0.0, f"input {n}: metres")),
                    "range_max": float(d(prefix + "range_max", math.inf, f"input {n}: metres")),
                    "min_height": float(d(prefix + "min_height", -math.inf,
                                          f"input {n}: band min, metres")),
                    "max_height": float(d(prefix + "max_height", math.inf,
                                          f"input {n}: band max, metres")),
                }
                for key in ("angle_min", "angle_max", "timeout"):
                    self.declare_parameter(prefix + key, Parameter.Type.DOUBLE)
                    value = self.get_parameter_or(prefix + key, Parameter(prefix + key)).value
                    if value is not None:
                        if key == "timeout":
                            cfg["timeout_ns"] = round(float(value) * 1e9)
                        else:
                            cfg[key] = float(value)
                inputs[n] = cfg
                fallback[n] = P.parse_extrinsics(extr, f"inputs.{n}.extrinsics") \
                    if extr else None
                topics[n] = (topic, qos)

            self.tf_buffer = TransformBuffer()
            self.tf_listener = TfListener(self, self.tf_buffer,
                                          on_error=lambda line: self._log(line, "tf")) \
                if use_tf else None

            def resolve(target: str, source: str) -> Any:
                try:
                    return self.tf_buffer.lookup(target, source)
                except TransformLookupError:
                    return None

            jump = float(d("jump_back", 1.0, "an input's stamps going back by more than this "
                           "(s), 2 scans in a row, start its new timeline (0 = never)"))
            self.core = MergerCore(inputs, fallback_extrinsics=fallback,
                                   resolve=resolve if use_tf else None,
                                   tf_version=lambda: self.tf_buffer.version,
                                   jump_back_ns=round(jump * 1e9) if jump > 0 else None,
                                   on_event=lambda line: self._log(line, "reset"), **options)
            self.stats = {"received": 0, "bad": 0, "idle": 0, "published": 0, "odometry": 0,
                          "bad_odometry": 0}

            from sensor_msgs.msg import LaserScan

            self.pub = self.create_publisher(LaserScan, output_topic,
                                             P.qos_profile(output_qos))
            for n, (topic, qos) in topics.items():
                self.create_subscription(LaserScan, topic,
                                         functools.partial(self._on_scan, n),
                                         P.qos_profile(qos), raw=True)
            if odom_topic:
                from nav_msgs.msg import Odometry

                self.create_subscription(Odometry, odom_topic, self._on_odom,
                                         P.qos_profile(odom_qos), raw=True)
            self.get_logger().info(
                f"merging {', '.join(f'{n} ({self.resolve_topic_name(t)})' for n, (t, _) in topics.items())}"
                f" -> '{self.resolve_topic_name(output_topic)}' in '{frame_id}', policy "
                f"{options['policy']}" + (f", odometry '{odom_topic}'" if odom_topic else ""))

        def _on_scan(self, name: str, raw: bytes) -> None:
            from lidarscan import decode

            self.stats["received"] += 1
            if self.pub.get_subscription_count() == 0:
                self.stats["idle"] += 1
                return
            try:
                scan = decode(raw, "sensor_msgs/msg/LaserScan")
                ready = self.core.push(name, scan)
            except LidarScanError as err:
                self.stats["bad"] += 1
                self._log(f"input {name}: scan dropped: {err}", f"bad {name}")
                return
            except Exception as err:  # noqa: BLE001 - a node must survive any input
                self.stats["bad"] += 1
                self._log(f"input {name}: scan dropped (internal error {type(err).__name__}: "
                          f"{err})", "internal")
                return
            for merged in ready:
                self.pub.publish(merged)
                self.stats["published"] += 1

        def _on_odom(self, raw: bytes) -> None:
            from lidarscan import decode

            try:
                self.core.push_odometry(decode(raw, "nav_msgs/msg/Odometry"))
                self.stats["odometry"] += 1
            except LidarScanError as err:
                self.stats["bad_odometry"] += 1
                self._log(f"odometry dropped: {err}", "bad odometry")

    return MergerNode


__getattr__, main = entry_points("MergerNode", _node_class, "lidarscan-merger")


if __name__ == "__main__":
    sys.exit(main())
