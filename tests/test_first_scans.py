"""A freshly started converter node, as a driver-side system starts it: the driver latches the
real OS-2-128 LidarInfo and publishes the real frame at 10 Hz (reliable) as soon as the node's
scan subscription matches. The node (a process of its own, numba's cache an empty temporary
directory: a plain ``pip install``) must lose no scan and publish them in order: it warms its
kernels and builds the info's tables before it subscribes to the scans, and no compiler runs on
its start (it says which backend runs). The latency figures (first ten scans against the steady
state) are measured by bench/bench_first_scans.py, not pinned here.
"""

from __future__ import annotations

import importlib.util
import re
import time
from pathlib import Path
from typing import Any

import pytest
from test_nodes import graph  # noqa: F401 - the in-process graph fixture

pytestmark = [pytest.mark.ros]

ROOT = Path(__file__).resolve().parents[1]


def _bench() -> Any:
    spec = importlib.util.spec_from_file_location("bench_first_scans",
                                                  ROOT / "bench" / "bench_first_scans.py")
    module = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
    spec.loader.exec_module(module)  # type: ignore[union-attr]
    return module


def _running(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie does not)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


def _check(result: dict[str, Any], count: int) -> str:
    """No scan lost, in order, and the node subscribed after it was ready with the info's
    tables; returns the node's log."""
    log = result["log"]
    lines = log.splitlines()
    ready = [i for i, line in enumerate(lines) if "ready: warm-up" in line]
    tables = [i for i, line in enumerate(lines) if "tables ready" in line]
    assert ready and tables and ready[0] < tables[0], log[-3000:]
    assert "kernels: cloud " in lines[ready[0]], log[-3000:]   # it says which backend runs
    sent = result["sent"]
    assert len(sent) == count
    for kind in ("clouds", "slices"):
        assert result[kind] == sent, (kind, len(result[kind]), log[-3000:])  # none lost, in order
    return log


@pytest.mark.slow
def test_a_cold_node_loses_no_scan_of_a_driver_that_starts_at_the_match(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("rclpy")
    pytest.importorskip("lidarscan_msgs.msg")
    monkeypatch.delenv("ROS_LOCALHOST_ONLY", raising=False)
    bench = _bench()
    cache = tmp_path / "numba-cache"
    cache.mkdir()
    log = _check(bench.measure(str(cache), scans=30), 30)
    from converters._kernels import numba_enabled

    if importlib.util.find_spec("numba") is None or not numba_enabled():
        return
    # an empty cache: the node compiled nothing on its start, said so, and fills the cache
    # for its configuration in the background; the next start runs numba from that cache
    match = re.search(r"numba not used: .* in the background, pid (\d+)", log)
    assert match, log[-3000:]
    pid = int(match.group(1))
    end = time.monotonic() + 600
    while _running(pid) and time.monotonic() < end:
        time.sleep(0.5)
    assert not _running(pid), "the background fill did not finish in 600 s"
    log = _check(bench.measure(str(cache), scans=30), 30)
    assert "numba not used" not in log and "slices" in log and "numba" in log, log[-3000:]


@pytest.mark.ros
def test_a_new_info_gets_its_tables_before_its_first_scan_and_no_queued_scan_is_dropped(
        graph: Any) -> None:  # noqa: F811 - the fixture
    """A LidarInfo version arriving mid-stream, with a burst of its scans right behind it on a
    reliable topic: its tables are built before its first scan is converted, and every scan
    of the burst (queued meanwhile in the reader, or held by the linkage when it came first)
    is converted, in order."""
    from lidarscan_msgs.msg import LidarInfo, LidarScan
    from sensor_msgs.msg import PointCloud2
    from test_nodes import overrides, small_info, small_scan

    from converters.edge.nodes.converter_node import ConverterNode
    from lidarscan.geometry import info_key

    info = small_info()
    info_pub = graph.publisher(LidarInfo, "lidar_info", "latched")
    info_pub.publish(info)
    from converters.edge.nodes import params as P

    # the driver keeps its burst (depth 32); the node's reader keeps max_pending (16) scans
    scan_pub = graph.tester.create_publisher(LidarScan, "lidar_scan",
                                             P.qos_profile("reliable", 32))
    clouds = graph.collect(PointCloud2, "points", "reliable")
    node = graph.add(ConverterNode(context=graph.context, parameter_overrides=overrides(
        scan_qos="reliable", output_qos="reliable", slice_names=["low"],
        slices__low__min_height=-0.5, slices__low__max_height=0.5)))
    # the latched info came before the scan subscription, with its tables
    assert node.stats.infos_received == 1 and node.core._clouds and node.core._slicers
    # /diagnostics' startup status says which backend runs
    status = node.startup.status().values
    assert status["ready"] is True and status["backend"] in ("auto", "c")
    assert status["kernels_cloud"] in ("C", "numpy") and status["kernels_slices"]
    assert graph.wait(lambda: node.cloud_pub.get_subscription_count() > 0)
    calls: list[tuple[str, Any]] = []
    prepare, convert = node.core.prepare, node.core.convert

    def spy_prepare(info: Any, *args: Any, **kwargs: Any) -> Any:
        calls.append(("prepare", info_key(info)))
        return prepare(info, *args, **kwargs)

    def spy_convert(scan: Any, info: Any, **kwargs: Any) -> Any:
        calls.append(("convert", info_key(info)))
        return convert(scan, info, **kwargs)

    node.core.prepare, node.core.convert = spy_prepare, spy_convert
    wider = small_info(stamp_ns=7_777, width=256)        # a new geometry: new tables
    burst = [small_scan(wider, 10**9 * (k + 1), seed=k) for k in range(12)]
    info_pub.publish(wider)
    for scan in burst:
        scan_pub.publish(scan)
    assert graph.wait(lambda: len(clouds) >= len(burst), timeout=30.0), (
        [c.header.stamp.sec for c in clouds], node.stats)
    stamps = [c.header.stamp.sec * 10**9 + c.header.stamp.nanosec for c in clouds]
    assert stamps == [10**9 * (k + 1) for k in range(12)]       # none lost, in order
    assert node.stats.scans_dropped == 0 and node.stats.scans_idle == 0
    key = info_key(lidarscan_decode(wider))
    first_prepare = calls.index(("prepare", key))
    assert first_prepare < calls.index(("convert", key)), calls[:4]


def lidarscan_decode(msg: Any) -> Any:
    """The dataclass of a message as the node decodes it (for its info key)."""
    import lidarscan

    return lidarscan.decode_info(lidarscan.encode(msg))
