"""``lidarscan-converter``: LidarScan + LidarInfo -> PointCloud2 and LaserScan height slices.

Topics (relative names, remap with ``--ros-args -r scan:=/os/scan``):

========================  =====================================  ==============================
topic                     type                                   QoS
========================  =====================================  ==============================
``scan`` (in)             lidarscan_msgs/LidarScan               ``scan_qos`` (sensor data)
``lidar_info`` (in)       lidarscan_msgs/LidarInfo               ``info_qos`` (reliable,
                                                                 transient local = latched)
``/tf``, ``/tf_static``   tf2_msgs/TFMessage                     when ``target_frame`` is set
``points`` (out)          sensor_msgs/PointCloud2                ``output_qos``
``<slice topic>`` (out)   sensor_msgs/LaserScan, one per slice   ``output_qos``
========================  =====================================  ==============================

Parameters (defaults in brackets; ``config/converter.yaml`` is a complete example):

* ``scan_topic`` [``scan``], ``info_topic`` [``lidar_info``], ``cloud_topic`` [``points``];
* ``scan_qos`` [``sensor_data``], ``info_qos`` [``latched``], ``output_qos`` [``sensor_data``]:
  one of sensor_data, best_effort, reliable, latched (see :func:`params.qos_profile`);
* ``pointcloud2.enabled`` [true]; ``pointcloud2.preset`` [""] (a preset of
  :mod:`converters.pointcloud2`, "" = use ``pointcloud2.fields``); ``pointcloud2.fields``
  [x, y, z, intensity]; ``pointcloud2.organized`` [true]; ``pointcloud2.destagger`` [true]
  (these three apply without a preset; a preset uses its driver's fields, organisation and
  column order);
* ``slice_names`` [[]]: names of the LaserScan slices; for each NAME:
  ``slices.NAME.min_height`` and ``slices.NAME.max_height`` (required, metres in
  ``target_frame``, inclusive), ``slices.NAME.topic`` [``slices/NAME``], and optional
  ``slices.NAME.angle_min`` / ``angle_max`` / ``angle_increment`` (radians; default a full
  circle from -pi at the sensor's column resolution 2 pi / W) and ``range_min`` /
  ``range_max`` (metres, planar; default the LidarInfo's limits);
* ``slice_intensity_channel`` [``intensity``]: channel copied into the slices' intensities
  ("" = none; a scan without that channel gets empty intensities);
* ``slices_file`` [""]: a YAML file of more slices (``config/slices.yaml``);
* ``target_frame`` [""]: frame of the slices' heights and output; "" = the LidarInfo's frame.
  Use a frame that moves with the robot and has z up (``base_link``, ``base_footprint``): planar
  ranges are measured from its origin. The sensor pose comes from TF (``/tf_static``, ``/tf``)
  at the scan stamp when available, else from ``extrinsics``. A fixed mount costs nothing per
  scan (tables are built once per LidarInfo version and mount); a mount that moves (a TF that
  changes) rebuilds the slice tables for every scan;
* ``extrinsics`` [[]]: ``target_frame <- sensor`` as 6 (x y z roll pitch yaw), 7
  (x y z qx qy qz qw) or 16 (row-major 4x4) numbers; [] = identity;
* ``max_pending`` [16] scans held while their LidarInfo is missing, for at most
  ``max_wait`` [2.0] seconds.

Behaviour: no conversion work while no output has a subscriber (``get_subscription_count``);
a malformed, unlinked or inconsistent message is dropped with one log line (rate-limited) and
counted (``node.stats``), never fatal; Ctrl-C exits cleanly with status 0.
"""

from __future__ import annotations

import functools
import sys
from collections import OrderedDict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from converters.nodes.common import entry_points
from converters.nodes.params import SliceConfig, parse_extrinsics
from lidarscan.errors import ConfigError, LidarScanError

__all__ = ["ConverterCore", "ConverterStats", "main"]  # + ConverterNode (lazy, imports rclpy)


@dataclass
class ConverterStats:
    """Counters of a converter (read them in tests or expose them in diagnostics)."""

    scans_received: int = 0
    infos_received: int = 0
    scans_converted: int = 0
    scans_idle: int = 0          # skipped because nobody subscribed
    bad_messages: int = 0        # undecodable / invalid input
    scans_dropped: int = 0       # dropped by the linkage resolver (no/ambiguous/mismatching info)
    conversion_errors: int = 0   # a pair that failed to convert (e.g. no transform)
    clouds_published: int = 0
    slices_published: int = 0
    reasons: dict[str, int] = field(default_factory=dict)

    def count(self, reason: str) -> None:
        """Count a drop reason (bounded: at most 64 distinct reasons kept)."""
        key = reason.split(":", 1)[0][:80]
        if key in self.reasons or len(self.reasons) < 64:
            self.reasons[key] = self.reasons.get(key, 0) + 1


class ConverterCore:
    """The node's logic without rclpy: link scans to infos, convert pairs to output messages.

    Args:
        cloud_options: keyword options of :class:`converters.pointcloud2.PointCloud2Converter`.
        slices: the LaserScan slices.
        target_frame: frame of the slices ("" = the LidarInfo's frame); then :meth:`convert`
            needs the extrinsics ``target_frame <- sensor frame``.
        slice_options: common keyword options of :class:`converters.laserscan.SliceConverter`
            (e.g. ``intensity_channel``).
        max_pending, max_wait_ns: bounds of the linkage resolver.
        on_event: one line per notable event (drops, info changes).
    """

    def __init__(self, *, cloud_options: Mapping[str, Any] | None = None,
                 slices: Sequence[SliceConfig] = (), target_frame: str = "",
                 slice_options: Mapping[str, Any] | None = None, max_pending: int = 16,
                 max_wait_ns: int | None = 2_000_000_000,
                 on_event: Any = None) -> None:
        from lidarscan.linkage import InfoResolver

        self.stats = ConverterStats()
        self.cloud_options = dict(cloud_options or {})
        self.slices = list(slices)
        self.target_frame = target_frame
        self.slice_options = dict(slice_options or {})
        self._on_event = on_event or (lambda line: None)
        self.resolver = InfoResolver(max_pending=max_pending, max_wait_ns=max_wait_ns,
                                     on_event=self._resolver_event)
        self._clouds: OrderedDict[Any, Any] = OrderedDict()
        self._slicers: OrderedDict[Any, Any] = OrderedDict()

    def _resolver_event(self, line: str) -> None:
        self._on_event(line)

    def _collect_drops(self) -> None:
        for drop in self.resolver.take_dropped():
            self.stats.scans_dropped += 1
            self.stats.count(drop.reason)

    # ---------------------------------------------------------------------------- input
    def add_info(self, message: Any) -> list[tuple[Any, Any]]:
        """Add a LidarInfo (CDR bytes or a message); returns the scans it releases.

        Raises:
            LidarScanError: undecodable or invalid info (counted as a bad message).
        """
        from lidarscan import decode_info

        self.stats.infos_received += 1
        try:
            info = decode_info(message) if isinstance(message, (bytes, bytearray, memoryview)) \
                else message
            ready = self.resolver.add_info(info)
        except LidarScanError as err:
            self.stats.bad_messages += 1
            self.stats.count(f"bad LidarInfo: {err}")
            raise
        self._collect_drops()
        return ready

    def add_scan(self, message: Any) -> list[tuple[Any, Any]]:
        """Add a LidarScan (CDR bytes, decoded zero-copy, or a message); returns ready pairs.

        Raises:
            LidarScanError: undecodable scan (counted as a bad message).
        """
        from lidarscan import decode_scan

        self.stats.scans_received += 1
        try:
            scan = decode_scan(message) if isinstance(message, (bytes, bytearray, memoryview)) \
                else message
            ready = self.resolver.add_scan(scan)
        except LidarScanError as err:
            self.stats.bad_messages += 1
            self.stats.count(f"bad LidarScan: {err}")
            raise
        self._collect_drops()
        return ready

    def expire(self) -> None:
        """Drop scans that waited too long for their info (call periodically)."""
        self.resolver.expire()
        self._collect_drops()

    # -------------------------------------------------------------------------- convert
    def convert(self, scan: Any, info: Any, *, cloud: bool = True,
                slices: Iterable[str] | None = None,
                extrinsics: np.ndarray[Any, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        """Convert one linked pair.

        Args:
            scan, info: a pair released by :meth:`add_scan` / :meth:`add_info`.
            cloud: produce the PointCloud2.
            slices: names of the slices to produce (default all).
            extrinsics: 4x4 ``target_frame <- sensor`` for the slices; None: the slices are in
                the info's frame (only allowed when ``target_frame`` is "" or that frame).

        Returns:
            (PointCloud2 or None, {slice name: LaserScan}).

        Raises:
            LidarScanError: the converters refused the pair.
        """
        from lidarscan import channel_names
        from lidarscan.geometry import info_key

        key = info_key(info)
        out_cloud = None
        if cloud:
            converter = self._cached(self._clouds, key, lambda: self._make_cloud(info))
            out_cloud = converter.convert(scan)
        wanted = [s for s in self.slices if slices is None or s.name in set(slices)]
        out_slices: dict[str, Any] = {}
        if wanted:
            matrix = None if extrinsics is None else np.asarray(extrinsics, np.float64)
            names = tuple(s.name for s in wanted)
            intensity = self.slice_options.get("intensity_channel", "intensity")
            if intensity and intensity not in channel_names(scan):
                intensity = None  # e.g. a range-only scan: empty intensities, not an error
            slicer = self._cached(
                self._slicers,
                (key, names, None if matrix is None else matrix.tobytes(), intensity),
                lambda: self._make_slicer(info, wanted, matrix, intensity))
            out_slices = dict(slicer.convert(scan))
        self.stats.scans_converted += 1
        return out_cloud, out_slices

    @staticmethod
    def _cached(cache: OrderedDict[Any, Any], key: Any, build: Any, size: int = 4) -> Any:
        value = cache.get(key)
        if value is None:
            value = build()
            cache[key] = value
            while len(cache) > size:
                cache.popitem(last=False)
        else:
            cache.move_to_end(key)
        return value

    def _make_cloud(self, info: Any) -> Any:
        from converters.pointcloud2 import PointCloud2Converter

        return PointCloud2Converter(info, **self.cloud_options)

    def _make_slicer(self, info: Any, specs: Sequence[SliceConfig],
                     extrinsics: np.ndarray[Any, Any] | None, intensity: str | None) -> Any:
        from converters.laserscan import SliceConverter

        frame = self.target_frame or info.header.frame_id
        if extrinsics is None and frame != info.header.frame_id:
            raise ConfigError("extrinsics", None,
                              f"the pose of '{info.header.frame_id}' in '{frame}'")
        return SliceConverter(info, {s.name: s.spec() for s in specs},
                              extrinsics=extrinsics,
                              frame_id=frame if extrinsics is not None else None,
                              **{**self.slice_options, "intensity_channel": intensity})


# ------------------------------------------------------------------------------------ node

@functools.cache
def _node_class() -> type:
    from rclpy.node import Node

    from converters.nodes import params as P
    from converters.nodes.common import LogLimiter
    from converters.nodes.tf import TfListener, TransformBuffer, TransformLookupError

    class ConverterNode(Node):
        """The rclpy node around :class:`ConverterCore` (see the module docstring)."""

        def __init__(self, name: str = "lidarscan_converter", **kwargs: Any) -> None:
            super().__init__(name, **kwargs)
            log = self.get_logger()
            self._log = LogLimiter(log.warning)
            def d(n: str, v: Any, doc: str, **kw: Any) -> Any:
                return P.declare(self, n, v, doc, **kw)

            scan_topic = d("scan_topic", "scan", "input LidarScan topic")
            info_topic = d("info_topic", "lidar_info", "input LidarInfo topic (latched)")
            cloud_topic = d("cloud_topic", "points", "output PointCloud2 topic")
            scan_qos = d("scan_qos", "sensor_data", f"QoS of the scan input: {P.QOS_NAMES}")
            info_qos = d("info_qos", "latched", f"QoS of the info input: {P.QOS_NAMES}")
            output_qos = d("output_qos", "sensor_data", f"QoS of the outputs: {P.QOS_NAMES}")
            cloud_enabled = d("pointcloud2.enabled", True, "publish the PointCloud2")
            preset = d("pointcloud2.preset", "", "PointCloud2 field preset ('' = fields)")
            fields = d("pointcloud2.fields", ["x", "y", "z", "intensity"],
                       "PointCloud2 fields (when no preset)")
            organized = d("pointcloud2.organized", True, "H x W cloud with NaN for no return")
            destagger = d("pointcloud2.destagger", True, "destagger the organized cloud")
            names = d("slice_names", [], "LaserScan slice names", type_name="string_array")
            slices_file = d("slices_file", "", "YAML file with more slices")
            intensity = d("slice_intensity_channel", "intensity",
                          "channel copied into the slices' intensities ('' = none)")
            self.target_frame = d("target_frame", "", "frame of the slices ('' = sensor)")
            extrinsics = d("extrinsics", [], "target_frame <- sensor when TF has none",
                           type_name="double_array")
            max_pending = d("max_pending", 16, "scans held while their LidarInfo is missing")
            max_wait = d("max_wait", 2.0, "seconds a scan may wait for its LidarInfo")

            specs = [self._declare_slice(str(n)) for n in names]
            if slices_file:
                specs.extend(P.load_slices_file(slices_file))
            seen: set[str] = set()
            for spec in specs:
                if spec.name in seen:
                    raise ConfigError("slice_names", spec.name, "unique slice names")
                seen.add(spec.name)
            specs = [P.with_topic(s, "slices") for s in specs]
            self.fallback_extrinsics = parse_extrinsics(extrinsics)
            self._have_fallback = bool(extrinsics)
            cloud_options: dict[str, Any]
            if preset:  # a preset brings its driver's own layout, organisation and order
                cloud_options = {"preset": preset}
            else:
                cloud_options = {"organized": organized, "destagger": destagger,
                                 "fields": tuple(fields)}
            self.core = ConverterCore(cloud_options=cloud_options, slices=specs,
                                      target_frame=self.target_frame,
                                      slice_options={"intensity_channel": intensity or None},
                                      max_pending=int(max_pending),
                                      max_wait_ns=int(float(max_wait) * 1e9),
                                      on_event=lambda line: self._log(line, "linkage"))
            self.stats = self.core.stats

            from lidarscan_msgs.msg import LidarInfo, LidarScan
            from sensor_msgs.msg import LaserScan, PointCloud2

            out_qos = P.qos_profile(output_qos)
            self.cloud_pub = self.create_publisher(PointCloud2, cloud_topic, out_qos) \
                if cloud_enabled else None
            self.slice_pubs = {s.name: self.create_publisher(LaserScan, s.topic, out_qos)
                               for s in specs}
            self.create_subscription(LidarScan, scan_topic, self._on_scan,
                                     P.qos_profile(scan_qos), raw=True)
            self.create_subscription(LidarInfo, info_topic, self._on_info,
                                     P.qos_profile(info_qos), raw=True)
            self.tf_buffer = TransformBuffer()
            self.tf_listener = TfListener(self, self.tf_buffer,
                                          on_error=lambda line: self._log(line, "tf")) \
                if self.target_frame else None
            self._lookup_error = TransformLookupError
            self.create_timer(0.5, self.core.expire)
            log.info(f"converting '{self.resolve_topic_name(scan_topic)}' -> "
                     f"{'PointCloud2 ' + repr(cloud_topic) if cloud_enabled else 'no cloud'}"
                     f"{', slices ' + ', '.join(s.name + '->' + s.topic for s in specs) if specs else ''}"
                     f"; target frame {self.target_frame or '(sensor frame)'}")

        def _declare_slice(self, name: str) -> SliceConfig:
            from rclpy.parameter import Parameter

            prefix = f"slices.{name}."
            values: dict[str, Any] = {}
            for key in ("min_height", "max_height"):
                self.declare_parameter(prefix + key, Parameter.Type.DOUBLE)
                value = self.get_parameter_or(prefix + key, Parameter(prefix + key)).value
                if value is None:
                    raise ConfigError(prefix + key, None, "a height in metres (required)")
                values[key] = float(value)
            values["topic"] = P.declare(self, prefix + "topic", "", "output topic")
            for key in ("angle_min", "angle_max", "angle_increment", "range_min", "range_max"):
                self.declare_parameter(prefix + key, Parameter.Type.DOUBLE)
                value = self.get_parameter_or(prefix + key, Parameter(prefix + key)).value
                values[key] = None if value is None else float(value)
            return SliceConfig(name, **values)

        # ------------------------------------------------------------------- callbacks
        def _on_info(self, raw: bytes) -> None:
            try:
                ready = self.core.add_info(raw)
            except LidarScanError as err:
                self._log(f"bad LidarInfo ignored: {err}", "bad info")
                return
            self._publish(ready)

        def _on_scan(self, raw: bytes) -> None:
            want_cloud = self.cloud_pub is not None and \
                self.cloud_pub.get_subscription_count() > 0
            want_slices = [n for n, p in self.slice_pubs.items() if p.get_subscription_count()]
            if not want_cloud and not want_slices:
                self.stats.scans_idle += 1
                return
            try:
                ready = self.core.add_scan(raw)
            except LidarScanError as err:
                self._log(f"bad LidarScan #{self.stats.scans_received} ignored: {err}",
                          "bad scan")
                return
            self._publish(ready, want_cloud, want_slices)

        def _publish(self, pairs: list[tuple[Any, Any]], want_cloud: bool | None = None,
                     want_slices: list[str] | None = None) -> None:
            if not pairs:
                return
            if want_cloud is None:
                want_cloud = self.cloud_pub is not None and \
                    self.cloud_pub.get_subscription_count() > 0
            if want_slices is None:
                want_slices = [n for n, p in self.slice_pubs.items()
                               if p.get_subscription_count()]
            if not want_cloud and not want_slices:
                self.stats.scans_idle += len(pairs)
                return
            for scan, info in pairs:
                try:
                    extrinsics = self._extrinsics(scan, info) if want_slices else None
                    cloud, slices = self.core.convert(scan, info, cloud=want_cloud,
                                                      slices=want_slices, extrinsics=extrinsics)
                except LidarScanError as err:
                    self.stats.conversion_errors += 1
                    self.stats.count(f"conversion: {err}")
                    self._log(f"scan not converted: {err}", "conversion")
                    continue
                except Exception as err:  # noqa: BLE001 - a node must survive any input
                    self.stats.conversion_errors += 1
                    self.stats.count(f"internal: {type(err).__name__}")
                    self._log(f"scan not converted (internal error {type(err).__name__}: "
                              f"{err})", "internal")
                    continue
                if cloud is not None and self.cloud_pub is not None:
                    self.cloud_pub.publish(cloud)
                    self.stats.clouds_published += 1
                for name, msg in slices.items():
                    self.slice_pubs[name].publish(msg)
                    self.stats.slices_published += 1

        def _extrinsics(self, scan: Any, info: Any) -> np.ndarray[Any, Any] | None:
            """target_from_sensor: TF at the scan stamp, else the parameter, else identity."""
            if not self.target_frame:
                return None
            from lidarscan.stamps import to_ns

            source = info.header.frame_id
            try:
                return self.tf_buffer.lookup(self.target_frame, source,
                                             to_ns(scan.header.stamp))
            except self._lookup_error as err:
                if self._have_fallback:
                    return self.fallback_extrinsics
                raise self._lookup_error(
                    "target_frame", self.target_frame,
                    f"a transform {self.target_frame} <- {source} on /tf or /tf_static, or the "
                    f"'extrinsics' parameter ({err})") from err

    return ConverterNode


__getattr__, main = entry_points("ConverterNode", _node_class, "lidarscan-converter")


if __name__ == "__main__":
    sys.exit(main())
