"""Real rclpy publish -> subscribe through Fast DDS, in one process.

A 128x2048 scan with six channels (range f32, intensity u16, reflectivity u8, ambient u16,
flags u8, range2 f32) goes through a typed and a ``raw=True`` subscription; a LidarInfo published
on a latched (reliable, transient-local) topic reaches a subscriber created afterwards.

Each test gets its own rclpy Context, a domain id derived from the pid and discovery limited to
localhost, and shuts everything down in ``finally``.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest

import lidarscan

pytestmark = pytest.mark.ros

TIMEOUT_S = 20.0
H, W = 128, 2048


@pytest.fixture
def ros(monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[Any, Any]]:
    """(node, executor) on a fresh Context; everything is destroyed afterwards."""
    rclpy = pytest.importorskip("rclpy")
    pytest.importorskip("lidarscan_msgs.msg")
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.delenv("ROS_LOCALHOST_ONLY", raising=False)
    context = Context()
    rclpy.init(context=context, domain_id=100 + os.getpid() % 100)
    node = executor = None
    try:
        node = rclpy.create_node(f"lidarscan_test_{os.getpid()}", context=context)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        yield node, executor
    finally:
        if executor is not None:
            executor.shutdown(timeout_sec=2.0)
        if node is not None:
            node.destroy_node()
        rclpy.shutdown(context=context)


def _spin_until(executor: Any, done: Callable[[], bool], timeout: float = TIMEOUT_S) -> bool:
    deadline = time.monotonic() + timeout
    while not done() and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.05)
    return done()


def _channels() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(128)
    rng_f = rng.random((H, W), np.float32) * 100
    rng_f[rng.random((H, W)) < 0.1] = np.inf  # no return
    return {
        "range": rng_f,
        "intensity": rng.integers(0, 2**16, (H, W), dtype=np.uint16),
        "reflectivity": rng.integers(0, 256, (H, W), dtype=np.uint8),
        "ambient": rng.integers(0, 2**16, (H, W), dtype=np.uint16),
        "flags": rng.integers(0, 256, (H, W), dtype=np.uint8),
        "range2": np.where(rng.random((H, W)) < 0.5, np.inf, rng_f + 1).astype(np.float32),
    }


def _info() -> Any:
    return lidarscan.make_info(
        stamp_ns=1_700_000_000_000_000_000, frame_id="os_sensor",
        vertical_angles=np.linspace(np.radians(22.5), np.radians(-22.5), H),
        horizontal_angles=2 * np.pi * (1 - np.arange(W) / W),
        beam_time_offsets=np.zeros(H, np.int64), column_time_increment=48_828,
        pixel_shift_by_row=np.tile([12, 4, -4, -12], H // 4), vendor="Ouster", model="OS-1-128")


def _topic(node: Any, name: str) -> str:
    return f"/lidarscan_test_{os.getpid()}_{id(node)}/{name}"


def _assert_scan_equal(got: Any, channels: dict[str, np.ndarray], sent: Any) -> None:
    assert lidarscan.channel_names(got) == list(channels)
    for name, expected in channels.items():
        np.testing.assert_array_equal(lidarscan.channel(got, name), expected, err_msg=name)
    assert np.array_equal(lidarscan.scan.data_view(got), lidarscan.scan.data_view(sent))
    assert lidarscan.encode(got) == lidarscan.encode(sent)


def test_scan_publish_subscribe_typed_and_raw(ros: tuple[Any, Any]) -> None:
    from lidarscan_msgs.msg import LidarScan
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    node, executor = ros
    info = _info()
    channels = _channels()
    scan = lidarscan.make_scan(info, channels, 1_700_000_000_050_000_000,
                               column_time_offsets=np.arange(W, dtype=np.int64) * 48_828)
    lidarscan.validate(scan, info)
    assert len(scan.data) == H * W * (4 + 2 + 1 + 2 + 1 + 4)

    qos = QoSProfile(depth=2, reliability=ReliabilityPolicy.RELIABLE)
    typed: list[Any] = []
    raw: list[bytes] = []
    topic = _topic(node, "scan")
    node.create_subscription(LidarScan, topic, typed.append, qos)
    node.create_subscription(LidarScan, topic, raw.append, qos, raw=True)
    pub = node.create_publisher(LidarScan, topic, qos)
    assert _spin_until(executor, lambda: pub.get_subscription_count() >= 2), "no discovery"
    pub.publish(scan)
    assert _spin_until(executor, lambda: bool(typed) and bool(raw)), \
        f"timeout: typed={len(typed)} raw={len(raw)}"

    got = typed[0]
    assert got.header == scan.header and got.lidar_info_time == scan.lidar_info_time
    assert (got.height, got.width) == (H, W)
    lidarscan.validate(got, info)
    _assert_scan_equal(got, channels, scan)

    payload = raw[0]
    assert isinstance(payload, bytes)
    decoded = lidarscan.decode_scan(payload)
    lidarscan.validate(decoded, info)
    _assert_scan_equal(decoded, channels, scan)
    assert np.shares_memory(lidarscan.channel(decoded, "range2"), np.frombuffer(payload, np.uint8))
    assert decoded.column_time_offsets.tolist() == list(np.arange(W) * 48_828)


def test_bytes_we_encode_are_what_dds_delivers(ros: tuple[Any, Any]) -> None:
    """Publishing our own CDR bytes (publish of serialized data) reaches a typed subscriber."""
    from lidarscan_msgs.msg import LidarScan
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    node, executor = ros
    info = _info()
    channels = {"range": _channels()["range"][:, :64]}
    small = lidarscan.make_info(stamp_ns=1_700_000_000_000_000_000, frame_id="os_sensor",
                                vertical_angles=np.asarray(info.vertical_angles),
                                horizontal_angles=np.asarray(info.horizontal_angles)[:64])
    scan = lidarscan.make_scan(small, channels, 5, as_dataclass=True)
    qos = QoSProfile(depth=2, reliability=ReliabilityPolicy.RELIABLE)
    received: list[Any] = []
    topic = _topic(node, "scan_bytes")
    node.create_subscription(LidarScan, topic, received.append, qos)
    pub = node.create_publisher(LidarScan, topic, qos)
    assert _spin_until(executor, lambda: pub.get_subscription_count() >= 1), "no discovery"
    pub.publish(lidarscan.encode(scan))  # rclpy publishes bytes as a serialized message
    assert _spin_until(executor, lambda: bool(received)), "timeout"
    np.testing.assert_array_equal(lidarscan.channel(received[0], "range"), channels["range"])
    assert lidarscan.encode(received[0]) == lidarscan.encode(scan)


def test_info_latched_reaches_late_subscriber(ros: tuple[Any, Any]) -> None:
    from lidarscan_msgs.msg import LidarInfo
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    node, executor = ros
    info = _info()
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    topic = _topic(node, "lidar_info")
    pub = node.create_publisher(LidarInfo, topic, latched)
    pub.publish(info)
    executor.spin_once(timeout_sec=0.1)
    received: list[Any] = []
    node.create_subscription(LidarInfo, topic, received.append, latched)  # joins late
    assert _spin_until(executor, lambda: bool(received)), "late subscriber got no LidarInfo"
    got = received[0]
    lidarscan.validate_info(got)
    assert got.header == info.header
    assert lidarscan.encode(got) == lidarscan.encode(info)
    assert len(received) == 1
