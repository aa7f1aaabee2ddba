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


# ------------------------------------------- options that do not fit the input are refused

LASER = Path(__file__).parent / "data" / "laserscan" / "scan_tools_laser_scan_matcher_demo.mcap"


@pytest.fixture(scope="module")
def scans_mcap(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The VLP-32C bag converted to a LidarScan recording (the tool's own output)."""
    out = tmp_path_factory.mktemp("scans") / "vlp32.mcap"
    assert cli.main(["convert", str(VLP32 / "bag"), str(out), "-q"]) == 0
    return out


@pytest.mark.parametrize(("source", "options", "words"), [
    ("scans", ["--calibration", str(VLP32 / "VLP32.yaml")],
     ("--calibration=", "raw lidar packets", "IN is a recording of LidarScans")),
    ("vlp32", ["--metadata", str(VLP32 / "VLP32.yaml")],
     ("--metadata=", "an Ouster .pcap/.pcapng/.osf or Ouster packets", "IN is a recording of raw lidar packets")),
    ("vlp32", ["--extrinsics", "0,0,1,0,0,0"], ("--extrinsics=", "--frame FRAME too")),
    ("vlp32", ["--frame", "base_link"], ("--frame='base_link'", "--slice or --merge-topic")),
    ("vlp32", ["--keep-clouds"], ("--keep-clouds=True", "driver PointCloud2")),
    ("scans", ["--keep-packets"], ("--keep-packets=True", "raw lidar packets")),
    ("scans", ["--firetimes", str(XT32 / "PandarXT32.csv")], ("--firetimes=", "Hesai")),
    ("vlp32", ["--preset", "velodyne"], ("--preset='velodyne'", "--pointcloud2 too")),
    ("vlp32", ["--merge-out", "/m"], ("--merge-out='/m'", "--merge or --merge-topic")),
    ("laser", ["--slice", "s:0:1", "--cloud-topic", "/nope"], ("--cloud-topic",)),
    ("laser", ["--exclude", "/nope"], ("--exclude='/nope'", "a topic read from IN (it has /scan)")),
    ("scans", ["--topics", "/sensing/lidar/front/velodyne_packets/lidar_scan", "--exclude",
               "/sensing/lidar/front/velodyne_packets/lidar_info"],
     ("--exclude='/sensing/lidar/front/velodyne_packets/lidar_info'", "a topic read from IN")),
    ("laser", ["--progress", "-q"], ("--progress=True", "one of --progress and -q")),
])
def test_an_option_that_does_not_fit_the_input_is_refused(
        source: str, options: list[str], words: tuple[str, ...], scans_mcap: Path,
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """(Each of these was silently ignored: exit 0 and an output made without it.)"""
    inputs = {"scans": scans_mcap, "vlp32": VLP32 / "bag", "laser": LASER}
    status, lines = run(["convert", str(inputs[source]), str(tmp_path / "o.mcap"), *options],
                        capsys)
    assert status == 2
    one_error(lines, "convert", *words)
    assert not list(tmp_path.iterdir())


def test_a_missing_calibration_names_the_flag_and_the_file(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for bag, file in ((DATA / "velodyne_vls128" / "bag", "VLS-128 calibration YAML"),
                      (XT32 / "bag", "angle-correction CSV")):
        status, lines = run(["convert", str(bag), str(tmp_path / "o.mcap")], capsys)
        assert status == 2
        one_error(lines, "convert", "--calibration='not given'", file,
                  "give the file with --calibration FILE")
    assert not list(tmp_path.iterdir())


# ------------------------------------------------------------------------ kinds of output

def test_out_ending_in_a_slash_or_an_empty_folder_writes_a_rosbag2_folder(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import yaml

    from converters.bags import open_bag
    from helpers import messages_by_topic

    alone = tmp_path / "alone.mcap"
    assert cli.main(["convert", str(VLP32 / "bag"), str(alone), "-q"]) == 0
    empty = tmp_path / "empty"
    empty.mkdir()
    for out in (f"{tmp_path / 'run1'}/", str(empty)):
        assert cli.main(["convert", str(VLP32 / "bag"), out, "-q"]) == 0
        folder = Path(out)
        storage = folder / f"{folder.name}_0.mcap"
        assert sorted(p.name for p in folder.iterdir()) == sorted([storage.name, "metadata.yaml"])
        meta = yaml.safe_load((folder / "metadata.yaml").read_text())
        info = meta["rosbag2_bagfile_information"]
        assert info["storage_identifier"] == "mcap"
        assert info["relative_file_paths"] == [storage.name]
        want, got = messages_by_topic(alone), messages_by_topic(storage)
        assert {t: [m.payload for m in v] for t, v in got.items()} == \
            {t: [m.payload for m in v] for t, v in want.items()}
        assert info["message_count"] == sum(map(len, got.values()))
        assert open_bag(folder).message_count == info["message_count"]   # read back as a bag
    assert sorted(p.name for p in tmp_path.iterdir()) == ["alone.mcap", "empty", "run1"]
    capsys.readouterr()


@pytest.mark.parametrize(("name", "words"), [
    ("o.db3", ("OUT='", "o.db3", "a rosbag2 sqlite3 file, which convert does not write")),
    ("full", ("a new or empty folder", "nothing is overwritten")),
])
def test_an_output_that_cannot_be_written_as_named_is_refused(
        name: str, words: tuple[str, ...], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """Never MCAP bytes under a .db3 name, never files added to a folder that has some."""
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("mine")
    status, lines = run(["convert", str(VLP32 / "bag"), str(tmp_path / name), "-q"], capsys)
    assert status == 2
    one_error(lines, "convert", *words)
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["full", "keep.txt"]


# ------------------------------------------------------ one plain line, naming what is wrong

@pytest.mark.parametrize(("bag", "calibration", "kind"), [
    (VLP32 / "bag", DATA / "velodyne_vls128" / "VLS128.yaml", "a Velodyne calibration YAML"),
    (VLP32 / "bag", VLP32 / "NOTICE.md", "a Velodyne calibration YAML"),
    (XT32 / "bag", VLP32 / "VLP32.yaml", "a Hesai angle-correction CSV"),
])
def test_a_calibration_error_names_the_file_and_the_format_on_one_line(
        bag: Path, calibration: Path, kind: str, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    status, lines = run(["convert", str(bag), str(tmp_path / "o.mcap"), "--calibration",
                         str(calibration)], capsys)
    assert status == 2 and len(lines) == 1, lines   # (a YAML parser's message had 2 lines)
    one_error(lines, "convert", f"--calibration='{calibration}': expected {kind}")


def test_input_errors_are_plain_lines_with_the_role_and_the_path(
        bags: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    gif = tmp_path / "pic.gif"
    gif.write_bytes(b"GIF89a\x00\x01rest")
    status, lines = run(["convert", str(gif), str(tmp_path / "o.mcap")], capsys)
    assert status == 2
    # the bytes escaped once (they were twice: b'GIF89a\\x00\\x01')
    one_error(lines, "convert", f"IN {gif}: not an MCAP file (starts with b'GIF89a\\x00\\x01'): "
                                "expected an MCAP file")
    status, lines = run(["info", str(bags["badmeta"])], capsys)
    assert status == 2 and "\\n" not in lines[0]            # no escaped newlines
    one_error(lines, "info", f"FILE {bags['badmeta'] / 'metadata.yaml'}: ParserError: while "
                             "parsing a flow sequence in")
    status, lines = run(["convert", str(bags["cut.db3"]), str(tmp_path / "o.mcap")], capsys)
    assert status == 2
    one_error(lines, "convert", f"IN {bags['cut.db3']}: database disk image is malformed: "
                                "expected a readable sqlite3 database")


def test_frame_without_tf_says_what_the_file_has_not_a_nested_error(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    status, lines = run(["convert", str(VLP32 / "bag"), str(tmp_path / "o.mcap"), "--slice",
                         "s:0:1", "--frame", "base_link"], capsys)
    assert status == 2
    one_error(lines, "convert", "--frame='base_link': expected a transform base_link <- "
              "velodyne_front in the file's /tf or /tf_static, or --extrinsics (the file has no "
              "/tf or /tf_static message (so far))")
    assert lines[-1].count("expected") == 1


@pytest.mark.parametrize("argv", [["convert", "IN", "OUT", "--jobs"],
                                  ["convert", "IN", "OUT", "--max-pending"],
                                  ["demo", "--frames"], ["view", "REC", "--out", "DIR", "--index"]])
@pytest.mark.parametrize("value", ["-1", "x", "2.5"])
def test_integer_options_name_the_text_and_the_bound(
        argv: list[str], value: str, capsys: pytest.CaptureFixture[str]) -> None:
    """A count option given a number below its bound or no integer: exit 2, one line naming
    the option, the text and the bound (the fleet's --jobs uses the same check)."""
    bound = ">= 0" if argv[-1] == "--index" else ">= 1"
    with pytest.raises(SystemExit) as stop:
        cli.main([*argv, value])
    assert stop.value.code == 2
    one_error(capsys.readouterr().err.splitlines()[1:], argv[0], argv[-1],
              f"'{value}': expected an integer {bound}")
