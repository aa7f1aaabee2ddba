"""Raw packet bags end to end: `lidarscan convert BAG OUT.mcap --calibration FILE` on the real
Nebula recordings (tests/data/nebula, see its NOTICE files) writes a linked LidarInfo + one
LidarScan per rotation that are byte-identical to what the decoder's Python API makes of the
same packets read by an independent reader (rosbags), and `lidarscan info` reads them back.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from converters.edge import cli

from converters.sources.hesai import decoder as hesai

from converters.sources import velodyne
from lidarscan.mcap import read_scans

DATA = Path(__file__).parent / "data" / "nebula"

RECORDINGS = {
    "velodyne_vlp32": ("VLP32.yaml", "/sensing/lidar/front/velodyne_packets"),
    "velodyne_vls128": ("VLS128.yaml", "/velodyne_packets"),
    "hesai_xt32": ("PandarXT32.csv", "/pandar_packets"),
    "hesai_pandar64": ("Pandar64.csv", "/pandar_packets"),
    "hesai_qt64": ("PandarQT64.csv", "/pandar_packets"),
}


def _reference(name: str, tmp_path: Path) -> list[tuple[Any, Any]]:
    """The decoder's API on the packets as rosbags reads them (the tests of each vendor)."""
    calibration = DATA / name / RECORDINGS[name][0]
    if name.startswith("velodyne"):
        from test_velodyne_packets import _read_bag
        packets = [p for _, msg in _read_bag(DATA / name, tmp_path) for p in msg]
        return list(velodyne.decode_packets(packets, calibration))
    from test_hesai import _packets
    return list(hesai.decode_packets(_packets(name), calibration))


@pytest.mark.parametrize("name", sorted(RECORDINGS))
def test_convert_packet_bag_equals_the_decoder_api(name: str, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    calibration, topic = RECORDINGS[name]
    out = tmp_path / "out.mcap"
    status = cli.main(["convert", str(DATA / name / "bag"), str(out),
                       "--calibration", str(DATA / name / calibration), "-q"])
    assert status == 0, capsys.readouterr().err
    errors: list[Any] = []
    got = list(read_scans(out, on_error=errors.append))
    assert errors == []
    ref = _reference(name, tmp_path)
    assert len(got) == len(ref) > 0
    for (scan, info), (rscan, rinfo) in zip(got, ref):
        assert scan.header.stamp.sec * 10**9 + scan.header.stamp.nanosec == \
            rscan.header.stamp.sec * 10**9 + rscan.header.stamp.nanosec
        assert (scan.height, scan.width) == (rscan.height, rscan.width)
        assert [c.name for c in scan.channels] == [c.name for c in rscan.channels]
        assert bytes(scan.data) == bytes(rscan.data)
        np.testing.assert_array_equal(np.asarray(scan.column_azimuth_angles),
                                      np.asarray(rscan.column_azimuth_angles))
        np.testing.assert_array_equal(np.asarray(info.vertical_angles),
                                      np.asarray(rinfo.vertical_angles))
        np.testing.assert_array_equal(np.asarray(info.beam_azimuth_offsets),
                                      np.asarray(rinfo.beam_azimuth_offsets))
    capsys.readouterr()
    assert cli.main(["info", str(out)]) == 0     # one layout per topic, no problem
    text = capsys.readouterr().out
    assert f"{topic}/lidar_info" in text and f"{topic}/lidar_scan" in text
    assert f"LidarScans linked to their LidarInfo: {len(got)} of {len(got)}" in text


def test_convert_packet_bag_without_calibration_names_the_file_needed(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out.mcap"
    status = cli.main(["convert", str(DATA / "hesai_qt64" / "bag"), str(out), "-q"])
    assert status != 0
    err = capsys.readouterr().err
    assert "csv" in err.lower() or "calibration" in err.lower()
    assert not out.exists()


@pytest.mark.parametrize("name", ["velodyne_vlp32", "hesai_qt64"])
def test_push_many_skips_bad_packets_like_push(name: str, tmp_path: Path) -> None:
    """The batch contract the CLI relies on, for both vendors: with ``errors=``, a malformed
    row is recorded with its index and skipped; the scans equal push() one by one without it."""
    calibration = DATA / name / RECORDINGS[name][0]
    if name.startswith("velodyne"):
        from test_velodyne_packets import _read_bag
        packets = [p for _, msg in _read_bag(DATA / name, tmp_path) for p in msg]
        module: Any = velodyne
    else:
        from test_hesai import _packets
        packets, module = _packets(name), hesai
    stamps = np.array([t for t, _ in packets], np.int64)
    rows = np.stack([np.frombuffer(p, np.uint8) for _, p in packets])
    bad_rows = (5, len(rows) // 2)
    damaged = rows.copy()
    for k in bad_rows:
        damaged[k, :8] = 0x5A                  # no valid header / block flag
    errors: list[Any] = []
    batch = module.PacketDecoder(calibration).push_many(stamps, damaged, errors=errors)
    assert [k for k, _ in errors] == list(bad_rows)
    one = module.PacketDecoder(calibration)
    single = [pair for k, (t, p) in enumerate(packets) if k not in bad_rows
              for pair in one.push(t, p)]
    assert len(batch) == len(single) > 0
    for (scan, _), (ref, _) in zip(batch, single):
        assert bytes(scan.data) == bytes(ref.data)


@pytest.mark.parametrize("name,kernel", [("velodyne_vls128", None), ("velodyne_vls128", False),
                                         ("velodyne_vlp32", None)])
def test_converted_velodyne_bag_reproduces_nebula_through_to_pointcloud2(
        name: str, kernel: bool | None, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """`lidarscan convert --cut-angle` (the ground truth's scan phase: 0 deg on the VLS-128,
    180 deg in the blind part of the VLP-32C's 270..90 deg field of view) on the bag, re-read,
    projected by to_pointcloud2 (compiled kernel and numpy path): every return within 2 mm of
    Nebula's points, both ways (>= 99 % / >= 95 %)."""
    from converters.pointcloud2.converter import PointCloud2Converter, read_points
    from pcd import read_pcd
    from test_velodyne_packets import RECORDINGS as TRUTH
    from test_velodyne_packets import _nearest, _within

    _, gt_stamp, settings = TRUTH[name]
    out = tmp_path / "out.mcap"
    assert cli.main(["convert", str(DATA / name / "bag"), str(out), "--calibration",
                     str(DATA / name / RECORDINGS[name][0]), "--cut-angle",
                     str(settings["cut"]), "-q"]) == 0
    capsys.readouterr()
    truth = read_pcd(DATA / name / f"ground_truth_{gt_stamp}.pcd").astype(np.float64)
    lo, hi = settings["range"]
    candidates = []
    for scan, info in read_scans(out):
        clouds = []
        for channel in [c.name for c in scan.channels if c.name in ("range", "range2")]:
            conv = PointCloud2Converter(info, fields=("x", "y", "z", "range"), organized=False,
                                        range_channel=channel, kernel=kernel)
            points = read_points(conv.convert(scan)).reshape(-1)
            metres = points["range"].astype(np.float64)
            keep = (metres > lo) & (metres < hi)       # dist_correction is 0 in both YAMLs
            clouds.append(np.stack([points[k][keep] for k in "xyz"], -1).astype(np.float64))
        ours = np.concatenate(clouds)
        candidates.append((float(np.mean(_nearest(truth[::500], ours) < 0.002)), ours))
    best = _within(truth, max(candidates, key=lambda c: c[0])[1])     # the matching rotation
    print(f"\nconvert -> to_pointcloud2 (kernel={kernel}): truth->decoded {best[0]:.4%}, "
          f"decoded->truth {best[1]:.4%} within 2 mm")
    assert best[0] >= 0.99 and best[1] >= 0.95


@pytest.mark.parametrize("name,error", [("hesai_qt64", "has none"),
                                        ("velodyne_vlp32", "finite angle")])
def test_cut_angle_is_refused_where_it_cannot_apply(name: str, error: str, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """--cut-angle on packets whose decoder has no cut (Hesai), or not an angle: exit 2 naming
    the option, nothing written."""
    out = tmp_path / "out.mcap"
    status = cli.main(["convert", str(DATA / name / "bag"), str(out), "--calibration",
                       str(DATA / name / RECORDINGS[name][0]), "--cut-angle", "nan", "-q"])
    err = capsys.readouterr().err
    assert status == 2 and "--cut-angle" in err and error in err, err
    assert not out.exists()


@pytest.mark.parametrize("name", ["velodyne_vls128", "hesai_pandar64"])
def test_convert_writes_the_same_file_with_any_number_of_threads(
        name: str, tmp_path: Path) -> None:
    """--threads 1 (everything in one thread), 2 (one writer thread) and the default (chunks
    compressed side by side) give the same bytes, read by the `mcap` package with CRCs checked;
    the rosbag2 metadata names the output file (not the temporary one it was written as)."""
    from mcap.reader import make_reader

    calibration = DATA / name / RECORDINGS[name][0]
    files = []
    for threads in ([], ["--threads", "1"], ["--threads", "2"],
                    ["--threads", "2", "--chunk-compression", "lz4"]):
        out = tmp_path / (threads[-1] if threads else "default") / "out.mcap"
        out.parent.mkdir(exist_ok=True)
        assert cli.main(["convert", str(DATA / name / "bag"), str(out), "--calibration",
                         str(calibration), "-q", *threads]) == 0
        files.append(out.read_bytes())
    assert files[0] == files[1] == files[2] != files[3]
    with open(tmp_path / "default" / "out.mcap", "rb") as stream:
        reader = make_reader(stream, validate_crcs=True)
        assert sum(1 for _ in reader.iter_messages()) > 1
        meta = next(m for m in reader.iter_metadata() if m.name == "rosbag2")
    assert "- out.mcap" in meta.metadata["serialized_metadata"]
    assert ".partial" not in meta.metadata["serialized_metadata"]


@pytest.mark.parametrize("threads", ["1", "2", "3"])
def test_a_failing_output_stops_the_threads_and_leaves_no_file(
        threads: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """The disk fills up while the chunks are written (in the writer threads, or in the caller's
    with --threads 1): exit 2 naming the error, no output or temporary file, no thread left."""
    import threading

    from lidarscan import _mcapfile

    real = _mcapfile.ChunkedMcapWriter._write_chunk
    calls = {"n": 0}

    def write_chunk(self: Any, *args: Any) -> None:
        calls["n"] += 1
        if calls["n"] == 2:
            raise OSError(28, "No space left on device")
        real(self, *args)

    monkeypatch.setattr(_mcapfile.ChunkedMcapWriter, "_write_chunk", write_chunk)
    before = threading.active_count()
    name = "velodyne_vls128"
    out = tmp_path / "out.mcap"
    status = cli.main(["convert", str(DATA / name / "bag"), str(out), "--calibration",
                       str(DATA / name / RECORDINGS[name][0]), "-q", "--threads", threads])
    assert status == 2 and "No space left on device" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
    assert threading.active_count() == before


def test_the_input_is_read_ahead_by_a_thread_unless_threads_is_1(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from converters.edge.cli import _common

    real = _common._read_ahead
    calls: list[int] = []

    def read_ahead(*args: Any, **kwargs: Any) -> Any:
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(_common, "_read_ahead", read_ahead)
    name = "velodyne_vls128"
    for threads, expected in (("1", []), ("2", [1])):
        calls.clear()
        assert cli.main(["convert", str(DATA / name / "bag"), str(tmp_path / f"{threads}.mcap"),
                         "--calibration", str(DATA / name / RECORDINGS[name][0]), "-q",
                         "--threads", threads]) == 0
        assert calls == expected
    assert (tmp_path / "1.mcap").stat().st_size == (tmp_path / "2.mcap").stat().st_size
