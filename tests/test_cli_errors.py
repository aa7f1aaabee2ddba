"""The ``lidarscan`` commands on the real recordings of ``tests/data`` given the wrong thing: a
rosbag2 folder without ``metadata.yaml`` or with a broken one, a truncated ``.db3`` (alone or in
its bag), a calibration of another sensor or vendor, a file of another format.

Every refusal is one line on stderr naming the bad value and what was expected, with no
traceback, and nothing is written (no output file, no partial file, no view folder).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from converters.edge import cli

DATA = Path(__file__).parent / "data" / "nebula"
VLP32 = DATA / "velodyne_vlp32"
XT32 = DATA / "hesai_xt32"


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, list[str]]:
    """(exit status, stderr lines) of one command; no traceback on either stream."""
    status = cli.main(argv)
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err + captured.out
    return status, captured.err.splitlines()


def one_error(lines: list[str], command: str, *words: str) -> None:
    """Exactly one error line, for ``command``, containing every one of ``words``."""
    errors = [line for line in lines if line.startswith(f"lidarscan {command}: error: ")]
    assert len(errors) == 1 and len(lines) <= 2, lines  # (plus a damaged-input line)
    for word in words:
        assert word in errors[0], errors[0]


@pytest.fixture
def bags(tmp_path: Path) -> dict[str, Path]:
    """Broken copies of the VLP-32C bag: no metadata.yaml, metadata.yaml only, a broken
    metadata.yaml, its .db3 cut to 200 kB (alone and in the bag)."""
    db3 = next((VLP32 / "bag").glob("*.db3"))
    out = {}
    for name in ("nometa", "metaonly", "badmeta", "cutbag"):
        (tmp_path / name).mkdir()
        out[name] = tmp_path / name
    shutil.copy(db3, out["nometa"])
    shutil.copy(VLP32 / "bag" / "metadata.yaml", out["metaonly"])
    shutil.copy(db3, out["badmeta"])
    (out["badmeta"] / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed\n")
    shutil.copy(VLP32 / "bag" / "metadata.yaml", out["cutbag"])
    (out["cutbag"] / db3.name).write_bytes(db3.read_bytes()[:200_000])
    out["cut.db3"] = tmp_path / "cut.db3"
    out["cut.db3"].write_bytes(db3.read_bytes()[:200_000])
    return out


def test_view_of_raw_packets_says_to_convert_them_first(
        bags: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A bag of packets has nothing to draw until converted: the one line says so (it used
    to say only "nothing to draw")."""
    status, lines = run(["view", str(bags["nometa"]), "--out", str(tmp_path / "v")], capsys)
    assert status == 1 and len(lines) == 1, lines
    assert "nothing to draw" in lines[0] and "/sensing/lidar/front/velodyne_packets" in lines[0]
    assert "`lidarscan convert` them to LidarScans first" in lines[0]
    assert not (tmp_path / "v").exists()


def test_a_bag_without_metadata_is_read_and_said_so(
        bags: dict[str, Path], capsys: pytest.CaptureFixture[str]) -> None:
    status = cli.main(["info", str(bags["nometa"])])
    out = capsys.readouterr().out
    assert status == 0 and "no metadata.yaml; read 1 storage file(s)" in out
    assert "velodyne_msgs/msg/VelodyneScan" in out and "(379 packets)" in out


@pytest.mark.parametrize("command", ["info", "view", "convert"])
@pytest.mark.parametrize(("case", "words"), [
    ("metaonly", ("metaonly", "no storage file", "expected the .db3 or .mcap files")),
    ("badmeta", ("metadata.yaml", "expected a rosbag2 metadata.yaml")),
    ("cut.db3", ("cut.db3", "malformed", "expected a readable sqlite3 database")),
])
def test_broken_bags_are_refused_in_one_line(
        command: str, case: str, words: tuple[str, ...], bags: dict[str, Path],
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    argv = {"info": ["info", str(bags[case])],
            "view": ["view", str(bags[case]), "--out", str(out)],
            "convert": ["convert", str(bags[case]), str(tmp_path / "o.mcap")]}[command]
    status, lines = run(argv, capsys)
    assert status == 2
    one_error(lines, command, *words)
    assert not out.exists() and not (tmp_path / "o.mcap").exists()
    assert not list(tmp_path.glob("*.mcap*"))


def test_a_truncated_db3_inside_its_bag_is_damage_not_a_crash(
        bags: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    status = cli.main(["info", str(bags["cutbag"])])
    out = capsys.readouterr().out
    assert status == 1 and "problem:" in out and "malformed" in out
    status, lines = run(["convert", str(bags["cutbag"]), str(tmp_path / "o.mcap")], capsys)
    assert status == 2
    assert lines[0].startswith("damaged input: ")
    one_error(lines, "convert", "expected at least one readable message; nothing written")
    assert not list(tmp_path.glob("*.mcap*"))


@pytest.mark.parametrize(("bag", "calibration", "words"), [
    (VLP32 / "bag", DATA / "velodyne_vls128" / "VLS128.yaml",
     ("128 lasers", "expected 32 lasers for the VLP-32C")),
    (VLP32 / "bag", XT32 / "PandarXT32.csv", ("calibration.lasers",)),
    (VLP32 / "bag", VLP32 / "NOTICE.md", ("calibration", "NOTICE.md", "expected valid YAML")),
    (XT32 / "bag", VLP32 / "VLP32.yaml", ("calibration line 2", "expected laser_id")),
    (VLP32 / "bag", Path("missing.yaml"), ("--calibration missing.yaml", "no such file")),
])
def test_a_calibration_of_another_sensor_is_refused_before_anything_is_written(
        bag: Path, calibration: Path, words: tuple[str, ...], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    status, lines = run(["convert", str(bag), str(tmp_path / "o.mcap"), "--calibration",
                         str(calibration)], capsys)
    assert status == 2
    assert any(w in line for line in lines for w in words)
    assert sum(line.startswith("lidarscan convert: error: ") for line in lines) == 1, lines
    assert not list(tmp_path.glob("*.mcap*"))


def test_a_hesai_calibration_of_another_model_is_refused_up_front(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    status, lines = run(["convert", str(XT32 / "bag"), str(tmp_path / "o.mcap"),
                         "--calibration", str(DATA / "hesai_qt64" / "PandarQT64.csv")], capsys)
    assert status == 2 and len(lines) == 1, (status, len(lines))
    one_error(lines, "convert", "calibration lasers=64", "32")
    assert not list(tmp_path.glob("*.mcap*"))


@pytest.mark.parametrize("option", [["--cloud-topic", "/nope"],
                                    ["--merge-topic", "/nope", "--merge"]])
def test_an_option_naming_a_topic_that_is_not_there_is_refused(
        option: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    status, lines = run(["convert", str(VLP32 / "bag"), str(tmp_path / "o.mcap"), "-q",
                         "--slice", "s:0:1", *option], capsys)
    assert status == 2 and "/nope" in lines[-1]
    assert not list(tmp_path.glob("*.mcap*"))


@pytest.mark.parametrize(("options", "words"), [
    (["--zstd-level", "99"], "'99': expected a zstd level from -131072 to 22"),
    (["--chunk-compression", "gzip"], "invalid choice: 'gzip'"),
    (["--compress=fast"], "'fast'"),
    (["--threads", "0"], "invalid choice: 0"),
])
def test_a_bad_option_value_is_one_error_line_after_a_short_usage(
        options: list[str], words: str, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """(argparse printed convert's whole 15-line usage before the error.)"""
    with pytest.raises(SystemExit) as exc:
        cli.main(["convert", str(VLP32 / "bag"), str(tmp_path / "o.mcap"), *options])
    lines = capsys.readouterr().err.splitlines()
    assert exc.value.code == 2
    assert lines == ["usage: lidarscan convert [-h] [options] IN OUT", lines[1]], lines
    assert lines[1].startswith("lidarscan convert: error: ") and words in lines[1]
    assert not list(tmp_path.iterdir())


def test_an_output_a_recording_without_lidar_cannot_make_is_refused(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--pointcloud2 / --slice on a recording of LaserScans only: nothing to make them from."""
    laser = next((Path(__file__).parent / "data" / "laserscan").glob("*.mcap"))
    for option in (["--pointcloud2"], ["--slice", "s:0:1"]):
        status, lines = run(["convert", str(laser), str(tmp_path / "o.mcap"), "-q", *option],
                            capsys)
        assert status == 2, (option, lines)
        one_error(lines, "convert", option[0], "sensor_msgs/msg/LaserScan")
    assert not list(tmp_path.glob("*.mcap*"))
