"""The ``lidarscan`` command line: info, convert (good, bad and interrupted input), view."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import lidarscan
from converters import cli
from lidarscan.mcap import BadMessage, McapWriter, read_messages, read_scans

PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def demo_mcap(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from converters.demo import run_demo

    out = tmp_path_factory.mktemp("demo")
    return run_demo(out, frames=3, images=False).mcap_path


def copy_topics(src: Path, dst: Path, topics: set[str],
                edit: Any = None) -> list[Any]:
    """Copy the raw records of some topics; ``edit(index, item) -> bytes | None`` may change or
    drop a payload. Returns the items written."""
    written = []
    with McapWriter(dst) as writer:
        for k, item in enumerate(m for m in read_messages(src) if m.topic in topics):
            payload = item.payload if edit is None else edit(k, item)
            if payload is None:
                continue
            writer.write(item.topic, payload, msgtype=item.msgtype,
                         log_time_ns=item.log_time_ns)
            written.append(item)
    return written


def messages(path: Path) -> dict[str, list[Any]]:
    out: dict[str, list[Any]] = {}
    for item in read_messages(path):
        assert not isinstance(item, BadMessage), item
        out.setdefault(item.topic, []).append(item)
    return out


SCAN_TOPICS = {"/tf_static", "/tf", "/lidar/info", "/lidar/scan", "/laser/scan"}


def test_info_lists_topics_versions_and_linkage(demo_mcap: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["info", str(demo_mcap)]) == 0
    out = capsys.readouterr().out
    assert "/lidar/scan" in out and "lidarscan_msgs/msg/LidarScan" in out
    assert "128x2048 Ouster OS-1-128 frame 'os_sensor'" in out
    assert "linked to their LidarInfo: 3 of 3" in out and "no problems found" in out


def test_info_reports_problems(tmp_path: Path, demo_mcap: Path,
                               capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.mcap"

    def edit(k: int, item: Any) -> bytes | None:
        if item.topic == "/lidar/info":
            return None  # scans without their info
        return item.payload
    copy_topics(demo_mcap, bad, SCAN_TOPICS, edit)
    assert cli.main(["info", str(bad)]) == 1
    out = capsys.readouterr().out
    assert "linked to their LidarInfo: 0 of 3" in out
    assert out.count("problem: message #") == 3 and "never arrived" in out


def test_convert_adds_cloud_slices_and_merged_scan(tmp_path: Path, demo_mcap: Path) -> None:
    from converters.laserscan import SliceConverter
    from converters.nodes.tf import TransformBuffer
    from converters.pointcloud2 import to_pointcloud2

    src, dst = tmp_path / "in.mcap", tmp_path / "out.mcap"
    copied = copy_topics(demo_mcap, src, SCAN_TOPICS)
    status = cli.main(["convert", str(src), str(dst), "--pointcloud2", "--slice",
                       "low:0.05:0.5", "--slice", "mid:0.5:1.0", "--frame", "base_link",
                       "--merge", "--merge-topic", "/laser/scan", "-q"])
    assert status == 0
    out = messages(dst)
    # every input message is there, byte for byte
    for topic in SCAN_TOPICS:
        assert [m.payload for m in out[topic]] == [m.payload for m in copied if m.topic == topic]
    assert len(out["/lidar/points"]) == len(out["/lidar/slices/low"]) == 3
    assert len(out["/scan_merged"]) == 3
    tf = TransformBuffer()
    tf.add_message(out["/tf_static"][0].decode(), static=True)
    pairs = list(read_scans(src))
    scan, info = pairs[0]
    assert out["/lidar/points"][0].decode().data.tobytes() == bytes(
        to_pointcloud2(scan, info).data)
    expected = SliceConverter(info, {"low": {"min_height": 0.05, "max_height": 0.5}},
                              extrinsics=tf.lookup("base_link", "os_sensor"),
                              frame_id="base_link").convert(scan)["low"]
    got = out["/lidar/slices/low"][0].decode()
    assert got.header.frame_id == "base_link"
    assert np.array_equal(np.asarray(got.ranges), np.asarray(expected.ranges), equal_nan=True)


def test_convert_reports_bad_messages_and_keeps_the_good_ones(
        tmp_path: Path, demo_mcap: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src, dst = tmp_path / "in.mcap", tmp_path / "out.mcap"
    state = {"scans": 0}

    def edit(k: int, item: Any) -> bytes:
        if item.topic == "/lidar/scan":
            state["scans"] += 1
            if state["scans"] == 2:
                return item.payload[: len(item.payload) // 2]  # truncated scan
        return item.payload
    copied = copy_topics(demo_mcap, src, SCAN_TOPICS, edit)
    bad_index = [i for i, m in enumerate(copied) if m.topic == "/lidar/scan"][1]
    assert cli.main(["convert", str(src), str(dst), "--slice", "low:0.05:0.5"]) == 1
    err = capsys.readouterr().err
    assert f"bad message #{bad_index} topic '/lidar/scan' stamp 1700000000.1" in err
    assert "1 BAD message(s)" in err
    out = messages(dst)
    assert len(out["/lidar/scan"]) == 2 and len(out["/lidar/slices/low"]) == 2
    assert len(out["/laser/scan"]) == 3


def test_convert_interrupted_leaves_a_readable_file(tmp_path: Path, demo_mcap: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    src, dst = tmp_path / "in.mcap", tmp_path / "out.mcap"
    copy_topics(demo_mcap, src, SCAN_TOPICS)
    real_write = McapWriter.write
    calls = {"n": 0}

    def write(self: McapWriter, topic: str, msg: Any, **kw: Any) -> None:
        calls["n"] += 1
        if calls["n"] == 9:
            raise KeyboardInterrupt  # Ctrl-C in the middle of the run
        real_write(self, topic, msg, **kw)

    monkeypatch.setattr(McapWriter, "write", write)
    assert cli.main(["convert", str(src), str(dst), "--pointcloud2", "-q"]) == 130
    monkeypatch.undo()
    out = messages(dst)  # no BadMessage: the file was finished properly
    assert sum(len(v) for v in out.values()) == 8


def test_convert_driver_clouds_to_lidarscan(tmp_path: Path, demo_mcap: Path) -> None:
    src, dst = tmp_path / "clouds.mcap", tmp_path / "scans.mcap"
    copy_topics(demo_mcap, src, {"/lidar/points", "/tf_static"})
    assert cli.main(["convert", str(src), str(dst), "-q"]) == 0
    out = messages(dst)
    assert len(out["/lidar/lidar_info"]) == 1 and len(out["/lidar/lidar_scan"]) == 3
    assert "/lidar/points" not in out and len(out["/tf_static"]) == 1
    pairs = list(read_scans(dst))
    assert len(pairs) == 3
    original = [s for s, _ in read_scans(demo_mcap)]
    for (scan, info), truth in zip(pairs, original):
        lidarscan.validate(scan, info)
        # same ranges where the cloud had points (the converter destaggered them)
        got = lidarscan.range_m(scan, info)
        assert np.isfinite(got).sum() == np.isfinite(lidarscan.range_m(truth)).sum()


def test_view_writes_pngs(tmp_path: Path, demo_mcap: Path,
                          capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["view", str(demo_mcap), "--out", str(tmp_path / "v"), "--index", "1"]) == 0
    paths = [Path(p) for p in capsys.readouterr().out.split()]
    assert {p.name for p in paths} >= {"range_image_os_sensor.png", "laserscans.png",
                                       "cloud_lidar_points.png"}
    for p in paths:
        assert p.read_bytes()[:8] == PNG


@pytest.mark.parametrize("argv", [
    ["convert", "missing.mcap", "out.mcap"],
    ["convert", "{demo}", "{tmp}/o.mcap", "--slice", "table:0.5"],
    ["convert", "{demo}", "{demo}"],
    ["convert", "{demo}", "{tmp}/o.mcap", "--merge"],
    ["info", "missing.mcap"],
])
def test_usage_and_fatal_errors_exit_2(argv: list[str], tmp_path: Path, demo_mcap: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    args = [a.format(demo=demo_mcap, tmp=tmp_path) for a in argv]
    assert cli.main(args) == 2
    assert "error" in capsys.readouterr().err


def test_argparse_usage_error_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        cli.main(["convert"])
    assert exc.value.code == 2


def test_console_script_help() -> None:
    exe = Path(sys.executable).parent / "lidarscan"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "converters.cli"]
    done = subprocess.run(cmd + ["--help"], check=False, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0
    for command in ("demo", "info", "convert", "view"):
        assert command in done.stdout
