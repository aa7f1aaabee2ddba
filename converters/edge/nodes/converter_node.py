"""``lidarscan-converter``: LidarScan + LidarInfo -> PointCloud2 and LaserScan height slices.

Topics (relative names, remap with ``--ros-args -r lidar_scan:=/os/lidar_scan``):

========================  =====================================  ==============================
topic                     type                                   QoS
========================  =====================================  ==============================
``lidar_scan`` (in)       lidarscan_msgs/LidarScan               ``scan_qos`` (sensor data)
``lidar_info`` (in)       lidarscan_msgs/LidarInfo               ``info_qos`` (reliable,
                                                                 transient local = latched)
``/tf``, ``/tf_static``   tf2_msgs/TFMessage                     when ``target_frame`` is set
``points`` (out)          sensor_msgs/PointCloud2                ``output_qos``
``<slice topic>`` (out)   sensor_msgs/LaserScan, one per slice   ``output_qos``
``/diagnostics`` (out)    diagnostic_msgs/DiagnosticArray        1 Hz: rates, drops, latency,
                                                                 linkage state, start-up
``depth/image_rect`` (in) sensor_msgs/Image                      ``depth.qos``, when
``depth/camera_info`` in  sensor_msgs/CameraInfo                 ``depth.enabled``
``depth/slices/NAME``     sensor_msgs/LaserScan, one per slice   ``output_qos``
``depth/lidar_scan``,     lidarscan_msgs/LidarScan, LidarInfo    ``depth.publish_scan``
``depth/lidar_info``                                             (the info latched)
``/ouster/lidar_packets`` ouster_sensor_msgs/PacketMsg           ``ouster.qos``, when
``/ouster/metadata`` (in) std_msgs/String (sensor JSON)          ``ouster.enabled`` (latched)
``ouster/lidar_scan``,    lidarscan_msgs/LidarScan, LidarInfo    ``ouster.enabled``
``ouster/lidar_info``                                            (the info latched)
========================  =====================================  ==============================

(``scan`` is left to sensor_msgs/LaserScan, as everywhere else in ROS.)

Parameters (defaults in brackets; ``config/converter.yaml`` is a complete example):

* ``scan_topic`` [``lidar_scan``], ``info_topic`` [``lidar_info``], ``cloud_topic`` [``points``];
* ``scan_qos`` [``sensor_data``], ``info_qos`` [``latched``], ``output_qos`` [``sensor_data``]:
  one of sensor_data, best_effort, reliable, latched (see :func:`params.qos_profile`);
* ``pointcloud2.enabled`` [true]; ``pointcloud2.preset`` [""] (a preset of
  :mod:`converters.pointcloud2.converter`, "" = use ``pointcloud2.fields``); ``pointcloud2.fields``
  [x, y, z, intensity]; ``pointcloud2.organized`` [true]; ``pointcloud2.destagger`` [true]
  (these three apply without a preset; a preset uses its driver's fields, organisation and
  column order);
* ``slice_names`` [[]]: names of the LaserScan slices; for each NAME:
  ``slices.NAME.min_height`` and ``slices.NAME.max_height`` (required, metres in
  ``target_frame``, inclusive), ``slices.NAME.topic`` [``slices/NAME``], and optional
  ``slices.NAME.angle_min`` / ``angle_max`` / ``angle_increment`` (radians; default a full
  circle from -pi at the sensor's column resolution 2 pi / W) and ``range_min`` /
  ``range_max`` (metres, planar; default the LidarInfo's limits); hole detection (negative
  obstacles, :mod:`converters.slices.converter`): ``slices.NAME.holes`` [false],
  ``floor_height`` [0.0] (metres in ``target_frame``), ``hole_depth`` [0.05],
  ``hole_range_max`` (metres, planar; default the slice's ``range_max``) and
  ``hole_no_return`` [true];
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
* ``moving`` [false]: the sensor's mount moves during a sweep (below); ``tf_wait`` [0.1] s:
  how long (data time) a scan waits for ``/tf`` to cover its sweep; ``tf_tolerance`` [0.0] s:
  how long the newest ``/tf`` pose is held past its stamp (0 = never beyond the newest);
* ``max_pending`` [16] scans held while their LidarInfo is missing (also the least depth of
  the scan subscription's queue, fixed at the start: scans that arrive while a new LidarInfo's
  tables are built wait there; under reliable QoS none is dropped), for at most
  ``max_wait`` [2.0] seconds; ``info_wait`` [1.0] s: how long the start waits for a latched
  LidarInfo before subscribing to the scans (its tables are built first); ``max_infos`` [8] LidarInfo versions kept pairable (see
  :mod:`lidarscan.linkage` for what happens to older ones: dropped, never mispaired);
* ``allow_unknown_parameters`` [false]: a parameter this node does not declare (a typo such as
  ``target_fram``) stops it at start-up with the list and a suggestion, unless true;
* ``depth.*``: a depth camera input (below).

**Moving mount** (``moving: true``, needs ``target_frame``; a lidar on a pan unit, an arm or a
nodding head): the slices' extrinsics are a :class:`converters.TransformTrack` ``target_frame <-
scan frame`` filled from ``/tf`` (each time a dynamic transform of the chain arrives, the chained
transform at its stamp is added; static edges compose in,
:meth:`converters.edge.nodes.tf.TransformBuffer.samples`), looked up at every pixel's time
(:mod:`converters.slices.converter`, **Moving mounts**: interpolated, linear translation and slerp,
never extrapolated), as the merger's moving inputs do. ``/tf`` usually arrives a little after a
sweep ends, so a linked scan is held until the track covers its whole sweep (first to last
pixel time), for at most ``tf_wait`` seconds of data time past its last pixel (the newest scan
or pose stamp seen) and at most ``max_pending`` scans; one that is still not covered then, or
whose sweep starts before the oldest pose kept, is dropped: one log line, counted
(``dropped_no_pose``, reason ``no pose``) and reported by the ``moving mount`` diagnostics
status (also the number held). A drop loses the scan's slices only: its PointCloud2 (in the
sensor frame, it needs no pose) is published when the scan arrives, and nothing is held while
no slice has a subscriber. ``tf_tolerance`` [0.0] s holds the newest pose that long past its
stamp (as the merger's: a pixel time up to that far after the newest pose gets the newest pose,
never an extrapolated one; 0 = strict, as tf2), so a sweep that ends a little after the newest
/tf is released at once instead of waiting for the next /tf; a sweep that starts before the
oldest pose kept gets no tolerance (dropped at once, as above). The ``extrinsics`` parameter is
not used. The chain
must contain a ``/tf`` (dynamic) edge: a mount known only from ``/tf_static`` gives no poses
(every scan dropped); leave ``moving`` false for it. ``moving`` false (the default) is the
fixed-mount path above, unchanged.

Depth camera (``depth.enabled`` [false], needs ``target_frame``): ``sensor_msgs/Image``
(``depth.image_topic`` [``depth/image_rect``], 16UC1 millimetres or 32FC1 metres) and its
``sensor_msgs/CameraInfo`` (``depth.camera_info_topic`` [``depth/camera_info``]) are paired by
identical header stamps, as message_filters' ExactTime policy does
(:class:`converters.edge.nodes.common.ExactSync`: ``depth.sync_queue`` [10] messages kept per input,
unpaired ones dropped and counted in the ``depth`` diagnostics). Each pair becomes a LidarScan
(:class:`converters.sources.depth.DepthImageConverter`: one ray per pixel, ``depth.rectified``
[auto], ``depth.no_measurement`` [invalid], ``depth.range_min`` / ``depth.range_max`` [0 = none])
and is sliced with the slices of ``slice_names`` in ``target_frame``, published on
``<depth.slice_namespace>/NAME`` [``depth/slices/NAME``]; the camera's pose comes from TF at the
image stamp, else ``depth.extrinsics``. ``depth.publish_scan`` [false] also publishes the
LidarScan and the latched LidarInfo. A new CameraInfo content rebuilds the rays and the slice
tables when it arrives, before the image that needs them (:mod:`converters.edge.nodes.depth_input`).

Ouster packets (``ouster.enabled`` [false]; needs ouster-ros's ``ouster_sensor_msgs``): the
packets and metadata ouster-ros publishes are decoded into LidarScan + LidarInfo (published on
``ouster.scan_topic`` / ``ouster.info_topic``) and converted like the scans of ``scan_topic``
(:mod:`converters.edge.nodes.ouster_input`).

Ready before listening: the node loads every kernel its configuration will call from numba's
cache (no compiler runs: when the cache lacks one, the C kernels and numpy run and the cache is
filled in the background, :mod:`converters.warmup`), logs ``ready: warm-up ... ms; kernels:
...`` (the backends that run; also in the ``startup`` status), subscribes to the LidarInfo and
waits up to ``info_wait`` for the latched one (building its converters and tables), and only
then subscribes to the scans: a driver that starts publishing when the subscription matches
meets a ready node. A later LidarInfo version's tables are built when it arrives, before its
first scan is converted (scans that arrive meanwhile wait in the reader's queue or the linkage,
not dropped), so the first scans cost about what the next ones cost (bench/bench_startup.py,
bench/bench_first_scans.py).

``lidarscan-converter --help`` prints every parameter with its default, rule and description
(from the one table in :func:`_specs`) without starting ROS. Topics, QoS, ``slice_names``,
``slices.NAME.topic``, ``slices_file``, ``target_frame``, ``moving``, ``tf_wait``,
``tf_tolerance`` and ``pointcloud2.enabled`` are read-only (a restart is needed); the others may be changed while
running (``ros2 param set``): each change is checked by the parameter's rule and then by
building the converters with it (:meth:`ConverterCore.check`), and refused with the reason
otherwise; an accepted change applies from the next scan.

Behaviour: no conversion work while no output has a subscriber (``get_subscription_count``);
a malformed, unlinked or inconsistent message is dropped with one log line (rate-limited) and
counted (``node.stats``), never fatal; Ctrl-C exits cleanly with status 0.
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from converters.edge.nodes.common import entry_points, kernels_status
from converters.edge.nodes.converter_core import ConverterCore, ConverterStats
from converters.edge.nodes.depth_input import depth_options  # noqa: F401 - its old home
from converters.edge.nodes.ouster_input import ouster_specs
from converters.edge.nodes.params import SliceConfig, parse_extrinsics
from converters.shared.options import HOLE_KEYS
from lidarscan.errors import ConfigError

__all__ = ["ConverterCore", "ConverterStats", "main"]  # + ConverterNode (lazy, imports rclpy);
# ConverterCore and ConverterStats live in converters.edge.nodes.converter_core (re-exported here)


def _specs() -> tuple[tuple[Any, ...], tuple[Any, ...]]:
    """(node parameters, per-slice templates ``slices.NAME.*``), from one table."""
    from converters.edge.nodes.params import QOS_NAMES, ParamSpec as S

    node = (
        S("scan_topic", "lidar_scan", "input lidarscan_msgs/LidarScan topic", read_only=True),
        S("info_topic", "lidar_info", "input lidarscan_msgs/LidarInfo topic (latched)",
          read_only=True),
        S("cloud_topic", "points", "output sensor_msgs/PointCloud2 topic", read_only=True),
        S("scan_qos", "sensor_data", "QoS of the scan input", choices=QOS_NAMES, read_only=True),
        S("info_qos", "latched", "QoS of the info input (the publisher must be latched too)",
          choices=QOS_NAMES, read_only=True),
        S("output_qos", "sensor_data", "QoS of the outputs", choices=QOS_NAMES, read_only=True),
        S("pointcloud2.enabled", True, "publish the PointCloud2", read_only=True),
        S("pointcloud2.preset", "", "PointCloud2 preset of converters.pointcloud2.converter ('' = use "
          "pointcloud2.fields)"),
        S("pointcloud2.fields", ("x", "y", "z", "intensity"),
          "PointCloud2 fields (when no preset)", kind="str_list"),
        S("pointcloud2.organized", True, "H x W cloud with NaN points for no return (no preset)"),
        S("pointcloud2.destagger", True, "destagger the organized cloud (no preset)"),
        S("slice_names", (), "names of the LaserScan slices (one slices.NAME block each)",
          kind="str_list", read_only=True),
        S("slices_file", "", "YAML file with more slices (config/slices.yaml)", read_only=True),
        S("slice_intensity_channel", "intensity",
          "channel copied into the slices' intensities ('' = none)"),
        S("target_frame", "", "frame of the slices' heights and output ('' = the LidarInfo's "
          "frame); z up, moving with the robot", read_only=True),
        S("extrinsics", (), "target_frame <- sensor when TF has none: 6 (x y z roll pitch "
          "yaw), 7 (x y z qx qy qz qw) or 16 numbers; [] = identity", kind="float_list"),
        S("moving", False, "the sensor's mount moves (pan unit, arm): slices use its pose in "
          "target_frame from /tf at every pixel's time; a scan waits tf_wait for /tf to cover "
          "its sweep, else it is dropped and counted", read_only=True),
        S("tf_wait", 0.1, "seconds (data time) a scan of a moving mount waits for /tf to cover "
          "its sweep", low=0.0, high=60.0, read_only=True),
        S("tf_tolerance", 0.0, "seconds a moving mount's newest /tf pose is held past its stamp "
          "(0 = never beyond the newest; never extrapolated)", low=0.0, high=60.0,
          read_only=True),
        S("max_pending", 16, "scans held while their LidarInfo is missing", low=0,
          high=100_000),
        S("max_wait", 2.0, "seconds a scan may wait for its LidarInfo", low=0.0, high=3600.0),
        S("info_wait", 1.0, "seconds the node waits at its start for a latched LidarInfo, so "
          "that its tables exist before it subscribes to the scans (0 = do not wait)",
          low=0.0, high=60.0, read_only=True),
        S("max_infos", 8, "LidarInfo versions kept pairable (older ones: scans dropped)",
          low=1, high=1024),
        S("allow_unknown_parameters", False, "start even with parameters this node does not "
          "know (a typo is otherwise an error)", read_only=True),
        *_depth_specs(S, QOS_NAMES),
        *ouster_specs(S, QOS_NAMES),
    )
    per_slice = (
        S("slices.NAME.min_height", None, "slice NAME: lowest z in target_frame, metres "
          "(required)", kind="float"),
        S("slices.NAME.max_height", None, "slice NAME: highest z, metres (required)",
          kind="float"),
        S("slices.NAME.topic", "", "slice NAME: output topic ('' = slices/NAME)",
          read_only=True),
        S("slices.NAME.angle_min", None, "slice NAME: first bin, radians (default -pi)",
          kind="float"),
        S("slices.NAME.angle_max", None, "slice NAME: last bin, radians (default a full "
          "circle)", kind="float"),
        S("slices.NAME.angle_increment", None, "slice NAME: bin width, radians (default 2 pi "
          "/ W)", kind="float", low=0.0),
        S("slices.NAME.range_min", None, "slice NAME: planar range min, metres (default the "
          "LidarInfo's)", kind="float", low=0.0),
        S("slices.NAME.range_max", None, "slice NAME: planar range max, metres (default the "
          "LidarInfo's)", kind="float", low=0.0),
        S("slices.NAME.holes", False, "slice NAME: report holes (a drop below the floor) as "
          "obstacles at their edge"),
        S("slices.NAME.floor_height", None, "slice NAME: z of the floor in target_frame, "
          "metres (default 0)", kind="float"),
        S("slices.NAME.hole_depth", None, "slice NAME: a point this far below the floor or "
          "more is in a hole, metres > 0 (default 0.05)", kind="float", low=0.0),
        S("slices.NAME.hole_range_max", None, "slice NAME: farthest hole edge reported, "
          "metres, planar (default the slice's range_max)", kind="float", low=0.0),
        S("slices.NAME.hole_no_return", True, "slice NAME: a ray with no return that crosses "
          "the floor is a hole too"),
    )
    return node, per_slice


def _depth_specs(S: Any, qos_names: tuple[str, ...]) -> tuple[Any, ...]:  # noqa: N803
    """Parameters of the depth-image input (``depth.*``), built with ``S`` = ParamSpec."""
    return (
        S("depth.enabled", False, "also slice a depth camera: sensor_msgs/Image + CameraInfo "
          "paired by identical stamps (needs target_frame)", read_only=True),
        S("depth.image_topic", "depth/image_rect", "input depth image (16UC1 mm or 32FC1 m, "
          "REP 118)", read_only=True),
        S("depth.camera_info_topic", "depth/camera_info", "input CameraInfo of the depth image",
          read_only=True),
        S("depth.qos", "sensor_data", "QoS of both depth inputs", choices=qos_names,
          read_only=True),
        S("depth.slice_namespace", "depth/slices", "the depth slices are published on "
          "<slice_namespace>/NAME for every NAME of slice_names", read_only=True),
        S("depth.publish_scan", False, "also publish the depth LidarScan and its latched "
          "LidarInfo", read_only=True),
        S("depth.scan_topic", "depth/lidar_scan", "output LidarScan of the depth image",
          read_only=True),
        S("depth.info_topic", "depth/lidar_info", "output LidarInfo of the depth camera "
          "(latched)", read_only=True),
        S("depth.rectified", "auto", "camera model: true = image_rect (P, R), false = "
          "image_raw (K, D), auto = decided from the CameraInfo when unambiguous",
          choices=("auto", "true", "false")),
        S("depth.no_measurement", "invalid", "range of a pixel without a depth (0 or NaN): "
          "invalid (NaN, REP 117) or no_return (+Inf: costmaps clear through it)",
          choices=("invalid", "no_return")),
        S("depth.range_min", 0.0, "nearest valid range along the ray, metres (0 = none)",
          low=0.0, high=1000.0),
        S("depth.range_max", 0.0, "farthest valid range along the ray, metres (0 = none)",
          low=0.0, high=1000.0),
        S("depth.extrinsics", (), "target_frame <- camera optical frame when TF has none: 6, "
          "7 or 16 numbers as extrinsics; [] = use TF only", kind="float_list"),
        S("depth.sync_queue", 10, "images and CameraInfos each kept while waiting for the "
          "partner with the same stamp (older ones dropped and counted)", low=1, high=1000),
    )


TOPICS = (("lidar_scan", "in  lidarscan_msgs/LidarScan", "scan_topic, scan_qos"),
          ("lidar_info", "in  lidarscan_msgs/LidarInfo", "info_topic, latched"),
          ("/tf, /tf_static", "in  tf2_msgs/TFMessage", "when target_frame is set"),
          ("points", "out sensor_msgs/PointCloud2", "cloud_topic, output_qos"),
          ("slices/NAME", "out sensor_msgs/LaserScan", "one per slice"),
          ("depth/image_rect", "in  sensor_msgs/Image", "depth.enabled; exact stamp sync"),
          ("depth/camera_info", "in  sensor_msgs/CameraInfo", "depth.enabled"),
          ("depth/slices/NAME", "out sensor_msgs/LaserScan", "one per slice (depth)"),
          ("depth/lidar_scan", "out lidarscan_msgs/LidarScan", "depth.publish_scan"),
          ("depth/lidar_info", "out lidarscan_msgs/LidarInfo", "depth.publish_scan, latched"),
          ("/ouster/lidar_packets", "in  ouster_sensor_msgs/PacketMsg", "ouster.enabled"),
          ("/ouster/metadata", "in  std_msgs/String", "ouster.enabled, latched"),
          ("ouster/lidar_scan", "out lidarscan_msgs/LidarScan", "ouster.enabled"),
          ("ouster/lidar_info", "out lidarscan_msgs/LidarInfo", "ouster.enabled, latched"),
          ("/diagnostics", "out diagnostic_msgs/DiagnosticArray", "1 Hz"))


def usage() -> str:
    """``lidarscan-converter --help``."""
    from converters.edge.nodes.params import help_text

    node, per_slice = _specs()
    return help_text("lidarscan-converter", __doc__.split("\n\n")[0], TOPICS, node,
                     {"per slice (for each NAME in slice_names):": per_slice},
                     "config/converter.yaml")


def settings(values: Mapping[str, Any], extra_slices: Sequence[SliceConfig] = ()
             ) -> dict[str, Any]:
    """Keyword arguments of :class:`ConverterCore` (+ ``extrinsics``) from checked parameter
    values (name -> value, as :meth:`ParamSpec.check` returns them).

    Raises:
        ConfigError: a slice without heights, duplicate slice names, bad extrinsics.
    """
    from converters.edge.nodes.params import with_topic

    specs = []
    for name in values["slice_names"]:
        prefix = f"slices.{name}."
        kw = {k: values.get(prefix + k) for k in ("min_height", "max_height", "angle_min",
                                                  "angle_max", "angle_increment", "range_min",
                                                  "range_max")}
        for key in ("min_height", "max_height"):
            if kw[key] is None:
                raise ConfigError(prefix + key, None, "a height in metres (required)")
        holes = {k: values.get(prefix + k) for k in HOLE_KEYS}
        specs.append(SliceConfig(str(name), topic=values.get(prefix + "topic", ""),
                                 extra={k: v for k, v in holes.items() if v is not None}, **kw))
    specs.extend(extra_slices)
    seen: set[str] = set()
    for spec in specs:
        if spec.name in seen:
            raise ConfigError("slice_names", spec.name, "unique slice names")
        seen.add(spec.name)
    preset = values["pointcloud2.preset"]
    cloud_options: dict[str, Any] = {"preset": preset} if preset else {
        "organized": values["pointcloud2.organized"],
        "destagger": values["pointcloud2.destagger"],
        "fields": tuple(values["pointcloud2.fields"])}
    return {"cloud_options": cloud_options, "slices": [with_topic(s, "slices") for s in specs],
            "target_frame": values["target_frame"],
            "slice_options": {"intensity_channel": values["slice_intensity_channel"] or None},
            "max_pending": values["max_pending"], "max_infos": values["max_infos"],
            "max_wait_ns": round(values["max_wait"] * 1e9),
            "extrinsics": parse_extrinsics(values["extrinsics"])}


def probe_info(info: Any = None) -> Any:
    """The info a configuration is checked against: ``info`` (the sensor's, when known) or a
    small synthetic one (2 x 8, frame 'probe')."""
    if info is not None:
        return info
    import lidarscan

    return lidarscan.make_info(stamp_ns=1, frame_id="probe", vertical_angles=[0.1, -0.1],
                               horizontal_angles=2 * np.pi * (1 - np.arange(8) / 8),
                               range_min=0.1, range_max=100.0, as_dataclass=True)


# ------------------------------------------------------------------------------------ node

@functools.cache
def _node_class() -> type:
    from rclpy.node import Node

    from converters.edge.nodes import params as P
    from converters.edge.nodes.common import (
        ERROR,
        WARN,
        Diagnostics,
        Guard,
        LatencyWindow,
        LogLimiter,
        RateMeter,
        Status,
        warm_up,
    )
    from converters.edge.nodes.depth_input import DepthInput
    from converters.edge.nodes.ouster_input import OusterInput
    from converters.edge.nodes.tf import TfListener, TransformBuffer, TransformLookupError

    class ConverterNode(DepthInput, OusterInput, Node):
        """The rclpy node around :class:`ConverterCore` (see the module docstring)."""

        def __init__(self, name: str = "lidarscan_converter", **kwargs: Any) -> None:
            super().__init__(name, **kwargs)
            log = self.get_logger()
            self._log = LogLimiter(log.warning)
            node_specs, per_slice = _specs()
            values = P.declare_specs(self, node_specs)
            slice_specs = [t.for_name(str(n)) for n in values["slice_names"] for t in per_slice]
            values.update(P.declare_specs(self, slice_specs))
            P.refuse_unknown(self, values["allow_unknown_parameters"])
            self._file_slices = P.load_slices_file(values["slices_file"]) \
                if values["slices_file"] else []
            config = settings(values, self._file_slices)
            self.target_frame = config["target_frame"]
            self.fallback_extrinsics = config.pop("extrinsics")
            self._have_fallback = bool(values["extrinsics"])
            self.moving = bool(values["moving"])
            self.tf_buffer = TransformBuffer()
            self.core = ConverterCore(**config, on_event=lambda line: self._log(line, "linkage"),
                                      moving=self.moving, tf_samples=self.tf_buffer.samples,
                                      tf_wait_ns=round(values["tf_wait"] * 1e9),
                                      tf_tolerance_ns=round(values["tf_tolerance"] * 1e9))
            self.core.check(probe_info(), np.eye(4) if self.target_frame else None)
            self.stats = self.core.stats
            self._no_pose_seen = 0
            self._converted_seen = 0
            self.guard = P.ParameterGuard(
                self, {s.name: s for s in (*node_specs, *slice_specs)}, values,
                self._validate, self._apply)

            from lidarscan_msgs.msg import LidarInfo, LidarScan
            from sensor_msgs.msg import LaserScan, PointCloud2

            specs = self.core.slices
            out_qos = P.qos_profile(values["output_qos"])
            cloud_topic = values["cloud_topic"]
            self.cloud_pub = self.create_publisher(PointCloud2, cloud_topic, out_qos) \
                if values["pointcloud2.enabled"] else None
            self.slice_pubs = {s.name: self.create_publisher(LaserScan, s.topic, out_qos)
                               for s in specs}
            scan_topic = values["scan_topic"]
            self._prepared: set[Any] = set()
            self._unmounted: Any = None    # an info prepared without its mount (cloud only)
            self._lookup_error = TransformLookupError
            self.create_timer(0.5, self.core.expire)
            self._rates = RateMeter()
            self._latency = LatencyWindow()
            self._status = (Status, WARN, ERROR)
            self._init_depth(values, out_qos)
            self._init_ouster(values, out_qos)
            self.diagnostics = Diagnostics(self, self._diagnose)
            log.info(f"converting '{self.resolve_topic_name(scan_topic)}' -> "
                     f"{'PointCloud2 ' + repr(cloud_topic) if self.cloud_pub else 'no cloud'}"
                     f"{', slices ' + ', '.join(s.name + '->' + s.topic for s in specs) if specs else ''}"
                     f"; target frame {self.target_frame or '(sensor frame)'}"
                     + (f"; depth images {self.resolve_topic_name(values['depth.image_topic'])!r}"
                        if self.depth_sync is not None else "")
                     + ("; moving mount (pose from /tf per pixel)" if self.moving else ""))
            # ready before listening: every kernel loaded (from numba's cache only: no compiler
            # here) before the subscriptions exist, so a publisher that waits for the match
            # never meets a node that is not ready
            self.kernels: Any = None
            self.startup = warm_up(self, {"kernels": self._warm}, self.diagnostics,
                                   describe=self._kernels_line)
            self.tf_listener = TfListener(self, self.tf_buffer,
                                          on_error=lambda line: self._log(line, "tf"),
                                          on_message=self._on_tf if self.moving else None) \
                if self.target_frame else None
            self._subscribe_depth()
            self._subscribe_ouster()
            self.create_subscription(LidarInfo, values["info_topic"], self._on_info,
                                     P.qos_profile(values["info_qos"]), raw=True)
            self._await_info(values["info_wait"])
            # the reader keeps at least max_pending scans: those that arrive while a new
            # LidarInfo's tables are built wait there (reliable QoS: none dropped)
            scan_qos = P.qos_profile(values["scan_qos"])
            scan_qos.depth = max(scan_qos.depth, values["max_pending"])
            self.create_subscription(LidarScan, scan_topic, self._on_scan, scan_qos, raw=True)

        def _await_info(self, seconds: float) -> None:
            """Before subscribing to the scans: take a latched LidarInfo (and build its
            tables, :meth:`_on_info`) if one comes within ``seconds``, so that a driver that
            starts publishing when the scan subscription matches meets built tables."""
            if seconds <= 0:
                return
            import time

            from rclpy.executors import SingleThreadedExecutor

            executor = SingleThreadedExecutor(context=self.context)
            executor.add_node(self)
            try:
                end = time.monotonic() + seconds
                while not self._mount_known() and time.monotonic() < end:
                    executor.spin_once(timeout_sec=min(0.05, max(end - time.monotonic(), 0)))
            finally:
                executor.remove_node(self)
                executor.shutdown(timeout_sec=0)
            if self._unmounted is not None and self._mount_known():
                # the mount came after the info: its slice tables now
                self._prepared.discard(self._unmounted)
                self._prepare(self.core.last_info)

        def _mount_known(self) -> bool:
            """A LidarInfo arrived, and the slices' mount is known (from TF, or the
            ``extrinsics`` parameter, or not needed)."""
            info = self.core.last_info
            if info is None:
                return False
            if not self.target_frame or self.moving or not self.core.slices \
                    or self._have_fallback:
                return True
            try:
                self.tf_buffer.lookup(self.target_frame, info.header.frame_id, None)
            except self._lookup_error:
                return False
            return True

        def _warm(self) -> None:
            self.kernels = self.core.warm(cloud=self.cloud_pub is not None)

        def _kernels_line(self) -> tuple[str, dict[str, Any]]:
            """(log line, diagnostics values) of the kernels that run."""
            return kernels_status(self.kernels)

        # ------------------------------------------------------------------ parameters
        def _validate(self, values: dict[str, Any]) -> None:
            """Build the converters with the candidate values (raises LidarScanError)."""
            config = settings(values, self._file_slices)
            config.pop("extrinsics")
            core = ConverterCore(**config)
            latest = self.core.resolver.latest_stamp_ns
            info = self.core.resolver.info(latest) if latest is not None else None
            core.check(probe_info(info), np.eye(4) if self.target_frame else None)
            parse_extrinsics(values["depth.extrinsics"], "depth.extrinsics")

        def _apply(self, values: dict[str, Any], changed: set[str]) -> None:
            """Warm the new configuration's kernels (from the cache only, as at the start),
            then apply it and rebuild the current LidarInfo's tables, before the next scan."""
            config = settings(values, self._file_slices)
            self.fallback_extrinsics = config.pop("extrinsics")
            self._have_fallback = bool(values["extrinsics"])
            candidate = ConverterCore(**config, moving=self.moving)
            self.kernels = candidate.warm(cloud=self.cloud_pub is not None)
            config["slice_options"] = candidate.slice_options
            self.core.reconfigure(**{k: v for k, v in config.items() if k != "target_frame"})
            self._prepared.clear()
            self._apply_depth(values, config)
            if self.core.last_info is not None:
                self._prepare(self.core.last_info)
            self.get_logger().info(f"parameters changed: {', '.join(sorted(changed))}; "
                                   f"{self.kernels.summary()}")

        # ----------------------------------------------------------------- diagnostics
        def _diagnose(self) -> list[Any]:
            Status, WARN, ERROR = self._status
            st = self.stats
            counters = {"scans_received": st.scans_received, "scans_idle": st.scans_idle,
                        "scans_converted": st.scans_converted,
                        "scans_dropped": st.scans_dropped, "bad_messages": st.bad_messages,
                        "conversion_errors": st.conversion_errors,
                        "clouds_published": st.clouds_published,
                        "slices_published": st.slices_published,
                        "infos_received": st.infos_received}
            delta, dt = self._rates.update(counters)
            rates = {f"{k}_per_s": round(v / dt, 2) for k, v in delta.items()}
            io = Status("conversion", {**rates, **counters, **self._latency.take()})
            arrived = delta["scans_received"]
            if delta["bad_messages"]:
                io.worse(WARN, f"{delta['bad_messages']} malformed message(s) in the last "
                         f"{dt:.1f} s")
            if delta["conversion_errors"]:
                level = ERROR if not delta["scans_converted"] else WARN
                io.worse(level, f"{delta['conversion_errors']} scan(s) not converted "
                         "(e.g. no transform)")
            if not arrived and not delta["scans_idle"]:
                io.worse(WARN, "no LidarScan received")
            state = self.core.resolver.state()
            linkage = Status("linkage", {**state, "max_infos": self.core.resolver.max_infos,
                                         "max_pending": self.core.resolver.max_pending,
                                         "dropped_last_period": delta["scans_dropped"]})
            if state["latest_stamp_ns"] is None:
                linkage.worse(WARN if not arrived else ERROR,
                              "no LidarInfo received (is its publisher latched?)")
            if delta["scans_dropped"]:
                level = ERROR if delta["scans_dropped"] >= max(arrived, 1) else WARN
                linkage.worse(level, f"{delta['scans_dropped']} scan(s) dropped by the "
                              f"linkage in the last {dt:.1f} s (see the log for reasons)")
            if state["conflicting"]:
                linkage.worse(WARN, f"{state['conflicting']} LidarInfo stamp(s) re-published "
                              "with different geometry (their scans are dropped)")
            statuses = [io, linkage]
            if self.moving:
                statuses.append(self._diagnose_moving(Status, WARN, ERROR))
            if self.depth_sync is not None:
                statuses.append(self._diagnose_depth())
            if self.ouster_info_pub is not None:
                statuses.append(self._diagnose_ouster())
            return statuses

        def _diagnose_moving(self, Status: Any, WARN: Any, ERROR: Any) -> Any:  # noqa: N803
            """The ``moving mount`` status: scans held for /tf, dropped without a pose."""
            dropped = self.stats.dropped_no_pose - self._no_pose_seen
            self._no_pose_seen = self.stats.dropped_no_pose
            spans = {f"poses {frame}": "none" if t.span is None else list(t.span)
                     for frame, t in self.core.tracks.items()}
            st = Status("moving mount", {"held": len(self.core.held),
                                         "tf_wait_s": self.core.tf_wait_ns / 1e9,
                                         "dropped_no_pose": self.stats.dropped_no_pose,
                                         "dropped_last_period": dropped, **spans})
            if dropped:
                converted = self.stats.scans_converted - self._converted_seen
                st.worse(ERROR if not converted else WARN,
                         f"{dropped} scan(s) dropped: /tf did not cover their sweep within "
                         "tf_wait (see the log)")
            self._converted_seen = self.stats.scans_converted
            return st

        # ------------------------------------------------------------------- callbacks
        def _on_info(self, raw: bytes) -> None:
            with self._guard("bad LidarInfo ignored", "bad info") as guard:
                ready = self.core.add_info(raw)
            if guard.failed:
                return
            self._prepare(self.core.last_info)
            self._publish(ready)

        def _prepare(self, info: Any) -> None:
            """Converters and tables of a new LidarInfo version, before its first scan (the
            mount from TF at the info's stamp, else the parameter; without either, only the
            cloud)."""
            from lidarscan.geometry import info_key
            from lidarscan.stamps import to_ns

            key = info_key(info)
            if key in self._prepared:
                return
            if len(self._prepared) >= 64:
                self._prepared.clear()
            self._prepared.add(key)
            start = self.get_clock().now().nanoseconds
            extrinsics = None
            if self.target_frame and not self.moving:   # a moving mount: the cloud only
                try:
                    extrinsics = self._mount(
                        info.header.frame_id, to_ns(info.header.stamp),
                        self.fallback_extrinsics if self._have_fallback else None, "extrinsics")
                except self._lookup_error:
                    pass                                # no mount yet: the cloud only
            self._unmounted = key if extrinsics is None and self.target_frame \
                and not self.moving else None
            try:
                self.core.prepare(info, extrinsics, cloud=self.cloud_pub is not None)
            except Exception as err:  # noqa: BLE001 - the first scan then builds them itself
                self._log(f"LidarInfo tables not prepared: {type(err).__name__}: {err}",
                          "prepare")
                return
            took = (self.get_clock().now().nanoseconds - start) / 1e6
            self.get_logger().info(f"LidarInfo {info.header.frame_id} "
                                   f"{int(info.height)}x{int(info.width)}: tables ready in "
                                   f"{took:.0f} ms")

        def _on_scan(self, raw: bytes) -> None:
            want_cloud = self.cloud_pub is not None and \
                self.cloud_pub.get_subscription_count() > 0
            want_slices = [n for n, p in self.slice_pubs.items() if p.get_subscription_count()]
            if not want_cloud and not want_slices:
                self.stats.scans_idle += 1
                return
            with self._guard(f"bad LidarScan #{self.stats.scans_received + 1} ignored",
                             "bad scan") as guard:
                ready = self.core.add_scan(raw)
            if guard.failed:
                return
            self._publish(ready, want_cloud, want_slices)

        def _on_tf(self, cleared: bool) -> None:
            """New /tf (moving mount): extend the tracks, convert the pairs they release."""
            with self._guard("moving mount: poses not updated", "moving",
                             bad=self._count_internal) as guard:
                ready = self.core.update_tracks(cleared)
            if guard.failed:
                return
            self._publish(ready, held=True)

        def _publish(self, pairs: list[tuple[Any, Any]], want_cloud: bool | None = None,
                     want_slices: list[str] | None = None, held: bool = False) -> None:
            """Convert and publish linked pairs. A moving mount's (with slices): the
            PointCloud2 at once (it is in the sensor frame: no pose needed), the slices when
            :meth:`ConverterCore.hold` releases the pair (``held``: pairs it released)."""
            if not pairs:
                return
            if want_cloud is None:
                want_cloud = self.cloud_pub is not None and \
                    self.cloud_pub.get_subscription_count() > 0
            if want_slices is None:
                want_slices = [n for n, p in self.slice_pubs.items()
                               if p.get_subscription_count()]
            if self.moving and self.core.slices:
                if not held:
                    if want_cloud:            # counted as converted when its slices are
                        self._convert(pairs, True, [], count=not want_slices)
                    pairs = self.core.hold(pairs) if want_slices else []
                want_cloud = False            # published at arrival
                if not pairs:
                    return
            if not want_cloud and not want_slices:
                self.stats.scans_idle += len(pairs)
                return
            self._convert(pairs, want_cloud, want_slices)

        def _convert(self, pairs: list[tuple[Any, Any]], want_cloud: bool,
                     want_slices: list[str], count: bool = True) -> None:
            """Convert pairs and publish the outputs (``count``: in ``scans_converted``)."""
            from lidarscan.stamps import to_ns

            for scan, info in pairs:
                with self._guard("scan not converted", "conversion",
                                 bad=self._count_conversion,
                                 internal=self._count_conversion_internal) as guard:
                    extrinsics = self._extrinsics(scan, info) if want_slices else None
                    cloud, slices = self.core.convert(scan, info, cloud=want_cloud,
                                                      slices=want_slices, extrinsics=extrinsics,
                                                      count=count)
                if guard.failed:
                    continue
                if cloud is not None and self.cloud_pub is not None:
                    self.cloud_pub.publish(cloud)
                    self.stats.clouds_published += 1
                for name, msg in slices.items():
                    if name in self.slice_pubs:
                        self.slice_pubs[name].publish(msg)
                        self.stats.slices_published += 1
                self._latency.add(self.get_clock().now().nanoseconds - to_ns(scan.header.stamp))

        def _guard(self, what: str, key: str, **counters: Any) -> Any:
            """:class:`converters.edge.nodes.common.Guard` logging through this node's limiter
            (internal errors counted in ``stats.reasons`` unless told otherwise)."""
            counters.setdefault("internal", self._count_internal)
            return Guard(self._log, what, key=key, **counters)

        def _count_internal(self, err: Exception) -> None:
            self.stats.count(f"internal: {type(err).__name__}")

        def _count_conversion(self, err: Exception) -> None:
            self.stats.conversion_errors += 1
            self.stats.count(f"conversion: {err}")

        def _count_conversion_internal(self, err: Exception) -> None:
            self.stats.conversion_errors += 1
            self._count_internal(err)

        def _extrinsics(self, scan: Any, info: Any) -> Any:
            """target_from_sensor: TF at the scan stamp, else the parameter, else identity; a
            moving mount's track (pose at every pixel's time)."""
            if not self.target_frame:
                return None
            if self.moving:
                return self.core.track(info.header.frame_id)
            from lidarscan.stamps import to_ns

            return self._mount(info.header.frame_id, to_ns(scan.header.stamp),
                               self.fallback_extrinsics if self._have_fallback else None,
                               "extrinsics")

        def _mount(self, source: str, stamp_ns: int | None,
                   fallback: np.ndarray[Any, Any] | None, parameter: str
                   ) -> np.ndarray[Any, Any]:
            """target_frame <- ``source``: TF at ``stamp_ns`` (None: the newest), else
            ``fallback`` (the value of ``parameter``).

            Raises:
                TransformLookupError: neither, naming both ways to give the mount.
            """
            try:
                return self.tf_buffer.lookup(self.target_frame, source, stamp_ns)
            except self._lookup_error as err:
                if fallback is not None:
                    return fallback
                raise self._lookup_error(
                    "target_frame", self.target_frame,
                    f"a transform {self.target_frame} <- {source} on /tf or /tf_static, or the "
                    f"'{parameter}' parameter ({err})") from err

    return ConverterNode


__getattr__, main = entry_points("ConverterNode", _node_class, "lidarscan-converter", usage)


if __name__ == "__main__":
    sys.exit(main())
