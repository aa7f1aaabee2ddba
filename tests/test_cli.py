"""The ``lidarscan`` command line: info, convert (good, bad and interrupted input), view."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import lidarscan
from converters.edge import cli
from lidarscan.mcap import McapWriter, read_messages, read_scans

from helpers import messages_by_topic

PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def demo_mcap(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from converters.edge.demo.run import run_demo

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
    from converters.slices.converter import SliceConverter
    from converters.edge.nodes.tf import TransformBuffer
    from converters.pointcloud2.converter import to_pointcloud2

    src, dst = tmp_path / "in.mcap", tmp_path / "out.mcap"
    copied = copy_topics(demo_mcap, src, SCAN_TOPICS)
    status = cli.main(["convert", str(src), str(dst), "--pointcloud2", "--slice",
                       "low:0.05:0.5", "--slice", "mid:0.5:1.0", "--frame", "base_link",
                       "--merge", "--merge-topic", "/laser/scan", "-q"])
    assert status == 0
    out = messages_by_topic(dst)
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
    out = messages_by_topic(dst)
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
    out = messages_by_topic(dst)  # no BadMessage: the file was finished properly
    assert sum(len(v) for v in out.values()) == 8


def test_convert_driver_clouds_to_lidarscan(tmp_path: Path, demo_mcap: Path) -> None:
    src, dst = tmp_path / "clouds.mcap", tmp_path / "scans.mcap"
    copy_topics(demo_mcap, src, {"/lidar/points", "/tf_static"})
    assert cli.main(["convert", str(src), str(dst), "-q"]) == 0
    out = messages_by_topic(dst)
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
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "converters.edge.cli"]
    done = subprocess.run(cmd + ["--help"], check=False, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0
    for command in ("demo", "info", "convert", "view"):
        assert command in done.stdout


def test_info_into_a_closed_pipe_exits_quietly() -> None:
    """`lidarscan info REC | head -1` with the reader gone before the text is written: exit 0,
    nothing on stderr (it printed "error: [Errno 32] Broken pipe" and exited 2)."""
    exe = Path(sys.executable).parent / "lidarscan"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "converters.edge.cli"]
    bag = Path(__file__).parent / "data" / "nebula" / "velodyne_vls128" / "bag"
    read_end, write_end = os.pipe()
    os.close(read_end)                                   # nobody reads: the first write fails
    try:
        done = subprocess.run(cmd + ["info", str(bag)], check=False, stdout=write_end,
                              stderr=subprocess.PIPE, text=True, timeout=120)
    finally:
        os.close(write_end)
    assert (done.returncode, done.stderr) == (0, ""), done.stderr


# ------------------------------------------------------- inputs checked before anything is written

def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        cli.main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.startswith("lidarscan ")


def _bad_inputs(tmp: Path, demo: Path) -> dict[str, tuple[Path, str]]:
    """name -> (path, words the error must contain)."""
    (tmp / "notes.txt").write_text("not a recording\n")
    (tmp / "empty.mcap").write_bytes(b"")
    (tmp / "stub.mcap").write_bytes(demo.read_bytes()[:20])  # cut inside the first record
    (tmp / "folder").mkdir(exist_ok=True)
    return {"text": (tmp / "notes.txt", "not an MCAP file"),
            "empty": (tmp / "empty.mcap", "empty"),
            "stub": (tmp / "stub.mcap", "truncated"),
            "folder": (tmp / "folder", "directory without metadata.yaml"),
            "missing": (tmp / "missing.mcap", "no such file")}


@pytest.mark.parametrize("command", ["info", "convert", "view"])
@pytest.mark.parametrize("case", ["text", "empty", "stub", "folder", "missing"])
def test_every_command_rejects_bad_inputs_with_a_reason(
        command: str, case: str, tmp_path: Path, demo_mcap: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    path, words = _bad_inputs(tmp_path, demo_mcap)[case]
    out = tmp_path / "out"
    argv = {"info": ["info", str(path)],
            "convert": ["convert", str(path), str(out / "o.mcap")],
            "view": ["view", str(path), "--out", str(out)]}[command]
    out.mkdir() if command == "convert" else None
    before = sorted(tmp_path.rglob("*"))
    status = cli.main(argv)
    captured = capsys.readouterr()
    text = captured.err + captured.out
    assert status in (1, 2), text
    assert words in text, text
    assert sorted(tmp_path.rglob("*")) == before  # nothing written, no partial file left


def test_db3_is_recognised_not_called_damaged(tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    import sqlite3

    db3 = tmp_path / "rec.db3"
    con = sqlite3.connect(db3)
    con.execute("CREATE TABLE unrelated(x)")
    con.commit()
    con.close()
    assert cli.main(["convert", str(db3), str(tmp_path / "o.mcap")]) == 2
    err = capsys.readouterr().err
    assert "'topics' and 'messages'" in err and "invalid magic" not in err
    assert not (tmp_path / "o.mcap").exists()


def test_truncated_recording_reports_the_cut_everywhere(
        tmp_path: Path, demo_mcap: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = demo_mcap.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:len(data) * 2 // 3])
    assert cli.main(["info", str(cut)]) == 1
    assert "truncated" in capsys.readouterr().out
    assert cli.main(["view", str(cut), "--out", str(tmp_path / "v")]) == 1  # drew, but damaged
    assert "truncated" in capsys.readouterr().err
    out = tmp_path / "o.mcap"
    assert cli.main(["convert", str(cut), str(out), "-q"]) == 1  # readable output: kept
    err = capsys.readouterr().err
    assert "damaged input" in err and "truncated" in err
    assert messages_by_topic(out)["/lidar/scan"]


@pytest.mark.parametrize("options,words", [
    (["--preset", "foo"], "--preset: 'foo': expected one of"),
    (["--fields", "x,y,q"], "x, y and z"),
    (["--preset", "ouster", "--fields", "x,y,z"], "give one of them"),
])
def test_bad_option_values_are_usage_errors(options: list[str], words: str, tmp_path: Path,
                                            demo_mcap: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        cli.main(["convert", str(demo_mcap), str(tmp_path / "o.mcap")] + options)
    assert exc.value.code == 2
    assert words in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("options,words", [
    (["--slice", "s:0:1", "--frame", "nosuch"], "--frame='nosuch'"),
    (["--pointcloud2", "--fields", "x,y,z,nosuch"], "--fields x,y,z,nosuch"),
])
def test_options_that_do_not_fit_the_recording_fail_once(
        options: list[str], words: str, tmp_path: Path, demo_mcap: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "in.mcap"
    copy_topics(demo_mcap, src, SCAN_TOPICS)
    out = tmp_path / "o.mcap"
    assert cli.main(["convert", str(src), str(out)] + options) == 2
    err = capsys.readouterr().err
    assert err.count("error:") == 1 and words in err and "bad message" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.mcap"]


# ----------------------------------------------------------- one topic, one frame, one layout

def test_readme_example_on_the_demo_refuses_the_clash_then_replaces(
        tmp_path: Path, demo_mcap: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out.mcap"
    argv = ["convert", str(demo_mcap), str(out), "--pointcloud2", "--slice", "table:0.5:1.0",
            "--merge", "-q"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    for topic in ("/lidar/points", "/lidar/slices/table", "/scan_merged"):
        assert topic in err
    assert not out.exists()
    assert cli.main(argv + ["--replace"]) == 0
    got = messages_by_topic(out)
    frames = {m.decode().header.frame_id for m in got["/lidar/slices/table"]}
    rays = {len(m.decode().ranges) for m in got["/lidar/slices/table"]}
    assert frames == {"os_sensor"} and len(rays) == 1
    assert len(got["/lidar/slices/table"]) == len(got["/lidar/scan"]) == 3
    assert cli.main(["info", str(out)]) == 0


def test_info_flags_a_topic_whose_frame_or_shape_changes(
        tmp_path: Path, demo_mcap: Path, capsys: pytest.CaptureFixture[str]) -> None:
    mixed = tmp_path / "mixed.mcap"
    src = messages_by_topic(demo_mcap)
    with McapWriter(mixed) as writer:
        for a, b in zip(src["/lidar/slices/table"], src["/laser/scan"]):
            writer.write("/mixed", a.payload, msgtype=a.msgtype, log_time_ns=a.log_time_ns)
            writer.write("/mixed", b.payload, msgtype=b.msgtype, log_time_ns=b.log_time_ns)
    assert cli.main(["info", str(mixed)]) == 1
    out = capsys.readouterr().out
    assert "topic '/mixed': frame_id changes mid-recording" in out
    assert "topic '/mixed': shape changes mid-recording" in out


def test_scan_topics_sharing_a_namespace_get_distinct_outputs(
        tmp_path: Path, demo_mcap: Path) -> None:
    src, out = tmp_path / "two.mcap", tmp_path / "out.mcap"
    items = messages_by_topic(demo_mcap)
    with McapWriter(src) as writer:
        for topic in ("/tf_static", "/lidar/info"):
            for m in items[topic]:
                writer.write(topic, m.payload, msgtype=m.msgtype, log_time_ns=m.log_time_ns)
        for m in items["/lidar/scan"]:
            for topic in ("/lidar/scan", "/lidar/scan_copy"):
                writer.write(topic, m.payload, msgtype=m.msgtype, log_time_ns=m.log_time_ns)
    assert cli.main(["convert", str(src), str(out), "--pointcloud2", "--slice", "s:0:1",
                     "--merge", "-q"]) == 0
    got = messages_by_topic(out)
    for topic in ("/lidar/scan", "/lidar/scan_copy"):
        assert len(got[f"{topic}/points"]) == len(got[f"{topic}/slices/s"]) == 3
    assert len(got["/scan_merged"]) == 3


def test_a_frame_known_only_later_reports_the_early_scans_not_a_usage_error(
        tmp_path: Path, demo_mcap: Path, capsys: pytest.CaptureFixture[str]) -> None:
    items = messages_by_topic(demo_mcap)
    src, out = tmp_path / "late_tf.mcap", tmp_path / "out.mcap"
    with McapWriter(src) as writer:  # the first scan is recorded before /tf_static
        order = [items["/lidar/info"][0], items["/lidar/scan"][0], items["/tf_static"][0],
                 *items["/lidar/scan"][1:]]
        for m in order:
            writer.write(m.topic, m.payload, msgtype=m.msgtype, log_time_ns=m.log_time_ns)
    status = cli.main(["convert", str(src), str(out), "--slice", "s:0:1", "--frame",
                       "base_link", "-q"])
    err = capsys.readouterr().err
    assert status == 1, err
    assert err.count("bad message #1 topic '/lidar/scan'") == 1 and "base_link" in err
    assert len(messages_by_topic(out)["/lidar/slices/s"]) == 2


def test_convert_keeps_channel_metadata_and_reports_progress(
        tmp_path: Path, demo_mcap: Path, capsys: pytest.CaptureFixture[str]) -> None:
    qos = "- history: 1\n  depth: 1\n  reliability: 1\n  durability: 1\n"
    src, out = tmp_path / "in.mcap", tmp_path / "out.mcap"
    items = messages_by_topic(demo_mcap)
    with McapWriter(src) as writer:
        for topic in ("/tf_static", "/lidar/info", "/lidar/scan", "/laser/scan"):
            for m in items[topic]:
                writer.write(topic, m.payload, msgtype=m.msgtype, log_time_ns=m.log_time_ns,
                             metadata={"offered_qos_profiles": qos} if topic != "/laser/scan"
                             else None)
    assert cli.main(["convert", str(src), str(out), "--progress"]) == 0
    err = capsys.readouterr().err
    assert "converting in.mcap: 100%" in err  # stderr is not a terminal: lines
    got = messages_by_topic(out)
    for topic in ("/tf_static", "/lidar/info", "/lidar/scan"):
        assert dict(got[topic][0].metadata).get("offered_qos_profiles") == qos, topic
    assert "offered_qos_profiles" not in dict(got["/laser/scan"][0].metadata) or \
        dict(got["/laser/scan"][0].metadata)["offered_qos_profiles"] != qos


def test_zstd_level_is_checked_and_written(tmp_path: Path, demo_mcap: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    from mcap.reader import make_reader

    out = tmp_path / "o.mcap"
    assert cli.main(["convert", str(demo_mcap), str(out), "--chunk-compression", "lz4",
                     "--zstd-level", "3"]) == 2
    assert "--zstd-level" in capsys.readouterr().err and not out.exists()
    with pytest.raises(SystemExit) as exc:
        cli.main(["convert", str(demo_mcap), str(out), "--zstd-level", "23"])
    assert exc.value.code == 2 and "zstd level" in capsys.readouterr().err
    sizes = {}
    for level in ("-5", "9"):
        assert cli.main(["convert", str(demo_mcap), str(out), "--zstd-level", level,
                         "--replace", "-q"]) == 0
        with open(out, "rb") as stream:
            reader = make_reader(stream, validate_crcs=True)
            assert {c.compression for c in reader.get_summary().chunk_indexes} == {"zstd"}
            assert sum(1 for _ in reader.iter_messages()) == \
                sum(1 for _ in read_messages(demo_mcap))
        sizes[level] = out.stat().st_size
    assert sizes["9"] < sizes["-5"]   # the level reached the compressor


# ------------------------------------------------------------------------------ read ahead

def test_read_ahead_gives_every_item_in_order_then_the_error_of_its_iterator() -> None:
    import threading

    from converters.edge.cli._common import _read_ahead

    threads: set[str] = set()

    def items() -> Any:
        for k in range(50):
            threads.add(threading.current_thread().name)
            yield k
        raise ValueError("damaged after 50")

    got: list[int] = []
    with pytest.raises(ValueError, match="damaged after 50"):
        for item in _read_ahead(items, depth=3):
            got.append(item)
    assert got == list(range(50))
    assert threads == {"read-ahead"}            # made in the background thread


def test_leaving_a_read_ahead_early_closes_its_iterator_in_its_thread() -> None:
    import threading

    from converters.edge.cli._common import _read_ahead

    before = threading.active_count()
    closed: list[str] = []

    def items() -> Any:
        try:
            yield from range(10_000)
        finally:
            closed.append(threading.current_thread().name)

    reader = _read_ahead(items, depth=2)
    assert [next(reader) for _ in range(5)] == [0, 1, 2, 3, 4]
    reader.close()                               # as a KeyboardInterrupt in the loop does
    assert closed == ["read-ahead"]
    assert threading.active_count() == before


def test_prepared_items_come_in_pairs_with_the_error_in_place_of_the_value() -> None:
    import threading

    from converters.edge.cli._common import _open_input
    from lidarscan.errors import DecodeError

    bag = Path(__file__).parent / "data" / "nebula" / "velodyne_vls128" / "bag"
    seen: list[str] = []

    def prepare(item: Any) -> int:
        seen.append(threading.current_thread().name)
        if item.index == 1:
            raise DecodeError("packets", item.index, "a message this test does not break")
        return item.index * 10

    source = _open_input(str(bag), "IN")
    pairs = list(source.items(prepare=prepare))
    plain = list(source.items())
    assert [item.index for item, _ in pairs] == [item.index for item in plain]
    assert len(pairs) > 2 and pairs[0][1] == 0 and pairs[2][1] == 20
    assert isinstance(pairs[1][1], DecodeError)
    assert set(seen) == {"read-ahead"}
