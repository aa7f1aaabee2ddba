"""The converter node's Ouster packet input (converters.edge.nodes.ouster_input) over real rclpy
publishers: the decoded LidarScan + latched LidarInfo and the node's own PointCloud2 of them.

ouster-ros's message package is not in this environment, so the PacketMsg subscription is made
with a stand-in type and the packets' CDR is handed to the node's callback; everything after
(decoder, publishers, conversion) is the node's."""

from __future__ import annotations

import struct
import sys
import types
from typing import Any

import numpy as np
import pytest

from converters import ouster
from lidarscan.errors import ConfigError

from ouster_packet_helpers import DATA, OS0
from test_nodes import Graph, graph, overrides  # noqa: F401 - graph is a fixture


def _cdr_bytes(payload: bytes, nul: bool = False) -> bytes:
    data = bytes(payload) + (b"\x00" if nul else b"")
    return b"\x00\x01\x00\x00" + struct.pack("<I", len(data)) + data


@pytest.mark.ros
def test_ouster_input_needs_ouster_sensor_msgs(graph: Graph) -> None:  # noqa: F811
    from converters.edge.nodes.converter_node import ConverterNode

    try:
        import ouster_sensor_msgs  # noqa: F401
        pytest.skip("ouster_sensor_msgs is installed here")
    except ImportError:
        pass
    with pytest.raises(ConfigError, match="ouster_sensor_msgs"):
        ConverterNode(context=graph.context, parameter_overrides=overrides(
            **{"ouster.enabled": True}))
    with pytest.raises(ConfigError, match="scan_topic"):
        ConverterNode(context=graph.context, parameter_overrides=overrides(
            **{"ouster.enabled": True, "ouster.scan_topic": "lidar_scan"}))


@pytest.mark.ros
def test_ouster_packets_to_scan_info_and_cloud(graph: Graph,  # noqa: F811
                                               monkeypatch: Any) -> None:
    from lidarscan_msgs.msg import LidarInfo, LidarScan
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import UInt8MultiArray

    import lidarscan
    from converters.edge.nodes.converter_node import ConverterNode

    stand_in = types.ModuleType("ouster_sensor_msgs.msg")
    stand_in.PacketMsg = UInt8MultiArray  # type: ignore[attr-defined]
    package = types.ModuleType("ouster_sensor_msgs")
    package.msg = stand_in  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "ouster_sensor_msgs", package)
    monkeypatch.setitem(sys.modules, "ouster_sensor_msgs.msg", stand_in)

    scans = graph.collect(LidarScan, "ouster/lidar_scan")
    infos = graph.collect(LidarInfo, "ouster/lidar_info", "latched")
    clouds = graph.collect(PointCloud2, "points")
    node = graph.add(ConverterNode(context=graph.context, parameter_overrides=overrides(
        **{"ouster.enabled": True})))
    meta = DATA / f"{OS0}.json"
    packets = [p for _, p in ouster.lidar_packets(DATA / f"{OS0}.pcap", meta)]
    node._on_ouster_packet(_cdr_bytes(packets[0]))          # before the metadata: dropped
    assert node.ouster_stats["packets_without_metadata"] == 1
    node._on_ouster_metadata(_cdr_bytes(meta.read_bytes(), nul=True))
    assert graph.wait(lambda: len(infos) >= 1)
    for p in packets:
        node._on_ouster_packet(_cdr_bytes(p))
    assert node.ouster_stats["frames"] == 1 and node.ouster_decoder.stats["packets"] == 64
    assert graph.wait(lambda: scans and clouds, timeout=20,
                      tick=lambda: node._ouster_frames([]))
    (expected, info), = ouster.scans_from_pcap(DATA / f"{OS0}.pcap", meta)
    assert lidarscan.encode(scans[0]) == lidarscan.encode(expected)
    assert lidarscan.encode(infos[-1]) == lidarscan.encode(info)
    assert clouds[0].header.stamp == expected.header.stamp
    assert clouds[0].width * clouds[0].height == 32 * 1024
    node._on_ouster_packet(b"\x00\x01\x00\x00" + struct.pack("<I", 3) + b"abc")
    assert node.ouster_stats["bad_packets"] == 1
    status = node._diagnose_ouster()
    assert status.values["frames"] == 1 and status.values["missing_columns"] == 0
    assert np.isfinite(lidarscan.channel(scans[0], "range")).any()
