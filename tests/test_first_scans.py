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
from pathlib import Path
from typing import Any

import pytest

pytestmark = [pytest.mark.ros]

ROOT = Path(__file__).resolve().parents[1]


def _bench() -> Any:
    spec = importlib.util.spec_from_file_location("bench_first_scans",
                                                  ROOT / "bench" / "bench_first_scans.py")
    module = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
    spec.loader.exec_module(module)  # type: ignore[union-attr]
    return module


@pytest.mark.slow
def test_a_cold_node_loses_no_scan_of_a_driver_that_starts_at_the_match(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("rclpy")
    pytest.importorskip("lidarscan_msgs.msg")
    monkeypatch.delenv("ROS_LOCALHOST_ONLY", raising=False)
    bench = _bench()
    cache = tmp_path / "numba-cache"
    cache.mkdir()
    result = bench.measure(str(cache), scans=30)
    log = result["log"]
    assert "ready: warm-up" in log and "kernels: cloud C" in log, log[-3000:]
    # the node subscribed to the scans after it was ready and had the info's tables
    lines = log.splitlines()
    ready = next(i for i, line in enumerate(lines) if "ready: warm-up" in line)
    tables = next(i for i, line in enumerate(lines) if "tables ready" in line)
    assert ready < tables, log[-3000:]
    sent = result["sent"]
    assert len(sent) == 30
    for kind in ("clouds", "slices"):
        assert result[kind] == sent, (kind, len(result[kind]), log[-3000:])  # none lost, in order
    numba = importlib.util.find_spec("numba") is not None
    from converters._kernels import numba_enabled

    if numba and numba_enabled():
        # an empty cache: the node did not compile on its start, it said so and fills the
        # cache in the background
        assert "numba not used" in log and "in the background" in log, log[-3000:]
