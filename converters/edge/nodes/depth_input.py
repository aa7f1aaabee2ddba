"""The depth-camera input of ``lidarscan-converter``: ``sensor_msgs/Image`` + ``CameraInfo``
paired by identical stamps, converted to LidarScans and sliced like the lidar's scans.

Parameters ``depth.*`` (declared with the node's others in
:func:`converters.edge.nodes.converter_node._specs`; behaviour in that module's docstring). This
module holds what the node does with them: :func:`depth_options` (the keyword options of
:class:`converters.sources.depth.DepthImageConverter`) and :class:`DepthInput`, the part of
``ConverterNode`` that subscribes to both inputs, pairs them with
:class:`converters.edge.nodes.common.ExactSync`, builds the converter and slice tables of each new
CameraInfo content before the image that needs them, publishes ``<depth.slice_namespace>/NAME``
(and the LidarScan + latched LidarInfo with ``depth.publish_scan``) and reports the ``depth``
diagnostics.

Importing this module does not import rclpy: :class:`DepthInput` is a plain mixin whose methods
use the rclpy ``Node`` they are mixed into (``create_publisher``, ``create_subscription``,
``get_clock``) and the converter node's ``core``, ``target_frame``, ``_mount``, ``_log``,
``_status`` and ``_lookup_error``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from converters.edge.nodes.common import ExactSync, Guard, LatencyWindow
from converters.edge.nodes.params import parse_extrinsics
from lidarscan.errors import ConfigError, LidarScanError

__all__ = ["DepthInput", "depth_options"]


def depth_options(values: Mapping[str, Any]) -> dict[str, Any]:
    """Keyword options of :class:`converters.sources.depth.DepthImageConverter` from checked
    parameter values."""
    rectified = {"auto": None, "true": True, "false": False}[values["depth.rectified"]]
    invalid = math.inf if values["depth.no_measurement"] == "no_return" else math.nan
    return {"rectified": rectified, "invalid": invalid, "range_min": values["depth.range_min"],
            "range_max": values["depth.range_max"]}


class DepthInput:
    """The depth-image input of ``ConverterNode`` (mixed in before rclpy's ``Node``)."""

    def _init_depth(self, values: dict[str, Any], out_qos: Any) -> None:
        """Subscriptions and publishers of the depth-image input (``depth.*``)."""
        from converters.edge.nodes.converter_core import ConverterCore, ConverterStats

        self.depth_sync: Any = None
        self._depth_latency = LatencyWindow()
        self.depth_converter: Any = None
        self.depth_pubs: dict[str, Any] = {}
        self.depth_scan_pub = self.depth_info_pub = None
        self.depth_stats = ConverterStats()
        self._depth_last: dict[str, Any] = {}
        if not values["depth.enabled"]:
            return
        if not self.target_frame:
            raise ConfigError("target_frame", "", "a frame with z up (e.g. base_link) "
                              "when depth.enabled: a camera's own frame has z forward")
        from lidarscan_msgs.msg import LidarInfo, LidarScan
        from sensor_msgs.msg import CameraInfo, Image, LaserScan

        from converters.edge.nodes import params as P

        self.depth_options = depth_options(values)
        self.depth_extrinsics = parse_extrinsics(values["depth.extrinsics"],
                                                 "depth.extrinsics") \
            if values["depth.extrinsics"] else None
        self.depth_core = ConverterCore(slices=self.core.slices,
                                        target_frame=self.target_frame,
                                        slice_options={"intensity_channel": None})
        self.depth_sync = ExactSync(("image", "camera_info"), values["depth.sync_queue"])
        space = values["depth.slice_namespace"].rstrip("/")
        self.depth_pubs = {s.name: self.create_publisher(
            LaserScan, f"{space}/{s.name}" if space else s.name, out_qos)
            for s in self.core.slices}
        if values["depth.publish_scan"]:
            self.depth_scan_pub = self.create_publisher(LidarScan, values["depth.scan_topic"],
                                                        out_qos)
            self.depth_info_pub = self.create_publisher(
                LidarInfo, values["depth.info_topic"], P.qos_profile("latched"))
        in_qos = P.qos_profile(values["depth.qos"])
        self.create_subscription(Image, values["depth.image_topic"], self._on_depth_image,
                                 in_qos, raw=True)
        self.create_subscription(CameraInfo, values["depth.camera_info_topic"],
                                 self._on_depth_info, in_qos, raw=True)

    def _on_depth_image(self, raw: bytes) -> None:
        self._depth_add("image", raw, "sensor_msgs/msg/Image")

    def _on_depth_info(self, raw: bytes) -> None:
        self._depth_add("camera_info", raw, "sensor_msgs/msg/CameraInfo")

    def _depth_add(self, name: str, raw: bytes, msgtype: str) -> None:
        """Decode one depth input (a new CameraInfo content builds its converter and
        tables at once) and pass it to the synchroniser, which may release a pair;
        malformed input is counted and logged."""
        from lidarscan import decode
        from lidarscan.stamps import to_ns

        st = self.depth_stats
        if name == "image":
            st.scans_received += 1
        else:
            st.infos_received += 1
        def bad(err: Exception) -> None:
            st.bad_messages += 1
            st.count(f"bad {msgtype}: {err}")

        with Guard(self._log, f"bad {msgtype} ignored", bad=bad, key=f"bad depth {name}",
                   internal=lambda err: st.count(f"internal: {type(err).__name__}"),
                   internal_key="depth internal") as guard:
            msg = decode(raw, msgtype)
            stamp = to_ns(msg.header.stamp, field=f"{msgtype}.header.stamp")
            if name == "camera_info":
                self._depth_camera(msg)
        if guard.failed:
            return
        pair = self.depth_sync.add(name, stamp, msg)
        if pair is not None:
            self._convert_depth(*pair)

    def _depth_camera(self, camera_info: Any) -> bool:
        """Build the depth converter for a new CameraInfo content, and the slice tables
        of its LidarInfo version (before the image that needs them); True if new."""
        from converters.sources.depth import DepthImageConverter

        if self.depth_converter is None:
            self.depth_converter = DepthImageConverter(camera_info, **self.depth_options)
        elif not self.depth_converter.update(camera_info):
            return False
        info = self.depth_converter.info
        if self.depth_info_pub is not None:
            self.depth_info_pub.publish(info)
        try:
            self.depth_core.prepare(info, self._depth_extrinsics(info, None), cloud=False,
                                    intensity=False)
        except (LidarScanError, self._lookup_error):
            pass                  # no transform yet: the first image reports it
        return True

    def _convert_depth(self, image: Any, camera_info: Any) -> None:
        st = self.depth_stats
        want = [n for n, p in self.depth_pubs.items() if p.get_subscription_count()]
        want_scan = self.depth_scan_pub is not None and \
            self.depth_scan_pub.get_subscription_count() > 0
        if not want and not want_scan:
            st.scans_idle += 1
            return
        from lidarscan.stamps import to_ns

        def failed(line: str) -> None:
            st.conversion_errors += 1
            st.count(line)

        slices: dict[str, Any] = {}
        with Guard(self._log, "depth image not converted", key="depth",
                   bad=lambda err: failed(f"depth: {err}"),
                   internal=lambda err: failed(f"internal: {type(err).__name__}"),
                   internal_key="depth internal") as guard:
            self._depth_camera(camera_info)
            scan, info = self.depth_converter.convert(image)
            if want:
                extrinsics = self._depth_extrinsics(info, to_ns(scan.header.stamp))
                _, slices = self.depth_core.convert(scan, info, cloud=False, slices=want,
                                                    extrinsics=extrinsics)
        if guard.failed:
            return
        if want_scan:
            self.depth_scan_pub.publish(scan)
        for name, msg in slices.items():
            self.depth_pubs[name].publish(msg)
            st.slices_published += 1
        self._depth_latency.add(self.get_clock().now().nanoseconds -
                                to_ns(scan.header.stamp))

    def _depth_extrinsics(self, info: Any, stamp_ns: int | None) -> np.ndarray[Any, Any]:
        """target_frame <- camera: TF at the image stamp, else ``depth.extrinsics``."""
        return self._mount(info.header.frame_id, stamp_ns, self.depth_extrinsics,
                           "depth.extrinsics")

    def _apply_depth(self, values: dict[str, Any], config: dict[str, Any]) -> None:
        """Accepted parameter changes (``config``: :func:`settings` of ``values``) for the
        depth input, when it is enabled."""
        if self.depth_sync is None:
            return
        self.depth_core.reconfigure(**{**{k: v for k, v in config.items()
                                          if k != "target_frame"},
                                       "slice_options": {"intensity_channel": None}})
        self.depth_options = depth_options(values)
        self.depth_extrinsics = parse_extrinsics(
            values["depth.extrinsics"], "depth.extrinsics") \
            if values["depth.extrinsics"] else None
        self.depth_converter = None       # rebuilt with the next CameraInfo
        self.depth_sync.queue_size = values["depth.sync_queue"]

    def _diagnose_depth(self) -> Any:
        Status, WARN, ERROR = self._status
        st, sync = self.depth_stats, self.depth_sync
        drops = sync.drops()
        values = {"images_received": st.scans_received,
                  "camera_infos_received": st.infos_received,
                  "pairs": sync.released, "images_idle": st.scans_idle,
                  "slices_published": st.slices_published,
                  "bad_messages": st.bad_messages, "conversion_errors": st.conversion_errors,
                  "sync_dropped": drops, **{f"waiting_{k}": v for k, v in
                                            sync.waiting().items()},
                  "camera": "none yet" if self.depth_converter is None else
                  f"{int(self.depth_converter.info.height)}x"
                  f"{int(self.depth_converter.info.width)} "
                  f"{'rectified' if self.depth_converter.rectified else 'raw'}"}
        status = Status("depth", {**values, **self._depth_latency.take()})
        last = self._depth_last
        self._depth_last = dict(values)
        for key, level, what in (("sync_dropped", WARN, "image/CameraInfo message(s) "
                                  "without a partner of the same stamp dropped"),
                                 ("bad_messages", WARN, "malformed depth message(s)"),
                                 ("conversion_errors", ERROR, "depth image(s) not "
                                  "converted (e.g. no transform)")):
            new = values[key] - last.get(key, 0)
            if new:
                status.worse(level, f"{new} {what}")
        if not st.scans_received:
            status.worse(WARN, "no depth image received")
        return status
