"""``lidarscan info`` and ``view`` on real recordings and on the tool's own output: what they
say about size, dates, the packets' sensor, Ouster files, partial rotations and indices."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from converters import cli
from lidarscan.mcap import read_scans

DATA = Path(__file__).parent / "data" / "nebula"
VLP32 = DATA / "velodyne_vlp32"
OUSTER = Path(__file__).parent / "data" / "ouster"


@pytest.fixture(scope="module")
def vlp32_clouds(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The VLP-32C bag converted with --pointcloud2 --preset velodyne: unorganized clouds whose
    point count changes with every rotation."""
    out = tmp_path_factory.mktemp("own") / "vlp32.mcap"
    assert cli.main(["convert", str(VLP32 / "bag"), str(out), "-q", "--pointcloud2",
                     "--preset", "velodyne"]) == 0
    return out


def test_info_of_the_tools_own_output_passes(vlp32_clouds: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    """An unorganized cloud changes width every message: not a "shape change" (it was)."""
    widths = set()
    from lidarscan.mcap import read_messages
    for item in read_messages(vlp32_clouds):
        if item.topic.endswith("/points"):
            cloud = item.decode()
            assert cloud.height == 1
            widths.add(cloud.width)
    assert len(widths) > 1          # the case the test is about
    assert cli.main(["info", str(vlp32_clouds)]) == 0
    out = capsys.readouterr().out
    assert "no problems found" in out and "shape changes" not in out


def test_info_says_size_dates_duration_and_the_packets_sensor(
        capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["info", str(VLP32 / "bag")]) == 0
    out = capsys.readouterr().out
    size = sum(p.stat().st_size for p in (VLP32 / "bag").glob("*.db3"))
    assert f"size {size / 1000:.1f} kB" in out
    # first and last log time of the bag (its metadata.yaml: starting_time, duration)
    assert ("2024-04-19 02:11:17.464078412 UTC .. 2024-04-19 02:11:17.841065510 UTC "
            "(duration 0.377 s)") in out
    assert "sensor on /sensing/lidar/front/velodyne_packets: Velodyne VLP-32C, strongest" in out
    assert cli.main(["info", str(DATA / "hesai_xt32" / "bag")]) == 0
    assert "sensor on /pandar_packets: Hesai PandarXT32" in capsys.readouterr().out


def test_info_reads_an_ouster_file_as_convert_does(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("ouster.sdk")
    from ouster.sdk import core, osf

    name = "OS-0-32-U1_v2.2.0_1024x10"
    text = (OUSTER / f"{name}.json").read_text()
    sensor = core.SensorInfo(text)
    frame = core.LidarFrame(sensor)
    frame.timestamp[:] = 1_700_000_000_000_000_000 + np.arange(frame.w) * 97_656
    frame.status[:] = 1                                # every column valid
    path = tmp_path / "one.osf"
    writer = osf.Writer(str(path), sensor)
    writer.save(0, frame)
    writer.close()
    assert cli.main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert f"{path} (an Ouster recording): 1 scans" in out
    assert "sensor: Ouster OS-0-32-U1 32x1024" in out and "2023-11-14 22:13:20" in out
    assert cli.main(["info", str(VLP32 / "bag"), "--metadata", str(OUSTER / f"{name}.json")]) \
        == 2
    assert "--metadata=" in capsys.readouterr().err


def test_view_draws_the_first_complete_rotation_and_marks_a_partial_one(
        vlp32_clouds: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from converters.cli.view_pick import ScanPicker, coverage

    pairs = list(read_scans(vlp32_clouds))
    covered = [coverage(s, i) for s, i in pairs]
    assert covered[0] < 0.6 * max(covered)        # the bag starts mid-rotation
    default, first = ScanPicker(None), ScanPicker(0)
    for scan, info in pairs:
        default.add(scan, info)
        first.add(scan, info)
    pick = default.chosen()["velodyne_front"]
    assert pick.index == 1 and "first complete rotation" in pick.note
    assert first.chosen()["velodyne_front"].note.startswith(" (PARTIAL rotation: ")
    assert cli.main(["view", str(vlp32_clouds), "--out", str(tmp_path / "v")]) == 0
    assert (tmp_path / "v" / "range_image_velodyne_front.png").exists()


def test_view_index_out_of_range_says_how_many_scans(
        vlp32_clouds: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["view", str(vlp32_clouds), "--out", str(tmp_path / "v"), "--index",
                     "9"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err == [("lidarscan view: error: --index=9: expected an index below 6 (the "
                    "LidarScans of frame 'velodyne_front' are 6: 0..5)")]
    assert not (tmp_path / "v").exists()


def test_view_index_past_the_laserscans_says_how_many(tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    laser = (Path(__file__).parent / "data" / "laserscan"
             / "scan_tools_laser_scan_matcher_demo.mcap")
    assert cli.main(["view", str(laser), "--out", str(tmp_path / "v"), "--index", "400"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err == [("lidarscan view: error: --index=400: expected an index below 360 (the "
                    "LaserScan and PointCloud2 topics have at most 360 messages: 0..359)")]
    assert not (tmp_path / "v").exists()
    assert cli.main(["view", str(laser), "--out", str(tmp_path / "v"), "--index", "359"]) == 0
