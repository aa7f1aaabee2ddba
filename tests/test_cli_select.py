"""``lidarscan convert --start/--end/--topics/--rename-topic``: what is read of IN and how the
output topics are named."""

from __future__ import annotations

import calendar
from pathlib import Path

import numpy as np
import pytest

import lidarscan
from converters import cli
from converters.cli.convert_filters import parse_time
from helpers import messages_by_topic
from lidarscan.mcap import McapWriter

T0 = 1_713_492_677_000_000_000       # 2024-04-19T02:11:17Z
STEP = 100_000_000


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """/tf_static and /lidar/info at T0, then 10 scans and 10 LaserScans 0.1 s apart."""
    from converters.laserscan import SliceConverter

    info = lidarscan.make_info(
        stamp_ns=T0, frame_id="lidar", vertical_angles=np.radians([10.0, 0.0, -10.0]),
        horizontal_angles=2 * np.pi * (1 - np.arange(64) / 64), as_dataclass=True)
    slicer = SliceConverter(info, {"band": {"min_height": -1.0, "max_height": 1.0}})
    path = tmp_path_factory.mktemp("select") / "in.mcap"
    rng = np.random.default_rng(7)
    with McapWriter(path) as writer:
        writer.write("/tf_static", _tf_static(), log_time_ns=T0)
        writer.write("/lidar/info", info, log_time_ns=T0)
        for k in range(10):
            stamp = T0 + (k + 1) * STEP
            scan = lidarscan.make_scan(info, {"range": rng.uniform(1, 5, (3, 64)).astype(
                np.float32)}, stamp, as_dataclass=True)
            writer.write("/lidar/scan", scan, log_time_ns=stamp)
            writer.write("/laser/scan", slicer.convert(scan)["band"], log_time_ns=stamp)
    return path


def _tf_static() -> object:
    """A TFMessage base_link -> lidar."""
    from geometry_msgs.msg import TransformStamped
    from tf2_msgs.msg import TFMessage

    t = TransformStamped()
    t.header.frame_id, t.child_frame_id = "base_link", "lidar"
    t.transform.rotation.w = 1.0
    return TFMessage(transforms=[t])


def stamps(path: Path, topic: str) -> list[int]:
    return [m.log_time_ns for m in messages_by_topic(path).get(topic, [])]


def test_time_forms() -> None:
    iso = calendar.timegm((2024, 4, 19, 2, 11, 17)) * 10**9
    assert iso == T0
    assert parse_time("1713492677").ns == T0
    assert parse_time("1713492677.25").ns == T0 + 250_000_000
    assert parse_time("1713492677000000123ns").ns == T0 + 123
    assert parse_time("1713492677000000123").ns == T0 + 123        # 16+ digits: ns
    assert parse_time("2024-04-19T02:11:17.5Z").ns == T0 + 500_000_000
    assert parse_time("2024-04-19T02:11:17.5").ns == T0 + 500_000_000   # UTC
    assert parse_time("2024-04-19T04:11:17+02:00").ns == T0
    relative = parse_time("+2.5")
    assert relative.relative and relative.ns == 2_500_000_000
    for bad in ("", "yesterday", "-3", "+x", "nan", "12ns5"):
        with pytest.raises(ValueError, match="expected seconds since the epoch"):
            parse_time(bad)


@pytest.mark.parametrize("bounds", [
    ["--start", f"{T0 + 3 * STEP}ns", "--end", f"{T0 + 6 * STEP}ns"],
    ["--start", "1713492677.3", "--end", "2024-04-19T02:11:17.6Z"],
    ["--start", "+0.3", "--end", "+0.6"],           # after the first message (T0)
])
def test_start_and_end_keep_the_range_and_the_latched_messages(
        bounds: list[str], recording: Path, tmp_path: Path) -> None:
    out = tmp_path / "o.mcap"
    assert cli.main(["convert", str(recording), str(out), "--pointcloud2", "-q", *bounds]) == 0
    want = [T0 + k * STEP for k in (3, 4, 5)]       # start inclusive, end exclusive
    assert stamps(out, "/lidar/scan") == want == stamps(out, "/laser/scan")
    assert stamps(out, "/lidar/points") == want     # made from the scans in range only
    assert stamps(out, "/lidar/info") == [T0] == stamps(out, "/tf_static")   # latched: kept


def test_topics_reads_only_those(recording: Path, tmp_path: Path,
                                 capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "o.mcap"
    assert cli.main(["convert", str(recording), str(out), "-q", "--topics",
                     "/lidar/info,/lidar/scan", "--topics", "/tf_static"]) == 0
    assert sorted(messages_by_topic(out)) == ["/lidar/info", "/lidar/scan", "/tf_static"]
    out2 = tmp_path / "o2.mcap"
    assert cli.main(["convert", str(recording), str(out2), "-q", "--topics", "/laser/scan",
                     "--slice", "s:0:1"]) == 2    # no LidarScan read: nothing to slice
    assert cli.main(["convert", str(recording), str(out2), "--topics", "/nope"]) == 2
    err = capsys.readouterr().err
    assert "--topics='/nope': expected topics of IN (it has /laser/scan, /lidar/info" in err
    assert not out2.exists()


def test_rename_topic_renames_copied_and_new_topics(recording: Path, tmp_path: Path) -> None:
    out = tmp_path / "o.mcap"
    assert cli.main(["convert", str(recording), str(out), "-q", "--pointcloud2",
                     "--rename-topic", "/lidar/scan=/front/scan",
                     "--rename-topic", "/lidar/points=/front/points"]) == 0
    got = messages_by_topic(out)
    assert sorted(got) == ["/front/points", "/front/scan", "/laser/scan", "/lidar/info",
                           "/tf_static"]
    assert len(got["/front/points"]) == len(got["/front/scan"]) == 10
    assert cli.main(["info", str(out)]) == 0      # scans still linked to their info


@pytest.mark.parametrize(("options", "words"), [
    (["--rename-topic", "/nope=/x"], "--rename-topic='/nope': expected a topic of the output"),
    (["--rename-topic", "/laser/scan=/lidar/scan"], "a name no other output topic has"),
    (["--rename-topic", "/laser/scan"], "expected OLD=NEW"),
    (["--start", "+2", "--end", "+1"], "--end='+1': expected a time after --start +2"),
])
def test_bad_selections_are_refused(options: list[str], words: str, recording: Path,
                                    tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["convert", str(recording), str(tmp_path / "o.mcap"), *options]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and words in err[0], err
    assert not list(tmp_path.iterdir())
