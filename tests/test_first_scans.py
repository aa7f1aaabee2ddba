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
