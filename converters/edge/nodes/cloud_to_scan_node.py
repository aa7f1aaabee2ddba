"""``lidarscan-cloud-to-scan``: a driver's PointCloud2 -> LidarScan + latched LidarInfo, and
LaserScan height slices of any cloud.

For drivers that publish only PointCloud2 (ouster-ros, velodyne, Hesai, RoboSense): the beam
geometry is estimated from the points by :func:`converters.pointcloud2.converter.from_pointcloud2`, and
each cloud becomes a compact LidarScan linked to a LidarInfo.

Slices (``slice_names``, optional): every cloud, with or without a firing grid (Livox and other
solid-state sensors, stereo, merged clouds), also gives LaserScan height slices computed from its
points in one pass by :class:`converters.slices.cloud.CloudSliceConverter` (the conventions of
the structured slices: inclusive bands in ``target_frame``, REP 117 values, nearest bin, min
range wins, ties to the first point). A cloud that has no grid is then no error: it gives its
slices and no LidarScan (counted as ``no_grid``; set ``publish_scan`` false to not even try).

The LidarInfo is published on a latched topic (reliable, transient local, depth 1) and only when
the geometry CHANGES: the first cloud's estimate is kept as long as later estimates agree with it
within ``angle_tolerance`` / ``offset_tolerance`` (estimates of one sensor differ slightly from
cloud to cloud); their scans are linked to it. A different grid, frame, stagger or a geometry beyond
the tolerances is a new version: a new LidarInfo with a new stamp (the cloud's stamp, made
strictly larger than the previous version's), and the following scans name it.

Topics: ``points`` (in, sensor_msgs/PointCloud2, ``cloud_qos`` [sensor_data]) ->
``lidar_scan`` (out, lidarscan_msgs/LidarScan, ``scan_qos`` [sensor_data]) and ``lidar_info``
(out, lidarscan_msgs/LidarInfo, latched); ``slices/NAME`` (out, sensor_msgs/LaserScan,
``scan_qos``) per slice; ``/tf``, ``/tf_static`` (in) when ``target_frame`` is set.

Parameters (defaults in brackets; ``config/cloud_to_scan.yaml``):

* ``cloud_topic`` [``points``], ``scan_topic`` [``lidar_scan``], ``info_topic``
  [``lidar_info``];
* ``cloud_qos`` [``sensor_data``], ``scan_qos`` [``sensor_data``];
* ``layout`` [``auto``]: ``organized``, ``ring`` or ``auto`` (see ``from_pointcloud2``);
* ``time_field`` [""]: per-point time field ("" = auto-detect);
* ``range_field`` [``auto``]: field with ranges along the beam ("auto", or "" = ignore);
* ``frame_id`` [""]: frame of scan and info ("" = the cloud's);
* ``angle_tolerance`` [1e-3] radians, ``offset_tolerance`` [5e-3] metres: how far the beams of a
  new estimate (per-pixel directions and origins) may differ from the published LidarInfo before
  it counts as a change. Estimates of one sensor from successive clouds differ by about 1e-5 to
  3e-4 rad (beams with few points); a scan linked to the kept info is then off by at most
  ``angle_tolerance * range`` (1 mm at 1 m with the default);
* ``publish_scan`` [true]: convert clouds to LidarScan + LidarInfo (false: slices only);
* ``slice_names`` [[]]: names of the LaserScan slices; for each NAME:
  ``slices.NAME.min_height`` and ``slices.NAME.max_height`` (required, metres in
  ``target_frame``, inclusive), ``slices.NAME.topic`` [``slices/NAME``], and optional
  ``slices.NAME.angle_min`` / ``angle_max`` / ``angle_increment`` (radians; default a full
  circle from -pi at pi/360) and ``slices.NAME.range_min`` / ``range_max`` (metres; default 0 /
  inf); ``slices_file`` [""]: a YAML file of more slices (``config/slices.yaml``);
* ``slice_intensity_field`` [``intensity``]: the cloud field copied into the slices'
  intensities when the cloud has it ("" = none);
* ``target_frame`` [""]: frame of the slices' heights and output ("" = the cloud's frame);
  the pose of the cloud's frame in it comes from /tf at the cloud's stamp, else from
  ``extrinsics`` [[]] (6, 7 or 16 numbers; a cloud is dropped when neither has it).

``--help`` prints every parameter. Topics and QoS are read-only; layout, fields, frame and the
tolerances may be changed while running (checked first, refused with the reason otherwise).
``/diagnostics`` (1 Hz): cloud rate, failures, LidarInfo versions.

Behaviour: no work while nobody subscribes to ``lidar_scan`` or a slice (the info is still
published on the first cloud so late joiners find it); a cloud that cannot be converted is
dropped with one log line (rate-limited) and counted; Ctrl-C exits cleanly.
"""

from __future__ import annotations

import dataclasses
import functools
import sys
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from converters.edge.nodes.common import Guard, entry_points
from converters.shared.options import IfPresent
from lidarscan.errors import LidarScanError

_DEFAULT_FIELD = IfPresent("intensity")

__all__ = ["CloudSlicer", "CloudToScanCore", "geometry_matches", "main"]

def geometry_matches(a: Any, b: Any, *, angle_tolerance: float = 1e-3,
                     offset_tolerance: float = 5e-3) -> bool:
    """Whether two LidarInfos describe the same sensor geometry within tolerances.

    Gauge-free: the per-pixel beam directions D and offsets O of the two projectors
    (``P = rho * D + O``) are compared, not the fields that produce them (an estimate may move a
    constant between ``horizontal_angles`` and ``beam_azimuth_offsets`` without changing any
    point). Equal: grid size, frame, stagger, range multiplier/offset, and
    ``max |D_a - D_b| <= angle_tolerance`` (radians, for unit vectors), ``max |O_a - O_b| <=
    offset_tolerance`` (metres), column_time_increment within 1 %. Stamps are ignored.
    """
    import lidarscan

    if (int(a.height), int(a.width), a.header.frame_id) != \
            (int(b.height), int(b.width), b.header.frame_id):
        return False
    if (float(a.range_multiplier), float(a.range_offset)) != \
            (float(b.range_multiplier), float(b.range_offset)):
        return False
    ia, ib = int(a.column_time_increment), int(b.column_time_increment)
    if abs(ia - ib) > 0.01 * max(abs(ia), abs(ib)):
        return False
    pa, pb = lidarscan.make_projector(a), lidarscan.Projector(b)
    if not np.array_equal(pa.shifts % max(pa.width, 1), pb.shifts % max(pb.width, 1)):
        return False
    if not np.array_equal(pa.beam_time_offsets, pb.beam_time_offsets):
        return False
    d = np.sqrt(np.max(np.sum((pa.directions - pb.directions) ** 2, axis=-1), initial=0.0))
    o = np.sqrt(np.max(np.sum((pa.offsets - pb.offsets) ** 2, axis=-1), initial=0.0))
    return bool(d <= angle_tolerance and o <= offset_tolerance)


class CloudToScanCore:
    """The node's logic without rclpy: cloud -> (scan, info, info_changed).

    Args:
        angle_tolerance, offset_tolerance: see :func:`geometry_matches`.
        **options: keyword options of :func:`converters.pointcloud2.converter.from_pointcloud2`
            (layout, time_field, range_field, range_scale, frame_id).

    Attributes:
        info: the current LidarInfo version (None before the first cloud).
        versions: how many versions were created.
    """

    def __init__(self, *, angle_tolerance: float = 1e-3, offset_tolerance: float = 5e-3,
                 **options: Any) -> None:
        self.options = options
        self.angle_tolerance = float(angle_tolerance)
        self.offset_tolerance = float(offset_tolerance)
        self.info: Any = None
        self.versions = 0

    def convert(self, cloud: Any) -> tuple[Any, Any, bool]:
        """Convert one cloud.

        Returns:
            (scan, info, changed): ``changed`` is true when ``info`` is a new version that must
            be (re-)published before ``scan``.

        Raises:
            LidarScanError: the cloud cannot be converted (the current info is kept).
        """
        from converters.pointcloud2.converter import from_pointcloud2
        from lidarscan.stamps import to_ns

        stamp = to_ns(cloud.header.stamp, field="cloud.header.stamp")
        current = self.info
        key = to_ns(current.header.stamp) if current is not None else stamp
        scan, info = from_pointcloud2(cloud, stamp_ns=key, **self.options)
        if current is not None and geometry_matches(
                info, current, angle_tolerance=self.angle_tolerance,
                offset_tolerance=self.offset_tolerance):
            return scan, current, False
        if current is not None:  # a new version: a new, strictly later stamp
            new_key = max(stamp, key + 1)
            scan, info = _restamp(scan, info, new_key)
        self.info = info
        self.versions += 1
        return scan, info, True


class CloudSlicer:
    """LaserScan slices of clouds from their points (no grid needed): one
    :class:`converters.slices.cloud.CloudSliceConverter` per (cloud frame, extrinsics).

    Args:
        slices: the slices (:class:`converters.edge.nodes.params.SliceConfig`).
        target_frame: frame of the heights and of the output ("" = each cloud's frame).
        intensity_field: cloud field copied into the intensities (None = none; the default uses
            ``intensity`` when the cloud has it).
        backend: see :class:`converters.slices.cloud.CloudSliceConverter`.

    Raises:
        ConfigError: bad slices or options (checked here, before any cloud).
    """

    def __init__(self, slices: Sequence[Any], *, target_frame: str = "",
                 intensity_field: Any = _DEFAULT_FIELD, backend: str = "auto") -> None:
        self.slices = list(slices)
        self.target_frame = target_frame
        self._options = {"intensity_field": intensity_field, "backend": backend}
        self._specs = {s.name: s.spec() for s in self.slices}
        self._converters: dict[Any, Any] = {}
        self._converter("check", None)                     # validate now

    def _converter(self, frame: str, extrinsics: Any) -> Any:
        from converters.slices.cloud import CloudSliceConverter

        matrix = None if extrinsics is None else np.asarray(extrinsics, np.float64)
        key = (frame, None if matrix is None else matrix.tobytes())
        conv = self._converters.get(key)
        if conv is None:
            if len(self._converters) >= 16:
                self._converters.clear()
            conv = CloudSliceConverter(self._specs, extrinsics=matrix,
                                       frame_id=self.target_frame or frame, **self._options)
            self._converters[key] = conv
        return conv

    def convert(self, cloud: Any, extrinsics: Any = None) -> dict[str, Any]:
        """slice name -> LaserScan of one cloud; ``extrinsics``: 4x4 target_frame <- the
        cloud's frame (None: the same frame).

        Raises:
            LidarScanError: the cloud cannot be read (see
                :meth:`converters.slices.cloud.CloudSliceConverter.convert`).
        """
        return self._converter(str(cloud.header.frame_id), extrinsics).convert(cloud)


def _restamp(scan: Any, info: Any, stamp_ns: int) -> tuple[Any, Any]:
    """Copies of scan and info whose version key is ``stamp_ns``."""
    from lidarscan import types
    from lidarscan.stamps import time_msg

    if isinstance(info, types.LidarInfo):
        t = time_msg(stamp_ns, types.Time)
        info = dataclasses.replace(info, header=dataclasses.replace(info.header, stamp=t))
        scan = dataclasses.replace(scan, lidar_info_time=t)
        return scan, info
    info.header.stamp = time_msg(stamp_ns)
    scan.lidar_info_time = time_msg(stamp_ns)
    return scan, info


# ------------------------------------------------------------------------------ parameters

def _specs() -> tuple[tuple[Any, ...], tuple[Any, ...]]:
    """(node parameters, per-slice templates ``slices.NAME.*``), from one table (declaration,
    checks, ``--help``)."""
    from converters.edge.nodes.params import QOS_NAMES, ParamSpec as S

    node = (
        S("cloud_topic", "points", "input sensor_msgs/PointCloud2 topic", read_only=True),
        S("scan_topic", "lidar_scan", "output lidarscan_msgs/LidarScan topic", read_only=True),
        S("info_topic", "lidar_info", "output lidarscan_msgs/LidarInfo topic (latched)",
          read_only=True),
        S("cloud_qos", "sensor_data", "QoS of the input", choices=QOS_NAMES, read_only=True),
        S("scan_qos", "sensor_data", "QoS of the scans and slices", choices=QOS_NAMES,
          read_only=True),
        S("layout", "auto", "cloud layout (see converters.pointcloud2.converter.from_pointcloud2)",
          choices=("auto", "organized", "ring")),
        S("time_field", "", "per-point time field ('' = auto-detect)"),
        S("range_field", "auto", "range field ('auto', or '' = ignore)"),
        S("frame_id", "", "frame of scan and info ('' = the cloud's)"),
        S("angle_tolerance", 1e-3, "radians the beams may differ before the LidarInfo counts "
          "as changed", low=0.0, high=3.2),
        S("offset_tolerance", 5e-3, "metres the beam origins may differ before the LidarInfo "
          "counts as changed", low=0.0, high=100.0),
        S("publish_scan", True, "convert clouds to LidarScan + LidarInfo (false: slices only)",
          read_only=True),
        S("slice_names", (), "names of the LaserScan slices of the clouds' points (one "
          "slices.NAME block each; any cloud, grid or not)", kind="str_list", read_only=True),
        S("slices_file", "", "YAML file with more slices (config/slices.yaml)", read_only=True),
        S("slice_intensity_field", "intensity", "cloud field copied into the slices' "
          "intensities when present ('' = none)"),
        S("target_frame", "", "frame of the slices' heights and output ('' = the cloud's "
          "frame); z up", read_only=True),
        S("extrinsics", (), "target_frame <- cloud frame when TF has none: 6 (x y z roll pitch "
          "yaw), 7 (x y z qx qy qz qw) or 16 numbers; [] = none", kind="float_list"),
        S("allow_unknown_parameters", False, "start even with parameters this node does not "
          "know (a typo is otherwise an error)", read_only=True),
    )
    # the converter node's slice templates, with the defaults of a cloud (no sensor grid)
    from converters.edge.nodes.converter_node import _specs as converter_specs

    cloud_defaults = {"angle_increment": "pi/360", "range_min": "0", "range_max": "inf"}
    per_slice = tuple(
        dataclasses.replace(t, description=t.description.rsplit("(default", 1)[0]
                            + f"(default {cloud_defaults[t.name.rsplit('.', 1)[1]]})")
        if t.name.rsplit(".", 1)[1] in cloud_defaults else t
        for t in converter_specs()[1])
    return node, per_slice


TOPICS = (("points", "in  sensor_msgs/PointCloud2", "cloud_topic, cloud_qos"),
          ("/tf, /tf_static", "in  tf2_msgs/TFMessage", "when target_frame is set"),
          ("lidar_scan", "out lidarscan_msgs/LidarScan", "scan_topic, scan_qos"),
          ("lidar_info", "out lidarscan_msgs/LidarInfo", "info_topic, latched"),
          ("slices/NAME", "out sensor_msgs/LaserScan", "one per slice, scan_qos"),
          ("/diagnostics", "out diagnostic_msgs/DiagnosticArray", "1 Hz"))


def usage() -> str:
    """``lidarscan-cloud-to-scan --help``."""
    from converters.edge.nodes.params import help_text

    node, per_slice = _specs()
    return help_text("lidarscan-cloud-to-scan", __doc__.split("\n\n")[0], TOPICS, node,
                     {"per slice (for each NAME in slice_names):": per_slice},
                     example="config/cloud_to_scan.yaml")


def settings(values: Any) -> dict[str, Any]:
    """:class:`CloudToScanCore` keyword arguments from checked parameter values."""
    options: dict[str, Any] = {"layout": values["layout"],
                               "range_field": values["range_field"] or None}
    if values["time_field"]:
        options["time_field"] = values["time_field"]
    if values["frame_id"]:
        options["frame_id"] = values["frame_id"]
    return {"angle_tolerance": values["angle_tolerance"],
            "offset_tolerance": values["offset_tolerance"], **options}


def slicer(values: Mapping[str, Any], extra_slices: Sequence[Any] = ()) -> CloudSlicer | None:
    """The :class:`CloudSlicer` of checked parameter values (None without slices); slice
    topics default to ``slices/NAME``.

    Raises:
        ConfigError: a slice without heights, duplicate names, bad slice options.
    """
    from converters.edge.nodes import converter_node

    # the converter node's rules for slice parameters (required heights, unique names, topics)
    keys = {s.name: s.default for s in converter_node._specs()[0]}
    keys.update({k: v for k, v in values.items()
                 if k == "slice_names" or k.startswith("slices.")})
    specs = converter_node.settings(keys, extra_slices)["slices"]
    if not specs:
        return None
    field = values["slice_intensity_field"]
    return CloudSlicer(specs, target_frame=values["target_frame"],
                       intensity_field=IfPresent(field) if field else None)


# ------------------------------------------------------------------------------------ node

@functools.cache
def _node_class() -> type:
    from rclpy.node import Node

    from converters.edge.nodes import params as P
    from converters.edge.nodes.common import ERROR, WARN, Diagnostics, LogLimiter, RateMeter, Status
    from converters.edge.nodes.tf import TfListener, TransformBuffer, TransformLookupError

    class CloudToScanNode(Node):
        """The rclpy node around :class:`CloudToScanCore` and :class:`CloudSlicer` (see the
        module docstring)."""

        def __init__(self, name: str = "lidarscan_cloud_to_scan", **kwargs: Any) -> None:
            super().__init__(name, **kwargs)
            self._log = LogLimiter(self.get_logger().warning)
            node_specs, per_slice = _specs()
            values = P.declare_specs(self, node_specs)
            slice_specs = [t.for_name(str(n)) for n in values["slice_names"] for t in per_slice]
            values.update(P.declare_specs(self, slice_specs))
            P.refuse_unknown(self, values["allow_unknown_parameters"])
            self._file_slices = P.load_slices_file(values["slices_file"]) \
                if values["slices_file"] else []
            self.core = CloudToScanCore(**settings(values))
            self.slicer = slicer(values, self._file_slices)
            self.publish_scan = values["publish_scan"]
            self.target_frame = values["target_frame"]
            self.fallback_extrinsics = P.parse_extrinsics(values["extrinsics"]) \
                if values["extrinsics"] else None
            self.guard = P.ParameterGuard(self, {s.name: s for s in (*node_specs, *slice_specs)},
                                          values, self._validate, self._apply)
            self.stats = {"clouds": 0, "scans": 0, "infos": 0, "bad": 0, "idle": 0,
                          "no_grid": 0, "slices": 0}
            self._scan_failed = False

            from lidarscan_msgs.msg import LidarInfo, LidarScan
            from sensor_msgs.msg import LaserScan, PointCloud2

            cloud_topic, scan_topic = values["cloud_topic"], values["scan_topic"]
            info_topic = values["info_topic"]
            out_qos = P.qos_profile(values["scan_qos"])
            self.scan_pub = self.create_publisher(LidarScan, scan_topic, out_qos)
            self.info_pub = self.create_publisher(LidarInfo, info_topic, P.qos_profile("latched"))
            self.slice_pubs = {s.name: self.create_publisher(LaserScan, s.topic, out_qos)
                               for s in (self.slicer.slices if self.slicer else ())}
            self.create_subscription(PointCloud2, cloud_topic, self._on_cloud,
                                     P.qos_profile(values["cloud_qos"]), raw=True)
            self.tf_buffer = TransformBuffer()
            self.tf_listener = TfListener(self, self.tf_buffer,
                                          on_error=lambda line: self._log(line, "tf")) \
                if self.target_frame and self.slicer else None
            self._lookup_error = TransformLookupError
            self._rates = RateMeter()
            self._status = (Status, WARN, ERROR)
            self.diagnostics = Diagnostics(self, self._diagnose)
            outputs = [f"LidarScan '{self.resolve_topic_name(scan_topic)}' + LidarInfo "
                       f"'{self.resolve_topic_name(info_topic)}' (latched)"] \
                if self.publish_scan else []
            outputs += [f"slice {n} -> '{self.resolve_topic_name(s.topic)}'"
                        for n, s in zip(self.slice_pubs, self.slicer.slices if self.slicer
                                        else ())]
            self.get_logger().info(f"'{self.resolve_topic_name(cloud_topic)}' -> "
                                   f"{', '.join(outputs) or 'nothing'}")
            import importlib

            from converters.edge.nodes.common import warm_up
            modules = ("converters.sources.clouds.importer", "converters.slices.cloud")
            steps: dict[str, Any] = {
                "imports": lambda: [importlib.import_module(m) for m in modules]}
            if self.slicer is not None:          # compile its kernels on a driver-like cloud
                from converters._kernels.warm import probe_cloud
                steps["slices"] = lambda: self.slicer.convert(probe_cloud())
            self.startup = warm_up(self, steps, self.diagnostics)

        def _validate(self, values: dict[str, Any]) -> None:
            CloudToScanCore(**settings(values))
            slicer(values, self._file_slices)
            if values["extrinsics"]:
                P.parse_extrinsics(values["extrinsics"])

        def _apply(self, values: dict[str, Any], changed: set[str]) -> None:
            fresh = CloudToScanCore(**settings(values))
            self.core.options = fresh.options
            self.core.angle_tolerance = fresh.angle_tolerance
            self.core.offset_tolerance = fresh.offset_tolerance
            self.slicer = slicer(values, self._file_slices)
            self.fallback_extrinsics = P.parse_extrinsics(values["extrinsics"]) \
                if values["extrinsics"] else None
            self.get_logger().info(f"parameters changed: {', '.join(sorted(changed))}")

        def _diagnose(self) -> list[Any]:
            Status, WARN, ERROR = self._status
            delta, dt = self._rates.update(self.stats)
            st = Status("conversion", {**{f"{k}_per_s": round(v / dt, 2)
                                          for k, v in delta.items()}, **self.stats,
                                       "info_versions": self.core.versions})
            if not delta["clouds"]:
                st.worse(WARN, "no PointCloud2 received")
            if delta["bad"]:
                level = ERROR if delta["bad"] >= delta["clouds"] else WARN
                st.worse(level, f"{delta['bad']} cloud(s) not converted in the last {dt:.1f} s")
            if delta["infos"] > 1:
                st.worse(WARN, f"the geometry changed {delta['infos']} times in {dt:.1f} s "
                         "(raise angle_tolerance / offset_tolerance?)")
            return [st]

        def _extrinsics(self, cloud: Any) -> np.ndarray[Any, Any] | None:
            """target_frame <- cloud frame: TF at the cloud's stamp, else the parameter."""
            if not self.target_frame:
                return None
            from lidarscan.stamps import to_ns

            source = str(cloud.header.frame_id)
            try:
                return self.tf_buffer.lookup(self.target_frame, source,
                                             to_ns(cloud.header.stamp))
            except self._lookup_error as err:
                if self.fallback_extrinsics is not None:
                    return self.fallback_extrinsics
                raise self._lookup_error(
                    "target_frame", self.target_frame,
                    f"a transform {self.target_frame} <- {source} on /tf or /tf_static, or the "
                    f"'extrinsics' parameter ({err})") from err

        def _on_cloud(self, raw: bytes) -> None:
            from lidarscan import decode

            self.stats["clouds"] += 1
            scan_wanted = self.scan_pub.get_subscription_count() > 0
            # the first cloud's info is published even without subscribers (late joiners)
            want_scan = self.publish_scan and (scan_wanted or (
                self.core.info is None and not self._scan_failed))
            want_slices = [n for n, p in self.slice_pubs.items() if p.get_subscription_count()]
            if not want_scan and not want_slices:
                self.stats["idle"] += 1
                return
            with Guard(self._log, f"PointCloud2 #{self.stats['clouds']} not converted",
                       bad=self._count_bad):
                cloud = decode(raw, "sensor_msgs/msg/PointCloud2")
                if want_scan:
                    self._scan(cloud)
                if want_slices and self.slicer is not None:
                    out = self.slicer.convert(cloud, self._extrinsics(cloud))
                    for name in want_slices:
                        self.slice_pubs[name].publish(out[name])
                        self.stats["slices"] += 1

        def _count_bad(self, err: Exception) -> None:
            self.stats["bad"] += 1

        def _scan(self, cloud: Any) -> None:
            """LidarScan (+ a new LidarInfo version) of one cloud; a cloud without a grid is
            no error when slices are configured (counted as ``no_grid``)."""
            try:
                scan, info, changed = self.core.convert(cloud)
            except LidarScanError as err:
                if self.slicer is None:
                    raise
                self._scan_failed = True
                self.stats["no_grid"] += 1
                self._log(f"no LidarScan from PointCloud2 #{self.stats['clouds']} ({err}); "
                          "publishing its slices only", "no grid")
                return
            if changed:
                self.info_pub.publish(info)
                self.stats["infos"] += 1
                self.get_logger().info(
                    f"LidarInfo version {self.core.versions}: {info.height}x{info.width}, "
                    f"frame '{info.header.frame_id}', stamp {info.header.stamp.sec}."
                    f"{info.header.stamp.nanosec:09d}")
            self.scan_pub.publish(scan)
            self.stats["scans"] += 1

    return CloudToScanNode


__getattr__, main = entry_points("CloudToScanNode", _node_class, "lidarscan-cloud-to-scan",
                                 usage)


if __name__ == "__main__":
    sys.exit(main())
