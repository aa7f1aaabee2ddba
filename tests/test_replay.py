"""Recordings the project writes replay right (rosbag2 QoS and metadata, lidarscan/rosbag2.py).

* Every MCAP written by :class:`lidarscan.mcap.McapWriter` carries, per channel, the QoS its
  publishers offer in rosbag2's form (read back with the ``mcap`` package and with ``rosbags``,
  two independent readers) and the ``rosbag2`` metadata record; :class:`BagWriter` makes a
  rosbag2 directory (``metadata.yaml`` + the .mcap) that ``rosbags`` opens as a bag.
* Replay through rclpy: a small player publishes each recorded channel with the QoS parsed from
  the recording, the latched LidarInfo BEFORE the converter node exists (as ``ros2 bag play``
  does when a node starts late); the converter receives it and publishes a cloud per scan. The
  same replay with the volatile QoS rosbag2 uses for a channel without recorded QoS delivers
  no LidarInfo and no cloud (the failure this fixes), so the test can fail.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

import lidarscan as ls
from lidarscan.errors import ConfigError
from lidarscan.mcap import INFO_TYPE, SCAN_TYPE, McapWriter, read_messages
from lidarscan.rosbag2 import (
    QOS_PROFILES,
    BagWriter,
    QosProfile,
    default_qos,
    dump_qos,
    parse_qos,
)

INFO_TOPIC = "/sensor/lidar_info"
SCAN_TOPIC = "/sensor/lidar_scan"
T0 = 1_700_000_000_000_000_000
N_SCANS = 5


def small_pair(h: int = 8, w: int = 64) -> tuple[Any, list[Any]]:
    info = ls.make_info(stamp_ns=T0, frame_id="lidar",
                        vertical_angles=np.radians(np.linspace(10, -10, h)),
                        horizontal_angles=2 * np.pi * (1 - np.arange(w) / w), as_dataclass=True)
    rng = np.random.default_rng(7)
    scans = [ls.make_scan(info, {"range": rng.uniform(1, 20, (h, w)).astype(np.float32),
                                 "intensity": rng.integers(0, 900, (h, w)).astype(np.uint16)},
                          stamp_ns=T0 + (i + 1) * 100_000_000, as_dataclass=True)
             for i in range(N_SCANS)]
    return info, scans


def record(directory: Path, **options: Any) -> Path:
    info, scans = small_pair()
    with BagWriter(directory, **options) as bag:
        bag.write(INFO_TOPIC, info)
        for scan in scans:
            bag.write(SCAN_TOPIC, scan)
    return bag.mcap_path


# ------------------------------------------------------------------------- QoS and metadata

def test_qos_yaml_round_trip_and_rosbag2_enum_forms() -> None:
    for profile in QOS_PROFILES.values():
        assert parse_qos(dump_qos([profile])) == [profile]
    # metadata version <= 8 stores the rmw enum values as integers
    old = ("- history: 1\n  depth: 1\n  reliability: 1\n  durability: 1\n"
           "  deadline: {sec: 2147483647, nsec: 4294967295}\n"
           "  lifespan: {sec: 0, nsec: 5}\n  liveliness: 1\n"
           "  liveliness_lease_duration: {sec: 9223372036, nsec: 854775807}\n"
           "  avoid_ros_namespace_conventions: false\n")
    assert parse_qos(old) == [QosProfile(depth=1, durability="transient_local",
                                         lifespan_ns=5)]
    assert parse_qos("") == []
    with pytest.raises(ls.errors.McapFormatError):
        parse_qos("- history: keep_some\n  depth: 1\n  reliability: reliable\n"
                  "  durability: volatile\n")
    with pytest.raises(ConfigError):
        McapWriter(Path(os.devnull), qos={"/x": "latchd"})


def test_default_qos_by_type_and_topic() -> None:
    assert default_qos("/a", INFO_TYPE) == QosProfile(depth=1, durability="transient_local")
    assert default_qos("/tf_static", "tf2_msgs/msg/TFMessage").durability == "transient_local"
    for msgtype in (SCAN_TYPE, "sensor_msgs/msg/PointCloud2", "sensor_msgs/msg/LaserScan"):
        assert default_qos("/a", msgtype) == QosProfile(depth=5, reliability="best_effort")
    assert default_qos("/odom", "nav_msgs/msg/Odometry") == QosProfile(depth=10)


def test_bag_directory_reads_back_with_mcap_and_rosbags(tmp_path: Path) -> None:
    from mcap.reader import make_reader
    from rosbags.rosbag2 import Reader

    bag = tmp_path / "run1"
    mcap_path = record(bag, qos={SCAN_TOPIC: {"reliability": "reliable", "depth": 3}})
    assert sorted(p.name for p in bag.iterdir()) == ["metadata.yaml", "run1_0.mcap"]
    expect = {INFO_TOPIC: QosProfile(depth=1, durability="transient_local"),
              SCAN_TOPIC: QosProfile(depth=3)}              # overridden for this topic

    with open(mcap_path, "rb") as f:                        # reader 1: the mcap package
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        channels = {c.topic: c for c in summary.channels.values()}
        assert {t: parse_qos(c.metadata["offered_qos_profiles"]) for t, c in channels.items()} \
            == {t: [q] for t, q in expect.items()}
        records = [m for m in reader.iter_metadata() if m.name == "rosbag2"]
    assert len(records) == 1 and set(records[0].metadata) == {"serialized_metadata"}
    embedded = yaml.safe_load(records[0].metadata["serialized_metadata"])
    on_disk = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert embedded == on_disk
    assert on_disk["version"] == 9 and on_disk["storage_identifier"] == "mcap"
    assert on_disk["message_count"] == 1 + N_SCANS
    assert on_disk["relative_file_paths"] == ["run1_0.mcap"]
    assert on_disk["starting_time"]["nanoseconds_since_epoch"] == T0
    assert on_disk["duration"]["nanoseconds"] == N_SCANS * 100_000_000
    counts = {t["topic_metadata"]["name"]: t["message_count"]
              for t in on_disk["topics_with_message_count"]}
    assert counts == {INFO_TOPIC: 1, SCAN_TOPIC: N_SCANS}

    with Reader(bag) as reader:                             # reader 2: rosbags, as a rosbag2 bag
        assert reader.message_count == 1 + N_SCANS
        assert reader.start_time == T0 and reader.duration == N_SCANS * 100_000_000 + 1
        got = {c.topic: c.ext.offered_qos_profiles for c in reader.connections}
        assert {t: [(q.depth, q.reliability.name, q.durability.name) for q in v]
                for t, v in got.items()} == {
            INFO_TOPIC: [(1, "RELIABLE", "TRANSIENT_LOCAL")],
            SCAN_TOPIC: [(3, "RELIABLE", "VOLATILE")]}
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types == {INFO_TOPIC: INFO_TYPE, SCAN_TOPIC: SCAN_TYPE}
        assert sum(1 for _ in reader.messages()) == 1 + N_SCANS


def test_plain_mcap_file_carries_qos_and_given_metadata_wins(tmp_path: Path) -> None:
    from mcap.reader import make_reader

    info, scans = small_pair()
    given = dump_qos([QosProfile(depth=7, reliability="best_effort")])
    path = tmp_path / "plain.mcap"
    with McapWriter(path) as writer:
        writer.write(INFO_TOPIC, info)
        writer.write(SCAN_TOPIC, scans[0], metadata={"offered_qos_profiles": given,
                                                     "note": "kept"})
        writer.write("/odom_raw", b"\x00\x01\x00\x00", msgtype="std_msgs/msg/Empty")
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        meta = {c.topic: c.metadata for c in summary.channels.values()}
        serialized = [m.metadata["serialized_metadata"] for m in reader.iter_metadata()]
    assert parse_qos(meta[INFO_TOPIC]["offered_qos_profiles"]) == [QOS_PROFILES["latched"]]
    assert parse_qos(meta[SCAN_TOPIC]["offered_qos_profiles"]) == parse_qos(given)
    assert meta[SCAN_TOPIC]["note"] == "kept"
    assert parse_qos(meta["/odom_raw"]["offered_qos_profiles"]) == [QOS_PROFILES["reliable"]]
    assert yaml.safe_load(serialized[0])["relative_file_paths"] == ["plain.mcap"]
    # the project's own reader is unaffected
    assert [m.topic for m in read_messages(path)] == [INFO_TOPIC, SCAN_TOPIC, "/odom_raw"]


def test_bag_writer_refuses_a_used_directory(tmp_path: Path) -> None:
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "x").write_text("x")
    with pytest.raises(ConfigError, match="empty directory"):
        BagWriter(tmp_path / "old")


# ------------------------------------------------------------------------------- replay

def rclpy_qos(profile: QosProfile) -> Any:
    """The rclpy QoSProfile a player offers for a recorded profile."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        history=HistoryPolicy.KEEP_ALL if profile.history == "keep_all"
        else HistoryPolicy.KEEP_LAST,
        depth=max(profile.depth, 1),
        reliability=ReliabilityPolicy.BEST_EFFORT if profile.reliability == "best_effort"
        else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if profile.durability == "transient_local"
        else DurabilityPolicy.VOLATILE)


def recorded_channels(mcap_path: Path) -> dict[str, tuple[str, QosProfile]]:
    """topic -> (type, the QoS to offer), as rosbag2's player chooses it: the recorded
    profile, or reliable + volatile when the channel has none."""
    from mcap.reader import make_reader

    with open(mcap_path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    out = {}
    for c in summary.channels.values():
        offered = parse_qos(c.metadata.get("offered_qos_profiles", ""))
        out[c.topic] = (summary.schemas[c.schema_id].name,
                        offered[0] if offered else QOS_PROFILES["reliable"])
    return out


def replay(mcap_path: Path, channels: dict[str, tuple[str, QosProfile]],
           wait_s: float) -> Any:
    """Publish the recording: LidarInfo first, then start the converter, then the scans until
    a cloud arrives (or ``wait_s`` passes). Returns the converter's stats and the clouds."""
    import rclpy
    from lidarscan_msgs.msg import LidarInfo, LidarScan
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import PointCloud2

    from converters.edge.nodes import converter_node

    types = {INFO_TYPE: LidarInfo, SCAN_TYPE: LidarScan}
    messages = [m for m in read_messages(mcap_path) if m.topic in channels]
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=1 + (os.getpid() + 50) % 100)
    executor = SingleThreadedExecutor(context=context)
    nodes = []
    try:
        player = Node("player", context=context)
        nodes.append(player)
        executor.add_node(player)
        pubs = {t: player.create_publisher(types[msgtype], t, rclpy_qos(qos))
                for t, (msgtype, qos) in channels.items()}
        for m in messages:                      # the latched info, before any subscriber
            if m.msgtype == INFO_TYPE:
                pubs[m.topic].publish(m.payload)
        executor.spin_once(timeout_sec=0.2)
        converter = converter_node.ConverterNode(context=context, parameter_overrides=[
            Parameter("scan_topic", value=SCAN_TOPIC), Parameter("info_topic", value=INFO_TOPIC),
            Parameter("cloud_topic", value="/sensor/points")])
        nodes.append(converter)
        executor.add_node(converter)
        clouds: list[Any] = []
        player.create_subscription(PointCloud2, "/sensor/points", clouds.append,
                                   qos_profile_sensor_data)
        scans = [m for m in messages if m.msgtype == SCAN_TYPE]
        end = time.monotonic() + wait_s
        i = 0
        while time.monotonic() < end and not clouds:
            pubs[scans[i % len(scans)].topic].publish(scans[i % len(scans)].payload)
            i += 1
            for _ in range(5):
                executor.spin_once(timeout_sec=0.02)
        return converter.stats, clouds
    finally:
        for node in nodes:
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown()
        rclpy.try_shutdown(context=context)


@pytest.mark.ros
def test_replay_delivers_the_latched_info_to_a_late_converter(tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch
                                                              ) -> None:
    pytest.importorskip("rclpy")
    pytest.importorskip("lidarscan_msgs.msg")
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    mcap_path = record(tmp_path / "bag")
    channels = recorded_channels(mcap_path)
    assert channels[INFO_TOPIC][1].durability == "transient_local"
    stats, clouds = replay(mcap_path, channels, wait_s=20.0)
    assert stats.infos_received == 1
    assert clouds, f"no cloud from the converter: {stats}"
    info, _ = small_pair()
    assert (clouds[0].height, clouds[0].width) == (info.height, info.width)

    # the same recording without QoS: rosbag2 offers reliable + volatile, the converter's
    # transient-local LidarInfo subscription does not match, nothing is converted
    volatile = {t: (msgtype, QOS_PROFILES["reliable"]) for t, (msgtype, _) in channels.items()}
    stats, clouds = replay(mcap_path, volatile, wait_s=3.0)
    assert stats.infos_received == 0 and not clouds
