"""``lidarscan convert IN... OUT`` over many recordings (converters.edge.cli.fleet): which paths are
recordings, the output names, calibration found next to each recording, outputs byte-identical
to converting each recording alone whatever --jobs (and on Dask), resumable runs (a run killed
half way, then run again), failure isolation, --force and no silent overwrite; and the .db3
reader streaming its rows. Real raw-packet recordings from tests/data/nebula (NOTICE files)."""

from __future__ import annotations

import math
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import pytest

from converters import cli
from converters.edge.cli import fleet
from converters.sources import bags
from lidarscan.errors import ConfigError

DATA = Path(__file__).parent / "data" / "nebula"
ROOT = Path(__file__).parents[1]


def _bag(src: str, dst: Path) -> Path:
    shutil.copytree(DATA / src / "bag", dst)
    return dst


@pytest.fixture
def fleet_in(tmp_path: Path) -> Path:
    """in/velo/vlp32 (+ velo/vlp32.yaml next to it), in/velo/vls128 (+ vls128.yaml),
    in/hesai/qt64 (calibration.csv inside the bag folder)."""
    root = tmp_path / "in"
    _bag("velodyne_vlp32", root / "velo" / "vlp32")
    shutil.copy(DATA / "velodyne_vlp32" / "VLP32.yaml", root / "velo" / "vlp32.yaml")
    _bag("velodyne_vls128", root / "velo" / "vls128")
    shutil.copy(DATA / "velodyne_vls128" / "VLS128.yaml", root / "velo" / "vls128.yaml")
    _bag("hesai_qt64", root / "hesai" / "qt64")
    shutil.copy(DATA / "hesai_qt64" / "PandarQT64.csv", root / "hesai" / "qt64" / "calibration.csv")
    return root


OUTPUTS = ["hesai/qt64.mcap", "velo/vlp32.mcap", "velo/vls128.mcap"]


def _outputs(out: Path) -> list[str]:
    return sorted(p.relative_to(out).as_posix() for p in out.rglob("*.mcap")
                  if not p.name.startswith("."))


def _leftovers(out: Path) -> list[Path]:
    return sorted(out.rglob("*.partial"))


def _alone(fleet_in: Path, tmp: Path) -> dict[str, bytes]:
    """Each recording converted alone by the single-recording command (same output name)."""
    calibrations = {"velo/vlp32": "velo/vlp32.yaml", "velo/vls128": "velo/vls128.yaml",
                    "hesai/qt64": "hesai/qt64/calibration.csv"}
    out = {}
    for rec, cal in calibrations.items():
        dst = tmp / "alone" / f"{rec}.mcap"
        dst.parent.mkdir(parents=True, exist_ok=True)
        assert cli.main(["convert", str(fleet_in / rec), str(dst), "--calibration",
                         str(fleet_in / cal), "-q"]) == 0
        out[f"{rec}.mcap"] = dst.read_bytes()
    return out


# ------------------------------------------------------------------------------ discovery

def test_which_paths_are_recordings(tmp_path: Path) -> None:
    """A folder with metadata.yaml is one recording; a folder of .mcap files without it is
    several; .db3 files alone in a folder are one (split storage without metadata.yaml);
    hidden names and OUT are skipped; the output keeps the relative path and name."""
    root = tmp_path / "runs"
    (root / "day1" / "bag_a").mkdir(parents=True)
    (root / "day1" / "bag_a" / "metadata.yaml").write_text("x")
    (root / "day1" / "bag_a" / "bag_a_0.mcap").write_bytes(b"x")
    (root / "day1" / "bag_a" / "bag_a_1.mcap").write_bytes(b"x")
    (root / "day1" / "one.mcap").write_bytes(b"x")
    (root / "day1" / "two.mcap").write_bytes(b"x")
    (root / "day2" / "split").mkdir(parents=True)
    (root / "day2" / "split" / "s_0.db3").write_bytes(b"x")
    (root / "day2" / "split" / "s_1.db3").write_bytes(b"x")
    (root / "day2" / "drive.pcap").write_bytes(b"x")
    (root / "day2" / "notes.txt").write_text("x")
    (root / ".hidden.mcap").write_bytes(b"x")
    (root / "out").mkdir()
    (root / "out" / "old.mcap").write_bytes(b"x")
    found = fleet.find_recordings([str(root)], root / "out")
    assert {r.rel.as_posix(): r.path.relative_to(root).as_posix() for r in found} == {
        "day1/bag_a.mcap": "day1/bag_a", "day1/one.mcap": "day1/one.mcap",
        "day1/two.mcap": "day1/two.mcap", "day2/split.mcap": "day2/split",
        "day2/drive.mcap": "day2/drive.pcap"}
    # a folder of .mcap files (no metadata.yaml) is a fleet; a rosbag2 folder is not
    assert fleet.is_fleet([str(root / "day1")])
    assert not fleet.is_fleet([str(root / "day1" / "bag_a")])
    assert not fleet.is_fleet([str(root / "day2" / "split")])
    assert not fleet.is_fleet([str(root / "day1" / "one.mcap")])
    assert fleet.is_fleet([str(root / "day1" / "one.mcap"), str(root / "day1" / "two.mcap")])
    # a glob: relative to its fixed part
    found = fleet.find_recordings([str(root / "day*" / "*.mcap")], tmp_path / "o")
    assert sorted(r.rel.as_posix() for r in found) == ["day1/one.mcap", "day1/two.mcap"]
    assert fleet.is_fleet([str(root / "*" / "*.mcap")])
    # files named on the command line: their names; the same recording twice: once
    found = fleet.find_recordings([str(root / "day1" / "one.mcap"), str(root / "day2"),
                                   str(root / "day1" / "one.mcap")], tmp_path / "o")
    assert sorted(r.rel.as_posix() for r in found) == ["drive.mcap", "one.mcap", "split.mcap"]


def test_two_recordings_with_one_output_name_are_refused(tmp_path: Path) -> None:
    (tmp_path / "a.mcap").write_bytes(b"x")
    (tmp_path / "a.db3").write_bytes(b"x")
    with pytest.raises(ConfigError, match=r"a\.mcap.*one output per recording"):
        fleet.find_recordings([str(tmp_path)], tmp_path / "out")
    with pytest.raises(FileNotFoundError, match="matches no recording"):
        fleet.find_recordings([str(tmp_path / "*.pcap")], tmp_path / "out")


def test_several_recordings_into_one_file_name_are_refused(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A folder of .mcap files without metadata.yaml used to be merged into one OUT.mcap (exit
    0); it is several recordings, and OUT.mcap is no folder name: exit 2, nothing written."""
    for name in ("a.mcap", "b.mcap"):
        (tmp_path / name).write_bytes(b"\x89MCAP0\r\n")   # refused before anything is read
    assert cli.main(["convert", str(tmp_path), str(tmp_path / "all.mcap")]) == 2
    err = capsys.readouterr().err
    assert "OUT" in err and "a folder for the outputs of several recordings" in err
    assert not (tmp_path / "all.mcap").exists()


def test_calibration_next_to_each_recording(tmp_path: Path) -> None:
    (tmp_path / "bag").mkdir()
    (tmp_path / "bag" / "metadata.yaml").write_text("x")
    assert fleet.companion(tmp_path / "bag") is None
    (tmp_path / "calibration.yaml").write_text("x")                 # the folder's
    assert fleet.companion(tmp_path / "bag") == tmp_path / "calibration.yaml"
    (tmp_path / "bag" / "calibration.csv").write_text("x")          # the bag's own
    assert fleet.companion(tmp_path / "bag") == tmp_path / "bag" / "calibration.csv"
    (tmp_path / "bag.yaml").write_text("x")                         # same name: first
    assert fleet.companion(tmp_path / "bag") == tmp_path / "bag.yaml"
    (tmp_path / "run.mcap").write_bytes(b"x")
    (tmp_path / "run.csv").write_text("x")
    assert fleet.companion(tmp_path / "run.mcap") == tmp_path / "run.csv"
    (tmp_path / "drive.pcap").write_bytes(b"x")
    assert fleet.companion(tmp_path / "drive.pcap") is None         # Ouster: metadata JSON
    (tmp_path / "drive.json").write_text("{}")
    assert fleet.companion(tmp_path / "drive.pcap") == tmp_path / "drive.json"


def test_imu_packets_alone_are_not_lidar_packets_for_fleet_and_convert(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """ouster-ros's IMU packets have the lidar packets' type (PacketMsg) but are never
    decoded: a recording of them alone is copied by ``convert`` (no packets mode), so the fleet
    does not hand it the file next to it as --calibration, and the topic can be renamed."""
    import numpy as np
    from test_ouster_packets_io import PACKET_TYPE, _cdr, _typestore, _write_mcap

    store = _typestore()
    root = tmp_path / "in"
    root.mkdir()
    _write_mcap(root / "imu.mcap", [("/ouster/imu_packets", PACKET_TYPE, 10**18 + 1000 * k,
                                     _cdr(store, PACKET_TYPE, buf=np.zeros(48, np.uint8)))
                                    for k in range(4)])
    (root / "imu.yaml").write_text("calibration: of some other recording\n")
    assert PACKET_TYPE in bags.PACKET_TYPES                  # the type alone says "packets"
    assert not fleet._packet_recording(str(root / "imu.mcap"))
    src, alone = str(root / "imu.mcap"), tmp_path / "alone" / "imu.mcap"   # same name
    alone.parent.mkdir()
    assert cli.main(["convert", src, str(alone), "-q"]) == 0
    assert cli.main(["convert", src, str(tmp_path / "renamed.mcap"), "-q",
                     "--rename-topic", "/ouster/imu_packets=/imu"]) == 0
    assert cli.main(["convert", src, str(tmp_path / "x.mcap"), "--calibration",
                     str(root / "imu.yaml")]) == 2
    assert cli.main(["convert", src, str(tmp_path / "x.mcap"), "--metadata",
                     str(root / "imu.yaml")]) == 2            # nothing for it to decode
    capsys.readouterr()
    assert cli.main(["convert", str(root), str(tmp_path / "out"), "-j", "1"]) == 0
    assert "1 ok" in capsys.readouterr().err
    assert (tmp_path / "out" / "imu.mcap").read_bytes() == alone.read_bytes()


# ----------------------------------------------------------------------------- conversion

def test_outputs_equal_converting_each_alone_whatever_jobs(
        fleet_in: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    alone = _alone(fleet_in, tmp_path)
    for jobs in ("1", "2"):
        out = tmp_path / f"out{jobs}"
        assert cli.main(["convert", str(fleet_in), str(out), "--jobs", jobs]) == 0
        err = capsys.readouterr().err
        assert _outputs(out) == OUTPUTS
        for name in OUTPUTS:
            assert (out / name).read_bytes() == alone[name], (jobs, name)
        assert not _leftovers(out)
        # one progress view (plain lines: not a terminal) and the table
        assert "converting 3 of 3 recordings: 100%" in err
        assert "recording" in err and "ratio" in err and "3 recordings: 3 ok" in err
        for name in OUTPUTS:
            assert any(line.startswith(name + " ") and line.rstrip().endswith("ok")
                       for line in err.splitlines()), (name, err)


def test_dask_local_cluster_gives_the_same_outputs(
        fleet_in: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    alone = _alone(fleet_in, tmp_path)
    out = tmp_path / "out"
    assert cli.main(["convert", str(fleet_in), str(out), "--jobs", "2", "--dask"]) == 0
    err = capsys.readouterr().err
    assert "3 recordings: 3 ok" in err
    for name in OUTPUTS:
        assert (out / name).read_bytes() == alone[name], name
    # run again on Dask: nothing to do
    assert cli.main(["convert", str(fleet_in), str(out), "--dask"]) == 0
    assert "3 recordings: 3 skipped" in capsys.readouterr().err


def test_rerun_skips_what_is_done_force_redoes_and_a_change_is_redone(
        fleet_in: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    assert cli.main(["convert", str(fleet_in), str(out), "-j", "2"]) == 0
    stamps = {n: (out / n).stat().st_mtime_ns for n in OUTPUTS}
    assert all(fleet.sidecar_path(out / n).is_file() for n in OUTPUTS)
    capsys.readouterr()
    assert cli.main(["convert", str(fleet_in), str(out), "-j", "2"]) == 0
    assert "3 recordings: 3 skipped" in capsys.readouterr().err
    assert stamps == {n: (out / n).stat().st_mtime_ns for n in OUTPUTS}
    # an input changed: that one is converted again, and said so
    meta = fleet_in / "velo" / "vlp32" / "metadata.yaml"
    os.utime(meta, ns=(meta.stat().st_atime_ns, meta.stat().st_mtime_ns + 10**9))
    assert cli.main(["convert", str(fleet_in), str(out), "-j", "2"]) == 0
    err = capsys.readouterr().err
    assert "redone: redone: input changed" not in err
    assert any(line.startswith("velo/vlp32.mcap ") and "redone: input changed" in line
               for line in err.splitlines()), err
    # other options: every output is redone
    assert cli.main(["convert", str(fleet_in), str(out), "-j", "2", "--compress"]) == 0
    assert "3 recordings: 3 redone" in capsys.readouterr().err
    stamps = {n: (out / n).stat().st_mtime_ns for n in OUTPUTS}
    assert cli.main(["convert", str(fleet_in), str(out), "-j", "2", "--compress",
                     "--force"]) == 0
    assert "3 recordings: 3 redone" in capsys.readouterr().err
    assert all((out / n).stat().st_mtime_ns != stamps[n] for n in OUTPUTS)


def test_an_output_not_written_by_this_command_is_never_overwritten(
        fleet_in: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    (out / "velo").mkdir(parents=True)
    (out / "velo" / "vlp32.mcap").write_bytes(b"mine")
    assert cli.main(["convert", str(fleet_in), str(out), "-j", "2"]) == 1
    err = capsys.readouterr().err
    assert (out / "velo" / "vlp32.mcap").read_bytes() == b"mine"
    line = next(x for x in err.splitlines() if x.startswith("velo/vlp32.mcap "))
    assert "failed" in line and "not overwritten" in line and "--force" in line
    assert "2 ok" in err and (out / "velo" / "vls128.mcap").stat().st_size > 0
    assert cli.main(["convert", str(fleet_in), str(out), "-j", "2", "--force"]) == 0
    assert (out / "velo" / "vlp32.mcap").read_bytes()[:5] == b"\x89MCAP"


def test_a_failing_recording_does_not_stop_the_others(
        fleet_in: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _bag("hesai_xt32", fleet_in / "hesai" / "xt32")     # no calibration anywhere near it
    (fleet_in / "broken.mcap").write_bytes(b"\x89MCAP0\r\nnot really")
    out = tmp_path / "out"
    assert cli.main(["convert", str(fleet_in), str(out), "-j", "2"]) == 1
    err = capsys.readouterr().err
    assert _outputs(out) == OUTPUTS
    xt32 = next(x for x in err.splitlines() if x.startswith("hesai/xt32.mcap "))
    assert "failed" in xt32 and "calibration" in xt32
    broken = next(x for x in err.splitlines() if x.startswith("broken.mcap "))
    assert "failed" in broken or "bad" in broken
    assert not _leftovers(out)


def test_bad_messages_are_reported_with_their_recording_and_again_when_skipped(
        fleet_in: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A recording with a bad message is converted (its good messages written), its reports
    prefixed by its name, status bad, exit 1; run again it is up to date and still counts."""
    db3 = next((fleet_in / "velo" / "vlp32").glob("*.db3"))
    con = sqlite3.connect(db3)
    con.execute("UPDATE messages SET data = ? WHERE id = (SELECT min(id) + 1 FROM messages)",
                (b"junk",))
    con.commit()
    con.close()
    out = tmp_path / "out"
    assert cli.main(["convert", str(fleet_in), str(out), "-j", "2"]) == 1
    lines = capsys.readouterr().err.splitlines()
    assert any(x.startswith("velo/vlp32.mcap: bad message #1 topic") for x in lines), lines
    row = next(x for x in lines if x.startswith("velo/vlp32.mcap "))
    assert " bad: 1 bad message(s)" in row and _outputs(out) == OUTPUTS
    assert cli.main(["convert", str(fleet_in), str(out), "-j", "2"]) == 1
    row = next(x for x in capsys.readouterr().err.splitlines()
               if x.startswith("velo/vlp32.mcap "))
    assert "skipped-bad: up to date; 1 bad message(s)" in row


def test_the_quiet_table_lists_only_what_went_wrong(
        fleet_in: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _bag("hesai_xt32", fleet_in / "hesai" / "xt32")
    assert cli.main(["convert", str(fleet_in), str(tmp_path / "out"), "-q"]) == 1
    lines = capsys.readouterr().err.splitlines()
    assert [x.split()[0] for x in lines[1:-1]] == ["hesai/xt32.mcap"], lines
    assert not any("%" in x for x in lines)


def test_dask_without_the_extra_says_what_to_install(
        fleet_in: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setitem(sys.modules, "distributed", None)     # import fails
    assert cli.main(["convert", str(fleet_in), str(tmp_path / "out"), "--dask"]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and "pip install '.[dask]'" in lines[0], lines
    assert not (tmp_path / "out").exists() or not _outputs(tmp_path / "out")


# ------------------------------------------------------------------------------ resuming

def _slow_fleet(root: Path, count: int) -> None:
    """``count`` copies of the VLS-128 bag whose .db3 repeats its rows (a few seconds each)."""
    for k in range(count):
        bag = _bag("velodyne_vls128", root / f"run{k}")
        db3 = next(bag.glob("*.db3"))
        con = sqlite3.connect(db3)
        rows = con.execute("SELECT topic_id, timestamp, data FROM messages").fetchall()
        for rep in range(1, 6):
            con.executemany("INSERT INTO messages (topic_id, timestamp, data) VALUES (?,?,?)",
                            [(t, s + rep * 300_000_000, d) for t, s, d in rows])
        con.commit()
        con.close()
        (bag / "metadata.yaml").unlink()   # its counts no longer hold; read from the .db3
        shutil.copy(DATA / "velodyne_vls128" / "VLS128.yaml", root / f"run{k}.yaml")


def _writing(root: Path, out: Path) -> tuple[list[str], subprocess.Popen[str]]:
    """The fleet command of ``root`` -> ``out`` (--jobs 2) and its process (a session of its
    own) once a temporary output file exists."""
    command = [sys.executable, "-m", "converters.edge.cli", "convert", str(root), str(out),
               "-j", "2"]
    run = subprocess.Popen(command, cwd=ROOT, stderr=subprocess.PIPE, text=True,
                           start_new_session=True)
    deadline = time.monotonic() + 120
    while not (out.is_dir() and _leftovers(out)) and time.monotonic() < deadline \
            and run.poll() is None:
        time.sleep(0.02)
    assert run.poll() is None, "the run ended before it could be stopped"
    return command, run


@pytest.mark.parametrize("how", [signal.SIGINT, signal.SIGKILL])
def test_a_run_stopped_half_way_is_finished_by_running_it_again(
        how: signal.Signals, tmp_path: Path) -> None:
    """Stopped while writing (Ctrl-C to the process group, or kill -9 of everything): no
    output under a final name is partial (each has its sidecar); the same command again
    removes the temporary files, skips what was done and converts the rest."""
    root, out = tmp_path / "in", tmp_path / "out"
    _slow_fleet(root, 4)
    command, run = _writing(root, out)
    os.killpg(run.pid, how)
    _, err = run.communicate(timeout=60)
    if how == signal.SIGINT:
        assert run.returncode == 130, err
        assert not _leftovers(out), err
        assert "interrupted" in err
    else:
        assert _leftovers(out)               # kill -9: the temporary file stays ...
    finished = [p for p in out.rglob("*.mcap") if not p.name.startswith(".")]
    assert all(fleet.sidecar_path(p).is_file() for p in finished)
    again = subprocess.run(command, cwd=ROOT, stderr=subprocess.PIPE, text=True, timeout=300,
                           check=False)
    assert again.returncode == 0, again.stderr
    assert not _leftovers(out)               # ... and the next run removes it
    assert _outputs(out) == [f"run{k}.mcap" for k in range(4)]
    assert f"{len(finished)} skipped" in again.stderr or not finished, again.stderr


def test_a_killed_worker_is_replaced_and_its_recording_converted_again(tmp_path: Path) -> None:
    """kill -9 of one worker process (its pid is in its temporary file's name): the run goes on
    with new workers, converts that recording again and ends with every output, exit 0."""
    root, out = tmp_path / "in", tmp_path / "out"
    _slow_fleet(root, 3)
    _, run = _writing(root, out)
    partial = _leftovers(out)[0]
    worker = int(partial.name[:-len(".partial")].rpartition(".")[2])
    assert worker != run.pid
    os.kill(worker, signal.SIGKILL)
    _, err = run.communicate(timeout=300)
    assert run.returncode == 0, err
    assert _outputs(out) == [f"run{k}.mcap" for k in range(3)] and not _leftovers(out)
    assert "3 recordings: 3 ok" in err


def test_dask_at_an_address(fleet_in: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                            capsys: pytest.CaptureFixture[str]) -> None:
    """An existing cluster: its scheduler's address from DASK_SCHEDULER_ADDRESS or --dask=."""
    import logging

    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                      dashboard_address=None, silence_logs=logging.ERROR) as cluster:
        monkeypatch.setenv("DASK_SCHEDULER_ADDRESS", cluster.scheduler_address)
        assert cli.main(["convert", str(fleet_in), str(tmp_path / "a"), "--dask"]) == 0
        monkeypatch.delenv("DASK_SCHEDULER_ADDRESS")
        assert cli.main(["convert", str(fleet_in), str(tmp_path / "b"),
                         f"--dask={cluster.scheduler_address}"]) == 0
    assert capsys.readouterr().err.count("3 recordings: 3 ok") == 2
    for name in OUTPUTS:
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()


# --------------------------------------------------------------------------- .db3 streaming

def _db3(path: Path, rows: int, size: int) -> list[tuple[int, int, int, bytes]]:
    con = sqlite3.connect(path)
    con.execute("CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, "
                "timestamp INTEGER NOT NULL, data BLOB NOT NULL)")
    con.execute("CREATE INDEX timestamp_idx ON messages (timestamp ASC)")
    # ties of the timestamp (3 rows each), ids not in time order
    data = [(k + 1, 1, (rows - k) // 3 * 1000, bytes([k % 251]) * size) for k in range(rows)]
    con.executemany("INSERT INTO messages VALUES (?, ?, ?, ?)", data)
    con.commit()
    con.close()
    return sorted(data, key=lambda r: (r[2], r[0]))


def test_db3_rows_are_streamed_through_bounded_connections(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every row once, in (timestamp, id) order across the chunk boundaries (ties included);
    a new connection per chunk; at no time more than a few rows held in Python."""
    path, rows, size, chunk = tmp_path / "big.db3", 200, 20_000, 100_000
    expected = _db3(path, rows, size)
    opened: list[sqlite3.Connection] = []
    connect = bags._connect
    monkeypatch.setattr(bags, "_connect", lambda p: opened.append(connect(p)) or opened[-1])
    con = connect(path)
    tracemalloc.start()
    try:
        seen = []
        for row in bags._rows(con, path, chunk_bytes=chunk):
            seen.append(row[:3])
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
        con.close()
    assert seen == [r[:3] for r in expected]
    chunks = math.ceil(rows * size / chunk)      # (+1: the last chunk may end at the end)
    assert chunks <= len(opened) <= chunks + 1, len(opened)
    assert peak < 20 * size, peak           # all rows would be rows * size = 4 MB
    # each chunk's connection is closed (its map released) once its rows are given
    for c in opened:
        with pytest.raises(sqlite3.ProgrammingError):
            c.execute("SELECT 1")


def test_db3_without_a_time_index_is_read_through_one_cursor(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Without rosbag2's timestamp index each chunk would sort the rest of the table again:
    one cursor then, same rows in the same order."""
    path = tmp_path / "noindex.db3"
    expected = _db3(path, 50, 10_000)
    con = sqlite3.connect(path)
    con.execute("DROP INDEX timestamp_idx")
    con.commit()
    con.close()
    opened: list[object] = []
    connect = bags._connect
    monkeypatch.setattr(bags, "_connect", lambda p: opened.append(p) or connect(p))
    con = connect(path)
    got = [r[:3] for r in bags._rows(con, path, chunk_bytes=30_000)]
    con.close()
    assert got == [r[:3] for r in expected] and not opened

