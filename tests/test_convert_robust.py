"""Offline conversion of damaged recordings: nothing good lost, every bad message reported.

* A recording mixing good scans with corrupt or invalid messages (truncated CDR, a scan that
  does not fit its info, a scan whose info never comes, an invalid info, a channel with an
  unusable schema): ``lidarscan convert`` writes every good message and converts every good
  scan, reports each bad one on stderr with its index, topic, stamp and reason, and exits 1.
* Ctrl-C midway (SIGINT to a real ``lidarscan convert`` process): exit status 130 and the
  output is a complete MCAP (summary and footer) that both lidarscan.mcap and the ``mcap``
  package read, holding a prefix of the input in order.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import lidarscan as ls
from lidarscan.mcap import BadMessage, McapMessage, McapWriter, read_messages

H, W = 8, 64
BASE = 1_700_000_000_000_000_000
SCAN_T, INFO_T = "lidarscan_msgs/msg/LidarScan", "lidarscan_msgs/msg/LidarInfo"

cli = pytest.importorskip("converters.edge.cli")


def _info(stamp_ns: int = BASE, **fields: Any) -> Any:
    return ls.make_info(stamp_ns=stamp_ns, frame_id="lidar",
                        vertical_angles=np.linspace(0.3, -0.3, H),
                        horizontal_angles=2 * np.pi * (1 - np.arange(W) / W),
                        as_dataclass=True, **fields)


def _scan(info: Any, stamp_ns: int) -> Any:
    ranges = np.full((H, W), 2.0 + (stamp_ns // 1000 % 7), np.float32)
    return ls.make_scan(info, {"range": ranges, "intensity": np.ones((H, W), np.uint16)},
                        stamp_ns, as_dataclass=True)



def _recording(path: Path) -> tuple[list[tuple[int, str, int]], list[tuple[int, str, int]]]:
    """Write the damaged recording; returns (good, bad) as (index, topic, stamp) lists."""
    info = _info()
    good: list[tuple[int, str, int]] = []
    bad: list[tuple[int, str, int]] = []
    index = 0

    with McapWriter(path, chunk_size=4096) as writer:
        def put(topic: str, payload: bytes, msgtype: str, stamp: int, ok: bool) -> None:
            nonlocal index
            writer.write(topic, payload, msgtype=msgtype, log_time_ns=stamp)
            (good if ok else bad).append((index, topic, stamp))
            index += 1

        put("/lidar/info", ls.encode(info), INFO_T, BASE, True)
        stamp = BASE + 100_000_000
        for k in range(12):
            stamp += 100_000_000
            scan_cdr = ls.encode(_scan(info, stamp))
            kind = k % 6
            if kind == 1:    # truncated payload: DecodeError
                put("/lidar/scan", scan_cdr[:len(scan_cdr) // 2], SCAN_T, stamp, False)
            elif kind == 2:  # decodes, but names an info that never comes
                orphan = _scan(_info(BASE + 5), stamp)
                put("/lidar/scan", ls.encode(orphan), SCAN_T, stamp, False)
            elif kind == 3:  # decodes, links, but its channel lies outside data
                broken = _scan(info, stamp)
                chans = list(broken.channels)
                chans[1] = dataclasses.replace(chans[1], offset=10**6)
                broken = dataclasses.replace(broken, channels=tuple(chans))
                put("/lidar/scan", ls.encode(broken), SCAN_T, stamp, False)
            elif kind == 4:  # an invalid info (NaN elevation) under another stamp
                bad_info = ls.encode(info)
                pos = bad_info.index(struct.pack("<d", float(info.vertical_angles[0])))
                bad_info = bad_info[:pos] + struct.pack("<d", float("nan")) + bad_info[pos + 8:]
                put("/lidar/info", bad_info, INFO_T, stamp, False)
            else:
                put("/lidar/scan", scan_cdr, SCAN_T, stamp, True)
            # an unrelated message that must be copied as it is
            laser = ls.encode(_laser(stamp), "sensor_msgs/msg/LaserScan")
            put("/scan2d", laser, "sensor_msgs/msg/LaserScan", stamp + 1, True)
    return good, bad


def _laser(stamp_ns: int) -> Any:
    from lidarscan import types as lt
    cls = lt.message_class("sensor_msgs/msg/LaserScan")
    sec, nanosec = divmod(stamp_ns, 10**9)
    return cls(header=lt.Header(lt.Time(sec, nanosec), "laser"), angle_min=-1.0, angle_max=1.0,
               angle_increment=0.5, time_increment=0.0, scan_time=0.1, range_min=0.1,
               range_max=20.0, ranges=np.ones(5, np.float32),
               intensities=np.zeros(0, np.float32))


def _payloads(path: Path) -> list[McapMessage]:
    items = list(read_messages(path))
    assert not [i for i in items if isinstance(i, BadMessage)], "output has bad records"
    return [i for i in items if isinstance(i, McapMessage)]


def test_damaged_recording_loses_no_good_message_and_reports_every_bad_one(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src, dst = tmp_path / "in.mcap", tmp_path / "out.mcap"
    good, bad = _recording(src)
    status = cli.main(["convert", str(src), str(dst), "--pointcloud2", "--slice",
                       "mid:-5:5"])
    err = capsys.readouterr().err
    assert status == 1, err  # "some messages were bad"

    # every bad message: one line with its index, topic, stamp and a reason
    lines = [ln for ln in err.splitlines() if ln.startswith("bad message #")]
    assert len(lines) == len(bad), err
    for (index, topic, stamp), line in zip(sorted(bad), sorted(
            lines, key=lambda ln: int(ln.split("#")[1].split()[0]))):
        assert line.startswith(f"bad message #{index} topic '{topic}' ")
        assert f"{stamp // 10**9}.{stamp % 10**9:09d}" in line
        assert line.split(": ", 1)[1].strip()  # a reason
    good_indices = {i for i, _, _ in good}
    assert not any(int(ln.split("#")[1].split()[0]) in good_indices for ln in lines)

    # every good input message is in the output, byte for byte, in order (a bad message that
    # still decodes, e.g. a scan whose info never came, may be copied too: it is reported)
    inputs = {m.index: m for m in _payloads(src)}
    out = _payloads(dst)
    copied = [(m.topic, m.payload) for m in out if not m.topic.endswith(("/points", "mid"))]
    wanted = [(inputs[i].topic, inputs[i].payload) for i, _, _ in good]
    allowed = wanted + [(inputs[i].topic, inputs[i].payload) for i, _, _ in bad if i in inputs]
    assert [c for c in copied if c in wanted] == wanted
    assert all(c in allowed for c in copied)

    # every good scan converted: one cloud and one slice each, with the scan's stamp
    scan_stamps = [s for _, t, s in good if t == "/lidar/scan"]
    clouds = [ls.decode(m.payload, m.msgtype) for m in out if m.topic == "/lidar/points"]
    slices = [ls.decode(m.payload, m.msgtype) for m in out if m.topic == "/lidar/slices/mid"]
    assert [ls.to_ns(c.header.stamp) for c in clouds] == scan_stamps
    assert [ls.to_ns(s.header.stamp) for s in slices] == scan_stamps
    # and with the right geometry: a cloud of the first good scan equals the exact projection
    from converters.pointcloud2.converter import read_points
    pts = read_points(clouds[0])
    scan0 = ls.decode_scan(inputs[good[1][0]].payload)
    expected = ls.geometry.exact_xyz(_info(), ls.range_m(scan0))
    xyz = np.stack([pts["x"], pts["y"], pts["z"]], -1).reshape(H, W, 3)
    np.testing.assert_allclose(xyz, expected, atol=1e-4)


def test_clean_recording_exits_zero(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src, dst = tmp_path / "in.mcap", tmp_path / "out.mcap"
    info = _info()
    with McapWriter(src) as writer:
        writer.write("/lidar/info", info)
        for k in range(3):
            writer.write("/lidar/scan", _scan(info, BASE + k))
    assert cli.main(["convert", str(src), str(dst), "--pointcloud2", "-q"]) == 0
    assert len([m for m in _payloads(dst) if m.topic == "/lidar/points"]) == 3


# ------------------------------------------------------------------------------ interrupted

def _big_recording(path: Path, scans: int) -> None:
    """Many cheap-to-write scans: one encoded scan with its stamp patched (CDR offset 4/8)."""
    info = _info()
    template = bytearray(ls.encode(_scan(info, BASE)))
    with McapWriter(path, chunk_size=1 << 20) as writer:
        writer.write("/lidar/info", info)
        for k in range(scans):
            sec, nanosec = divmod(BASE + (k + 1) * 10_000_000, 10**9)
            struct.pack_into("<iI", template, 4, sec, nanosec)
            writer.write("/lidar/scan", bytes(template), msgtype=SCAN_T,
                         log_time_ns=BASE + (k + 1) * 10_000_000)


_MAIN = "import sys; from converters.edge.cli import main; sys.exit(main(sys.argv[1:]))"


def _partial_size(folder: Path) -> int:
    """Size of the output being written (``convert`` writes ``.OUT.<pid>.partial``)."""
    return sum(p.stat().st_size for p in folder.glob(".out.mcap.*.partial") if p.exists())


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("_ROS_WHEELS_BOOTSTRAP_COMPLETE", None)  # let the venv's python set up its libs
    return env


@pytest.mark.parametrize("sig", [signal.SIGINT])
def test_interrupted_convert_leaves_a_readable_prefix(tmp_path: Path, sig: int) -> None:
    from mcap.reader import make_reader

    src, dst = tmp_path / "in.mcap", tmp_path / "out.mcap"
    _big_recording(src, 6000)
    proc = subprocess.Popen(
        [sys.executable, "-c", _MAIN, "convert", str(src), str(dst), "--slice",
         "mid:-5:5", "--pointcloud2", "-q"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env())
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and proc.poll() is None:
            if _partial_size(tmp_path) > 64 << 10:  # several chunks written
                break
            time.sleep(0.02)
        assert proc.poll() is None, "conversion finished before it could be interrupted"
        assert not dst.exists()  # written under a temporary name until the run ends
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, err.decode()
    assert b"interrupted" in err

    inputs = _payloads(src)
    out = _payloads(dst)  # no BadMessage: the file was finished properly
    copied = [(m.topic, m.payload) for m in out if m.topic in ("/lidar/info", "/lidar/scan")]
    assert 1 < len(copied) < len(inputs)
    assert copied == [(m.topic, m.payload) for m in inputs[:len(copied)]]
    # every copied scan before the last one also has its cloud (converted in order)
    clouds = [m for m in out if m.topic == "/lidar/points"]
    assert len(copied) - 2 <= len(clouds) <= len(copied) - 1
    with open(dst, "rb") as stream:  # the mcap package agrees, summary included
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == len(out)
        assert sum(1 for _ in reader.iter_messages()) == len(out)


def test_killed_convert_output_still_yields_its_complete_chunks(tmp_path: Path) -> None:
    """SIGKILL (no chance to finish the file): OUT does not appear; the partial file left
    under its temporary name yields every message of the chunks on disk, in order, then one
    BadMessage for the cut; the reader never raises."""
    src, dst = tmp_path / "in.mcap", tmp_path / "out.mcap"
    _big_recording(src, 6000)
    proc = subprocess.Popen(
        [sys.executable, "-c", _MAIN, "convert", str(src), str(dst), "--slice",
         "mid:-5:5", "-q"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=_env())
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and proc.poll() is None:
            if _partial_size(tmp_path) > 64 << 10:
                break
            time.sleep(0.02)
        assert proc.poll() is None, "conversion finished before it could be killed"
        proc.kill()
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert not dst.exists()  # a killed run never leaves a partial file where OUT is expected
    (partial,) = tmp_path.glob(".out.mcap.*.partial")
    items = list(read_messages(partial))
    good = [m for m in items if isinstance(m, McapMessage)]
    assert isinstance(items[-1], BadMessage) and "damaged" in items[-1].reason
    assert not [m for m in items[:-1] if isinstance(m, BadMessage)]
    inputs = _payloads(src)
    copied = [(m.topic, m.payload) for m in good if m.topic in ("/lidar/info", "/lidar/scan")]
    assert len(copied) > 1
    assert copied == [(m.topic, m.payload) for m in inputs[:len(copied)]]
