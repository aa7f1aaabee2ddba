"""rosbag2 recordings in (converters.sources.bags) and through the CLI.

* Packet messages of real bags (Nebula's VLP-32C and PandarQT64 recordings, tests/data/nebula)
  parse exactly as ``rosbags`` deserialises them; synthetic ones (both byte orders, odd counts)
  too, and damaged ones raise DecodeError.
* Bags: directories with metadata.yaml (and its real-world quirks), without it, single .db3
  files, old and new sqlite schemas, several storage files merged in time order, MCAP storage,
  damaged rows reported while the others are read.
* ``lidarscan info/convert`` on bags: LidarScan and PointCloud2 bags convert exactly like the same
  messages in an MCAP file; packet topics go through the PacketDecoder contract (a stand-in
  decoder here; the real ones are tested end to end elsewhere) and fail clearly without one.
"""

from __future__ import annotations

import shutil
import sqlite3
import struct
import sys
import types
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import lidarscan as ls
from converters.sources import bags
from converters.edge import cli
from lidarscan.errors import DecodeError, LidarScanError
from lidarscan.mcap import BadMessage, McapMessage, McapWriter, read_messages

from helpers import messages_by_topic

DATA = Path(__file__).parent / "data" / "nebula"
VLP32 = DATA / "velodyne_vlp32" / "bag"
QT64 = DATA / "hesai_qt64" / "bag"
H, W = 8, 64
BASE = 1_700_000_000_000_000_000
QOS = "- history: 3\n  depth: 0\n  reliability: 1\n  durability: 2\n"


# ------------------------------------------------------------------------------ helpers

def _typestore() -> Any:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    add: dict[str, Any] = {}
    for name, text in bags._PACKET_MSGS.items():
        add.update(get_types_from_msg(text, name))
    store.register(add)
    return store


def write_db3(path: Path, topics: list[tuple[int, str, str, str, str]],
              rows: list[tuple[int, int, Any]], *, schema: str = "new",
              definitions: list[tuple[str, str, str]] = ()) -> None:
    """A rosbag2 sqlite3 file. topics: (id, name, type, format, qos); rows: (topic, ts, data).
    schema "old": no offered_qos_profiles column, no schema/metadata tables."""
    con = sqlite3.connect(path)
    if schema == "old":
        con.execute("CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT NOT NULL, "
                    "type TEXT NOT NULL, serialization_format TEXT NOT NULL)")
        con.executemany("INSERT INTO topics VALUES (?,?,?,?)", [t[:4] for t in topics])
    else:
        con.execute("CREATE TABLE schema(schema_version INTEGER PRIMARY KEY, ros_distro TEXT)")
        con.execute("INSERT INTO schema VALUES (4, 'jazzy')")
        con.execute("CREATE TABLE metadata(id INTEGER PRIMARY KEY, metadata_version INTEGER, "
                    "metadata TEXT)")
        con.execute("CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT NOT NULL, "
                    "type TEXT NOT NULL, serialization_format TEXT NOT NULL, "
                    "offered_qos_profiles TEXT NOT NULL, type_description_hash TEXT)")
        con.executemany("INSERT INTO topics VALUES (?,?,?,?,?,'')", topics)
        con.execute("CREATE TABLE message_definitions(id INTEGER PRIMARY KEY, topic_type TEXT, "
                    "encoding TEXT, encoded_message_definition TEXT, type_description_hash TEXT)")
        con.executemany("INSERT INTO message_definitions(topic_type, encoding, "
                        "encoded_message_definition, type_description_hash) VALUES (?,?,?,'')",
                        definitions)
    con.execute("CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER, "
                "timestamp INTEGER, data BLOB)")  # no NOT NULL: damaged rows
    con.execute("CREATE INDEX timestamp_idx ON messages (timestamp ASC)")
    con.executemany("INSERT INTO messages(topic_id, timestamp, data) VALUES (?,?,?)", rows)
    con.commit()
    con.close()


def _info(stamp_ns: int = BASE) -> Any:
    return ls.make_info(stamp_ns=stamp_ns, frame_id="lidar",
                        vertical_angles=np.linspace(0.3, -0.3, H),
                        horizontal_angles=2 * np.pi * (1 - np.arange(W) / W), as_dataclass=True)


def _scan(info: Any, stamp_ns: int) -> Any:
    rng = np.random.default_rng(stamp_ns % 1000)
    return ls.make_scan(info, {"range": rng.uniform(1, 9, (H, W)).astype(np.float32),
                               "intensity": rng.integers(0, 999, (H, W)).astype(np.uint16)},
                        stamp_ns, as_dataclass=True)


def _string(text: str) -> bytes:
    raw = text.encode() + b"\x00"
    return b"\x00\x01\x00\x00" + struct.pack("<I", len(raw)) + raw


def _copy_bag(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    for f in dst.iterdir():
        f.chmod(0o644)
    return dst


# ------------------------------------------------------------------------ packet parsing

@pytest.mark.parametrize("folder,parse", [(VLP32, bags.velodyne_packets),
                                          (QT64, bags.pandar_packets)])
def test_real_packet_messages_parse_like_rosbags(folder: Path, parse: Any) -> None:
    store = _typestore()
    bag = bags.open_bag(folder)
    (topic,) = bag.topics.values()
    items = list(bag.messages())
    assert len(items) == topic.count > 0
    for item in items:
        assert isinstance(item, McapMessage)
        got = parse(item.payload)
        truth = store.deserialize_cdr(item.payload, topic.msgtype)
        assert got.frame_id == truth.header.frame_id
        assert got.stamp_ns == truth.header.stamp.sec * 10**9 + truth.header.stamp.nanosec
        assert len(got.packets) == len(truth.packets) > 10
        for (stamp, payload), packet in zip(got.packets, truth.packets):
            assert stamp == packet.stamp.sec * 10**9 + packet.stamp.nanosec
            size = getattr(packet, "size", len(packet.data))
            assert bytes(payload) == packet.data[:size].tobytes()
    if parse is bags.pandar_packets:  # the QT64 uses less than the 1500-byte array
        assert {len(p) for _, p in got.packets} == {1072}


@pytest.mark.parametrize("little_endian", [True, False])
@pytest.mark.parametrize("frame", ["", "v", "velo", "a_longer_frame_id"])
def test_synthetic_packets_both_byte_orders(little_endian: bool, frame: str) -> None:
    store = _typestore()
    rng = np.random.default_rng(len(frame))
    Time = store.types["builtin_interfaces/msg/Time"]
    Header = store.types["std_msgs/msg/Header"]
    VP = store.types["velodyne_msgs/msg/VelodynePacket"]
    VS = store.types["velodyne_msgs/msg/VelodyneScan"]
    PP = store.types["pandar_msgs/msg/PandarPacket"]
    PS = store.types["pandar_msgs/msg/PandarScan"]
    header = Header(stamp=Time(sec=7, nanosec=999_999_999), frame_id=frame)
    vel = [VP(stamp=Time(sec=k, nanosec=k * 3), data=rng.integers(0, 256, 1206, dtype=np.uint8))
           for k in range(3)]
    pan = [PP(stamp=Time(sec=k, nanosec=5), data=rng.integers(0, 256, 1500, dtype=np.uint8),
              size=[0, 1, 861, 1500][k]) for k in range(4)]
    for msg, parse, typename in ((VS(header=header, packets=vel), bags.velodyne_packets,
                                  bags.VELODYNE_SCAN),
                                 (PS(header=header, packets=pan), bags.pandar_packets,
                                  bags.PANDAR_SCAN)):
        cdr = bytes(store.serialize_cdr(msg, typename, little_endian=little_endian))
        got = parse(cdr)
        assert (got.frame_id, got.stamp_ns) == (frame, 7_999_999_999)
        for (stamp, payload), packet in zip(got.packets, msg.packets, strict=True):
            assert stamp == packet.stamp.sec * 10**9 + packet.stamp.nanosec
            size = getattr(packet, "size", 1206)
            assert bytes(payload) == packet.data[:size].tobytes()
        for cut in (0, 3, 10, len(cdr) // 2, len(cdr) - 1):
            with pytest.raises(DecodeError):
                parse(cdr[:cut])


def test_damaged_packet_messages_raise_decode_error() -> None:
    item = next(iter(bags.open_bag(QT64).messages()))
    cdr = bytearray(item.payload)
    count_at = 4 + 8 + 4 + len(b"hesai\x00") + 2  # frame "hesai": 6 bytes, aligned to 4
    assert struct.unpack_from("<I", cdr, count_at)[0] == 300
    huge = bytearray(cdr)
    struct.pack_into("<I", huge, count_at, 10**6)
    with pytest.raises(DecodeError, match="packets length"):
        bags.pandar_packets(huge)
    bad_size = bytearray(cdr)
    struct.pack_into("<I", bad_size, count_at + 4 + 8 + 1500, 1501)
    with pytest.raises(DecodeError, match="size"):
        bags.pandar_packets(bad_size)
    with pytest.raises(DecodeError, match="encapsulation"):
        bags.pandar_packets(b"\x01\x00\x00\x00" + bytes(cdr[4:]))


# ---------------------------------------------------------------------------------- bags

def test_detect_input(tmp_path: Path) -> None:
    (tmp_path / "empty").write_bytes(b"")
    (tmp_path / "text.mcap").write_text("hello")
    (tmp_path / "dir").mkdir()
    kinds = {name: bags.detect_input(tmp_path / name).kind
             for name in ("empty", "text.mcap", "dir", "missing")}
    assert kinds == {"empty": "empty", "text.mcap": "other", "dir": "directory",
                     "missing": "missing"}
    assert bags.detect_input(VLP32).kind == "rosbag2"
    db3 = next(VLP32.glob("*.db3"))
    assert bags.detect_input(db3).kind == "db3"
    assert "SQLite" in bags.detect_input(db3).description


def test_metadata_quirks_and_missing_metadata(tmp_path: Path) -> None:
    truth = [(m.topic, m.log_time_ns, m.payload) for m in bags.open_bag(VLP32).messages()]
    bag_dir = _copy_bag(VLP32, tmp_path / "quirks")
    meta = bag_dir / "metadata.yaml"
    text = meta.read_text().replace("serialization_format: cdr", 'serialization_format: ""')
    text = text.replace("storage_identifier: sqlite3", 'storage_identifier: ""')
    meta.write_text(text)
    bag = bags.open_bag(bag_dir)
    assert any("empty serialization_format" in n for n in bag.notes)
    assert any("empty storage_identifier" in n for n in bag.notes)
    assert [(m.topic, m.log_time_ns, m.payload) for m in bag.messages()] == truth
    meta.unlink()  # no metadata.yaml: the .db3 files of the directory
    bag = bags.open_bag(bag_dir)
    assert [(m.topic, m.log_time_ns, m.payload) for m in bag.messages()] == truth
    assert bag.topics[truth[0][0]].count == len(truth)
    # a single .db3
    single = bags.open_bag(next(bag_dir.glob("*.db3")))
    assert [(m.topic, m.log_time_ns, m.payload) for m in single.messages()] == truth


def test_schemas_qos_several_files_and_damaged_rows(tmp_path: Path) -> None:
    folder = tmp_path / "bag"
    folder.mkdir()
    custom = "string text\nint32 number\n"
    topics = [(1, "/chatter", "std_msgs/msg/String", "cdr", QOS),
              (2, "/custom", "test_pkg/msg/Thing", "cdr", "")]
    thing = b"\x00\x01\x00\x00" + struct.pack("<I", 3) + b"hi\x00\x00" + struct.pack("<i", -5)
    write_db3(folder / "b_0.db3", topics,
              [(1, 10, _string("a")), (2, 30, thing), (1, 50, _string("c")),
               (9, 60, _string("orphan")), (1, 70, None)],
              definitions=[("test_pkg/msg/Thing", "ros2msg", custom)])
    # second file, old schema, interleaved times; a row with a text timestamp
    write_db3(folder / "b_1.db3", topics[:1], [(1, 20, _string("b")), (1, 40, _string("d")),
                                               (1, "soon", _string("e"))], schema="old")
    (folder / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  version: 8\n  storage_identifier: sqlite3\n"
        "  relative_file_paths: [b_0.db3, b_1.db3]\n  topics_with_message_count:\n"
        "    - topic_metadata: {name: /chatter, type: std_msgs/msg/String, "
        "serialization_format: cdr, offered_qos_profiles: " + repr(QOS).replace("'", '"')
        + "}\n      message_count: 6\n"
        "    - topic_metadata: {name: /custom, type: test_pkg/msg/Thing, "
        "serialization_format: cdr, offered_qos_profiles: ''}\n      message_count: 1\n")
    bag = bags.open_bag(folder)
    assert bag.topics["/chatter"].metadata == {"offered_qos_profiles": QOS}
    items = list(bag.messages())
    good = [m for m in items if isinstance(m, McapMessage)]
    bad = [m for m in items if isinstance(m, BadMessage)]
    assert [(m.log_time_ns, m.topic) for m in good] == [
        (10, "/chatter"), (20, "/chatter"), (30, "/custom"), (40, "/chatter"), (50, "/chatter")]
    assert [m.decode().data for m in good if m.topic == "/chatter"] == list("abdc")
    assert good[0].metadata == {"offered_qos_profiles": QOS}
    thing_msg = good[2].decode()  # its definition came from the message_definitions table
    assert (thing_msg.text, thing_msg.number) == ("hi", -5)
    assert sorted(b.reason.split("=")[0] for b in bad) == [
        "messages.data (row 5)", "messages.timestamp (row 3)", "messages.topic_id (row 4)"]
    assert all(isinstance(b.error, LidarScanError) for b in bad)


def test_mcap_storage_bag_and_damaged_db3(tmp_path: Path) -> None:
    folder = tmp_path / "mcapbag"
    folder.mkdir()
    with McapWriter(folder / "x_0.mcap") as writer:
        for k in range(3):
            writer.write("/chatter", _string(str(k)), msgtype="std_msgs/msg/String",
                         log_time_ns=k, metadata={"offered_qos_profiles": QOS})
    (folder / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  storage_identifier: mcap\n"
        "  relative_file_paths: [x_0.mcap]\n  topics_with_message_count: []\n")
    bag = bags.open_bag(folder)
    assert bag.topics["/chatter"].count == 3
    items = list(bag.messages())
    assert [m.decode().data for m in items] == ["0", "1", "2"]
    assert items[0].metadata == {"offered_qos_profiles": QOS}
    # a .db3 that is not a database past its header
    broken = tmp_path / "broken.db3"
    broken.write_bytes(b"SQLite format 3\x00" + b"\xff" * 5000)
    with pytest.raises(LidarScanError, match="sqlite3|database"):
        bags.open_bag(broken)


# ----------------------------------------------------------------------------------- CLI

def _scan_rows(info: Any, count: int) -> list[tuple[int, int, bytes]]:
    rows = [(1, BASE, ls.encode(info))]
    for k in range(count):
        stamp = BASE + (k + 1) * 100_000_000
        rows.append((2, stamp, ls.encode(_scan(info, stamp))))
    return rows


def _same_rows_as_mcap(rows: list[tuple[int, int, bytes]], topics: list[Any], path: Path) -> None:
    names = {t[0]: (t[1], t[2]) for t in topics}
    with McapWriter(path) as writer:
        for tid, stamp, data in rows:
            writer.write(names[tid][0], data, msgtype=names[tid][1], log_time_ns=stamp)


def test_convert_lidarscan_bag_like_mcap(tmp_path: Path) -> None:
    info = _info()
    topics = [(1, "/lidar/info", ls.mcap.INFO_TYPE, "cdr", QOS),
              (2, "/lidar/scan", ls.mcap.SCAN_TYPE, "cdr", "")]
    rows = _scan_rows(info, 3)
    write_db3(tmp_path / "scans.db3", topics, rows)
    _same_rows_as_mcap(rows, topics, tmp_path / "scans.mcap")
    argv = ["--pointcloud2", "--slice", "mid:-5:5", "-q"]
    assert cli.main(["convert", str(tmp_path / "scans.db3"), str(tmp_path / "a.mcap")]
                    + argv) == 0
    assert cli.main(["convert", str(tmp_path / "scans.mcap"), str(tmp_path / "b.mcap")]
                    + argv) == 0
    a, b = messages_by_topic(tmp_path / "a.mcap"), messages_by_topic(tmp_path / "b.mcap")
    assert a.keys() == b.keys() >= {"/lidar/points", "/lidar/slices/mid", "/lidar/scan"}
    for topic in a:
        assert [m.payload for m in a[topic]] == [m.payload for m in b[topic]]
    assert dict(a["/lidar/info"][0].metadata) == {"offered_qos_profiles": QOS}  # issue 19
    views = tmp_path / "views"
    assert cli.main(["view", str(tmp_path / "scans.db3"), "--out", str(views)]) == 0
    assert (views / "range_image_lidar.png").read_bytes()[:4] == b"\x89PNG"
    assert cli.main(["info", str(tmp_path / "scans.db3")]) == 0


def test_convert_pointcloud2_bag_like_mcap(tmp_path: Path) -> None:
    from converters.pointcloud2.converter import to_pointcloud2

    info = _info()
    rows = []
    for k in range(3):
        stamp = BASE + k * 100_000_000
        rows.append((1, stamp, ls.encode(to_pointcloud2(_scan(info, stamp), info))))
    topics = [(1, "/velo/points", "sensor_msgs/msg/PointCloud2", "cdr", QOS)]
    write_db3(tmp_path / "clouds.db3", topics, rows)
    _same_rows_as_mcap(rows, topics, tmp_path / "clouds.mcap")
    assert cli.main(["convert", str(tmp_path / "clouds.db3"), str(tmp_path / "a.mcap"),
                     "-q", "--keep-clouds"]) == 0
    assert cli.main(["convert", str(tmp_path / "clouds.mcap"), str(tmp_path / "b.mcap"),
                     "-q", "--keep-clouds"]) == 0
    a, b = messages_by_topic(tmp_path / "a.mcap"), messages_by_topic(tmp_path / "b.mcap")
    assert len(a["/velo/lidar_scan"]) == 3 and len(a["/velo/lidar_info"]) == 1
    for topic in a:
        assert [m.payload for m in a[topic]] == [m.payload for m in b[topic]]
    assert dict(a["/velo/points"][0].metadata) == {"offered_qos_profiles": QOS}


def test_info_on_a_real_bag(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["info", str(QT64)]) == 0
    out = capsys.readouterr().out
    assert "a rosbag2 directory" in out and "pandar_msgs/msg/PandarScan" in out
    assert "(1200 packets)" in out and "no problems found" in out


def test_convert_packets_without_a_decoder_fails_clearly(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setitem(sys.modules, "converters.sources.hesai.decoder", None)  # import fails
    out = tmp_path / "out.mcap"
    assert cli.main(["convert", str(QT64), str(out)]) == 2
    err = capsys.readouterr().err
    assert "no decoder for pandar_msgs/msg/PandarScan in this installation" in err
    assert not out.exists() and not list(tmp_path.iterdir())


class _StandInDecoder:
    """Follows /work/DECODER_CONTRACT.md: one 'rotation' per 100 packets, a new info version
    after the first two rotations; a packet starting with 0xFF is malformed."""

    created: list[Any] = []

    def __init__(self, calibration: Any = None, *, frame_id: str = "lidar") -> None:
        self.frame_id, self.calibration = frame_id, calibration
        self.stamps: list[int] = []
        self.rotations = 0
        self.infos: dict[int, Any] = {}
        _StandInDecoder.created.append(self)

    def _info(self) -> Any:
        version = 0 if self.rotations < 2 else 1
        if version not in self.infos:
            self.infos[version] = ls.make_info(
                stamp_ns=self.stamps[0], frame_id=self.frame_id,
                vertical_angles=np.linspace(0.2, -0.2, 4),
                horizontal_angles=np.zeros(10), as_dataclass=True)
        return self.infos[version]

    def _rotation(self) -> list[Any]:
        info = self._info()
        scan = ls.make_scan(info, {"range": np.full((4, 10), len(self.stamps), np.float32)},
                            self.stamps[0], as_dataclass=True)
        self.rotations += 1
        self.stamps = []
        return [(scan, info)]

    def push(self, stamp_ns: int, packet: Any) -> list[Any]:
        if bytes(packet[:1]) == b"\xff":
            raise DecodeError("packet[0]", 255, "a data block flag")
        self.stamps.append(stamp_ns)
        return self._rotation() if len(self.stamps) == 100 else []

    def flush(self) -> list[Any]:
        return self._rotation() if self.stamps else []


def test_convert_packets_through_the_decoder_contract(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    module = types.ModuleType("converters.sources.hesai.decoder")
    module.PacketDecoder = _StandInDecoder  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "converters.sources.hesai.decoder", module)
    _StandInDecoder.created = []
    src = _copy_bag(QT64, tmp_path / "bag")
    # damage one packet of the second message: reported, the others decoded
    db3 = next(src.glob("*.db3"))
    con = sqlite3.connect(db3)
    (row_id, data), *_ = con.execute("SELECT id, data FROM messages ORDER BY timestamp "
                                     "LIMIT 1 OFFSET 1").fetchall()
    data = bytearray(data)
    first_packet = 4 + 8 + 4 + 8 + 4 + 8  # header (frame 'hesai' padded), count, stamp
    data[first_packet] = 0xFF
    con.execute("UPDATE messages SET data = ? WHERE id = ?", (bytes(data), row_id))
    con.commit()
    con.close()
    calib = tmp_path / "calib.csv"
    calib.write_text("Laser id,Elevation,Azimuth\n")
    out = tmp_path / "out.mcap"
    status = cli.main(["convert", str(src), str(out), "--calibration", str(calib),
                       "--keep-packets"])
    err = capsys.readouterr().err
    assert status == 1, err
    assert err.count("bad message #1 topic '/pandar_packets'") == 1
    assert "packet 0 of 300" in err and "data block flag" in err
    (decoder,) = _StandInDecoder.created
    assert decoder.calibration == str(calib) and decoder.frame_id == "hesai"
    got = messages_by_topic(out)
    scans = [m.decode() for m in got["/pandar_packets/lidar_scan"]]
    infos = [m.decode() for m in got["/pandar_packets/lidar_info"]]
    assert len(scans) == 12 and len(infos) == 2  # 1199 packets; each version written once
    order = [m.topic.rsplit("/", 1)[1] for m in read_messages(out)
             if isinstance(m, McapMessage) and m.topic.startswith("/pandar_packets/")]
    assert order[0] == "lidar_info" and order[3] == "lidar_info"  # before their first scan
    assert {s.lidar_info_time.sec for s in scans[:2]} == {infos[0].header.stamp.sec}
    assert len(got["/pandar_packets"]) == 4  # --keep-packets copies them, with a schema
    # without --keep-packets the packets are not copied
    assert cli.main(["convert", str(src), str(tmp_path / "o2.mcap"), "-q"]) == 1
    assert "/pandar_packets" not in messages_by_topic(tmp_path / "o2.mcap")


def test_damaged_db3_time_index_and_truncated_db3(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    full = [(m.log_time_ns, m.payload) for m in bags.open_bag(QT64).messages()]
    bag_dir = _copy_bag(QT64, tmp_path / "bag")
    db3 = next(bag_dir.glob("*.db3"))
    con = sqlite3.connect(db3)
    page = con.execute("PRAGMA page_size").fetchone()[0]
    (root,) = con.execute("SELECT rootpage FROM sqlite_master WHERE name = 'timestamp_idx'"
                          ).fetchone()
    con.close()
    raw = bytearray(db3.read_bytes())
    raw[(root - 1) * page:root * page] = b"\xff" * page  # the time index is unreadable
    db3.write_bytes(bytes(raw))
    items = list(bags.open_bag(bag_dir).messages())  # read in row (recording) order instead
    assert [(m.log_time_ns, m.payload) for m in items] == full
    # cut short: sqlite refuses the whole file; reported, not raised, and info exits 1
    db3.write_bytes(bytes(raw[:len(raw) * 3 // 5]))
    items = list(bags.open_bag(bag_dir).messages())  # topics from metadata.yaml
    (bad,) = items
    assert isinstance(bad, BadMessage) and isinstance(bad.error, LidarScanError)
    assert "malformed" in bad.reason
    assert cli.main(["info", str(bag_dir)]) == 1
    assert "problem:" in capsys.readouterr().out
