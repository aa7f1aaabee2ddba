"""The ROS 2 nodes: pure parts (TF buffer, parameters, log limiter, cores) and the real nodes
exchanging messages over Fast DDS.

Graph tests run every node in-process on one MultiThreadedExecutor, in a private rclpy Context
on a domain id derived from the pid (no cross-talk with other test runs) with discovery limited
to localhost; console scripts run as subprocesses. Every wait has a timeout; everything is shut
down in ``finally`` blocks.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import lidarscan
from converters.edge.nodes import params as P
from converters.edge.nodes.common import LogLimiter
from converters.edge.nodes.tf import (
    TransformBuffer,
    TransformLookupError,
    matrix_from_quaternion,
    matrix_from_xyz_rpy,
    quaternion_from_matrix,
    slerp,
)
from lidarscan.errors import ConfigError, LidarScanError, ValidationError

DOMAIN = 1 + os.getpid() % 100
VENV_BIN = Path(sys.executable).parent


# ------------------------------------------------------------------------------- fixtures

def small_info(stamp_ns: int = 5_000, frame: str = "lidar", width: int = 128) -> Any:
    """16 beams x ``width`` columns, +-15 deg, staggered (6, 4, 2, 0)."""
    return lidarscan.make_info(
        stamp_ns=stamp_ns, frame_id=frame, vertical_angles=np.radians(np.linspace(15, -15, 16)),
        horizontal_angles=2 * np.pi * (1 - np.arange(width) / width),
        pixel_shift_by_row=np.tile([6, 4, 2, 0], 4), column_time_increment=781_250,
        range_min=0.1, range_max=50.0)


def small_scan(info: Any, stamp_ns: int, seed: int = 0) -> Any:
    rng = np.random.default_rng(seed)
    shape = (int(info.height), int(info.width))
    ranges = rng.uniform(1.0, 5.0, shape).astype(np.float32)
    ranges[0, :5] = np.inf  # a few pixels without return
    return lidarscan.make_scan(info, {"range": ranges,
                                      "intensity": rng.integers(0, 1000, shape).astype(np.uint16)},
                               stamp_ns)


class Graph:
    """An executor spinning in a thread, plus a tester node to publish / subscribe."""

    def __init__(self, context: Any) -> None:
        from rclpy.executors import MultiThreadedExecutor
        from rclpy.node import Node

        self.context = context
        self.executor = MultiThreadedExecutor(num_threads=3, context=context)
        self.tester = Node("tester", context=context)
        self.nodes: list[Any] = [self.tester]
        self.executor.add_node(self.tester)
        self.received: dict[str, list[Any]] = {}
        self.closing = False
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            self.executor.spin()
        except (ExternalShutdownException, KeyboardInterrupt):
            pass
        except Exception:
            # rclpy's shutdown destroys the executor's guard condition while a spin round may
            # still trigger it (InvalidHandle): expected only once close() began
            if not self.closing:
                raise

    def add(self, node: Any) -> Any:
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def publisher(self, msg_type: Any, topic: str, qos: str = "reliable") -> Any:
        return self.tester.create_publisher(msg_type, topic, P.qos_profile(qos))

    def collect(self, msg_type: Any, topic: str, qos: str = "sensor_data") -> list[Any]:
        box = self.received.setdefault(topic, [])
        self.tester.create_subscription(msg_type, topic, box.append, P.qos_profile(qos))
        return box

    def wait(self, condition: Callable[[], bool], timeout: float = 10.0,
             tick: Callable[[], None] | None = None) -> bool:
        """Poll ``condition`` (calling ``tick`` each round, e.g. to re-publish) until true."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if tick is not None:
                tick()
            if condition():
                return True
            time.sleep(0.05)
        return condition()

    def close(self) -> None:
        self.closing = True
        self.executor.shutdown(timeout_sec=5.0)
        self._thread.join(timeout=5.0)
        for node in self.nodes:
            self.executor.remove_node(node)
            node.destroy_node()


@pytest.fixture
def graph(monkeypatch: pytest.MonkeyPatch) -> Any:
    rclpy = pytest.importorskip("rclpy")
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=DOMAIN)
    g = None
    try:
        g = Graph(context)
        yield g
    finally:
        if g is not None:
            g.close()
        rclpy.try_shutdown(context=context)


def overrides(**values: Any) -> list[Any]:
    from rclpy.parameter import Parameter

    return [Parameter(name.replace("__", "."), value=value) for name, value in values.items()]


def wire(msg: Any) -> Any:
    """The message as a subscriber receives it (float32 fields rounded by serialization)."""
    return lidarscan.decode(lidarscan.encode(msg), lidarscan.types.msgtype_of(msg))


def same_floats(a: Any, b: Any) -> bool:
    x = np.asarray(a, dtype=np.float32)
    y = np.asarray(b, dtype=np.float32)
    return x.shape == y.shape and bool(np.all((x == y) | (np.isnan(x) & np.isnan(y))))


# ------------------------------------------------------------------------------ TF buffer

def test_importing_nodes_cli_and_demo_does_not_import_rclpy() -> None:
    code = ("import sys, converters.edge.cli, converters.edge.demo.run, converters.edge.demo.viz, converters.edge.nodes, "
            "converters.edge.nodes.converter_node, converters.edge.nodes.merger_node, "
            "converters.edge.nodes.cloud_to_scan_node, converters.edge.nodes.tf, converters.edge.nodes.params; "
            "assert 'rclpy' not in sys.modules, 'rclpy imported'; "
            "assert 'matplotlib' not in sys.modules, 'matplotlib imported'")
    env = {k: v for k, v in os.environ.items() if k != "_ROS_WHEELS_BOOTSTRAP_COMPLETE"}
    done = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True, text=True,
                          timeout=60, env=env)
    assert done.returncode == 0, done.stderr


def test_quaternion_matrix_round_trip_and_rpy() -> None:
    m = matrix_from_xyz_rpy(1.0, -2.0, 0.5, 0.3, -0.2, 2.5)
    q = quaternion_from_matrix(m)
    assert q[3] >= 0
    back = matrix_from_quaternion(q, m[:3, 3])
    assert np.allclose(back, m, atol=1e-12)
    # yaw 90 deg maps +x to +y (REP 103, CCW)
    assert np.allclose(matrix_from_xyz_rpy(yaw=math.pi / 2)[:3, :3] @ [1, 0, 0], [0, 1, 0])
    with pytest.raises(ValidationError):
        matrix_from_quaternion((0, 0, 0, 0))


def test_slerp_takes_the_short_arc() -> None:
    q0 = quaternion_from_matrix(matrix_from_xyz_rpy(yaw=0.1))
    q1 = quaternion_from_matrix(matrix_from_xyz_rpy(yaw=0.5))
    antipodal = tuple(-v for v in q1)
    for target in (q1, antipodal):
        mid = matrix_from_quaternion(slerp(q0, target, 0.5))
        assert np.allclose(mid, matrix_from_xyz_rpy(yaw=0.3), atol=1e-12)


def test_transform_buffer_chains_interpolates_and_bounds() -> None:
    buf = TransformBuffer(tolerance_ns=50)
    base_from_lidar = matrix_from_xyz_rpy(0.2, 0.0, 0.5, 0.0, 0.1, math.pi)
    buf.set_transform("base_link", "lidar", base_from_lidar, static=True)
    buf.set_transform("odom", "base_link", matrix_from_xyz_rpy(0, 0, 0, yaw=0.0), 1000)
    buf.set_transform("odom", "base_link", matrix_from_xyz_rpy(2, 0, 0, yaw=1.0), 2000)
    # static + dynamic chain, interpolated at the middle (linear translation, slerp)
    got = buf.lookup("odom", "lidar", 1500)
    assert np.allclose(got, matrix_from_xyz_rpy(1, 0, 0, yaw=0.5) @ base_from_lidar, atol=1e-12)
    # inverse direction and a leading slash
    assert np.allclose(buf.lookup("/lidar", "odom", 1500), np.linalg.inv(got), atol=1e-12)
    # newest sample for time None; nearest within tolerance; beyond it an error
    assert np.allclose(buf.lookup("odom", "base_link"), matrix_from_xyz_rpy(2, 0, 0, yaw=1.0))
    assert np.allclose(buf.lookup("odom", "base_link", 2040), buf.lookup("odom", "base_link"))
    with pytest.raises(TransformLookupError):
        buf.lookup("odom", "base_link", 2100)
    with pytest.raises(TransformLookupError):
        buf.lookup("odom", "camera")
    assert buf.is_static("base_link", "lidar") and not buf.is_static("odom", "lidar")
    # dynamic samples are bounded in count and age; clear() keeps static edges
    small = TransformBuffer(cache_ns=10**12, max_per_edge=5, tolerance_ns=2)
    for k in range(20):
        small.set_transform("a", "b", np.eye(4), k)
    with pytest.raises(TransformLookupError):
        small.lookup("a", "b", 0)
    small.set_transform("a", "c", np.eye(4), static=True)
    small.clear()
    assert small.can_transform("a", "c") and not small.can_transform("a", "b")


def test_transform_buffer_reads_tf_messages_and_rejects_bad_ones() -> None:
    from geometry_msgs.msg import TransformStamped

    from converters.edge.demo.run import tf_message

    good = TransformStamped()
    good.header.frame_id, good.child_frame_id = "base_link", "laser"
    good.transform.translation.x = 0.25
    good.transform.rotation.w = 1.0
    buf = TransformBuffer()
    assert buf.add_message(tf_message([good]), static=True) == 1
    assert np.allclose(buf.lookup("base_link", "laser")[:3, 3], [0.25, 0, 0])
    bad = TransformStamped()
    bad.header.frame_id, bad.child_frame_id = "base_link", "cam"
    bad.transform.rotation.w = 0.0  # zero quaternion
    with pytest.raises(ValidationError):
        buf.add_message(tf_message([bad]))
    nan = TransformStamped()
    nan.header.frame_id, nan.child_frame_id = "base_link", "cam"
    nan.transform.rotation.w = 1.0
    nan.transform.translation.y = float("nan")
    with pytest.raises(ValidationError):
        buf.add_message(tf_message([nan]))
    assert not buf.can_transform("base_link", "cam")


# ----------------------------------------------------------------------------- parameters

def test_parse_extrinsics_forms() -> None:
    assert np.array_equal(P.parse_extrinsics([]), np.eye(4))
    m6 = P.parse_extrinsics([1, 2, 3, 0.1, 0.2, 0.3])
    assert np.allclose(m6, matrix_from_xyz_rpy(1, 2, 3, 0.1, 0.2, 0.3))
    q = quaternion_from_matrix(m6)
    assert np.allclose(P.parse_extrinsics([1, 2, 3, *q]), m6, atol=1e-12)
    assert np.allclose(P.parse_extrinsics(m6.reshape(-1)), m6)
    for bad in ([1, 2, 3], [0] * 16, [float("nan")] * 6, [0, 0, 0, 0, 0, 0, 0]):
        with pytest.raises(ConfigError):
            P.parse_extrinsics(bad)


def test_slice_configs_from_args_mappings_and_yaml(tmp_path: Path) -> None:
    s = P.parse_slice_arg("table:0.5:1.0")
    assert (s.name, s.min_height, s.max_height) == ("table", 0.5, 1.0)
    for bad in ("table:0.5", "t:a:b", ":0:1", "t:1:0"):
        with pytest.raises(ConfigError):
            P.parse_slice_arg(bad)
    path = tmp_path / "slices.yaml"
    path.write_text("slices:\n  low: {min_height: 0.05, max_height: 0.5, use_inf: false}\n"
                    "  high: {min_height: 0.5, max_height: .inf, angle_increment: 0.01,"
                    " topic: /x/high}\n")
    low, high = P.load_slices_file(path)
    assert low.extra == {"use_inf": False} and low.spec().use_inf is False
    assert high.max_height == math.inf and high.topic == "/x/high"
    assert high.spec().angle_increment == 0.01
    assert P.with_topic(low, "slices").topic == "slices/low"
    with pytest.raises(ConfigError):
        P.slices_from_mapping({"x": {"min_height": 0.1}})
    with pytest.raises(ConfigError):
        P.load_slices_file(tmp_path / "missing.yaml")
    with pytest.raises(ConfigError):
        P.slices_from_mapping({"x": {"min_height": 0, "max_height": 1, "bogus": 1}})[0].spec()


def test_log_limiter_bounds_lines_and_summarises() -> None:
    now = [0.0]
    lines: list[str] = []
    log = LogLimiter(lines.append, per_second=2, clock=lambda: now[0])
    for _ in range(10):
        log("bad scan", "bad")
    log("other", "tf")
    assert lines == ["bad scan", "bad scan", "other"]
    now[0] = 1.5
    log("bad scan", "bad")
    assert lines[-2].startswith("(8 more like 'bad'") and lines[-1] == "bad scan"


def test_guard_counts_logs_and_swallows_errors_of_a_callback() -> None:
    """The one guard of the nodes' callbacks: a project error is counted as bad and logged in
    one line; any other exception is counted as internal and logged with its traceback; the
    rest of the callback is skipped (``failed``); KeyboardInterrupt is not swallowed."""
    from converters.edge.nodes.common import Guard
    from lidarscan.errors import ValidationError

    lines: list[tuple[str, str]] = []
    bad: list[Exception] = []
    internal: list[Exception] = []

    def log(line: str, key: str) -> None:
        lines.append((line, key))

    with Guard(log, "scan not converted", bad=bad.append, internal=internal.append,
               key="conversion") as guard:
        pass
    assert not guard.failed and not lines
    with Guard(log, "scan not converted", bad=bad.append, internal=internal.append,
               key="conversion") as guard:
        raise ValidationError("LidarScan.height", 0, "> 0")
    assert guard.failed and len(bad) == 1 and not internal
    assert lines[-1][1] == "conversion" and lines[-1][0].startswith("scan not converted: ")
    assert "\n" not in lines[-1][0] and "LidarScan.height" in lines[-1][0]

    def broken() -> None:
        {}["missing"]

    with Guard(log, "scan not converted", bad=bad.append, internal=internal.append) as guard:
        broken()
    assert guard.failed and len(internal) == 1 and isinstance(guard.error, KeyError)
    line, key = lines[-1]
    assert key == "internal" and line.startswith("scan not converted (internal error KeyError: ")
    assert "Traceback" in line and "in broken" in line
    with Guard(log, "odometry dropped", bad=bad.append) as guard:      # internal -> bad
        broken()
    assert len(bad) == 2 and guard.failed
    with pytest.raises(KeyboardInterrupt), Guard(log, "x", bad=bad.append):
        raise KeyboardInterrupt
    assert len(bad) == 2


# ---------------------------------------------------------------------------------- cores

def test_converter_core_matches_direct_converters_and_counts_bad_input() -> None:
    from converters.slices.converter import SliceConverter
    from converters.edge.nodes.converter_node import ConverterCore
    from converters.pointcloud2.converter import to_pointcloud2

    info = small_info()
    scan = small_scan(info, 10**9)
    slices = [P.SliceConfig("low", -0.5, 0.5), P.SliceConfig("all", -10, 10)]
    core = ConverterCore(slices=slices, cloud_options={"fields": ("x", "y", "z", "intensity")})
    assert core.add_scan(lidarscan.encode(scan)) == []  # held until its info comes
    ready = core.add_info(lidarscan.encode(info))
    assert len(ready) == 1
    cloud, out = core.convert(*ready[0])
    assert bytes(cloud.data) == bytes(to_pointcloud2(scan, info).data)
    direct = SliceConverter(info, {s.name: s.spec() for s in slices}).convert(scan)
    assert list(out) == ["low", "all"]
    for name in out:
        assert same_floats(out[name].ranges, direct[name].ranges)
    with pytest.raises(LidarScanError):
        core.add_scan(b"\x00\x01\x00\x00\x01")
    other = small_info(stamp_ns=9_999)
    core.add_scan(lidarscan.encode(small_scan(other, 2 * 10**9)))  # its info never comes
    core.resolver.flush()
    core.expire()
    assert core.stats.bad_messages == 1 and core.stats.scans_dropped == 1
    # a target frame needs extrinsics
    core_tf = ConverterCore(slices=slices, target_frame="base_link")
    with pytest.raises(ConfigError):
        core_tf.convert(scan, info)


def test_merger_core_resolves_mounts_and_rebuilds_on_change() -> None:
    from converters.merger import LaserScanMerger, MergerInput
    from converters.edge.nodes.merger_node import MergerCore

    scan_a = laser_scan("a_frame", 10**9, 2.0)
    scan_b = laser_scan("b_frame", 10**9 + 10**7, 3.0)
    mounts = {"a_frame": matrix_from_xyz_rpy(0.3, 0, 0)}
    version = [0]
    core = MergerCore({"a": {}, "b": {}},
                      fallback_extrinsics={"b": matrix_from_xyz_rpy(yaw=math.pi)},
                      resolve=lambda target, source: mounts.get(source),
                      tf_version=lambda: version[0], frame_id="base_link",
                      angle_increment=math.radians(1.0), range_max=20.0)
    assert core.push("a", scan_a) == []
    merged = core.push("b", scan_b)[0]
    expected = LaserScanMerger(
        {"a": MergerInput(extrinsics=mounts["a_frame"]),
         "b": MergerInput(extrinsics=matrix_from_xyz_rpy(yaw=math.pi))},
        frame_id="base_link", angle_increment=math.radians(1.0), range_max=20.0).merge(
        {"a": scan_a, "b": scan_b})
    assert merged is not None and same_floats(merged.ranges, expected.ranges)
    built = core.rebuilds
    version[0] += 1  # TF changed but the mount did not: no rebuild
    core.push("a", laser_scan("a_frame", 2 * 10**9, 2.0))
    assert core.rebuilds == built
    mounts["a_frame"] = matrix_from_xyz_rpy(0.5, 0, 0)
    version[0] += 1
    core.push("a", laser_scan("a_frame", 3 * 10**9, 2.0))
    assert core.rebuilds == built + 1
    unknown = MergerCore({"c": {}}, frame_id="base_link")
    with pytest.raises(LidarScanError):
        unknown.push("c", laser_scan("c_frame", 10**9, 1.0))  # no pose for c_frame
    assert len(unknown.push("c", laser_scan("base_link", 10**9, 1.0))) == 1


def laser_scan(frame: str, stamp_ns: int, value: float, n: int = 360) -> Any:
    import array

    from sensor_msgs.msg import LaserScan

    from lidarscan.stamps import time_msg

    msg = LaserScan()
    msg.header.stamp = time_msg(stamp_ns)
    msg.header.frame_id = frame
    msg.angle_min, msg.angle_increment = -math.pi, 2 * math.pi / n
    msg.angle_max = msg.angle_min + (n - 1) * msg.angle_increment
    msg.range_min, msg.range_max = 0.05, 30.0
    ranges = np.full(n, value, np.float32)
    ranges[::7] = np.inf
    msg.ranges = array.array("f", ranges.tobytes())
    return msg


def test_cloud_to_scan_core_keeps_one_info_until_the_geometry_changes() -> None:
    from converters.edge.nodes.cloud_to_scan_node import CloudToScanCore, geometry_matches
    from converters.pointcloud2.converter import to_pointcloud2

    info = small_info()
    core = CloudToScanCore()
    stamps = []
    for k in range(3):
        scan, out_info, changed = core.convert(
            to_pointcloud2(small_scan(info, 10**9 + k * 10**8, seed=k), info, preset="ouster"))
        assert changed == (k == 0)
        assert lidarscan.to_ns(scan.lidar_info_time) == lidarscan.to_ns(out_info.header.stamp)
        lidarscan.validate(scan, out_info)
        stamps.append(lidarscan.to_ns(out_info.header.stamp))
    assert len(set(stamps)) == 1 and core.versions == 1
    wider = small_info(width=256)
    scan, new_info, changed = core.convert(
        to_pointcloud2(small_scan(wider, 10**9 + 5 * 10**8), wider, preset="ouster"))
    assert changed and new_info.width == 256
    assert lidarscan.to_ns(new_info.header.stamp) > stamps[0]
    assert lidarscan.to_ns(scan.lidar_info_time) == lidarscan.to_ns(new_info.header.stamp)
    assert not geometry_matches(info, wider)
    tilted = lidarscan.make_info(
        stamp_ns=1, frame_id="lidar", vertical_angles=np.radians(np.linspace(15, -15, 16)) + 0.01,
        horizontal_angles=2 * np.pi * (1 - np.arange(128) / 128),
        pixel_shift_by_row=np.tile([6, 4, 2, 0], 4), column_time_increment=781_250)
    assert geometry_matches(info, info) and not geometry_matches(info, tilted)


# ------------------------------------------------------------------------- real DDS graphs

CONFIG = Path(__file__).resolve().parent.parent / "config"


@pytest.mark.ros
@pytest.mark.parametrize("name", ["converter", "merger", "cloud_to_scan"])
def test_config_yaml_files_start_the_nodes(name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    rclpy = pytest.importorskip("rclpy")
    from converters.edge.nodes import cloud_to_scan_node, converter_node, merger_node

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    module = {"converter": converter_node, "merger": merger_node,
              "cloud_to_scan": cloud_to_scan_node}[name]
    context = rclpy.Context()
    rclpy.init(args=["--ros-args", "--params-file", str(CONFIG / f"{name}.yaml")],
               context=context, domain_id=DOMAIN)
    node = None
    try:
        node = module._node_class()(context=context)
        if name == "converter":
            assert [s.name for s in node.core.slices] == ["floor_to_knee", "table", "full"]
            assert node.core.slices[1].angle_increment == pytest.approx(math.radians(0.25))
            assert node.target_frame == "base_link"
            assert np.allclose(node.fallback_extrinsics, matrix_from_xyz_rpy(z=0.4))
        elif name == "merger":
            assert list(node.core.inputs) == ["full", "laser"]
            assert node.core.merger.policy == "timeout"
            assert np.allclose(node.core.fallback["laser"], matrix_from_xyz_rpy(0.25, 0, 0.2))
        else:
            assert node.core.angle_tolerance == 0.001
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown(context=context)


@pytest.mark.ros
def test_converter_node_end_to_end(graph: Graph) -> None:
    from lidarscan_msgs.msg import LidarInfo, LidarScan
    from sensor_msgs.msg import LaserScan, PointCloud2

    from converters.slices.converter import SliceConverter
    from converters.edge.nodes.converter_node import ConverterNode
    from converters.pointcloud2.converter import to_pointcloud2

    info = small_info()
    # the info is latched: published BEFORE the node exists, it still reaches it
    info_pub = graph.publisher(LidarInfo, "lidar_info", "latched")
    info_pub.publish(info)
    scan_pub = graph.publisher(LidarScan, "lidar_scan")
    clouds = graph.collect(PointCloud2, "points")
    lows = graph.collect(LaserScan, "slices/low")
    node = graph.add(ConverterNode(context=graph.context, parameter_overrides=overrides(
        slice_names=["low", "high"], slices__low__min_height=-0.5, slices__low__max_height=0.5,
        slices__high__min_height=0.0, slices__high__max_height=5.0,
        slices__high__topic="slices/up")))
    asked: list[list[str]] = []            # the slices each conversion was asked for
    convert = node.core.convert

    def spy(*args: Any, **kw: Any) -> Any:
        asked.append(list(kw.get("slices") or []))
        return convert(*args, **kw)

    node.core.convert = spy
    scan = small_scan(info, 10**9)
    assert graph.wait(lambda: node.core.stats.infos_received >= 1)
    assert graph.wait(lambda: clouds and lows, tick=lambda: scan_pub.publish(scan))
    assert bytes(clouds[0].data) == bytes(to_pointcloud2(scan, info).data)
    assert clouds[0].height == 16 and clouds[0].width == 128
    expected = SliceConverter(info, {"low": P.SliceConfig("low", -0.5, 0.5).spec()}).convert(
        scan)["low"]
    assert same_floats(lows[0].ranges, expected.ranges)
    assert node.stats.slices_published >= 1
    # nobody listens to slices/up: lazy, never computed nor published
    assert asked and all(names == ["low"] for names in asked), asked
    assert node.stats.slices_published == len(asked)
    # ... until somebody does
    ups = graph.collect(LaserScan, "slices/up")
    assert graph.wait(lambda: ups, tick=lambda: scan_pub.publish(scan))
    assert sorted(asked[-1]) == ["high", "low"]
    high = SliceConverter(info, {"high": P.SliceConfig("high", 0.0, 5.0).spec()}).convert(
        scan)["high"]
    assert same_floats(ups[0].ranges, high.ranges)
    # garbage on the scan topic: counted, logged, the node keeps working
    good_before = node.stats.scans_converted
    scan_pub.publish(b"\x00\x01\x00\x00 definitely not a LidarScan")
    assert graph.wait(lambda: node.stats.bad_messages >= 1)
    assert graph.wait(lambda: node.stats.scans_converted > good_before,
                      tick=lambda: scan_pub.publish(small_scan(info, 2 * 10**9)))
    # a scan naming an unknown info is held, then released when that info is published
    info2 = small_info(stamp_ns=7_777)
    scan2 = small_scan(info2, 3 * 10**9, seed=3)
    scan_pub.publish(scan2)
    assert graph.wait(lambda: node.core.resolver.pending >= 1)
    count = len(clouds)
    info_pub.publish(info2)
    assert graph.wait(lambda: any(bytes(c.data) == bytes(to_pointcloud2(scan2, info2).data)
                                  for c in clouds[count:]))


@pytest.mark.ros
def test_converter_node_is_lazy_without_subscribers(graph: Graph) -> None:
    from lidarscan_msgs.msg import LidarInfo, LidarScan

    from converters.edge.nodes.converter_node import ConverterNode

    info = small_info()
    graph.publisher(LidarInfo, "lidar_info", "latched").publish(info)
    scan_pub = graph.publisher(LidarScan, "lidar_scan")
    node = graph.add(ConverterNode(context=graph.context))
    assert graph.wait(lambda: node.stats.scans_idle >= 3,
                      tick=lambda: scan_pub.publish(small_scan(info, 10**9)))
    assert node.stats.scans_converted == 0 and node.stats.scans_received == 0


@pytest.mark.ros
def test_converter_node_takes_extrinsics_from_tf_static(graph: Graph) -> None:
    from geometry_msgs.msg import TransformStamped
    from lidarscan_msgs.msg import LidarInfo, LidarScan
    from sensor_msgs.msg import LaserScan

    from converters.slices.converter import SliceConverter
    from converters.edge.nodes.converter_node import ConverterNode

    tf2_msgs = pytest.importorskip("tf2_msgs.msg")
    info = small_info()
    mount = matrix_from_xyz_rpy(0.1, 0.0, 0.6, 0.0, 0.05, 0.3)
    t = TransformStamped()
    t.header.frame_id, t.child_frame_id = "base_link", "lidar"
    t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = \
        (float(v) for v in mount[:3, 3])
    qx, qy, qz, qw = quaternion_from_matrix(mount)
    t.transform.rotation.x, t.transform.rotation.y = qx, qy
    t.transform.rotation.z, t.transform.rotation.w = qz, qw
    graph.publisher(tf2_msgs.TFMessage, "/tf_static", "latched").publish(
        tf2_msgs.TFMessage(transforms=[t]))
    graph.publisher(LidarInfo, "lidar_info", "latched").publish(info)
    scan_pub = graph.publisher(LidarScan, "lidar_scan")
    out = graph.collect(LaserScan, "slices/band")
    node = graph.add(ConverterNode(context=graph.context, parameter_overrides=overrides(
        target_frame="base_link", slice_names=["band"], slices__band__min_height=0.2,
        slices__band__max_height=1.5, extrinsics=[9.0, 9.0, 9.0, 0.0, 0.0, 0.0])))
    assert graph.wait(lambda: node.tf_buffer.can_transform("base_link", "lidar"))
    scan = small_scan(info, 10**9)
    assert graph.wait(lambda: bool(out), tick=lambda: scan_pub.publish(scan))
    expected = SliceConverter(info, {"band": P.SliceConfig("band", 0.2, 1.5).spec()},
                              extrinsics=mount, frame_id="base_link").convert(scan)["band"]
    assert out[0].header.frame_id == "base_link"
    assert same_floats(out[0].ranges, expected.ranges)  # TF won over the bogus parameter


@pytest.mark.ros
def test_merger_node_merges_and_survives_bad_input(graph: Graph) -> None:
    from sensor_msgs.msg import LaserScan

    from converters.merger import LaserScanMerger, MergerInput
    from converters.edge.nodes.merger_node import MergerNode

    out = graph.collect(LaserScan, "scan_merged")
    pub_a = graph.publisher(LaserScan, "front/scan", "sensor_data")
    pub_b = graph.publisher(LaserScan, "rear/scan")
    node = graph.add(MergerNode(context=graph.context, parameter_overrides=overrides(
        input_names=["front", "rear"], inputs__front__topic="front/scan",
        inputs__rear__topic="rear/scan", inputs__rear__qos="reliable",
        inputs__front__extrinsics=[0.3, 0.0, 0.2, 0.0, 0.0, 0.0],
        inputs__rear__extrinsics=[-0.3, 0.0, 0.2, 0.0, 0.0, math.pi],
        angle_increment=math.radians(1.0), range_max=20.0, use_tf=False)))
    stamp = [10**9]

    def tick() -> None:
        stamp[0] += 10**8
        pub_a.publish(laser_scan("front_laser", stamp[0], 2.0))
        pub_b.publish(laser_scan("rear_laser", stamp[0] + 5 * 10**6, 3.0))

    # both inputs matched first, so that no set is merged with an input missing
    assert graph.wait(lambda: pub_a.get_subscription_count() > 0 and
                      pub_b.get_subscription_count() > 0)
    expected = LaserScanMerger(
        {"front": MergerInput(extrinsics=matrix_from_xyz_rpy(0.3, 0, 0.2)),
         "rear": MergerInput(extrinsics=matrix_from_xyz_rpy(-0.3, 0, 0.2, yaw=math.pi))},
        frame_id="base_link", angle_increment=math.radians(1.0), range_max=20.0).merge(
        {"front": wire(laser_scan("front_laser", 0, 2.0)),
         "rear": wire(laser_scan("rear_laser", 0, 3.0))})
    assert graph.wait(lambda: any(same_floats(o.ranges, expected.ranges) for o in out),
                      tick=tick)
    assert all(o.header.frame_id == "base_link" for o in out)
    pub_a.publish(b"\x00\x01\x00\x00\xff\xff\xff\x7f")  # corrupt: huge declared string
    assert graph.wait(lambda: node.stats["bad"] >= 1)
    count = len(out)
    assert graph.wait(lambda: len(out) > count, tick=tick)  # still merging


@pytest.mark.ros
@pytest.mark.parametrize("kind", ["converter", "merger"])
def test_nodes_say_when_numba_s_cache_is_being_filled(
        graph: Graph, monkeypatch: pytest.MonkeyPatch, kind: str) -> None:
    """While numba's cache lacks a kernel (the C kernels run meanwhile), the converter and the
    merger both report the backend, the kernels and ``numba_cache`` in their startup status."""
    from converters import warmup
    from converters.edge.nodes.converter_node import ConverterNode
    from converters.edge.nodes.merger_node import MergerNode

    def cold(tasks: Any, **_: Any) -> Any:          # no background compiler in a test
        return warmup.Prepared("c", {}, warmup.describe(tasks, "c"),
                               "a kernel is not in numba's cache (test)")

    monkeypatch.setattr(warmup, "prepare", cold)
    if kind == "converter":
        node = graph.add(ConverterNode(context=graph.context))
    else:
        node = graph.add(MergerNode(context=graph.context, parameter_overrides=overrides(
            input_names=["front"], inputs__front__topic="front/scan", use_tf=False)))
    status = node.startup.status().values
    assert status["ready"] is True and status["backend"] == "c"
    assert status["numba_cache"] == "filling in the background"
    assert any(k.startswith("kernels_") for k in status), status


@pytest.mark.ros
def test_cloud_to_scan_node_latches_one_info(graph: Graph) -> None:
    from lidarscan_msgs.msg import LidarInfo, LidarScan
    from sensor_msgs.msg import PointCloud2

    from converters.edge.nodes.cloud_to_scan_node import CloudToScanNode
    from converters.pointcloud2.converter import to_pointcloud2

    info = small_info()
    cloud_pub = graph.publisher(PointCloud2, "points", "sensor_data")
    scans = graph.collect(LidarScan, "lidar_scan")
    node = graph.add(CloudToScanNode(context=graph.context))
    k = [0]

    def tick() -> None:
        k[0] += 1
        cloud_pub.publish(to_pointcloud2(small_scan(info, 10**9 + k[0] * 10**8, seed=k[0]),
                                         info, preset="ouster"))

    assert graph.wait(lambda: len(scans) >= 3, tick=tick)
    infos = graph.collect(LidarInfo, "lidar_info", "latched")  # a late joiner
    assert graph.wait(lambda: bool(infos))
    assert node.stats["infos"] == 1 and node.stats["bad"] == 0
    for scan in scans:
        lidarscan.validate(scan, infos[0])
    cloud_pub.publish(b"\x00\x01\x00\x00")  # truncated cloud: dropped, counted
    assert graph.wait(lambda: node.stats["bad"] >= 1)


# ---------------------------------------------------------------------- console scripts

def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("_ROS_WHEELS_BOOTSTRAP_COMPLETE", None)  # let the venv's bootstrapper run
    env["ROS_DOMAIN_ID"] = str(DOMAIN)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env["PYTHONUNBUFFERED"] = "1"
    env["RCUTILS_LOGGING_BUFFERED_STREAM"] = "0"
    return env


def _script(name: str) -> list[str]:
    path = VENV_BIN / name
    if path.exists():
        return [str(path)]
    module = {"lidarscan-converter": "converters.edge.nodes.converter_node",
              "lidarscan-merger": "converters.edge.nodes.merger_node",
              "lidarscan-cloud-to-scan": "converters.edge.nodes.cloud_to_scan_node"}[name]
    return [sys.executable, "-m", module]


@pytest.mark.ros
@pytest.mark.parametrize("script", ["lidarscan-converter", "lidarscan-cloud-to-scan"])
def test_console_script_stops_cleanly_on_ctrl_c(script: str, tmp_path: Path) -> None:
    log = tmp_path / "log.txt"
    with open(log, "w") as out:
        proc = subprocess.Popen(_script(script) + ["--ros-args", "-p", "slice_names:=[a]",
                                                   "-p", "slices.a.min_height:=0.0",
                                                   "-p", "slices.a.max_height:=1.0"]
                                if script == "lidarscan-converter" else _script(script),
                                stdout=out, stderr=subprocess.STDOUT, env=_env())
    try:
        end = time.monotonic() + 30
        while time.monotonic() < end and "->" not in log.read_text():
            assert proc.poll() is None, log.read_text()
            time.sleep(0.1)
        assert "->" in log.read_text(), log.read_text()
        proc.send_signal(signal.SIGINT)
        # a Ctrl-C during the kernel warm-up is honoured when the warm-up ends (seconds when
        # the machine is loaded), then the node stops cleanly
        assert proc.wait(timeout=60) == 0, log.read_text()
        assert "Traceback" not in log.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


_CTRL_C_WHILE_BUILDING = """
import os, signal, sys, time
import rclpy
from converters.edge.nodes.common import run_node

def make_node():
    node = rclpy.create_node("ctrl_c_while_building")
    deadline = time.monotonic() + 10
    try:
        os.kill(os.getpid(), signal.SIGINT)  # as a user's Ctrl-C during the kernel warm-up
        while rclpy.ok() and time.monotonic() < deadline:
            time.sleep(0.01)
    except KeyboardInterrupt:
        pass  # lost on the way, as in a real warm-up (it happened): only the shutdown remains
    while rclpy.ok() and time.monotonic() < deadline:
        time.sleep(0.01)                     # rclpy's signal thread shuts the context down
    print("context ok after SIGINT:", rclpy.ok(), flush=True)
    return node

sys.exit(run_node(make_node, [sys.argv[0]]))
"""


@pytest.mark.ros
def test_ctrl_c_while_the_node_is_built_stops_cleanly() -> None:
    # rclpy's SIGINT handler shuts the context down instead of raising KeyboardInterrupt, so a
    # Ctrl-C during a node's construction used to end in an RCLError traceback from spin().
    done = subprocess.run([sys.executable, "-c", _CTRL_C_WHILE_BUILDING], check=False,
                          capture_output=True, text=True, env=_env(), timeout=60)
    assert "context ok after SIGINT: False" in done.stdout, done.stdout + done.stderr
    assert done.returncode == 0, done.stdout + done.stderr
    assert "Traceback" not in done.stderr, done.stderr


@pytest.mark.ros
def test_console_script_rejects_bad_parameters() -> None:
    done = subprocess.run(_script("lidarscan-merger"), check=False, capture_output=True, text=True,
                          env=_env(), timeout=30)
    assert done.returncode == 2
    assert "input_names" in done.stderr and "Traceback" not in done.stderr


def test_merger_core_restarts_after_a_clock_jump_back() -> None:
    from converters.edge.nodes.merger_node import MergerCore

    events: list[str] = []
    core = MergerCore({"a": {}, "b": {}}, frame_id="base_link", on_event=events.append,
                      angle_increment=math.radians(1.0))

    def pair(t: int) -> list[Any]:
        return core.push("a", laser_scan("base_link", t, 1.0)) + \
            core.push("b", laser_scan("base_link", t + 1000, 2.0))

    assert len(pair(100 * 10**9)) == 1 and len(pair(102 * 10**9)) == 1
    # the recording loops: back to t = 100 s; without the reset every scan would be "late".
    # Each input's first scan back is held as unconfirmed (dropped as late), its second one
    # confirms the jump of that input (2 resets: a and b), and fusion resumes.
    assert pair(100 * 10**9) == [] and core.resets == 0
    assert len(pair(100 * 10**9 + 10**8)) == 1
    assert core.resets == 2 and all("jumped back" in e for e in events) and len(events) == 2
    assert len(pair(100 * 10**9 + 2 * 10**8)) == 1
    # small out-of-order stamps are not a jump (the merger drops them as late)
    assert pair(100 * 10**9 + 15 * 10**7) == [] and core.resets == 2
    # nor is one scan far in the past (stale / zero stamp): dropped, nothing reset
    assert core.push("b", laser_scan("base_link", 0, 2.0)) == [] and core.resets == 2
    assert len(pair(100 * 10**9 + 3 * 10**8)) == 1 and core.resets == 2


# ------------------------------------------------------- runtime parameters, /diagnostics

def _set(graph: Graph, node_name: str, **values: Any) -> list[Any]:
    """Set parameters through the node's SetParametersAtomically service (one result for all;
    ``ros2 param set`` uses SetParameters, the same callbacks)."""
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    client = AsyncParameterClient(graph.tester, node_name)
    assert client.wait_for_services(timeout_sec=10.0)
    params = [Parameter(k.replace("__", "."), value=v) for k, v in values.items()]
    future = client.set_parameters_atomically(params) if len(params) > 1 else \
        client.set_parameters(params)
    assert graph.wait(future.done, timeout=10.0)
    result = future.result()
    return list(result.results) if hasattr(result, "results") else [result.result]


@pytest.mark.ros
def test_converter_parameters_are_checked_and_applied_live(graph: Graph) -> None:
    from lidarscan_msgs.msg import LidarInfo, LidarScan
    from sensor_msgs.msg import LaserScan

    from converters.slices.converter import SliceConverter
    from converters.edge.nodes.converter_node import ConverterNode

    info = small_info()
    graph.publisher(LidarInfo, "lidar_info", "latched").publish(info)
    scan_pub = graph.publisher(LidarScan, "lidar_scan")
    lows = graph.collect(LaserScan, "slices/low")
    node = graph.add(ConverterNode(context=graph.context, parameter_overrides=overrides(
        slice_names=["low"], slices__low__min_height=-0.5, slices__low__max_height=0.5)))
    scan = small_scan(info, 10**9)
    assert graph.wait(lambda: bool(lows), tick=lambda: scan_pub.publish(scan))

    def expect(lo: float, hi: float, **kw: Any) -> Any:
        return SliceConverter(info, {"low": P.SliceConfig("low", lo, hi, **kw).spec()}
                              ).convert(scan)["low"]

    assert same_floats(lows[-1].ranges, expect(-0.5, 0.5).ranges)
    # bad values: refused with a reason naming the parameter; nothing changes
    bad = {"max_wait": (-5.0, "max_wait"), "scan_qos": ("bogus", "read-only"),
           "slices__low__max_height": ("high", "slices.low.max_height"),
           "slices__low__range_max": (-1.0, "range_max"),
           "pointcloud2__preset": ("nope", "preset")}
    for name, (value, reason) in bad.items():
        (result,) = _set(graph, "lidarscan_converter", **{name: value})
        assert not result.successful and reason in result.reason, (name, result.reason)
    # a band the library refuses (range_min > range_max): the library's own reason
    (result,) = _set(graph, "lidarscan_converter", slices__low__range_min=9.0,
                     slices__low__range_max=2.0)
    assert not result.successful and "range" in result.reason
    assert node.core.resolver.max_wait_ns == 2 * 10**9 and node.guard.rejected >= 3
    assert node.get_parameter("max_wait").value == 2.0
    # good values take effect without a restart (an int is fine for a float)
    (result,) = _set(graph, "lidarscan_converter", max_wait=3, slices__low__min_height=0.3,
                     slices__low__max_height=5.0, slices__low__range_max=3.0)
    assert result.successful, result.reason
    assert node.core.resolver.max_wait_ns == 3 * 10**9
    want = expect(0.3, 5.0, range_max=3.0)
    assert not same_floats(want.ranges, expect(-0.5, 0.5).ranges)
    count = len(lows)
    assert graph.wait(lambda: any(same_floats(m.ranges, want.ranges) for m in lows[count:]),
                      tick=lambda: scan_pub.publish(scan))


@pytest.mark.ros
def test_merger_parameters_are_checked_and_applied_live(graph: Graph) -> None:
    from sensor_msgs.msg import LaserScan

    from converters.edge.nodes.merger_node import MergerNode

    out = graph.collect(LaserScan, "scan_merged")
    pub_a = graph.publisher(LaserScan, "a")
    pub_b = graph.publisher(LaserScan, "b")
    node = graph.add(MergerNode(context=graph.context, parameter_overrides=overrides(
        input_names=["a", "b"], angle_increment=math.radians(1.0), range_max=20.0,
        use_tf=False, inputs__a__qos="reliable", inputs__b__qos="reliable")))
    stamp = [10**9]

    def tick() -> None:
        stamp[0] += 10**8
        pub_a.publish(laser_scan("base_link", stamp[0], 2.0))
        pub_b.publish(laser_scan("base_link", stamp[0] + 10**6, 3.0))

    assert graph.wait(lambda: pub_a.get_subscription_count() > 0 and
                      pub_b.get_subscription_count() > 0)
    assert graph.wait(lambda: len(out) >= 2, timeout=20, tick=tick), node.stats
    for name, value, reason in (("slop", -1.0, "slop"), ("policy", "sometimes", "policy"),
                                ("angle_increment", 0.0, "angle_increment"),
                                ("inputs__b__range_min", "far", "inputs.b.range_min"),
                                ("input_names", ["a"], "read-only")):
        (result,) = _set(graph, "lidarscan_merger", **{name: value})
        assert not result.successful and reason in result.reason, (name, result.reason)
    assert node.core.merger.slop_ns == 50_000_000
    # a user range limit on input b, live: its 3 m ranges leave the output
    (result,) = _set(graph, "lidarscan_merger", inputs__b__range_max=2.5, slop=0.02)
    assert result.successful, result.reason
    assert node.core.merger.slop_ns == 20_000_000 and node.core.inputs["b"]["range_max"] == 2.5
    count = len(out)
    assert graph.wait(lambda: any(np.all(np.isin(np.asarray(o.ranges)[np.isfinite(o.ranges)],
                                                 [2.0])) and np.isfinite(o.ranges).any()
                                  for o in out[count:]), tick=tick)


@pytest.mark.ros
def test_nodes_publish_diagnostics_with_linkage_state(graph: Graph) -> None:
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from lidarscan_msgs.msg import LidarInfo, LidarScan
    from sensor_msgs.msg import PointCloud2

    from converters.edge.nodes.cloud_to_scan_node import CloudToScanNode
    from converters.edge.nodes.converter_node import ConverterNode

    arrays = graph.collect(DiagnosticArray, "/diagnostics", "reliable")
    scan_pub = graph.publisher(LidarScan, "lidar_scan")
    graph.collect(PointCloud2, "points")
    node = graph.add(ConverterNode(context=graph.context, parameter_overrides=overrides(
        max_wait=0.3)))
    graph.add(CloudToScanNode(context=graph.context,
                              parameter_overrides=overrides(cloud_topic="silent_points")))
    info = small_info(stamp_ns=4_242)

    def latest(name: str) -> Any:
        for array in reversed(arrays):
            for status in array.status:
                if status.name.endswith(name):
                    return status
        return None

    def level(status: Any) -> int:
        return status.level[0] if isinstance(status.level, bytes) else int(status.level)

    k = [0]

    def tick() -> None:
        k[0] += 1
        scan_pub.publish(small_scan(info, 10**9 + k[0] * 10**8))

    # scans whose LidarInfo never comes: ERROR with the reason, drops counted
    assert graph.wait(lambda: (s := latest("lidarscan_converter: linkage")) is not None and
                      level(s) == DiagnosticStatus.ERROR[0] and "no LidarInfo" in s.message,
                      timeout=15, tick=tick)
    values = {kv.key: kv.value for kv in latest("lidarscan_converter: linkage").values}
    assert {"pending", "infos", "conflicting", "max_infos"} <= set(values)
    # the info arrives: OK, rates and latency reported
    graph.publisher(LidarInfo, "lidar_info", "latched").publish(info)
    assert graph.wait(lambda: (s := latest("lidarscan_converter: linkage")) is not None and
                      level(s) == DiagnosticStatus.OK[0] and
                      (c := latest("lidarscan_converter: conversion")) is not None and
                      level(c) == DiagnosticStatus.OK[0], timeout=15, tick=tick)
    conv = {kv.key: kv.value for kv in latest("lidarscan_converter: conversion").values}
    assert float(conv["scans_converted_per_s"]) > 0 and "latency_p50_ms" in conv
    assert node.stats.scans_dropped >= 1
    # the cloud-to-scan node reports too: no clouds yet is a warning with its reason
    c2s = latest("lidarscan_cloud_to_scan: conversion")
    assert c2s is not None and level(c2s) == DiagnosticStatus.WARN[0]
    assert "no PointCloud2" in c2s.message
    for name in ("lidarscan_converter", "lidarscan_cloud_to_scan"):   # warmed up, then ready
        start = latest(f"{name}: startup")
        assert start is not None and level(start) == DiagnosticStatus.OK[0]
        assert {kv.key: kv.value for kv in start.values}["ready"] == "True"
