"""The Ouster packet input of ``lidarscan-converter``: ouster-ros's ``lidar_packets``
(``ouster_sensor_msgs/msg/PacketMsg``, one UDP payload each) and ``metadata``
(``std_msgs/msg/String``, the sensor's JSON, latched) decoded into LidarScan + LidarInfo.

Parameters ``ouster.*`` (declared with the node's others in
:func:`converters.edge.nodes.converter_node._specs`): ``ouster.enabled`` [false],
``ouster.packet_topic`` [``/ouster/lidar_packets``], ``ouster.metadata_topic``
[``/ouster/metadata``], ``ouster.metadata_file`` [""] (the JSON to use until, or instead of, a
metadata message), ``ouster.qos`` [sensor_data] (of the packets; the metadata is read latched),
``ouster.scan_topic`` [``ouster/lidar_scan``], ``ouster.info_topic`` [``ouster/lidar_info``]
(latched). Each decoded frame (:class:`converters.sources.ouster.decoder.PacketDecoder`) is
published there and goes through the node's own conversion (PointCloud2, slices), as if it had
arrived on ``scan_topic``. Packets that arrive before any metadata are dropped and counted; a
new metadata text rebuilds the decoder (the frame being gathered is emitted first).

Needs ouster-ros's message package (``ouster_sensor_msgs``) in the ROS environment: rclpy
subscribes only to types it has the generated code of; without it ``ouster.enabled`` is refused
at start-up with that reason.

Importing this module does not import rclpy: :class:`OusterInput` is a mixin whose methods use
the rclpy ``Node`` they are mixed into and the converter node's ``core``, ``_prepare``,
``_publish``, ``_log`` and ``_status``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from lidarscan.errors import ConfigError, LidarScanError

__all__ = ["OusterInput", "ouster_specs"]


def ouster_specs(S: Any, qos_names: tuple[str, ...]) -> tuple[Any, ...]:  # noqa: N803
    """Parameters of the Ouster packet input (``ouster.*``), built with ``S`` = ParamSpec."""
    return (
        S("ouster.enabled", False, "also decode ouster-ros lidar packets (PacketMsg + the "
          "metadata String) into LidarScan + LidarInfo", read_only=True),
        S("ouster.packet_topic", "/ouster/lidar_packets", "input ouster_sensor_msgs/PacketMsg",
          read_only=True),
        S("ouster.metadata_topic", "/ouster/metadata", "input std_msgs/String with the "
          "sensor's metadata JSON (latched)", read_only=True),
        S("ouster.metadata_file", "", "the sensor's metadata JSON file, used until (or "
          "instead of) a metadata message", read_only=True),
        S("ouster.qos", "sensor_data", "QoS of the packet input", choices=qos_names,
          read_only=True),
        S("ouster.scan_topic", "ouster/lidar_scan", "output LidarScan of the decoded frames",
          read_only=True),
        S("ouster.info_topic", "ouster/lidar_info", "output LidarInfo of the sensor (latched)",
          read_only=True),
    )


class OusterInput:
    """The Ouster packet input of ``ConverterNode`` (mixed in before rclpy's ``Node``)."""

    def _init_ouster(self, values: dict[str, Any], out_qos: Any) -> None:
        """Subscriptions and publishers of the Ouster packet input (``ouster.*``)."""
        self.ouster_decoder: Any = None
        self.ouster_metadata: str | None = None
        self.ouster_stats = {"packets": 0, "packets_without_metadata": 0, "bad_packets": 0,
                             "frames": 0, "metadata_received": 0}
        self.ouster_scan_pub = self.ouster_info_pub = None
        if not values["ouster.enabled"]:
            return
        if values["ouster.scan_topic"] == values["scan_topic"]:
            raise ConfigError("ouster.scan_topic", values["ouster.scan_topic"],
                              "a topic other than scan_topic (the node converts the decoded "
                              "scans itself)")
        try:
            from ouster_sensor_msgs.msg import PacketMsg
        except ImportError as err:
            raise ConfigError("ouster.enabled", True, "ouster-ros's message package "
                              "ouster_sensor_msgs in this ROS environment (rclpy needs its "
                              f"generated code to subscribe to PacketMsg): {err}") from err
        from lidarscan_msgs.msg import LidarInfo, LidarScan
        from std_msgs.msg import String

        from converters.edge.nodes import params as P

        if values["ouster.metadata_file"]:
            path = Path(values["ouster.metadata_file"])
            try:
                self._ouster_use(path.read_text(encoding="utf-8"))
            except OSError as err:
                raise ConfigError("ouster.metadata_file", str(path), "a readable Ouster "
                                  f"metadata JSON file ({err})") from err
        self.ouster_scan_pub = self.create_publisher(LidarScan, values["ouster.scan_topic"],
                                                     out_qos)
        self.ouster_info_pub = self.create_publisher(LidarInfo, values["ouster.info_topic"],
                                                     P.qos_profile("latched"))
        if self.ouster_decoder is not None:
            self.ouster_info_pub.publish(self.ouster_decoder.info)
        self._ouster_subscriptions = [
            (String, values["ouster.metadata_topic"], self._on_ouster_metadata,
             P.qos_profile("latched")),
            (PacketMsg, values["ouster.packet_topic"], self._on_ouster_packet,
             P.qos_profile(values["ouster.qos"]))]

    def _subscribe_ouster(self) -> None:
        """The metadata and packet subscriptions (made after the warm-up: ready before
        listening), when the Ouster input is enabled."""
        for msgtype, topic, callback, qos in getattr(self, "_ouster_subscriptions", []):
            self.create_subscription(msgtype, topic, callback, qos, raw=True)

    def _ouster_use(self, text: str) -> None:
        """A decoder for this metadata text (raises LidarScanError for a bad one)."""
        from converters.sources.ouster.decoder import PacketDecoder

        if text == self.ouster_metadata:
            return
        decoder = PacketDecoder(text)
        if self.ouster_decoder is not None:
            self._ouster_frames(self.ouster_decoder.flush())
        self.ouster_decoder, self.ouster_metadata = decoder, text
        if self.ouster_info_pub is not None:
            self.ouster_info_pub.publish(decoder.info)

    def _on_ouster_metadata(self, raw: bytes) -> None:
        from converters.sources.ouster.bag import string_payload

        self.ouster_stats["metadata_received"] += 1
        try:
            self._ouster_use(string_payload(raw))
        except LidarScanError as err:
            self._log(f"Ouster metadata ignored: {err}", "ouster metadata")

    def _on_ouster_packet(self, raw: bytes) -> None:
        from converters.sources.bags import ouster_packets

        st = self.ouster_stats
        st["packets"] += 1
        if self.ouster_decoder is None:
            st["packets_without_metadata"] += 1
            return
        try:
            frames = self.ouster_decoder.push(0, ouster_packets(raw).data[0])
        except LidarScanError as err:
            st["bad_packets"] += 1
            self._log(f"Ouster packet ignored: {err}", "ouster packet")
            return
        self._ouster_frames(frames)

    def _ouster_frames(self, frames: list[tuple[Any, Any]]) -> None:
        """Publish decoded frames and hand them to the node's own conversion."""
        for scan, info in frames:
            self.ouster_stats["frames"] += 1
            if self.ouster_scan_pub is not None:
                self.ouster_scan_pub.publish(scan)
            ready = []
            if self.core.last_info is not info:     # the decoder's info: one object a version
                ready = self.core.add_info(info)
                self._prepare(info)
            self._publish(ready + self.core.add_scan(scan))

    def _diagnose_ouster(self) -> Any:
        Status, WARN, _ = self._status
        st = Status("ouster packets", {**self.ouster_stats, **(
            self.ouster_decoder.stats if self.ouster_decoder is not None else {})})
        if self.ouster_decoder is None:
            st.worse(WARN, "no Ouster metadata received (is /ouster/metadata latched?)")
        elif not self.ouster_stats["frames"]:
            st.worse(WARN, "no Ouster frame decoded yet")
        return st
