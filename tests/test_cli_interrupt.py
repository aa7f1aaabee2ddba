"""Ctrl-C during ``lidarscan convert``: a real SIGINT sent to a real process at several points
of the run always ends with exit 130 and a valid MCAP of what was written so far (it twice
ended in ``SystemError: CPUDispatcher(...) returned a result with an exception set``: a numba
kernel interrupted by the KeyboardInterrupt raised inside it, exit 1 and no output)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import lidarscan
from helpers import messages_by_topic
from lidarscan.mcap import McapWriter

ROOT = Path(__file__).resolve().parents[1]
#: the console script's entry point, in a fresh interpreter
MAIN = "import sys; from converters.cli import main; sys.exit(main(sys.argv[1:]))"


@pytest.fixture(scope="module")
def many_scans(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An MCAP of one LidarInfo and 300 LidarScans (32 x 1024, random ranges): long enough to
    convert (--compress --pointcloud2) that a Ctrl-C lands in the middle."""
    rng = np.random.default_rng(31)
    height, width = 32, 1024
    info = lidarscan.make_info(
        stamp_ns=1_000_000_000, frame_id="lidar",
        vertical_angles=np.radians(np.linspace(15.0, -15.0, height)),
        horizontal_angles=2 * np.pi * (1 - np.arange(width) / width), as_dataclass=True)
    path = tmp_path_factory.mktemp("sigint") / "many.mcap"
    with McapWriter(path) as writer:
        writer.write("/lidar/info", info, log_time_ns=1_000_000_000)
        for k in range(300):
            ranges = rng.uniform(0.5, 40.0, (height, width)).astype(np.float32)
            ranges[rng.random((height, width)) < 0.1] = np.inf
            stamp = 1_000_000_000 + k * 100_000_000
            scan = lidarscan.make_scan(info, {"range": ranges}, stamp, as_dataclass=True)
            writer.write("/lidar/scan", scan, log_time_ns=stamp)
    return path


def _partial_bytes(out: Path) -> int | None:
    """Bytes written so far under the temporary name of ``out`` (a file, or a folder's files),
    or None before it exists."""
    parts = list(out.parent.glob(f".{out.name}.*.partial"))
    if not parts:
        return None
    files = [parts[0]] if parts[0].is_file() else [f for f in parts[0].rglob("*") if f.is_file()]
    total = 0
    for f in files:
        try:
            total += f.stat().st_size
        except FileNotFoundError:          # renamed or removed meanwhile
            pass
    return total


def _interrupt(argv: list[str], out: Path, at_bytes: int) -> tuple[int, str]:
    """Run ``lidarscan`` ``argv``; once its temporary output holds ``at_bytes`` bytes (0: once
    it exists), send SIGINT; (exit status, stderr). Progress, not a clock, decides when: the
    signal lands at the same point of the run on a fast machine as on a slow one."""
    proc = subprocess.Popen([sys.executable, "-c", MAIN, *argv], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while proc.poll() is None:
        done = _partial_bytes(out)
        if done is not None and done >= at_bytes:
            break
        assert time.monotonic() < deadline, f"fewer than {at_bytes} bytes written after 120 s"
        time.sleep(0.005)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=300)
    return proc.returncode, err


@pytest.fixture(scope="module")
def full_output_bytes(many_scans: Path, tmp_path_factory: pytest.TempPathFactory) -> int:
    """Size of the uninterrupted conversion's output (the Ctrl-C points are fractions of it)."""
    out = tmp_path_factory.mktemp("full") / "out.mcap"
    done = subprocess.run([sys.executable, "-c", MAIN, "convert", str(many_scans), str(out),
                           "--compress", "--pointcloud2"], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return out.stat().st_size


@pytest.mark.parametrize("threads", ["1", "3"])
@pytest.mark.parametrize("fraction", [0.0, 0.15, 0.5])
def test_ctrl_c_exits_130_with_a_valid_partial_output(
        many_scans: Path, tmp_path: Path, fraction: float, threads: str,
        full_output_bytes: int) -> None:
    out = tmp_path / "out.mcap"
    status, err = _interrupt(["convert", str(many_scans), str(out), "--compress",
                              "--pointcloud2", "--threads", threads], out,
                             int(fraction * full_output_bytes))
    assert status == 130, err
    assert "Traceback" not in err and "SystemError" not in err, err
    assert "interrupted: " in err and "is a valid MCAP file" in err, err
    got = messages_by_topic(out)   # fails on any damaged record
    scans = len(got.get("/lidar/scan", []))
    assert scans < 300, "the run finished before the Ctrl-C: nothing was tested"
    assert len(got.get("/lidar/points", [])) in (scans, scans - 1)   # outputs follow inputs
    assert not list(tmp_path.glob(".*.partial"))
    summary = [line for line in err.splitlines() if line.startswith("interrupted: ")]
    assert f"with the {sum(map(len, got.values()))} messages" in summary[0], summary


def test_a_second_ctrl_c_still_closes_the_output(many_scans: Path, tmp_path: Path,
                                                 full_output_bytes: int) -> None:
    """Twice Ctrl-C (a user who will not wait): still 130 and a readable file."""
    out = tmp_path / "out.mcap"
    proc = subprocess.Popen([sys.executable, "-c", MAIN, "convert", str(many_scans),
                             str(out), "--compress", "--pointcloud2"], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    while (_partial_bytes(out) or 0) < full_output_bytes // 10 and proc.poll() is None:
        time.sleep(0.005)
    proc.send_signal(signal.SIGINT)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 130, err
    assert "Traceback" not in err, err
    messages_by_topic(out)


def test_the_stop_request_restores_the_previous_handler() -> None:
    from converters.cli._interrupt import StopRequest, is_interrupt

    before = signal.getsignal(signal.SIGINT)
    with StopRequest() as stop:
        assert signal.getsignal(signal.SIGINT) is not before and not stop()
        signal.raise_signal(signal.SIGINT)      # no KeyboardInterrupt: a flag
        assert stop()
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)  # the second one raises
    assert signal.getsignal(signal.SIGINT) is before
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as inner:
            raise SystemError("CPUDispatcher returned a result with an exception set") from inner
    except SystemError as err:
        assert is_interrupt(err)
    assert not is_interrupt(SystemError("other"))


def test_ctrl_c_leaves_a_readable_rosbag2_folder(many_scans: Path, tmp_path: Path,
                                                 full_output_bytes: int) -> None:
    """OUT/ (a rosbag2 folder): interrupted, it still has its MCAP and metadata.yaml."""
    from converters.bags import open_bag

    out = tmp_path / "bag"
    status, err = _interrupt(["convert", str(many_scans), f"{out}/", "--compress",
                              "--pointcloud2"], out, full_output_bytes // 5)
    assert status == 130 and "is a valid rosbag2 folder" in err, err
    assert sorted(p.name for p in out.iterdir()) == ["bag_0.mcap", "metadata.yaml"]
    got = messages_by_topic(out / "bag_0.mcap")
    assert 0 < len(got.get("/lidar/scan", [])) < 300
    assert open_bag(out).message_count == sum(map(len, got.values()))
    assert not list(tmp_path.glob(".*.partial"))
