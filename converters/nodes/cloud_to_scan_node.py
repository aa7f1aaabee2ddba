"""``lidarscan-cloud-to-scan``: a driver's organized PointCloud2 -> LidarScan + latched LidarInfo.

For drivers that publish only PointCloud2 (ouster-ros, velodyne, Hesai, RoboSense): the beam
geometry is estimated from the points by :func:`converters.pointcloud2.from_pointcloud2`, and
each cloud becomes a compact LidarScan linked to a LidarInfo.

The LidarInfo is published on a latched topic (reliable, transient local, depth 1) and only when
the geometry CHANGES: the first cloud's estimate is kept as long as later estimates agree with it
within ``angle_tolerance`` / ``offset_tolerance`` (estimates of one sensor differ slightly from
cloud to cloud); their scans are linked to it. A different grid, frame, stagger or a geometry beyond
the tolerances is a new version: a new LidarInfo with a new stamp (the cloud's stamp, made
strictly larger than the previous version's), and the following scans name it.

Topics: ``points`` (in, sensor_msgs/PointCloud2, ``cloud_qos`` [sensor_data]) ->
``lidar_scan`` (out, lidarscan_msgs/LidarScan, ``scan_qos`` [sensor_data]) and ``lidar_info``
(out, lidarscan_msgs/LidarInfo, latched).

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
  ``angle_tolerance * range`` (1 mm at 1 m with the default).

``--help`` prints every parameter. Topics and QoS are read-only; layout, fields, frame and the
tolerances may be changed while running (checked first, refused with the reason otherwise).
``/diagnostics`` (1 Hz): cloud rate, failures, LidarInfo versions.

Behaviour: no work while nobody subscribes to ``lidar_scan`` (the info is still published on the
first cloud so late joiners find it); a cloud that cannot be converted is dropped with one log
line (rate-limited) and counted; Ctrl-C exits cleanly.
"""

from __future__ import annotations

import dataclasses
import functools
import sys
from typing import Any

import numpy as np

from converters.nodes.common import entry_points
from lidarscan.errors import LidarScanError

__all__ = ["CloudToScanCore", "geometry_matches", "main"]

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
        **options: keyword options of :func:`converters.pointcloud2.from_pointcloud2`
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
        from converters.pointcloud2 import from_pointcloud2
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

def _specs() -> tuple[Any, ...]:
    """The node's parameters (one table: declaration, checks, ``--help``)."""
    from converters.nodes.params import QOS_NAMES, ParamSpec as S

    return (
        S("cloud_topic", "points", "input sensor_msgs/PointCloud2 topic", read_only=True),
        S("scan_topic", "lidar_scan", "output lidarscan_msgs/LidarScan topic", read_only=True),
        S("info_topic", "lidar_info", "output lidarscan_msgs/LidarInfo topic (latched)",
          read_only=True),
        S("cloud_qos", "sensor_data", "QoS of the input", choices=QOS_NAMES, read_only=True),
        S("scan_qos", "sensor_data", "QoS of the scans", choices=QOS_NAMES, read_only=True),
        S("layout", "auto", "cloud layout (see converters.pointcloud2.from_pointcloud2)",
          choices=("auto", "organized", "ring")),
        S("time_field", "", "per-point time field ('' = auto-detect)"),
        S("range_field", "auto", "range field ('auto', or '' = ignore)"),
        S("frame_id", "", "frame of scan and info ('' = the cloud's)"),
        S("angle_tolerance", 1e-3, "radians the beams may differ before the LidarInfo counts "
          "as changed", low=0.0, high=3.2),
        S("offset_tolerance", 5e-3, "metres the beam origins may differ before the LidarInfo "
          "counts as changed", low=0.0, high=100.0),
        S("allow_unknown_parameters", False, "start even with parameters this node does not "
          "know (a typo is otherwise an error)", read_only=True),
    )


TOPICS = (("points", "in  sensor_msgs/PointCloud2", "cloud_topic, cloud_qos"),
          ("lidar_scan", "out lidarscan_msgs/LidarScan", "scan_topic, scan_qos"),
          ("lidar_info", "out lidarscan_msgs/LidarInfo", "info_topic, latched"),
          ("/diagnostics", "out diagnostic_msgs/DiagnosticArray", "1 Hz"))


def usage() -> str:
    """``lidarscan-cloud-to-scan --help``."""
    from converters.nodes.params import help_text

    return help_text("lidarscan-cloud-to-scan", __doc__.split("\n\n")[0], TOPICS, _specs(),
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


# ------------------------------------------------------------------------------------ node

@functools.cache
def _node_class() -> type:
    from rclpy.node import Node

    from converters.nodes import params as P
    from converters.nodes.common import ERROR, WARN, Diagnostics, LogLimiter, RateMeter, Status

    class CloudToScanNode(Node):
        """The rclpy node around :class:`CloudToScanCore` (see the module docstring)."""

        def __init__(self, name: str = "lidarscan_cloud_to_scan", **kwargs: Any) -> None:
            super().__init__(name, **kwargs)
            self._log = LogLimiter(self.get_logger().warning)
            specs = _specs()
            values = P.declare_specs(self, specs)
            P.refuse_unknown(self, values["allow_unknown_parameters"])
            self.core = CloudToScanCore(**settings(values))
            self.guard = P.ParameterGuard(self, {s.name: s for s in specs}, values,
                                          self._validate, self._apply)
            self.stats = {"clouds": 0, "scans": 0, "infos": 0, "bad": 0, "idle": 0}

            from lidarscan_msgs.msg import LidarInfo, LidarScan
            from sensor_msgs.msg import PointCloud2

            cloud_topic, scan_topic = values["cloud_topic"], values["scan_topic"]
            info_topic = values["info_topic"]
            self.scan_pub = self.create_publisher(LidarScan, scan_topic,
                                                  P.qos_profile(values["scan_qos"]))
            self.info_pub = self.create_publisher(LidarInfo, info_topic, P.qos_profile("latched"))
            self.create_subscription(PointCloud2, cloud_topic, self._on_cloud,
                                     P.qos_profile(values["cloud_qos"]), raw=True)
            self._rates = RateMeter()
            self._status = (Status, WARN, ERROR)
            self.diagnostics = Diagnostics(self, self._diagnose)
            self.get_logger().info(
                f"'{self.resolve_topic_name(cloud_topic)}' -> LidarScan "
                f"'{self.resolve_topic_name(scan_topic)}' + LidarInfo "
                f"'{self.resolve_topic_name(info_topic)}' (latched)")
            import importlib

            from converters.nodes.common import warm_up
            self.startup = warm_up(self, {"imports": lambda: importlib.import_module(
                "converters.cloud_import")}, self.diagnostics)

        def _validate(self, values: dict[str, Any]) -> None:
            CloudToScanCore(**settings(values))

        def _apply(self, values: dict[str, Any], changed: set[str]) -> None:
            fresh = CloudToScanCore(**settings(values))
            self.core.options = fresh.options
            self.core.angle_tolerance = fresh.angle_tolerance
            self.core.offset_tolerance = fresh.offset_tolerance
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

        def _on_cloud(self, raw: bytes) -> None:
            from lidarscan import decode

            self.stats["clouds"] += 1
            if self.core.info is not None and self.scan_pub.get_subscription_count() == 0:
                self.stats["idle"] += 1
                return
            try:
                cloud = decode(raw, "sensor_msgs/msg/PointCloud2")
                scan, info, changed = self.core.convert(cloud)
            except LidarScanError as err:
                self.stats["bad"] += 1
                self._log(f"PointCloud2 #{self.stats['clouds']} not converted: {err}", "bad")
                return
            except Exception as err:  # noqa: BLE001 - a node must survive any input
                self.stats["bad"] += 1
                self._log(f"PointCloud2 #{self.stats['clouds']} not converted (internal error "
                          f"{type(err).__name__}: {err})", "internal")
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
