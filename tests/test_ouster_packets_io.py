"""Ouster packets from where users have them: pcap/pcapng captures (IPv4 fragments, link types,
the lidar port), ouster-ros rosbag2 recordings (MCAP and .db3) and ``lidarscan convert``.

The captures are written here from the shipped real pcaps (their frames re-wrapped) or from
synthetic datagrams; the recordings' CDR is made by ``rosbags`` (a serializer that is not this
project's) and the expected scans by the decoder on the shipped pcaps, which
tests/test_ouster_packets.py checks against ouster-sdk's frames.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from converters import bags, cli, ouster
from converters.sources.ouster import pcap
from lidarscan.errors import ConfigError

from helpers import messages_by_topic
from ouster_packet_helpers import DATA, OS0, OS2
from test_bags import write_db3

PACKET_TYPE = "ouster_sensor_msgs/msg/PacketMsg"


# --------------------------------------------------------------------------- capture writers

def _classic_records(path: Path) -> tuple[int, list[tuple[int, int, bytes]]]:
    """(link type, [(sec, usec, frame bytes)]) of a little-endian microsecond pcap."""
    data = path.read_bytes()
    assert data[:4] == b"\xd4\xc3\xb2\xa1"
    link = struct.unpack_from("<I", data, 20)[0]
    out, at = [], 24
    while at + 16 <= len(data):
        sec, usec, caplen, _ = struct.unpack_from("<IIII", data, at)
        out.append((sec, usec, data[at + 16:at + 16 + caplen]))
        at += 16 + caplen
    return link, out


def _write_pcapng(path: Path, link: int, records: list[tuple[int, bytes]], *,
                  big: bool = False) -> None:
    """pcapng with one interface in nanoseconds (if_tsresol 9): records (ns, frame)."""
    o = ">" if big else "<"

    def block(kind: int, body: bytes) -> bytes:
        body += b"\x00" * (-len(body) % 4)
        return struct.pack(o + "II", kind, len(body) + 12) + body + struct.pack(o + "I",
                                                                                len(body) + 12)
    out = [block(0x0A0D0D0A, struct.pack(o + "IHHq", 0x1A2B3C4D, 1, 0, -1))]
    options = struct.pack(o + "HHB3x", 9, 1, 9) + struct.pack(o + "HH", 0, 0)
    out.append(block(1, struct.pack(o + "HHI", link, 0, 65535) + options))
    for ns, frame in records:
        out.append(block(6, struct.pack(o + "IIIII", 0, ns >> 32, ns & 0xFFFFFFFF, len(frame),
                                        len(frame)) + frame))
    path.write_bytes(b"".join(out))


def _ipv4_udp(payload: bytes, dport: int, ident: int, mtu: int = 1500) -> list[bytes]:
    """IPv4 packets (no link header) of one UDP datagram, fragmented to ``mtu``."""
    udp = struct.pack(">HHHH", 7502, dport, 8 + len(payload), 0) + payload
    step = (mtu - 20) // 8 * 8
    out = []
    for start in range(0, len(udp), step):
        chunk = udp[start:start + step]
        more = start + step < len(udp)
        flags = (0x2000 if more else 0) | (start // 8)
        out.append(struct.pack(">BBHHHBBH4s4s", 0x45, 0, 20 + len(chunk), ident, flags, 64,
                               17, 0, b"\x0a\x05\x05\x57", b"\x0a\x05\x05\x01") + chunk)
    return out


def _ethernet(ip: bytes, vlan: bool = False) -> bytes:
    head = b"\x01" * 6 + b"\x02" * 6 + (b"\x81\x00\x00\x07" if vlan else b"")
    return head + b"\x08\x00" + ip


def _write_classic(path: Path, link: int, frames: list[tuple[int, bytes]], *,
                   big: bool = False, nanos: bool = False) -> None:
    o = ">" if big else "<"
    magic = 0xA1B23C4D if nanos else 0xA1B2C3D4
    out = [struct.pack(o + "IHHiIII", magic, 2, 4, 0, 0, 65535, link)]
    for ns, frame in frames:
        frac = ns % 10**9 if nanos else ns % 10**9 // 1000
        out.append(struct.pack(o + "IIII", ns // 10**9, frac, len(frame), len(frame)) + frame)
    path.write_bytes(b"".join(out))


def _packets(name: str) -> list[tuple[int, bytes]]:
    return list(ouster.lidar_packets(DATA / f"{name}.pcap", DATA / f"{name}.json"))


def _scan_bytes(results: list[Any]) -> list[bytes]:
    return [np.asarray(s.data).tobytes() for s, _ in results]


# ---------------------------------------------------------------------------------- pcap

@pytest.mark.parametrize("name,size", [(OS2, 24832), (OS0, 8448)])
def test_real_pcap_fragments_and_ports(name: str, size: int) -> None:
    stats = pcap.PcapStats()
    datagrams = list(pcap.read_pcap(DATA / f"{name}.pcap", stats))
    assert stats.ports == {7502: {size: 64}, 7503: {48: 10}}
    # ouster-sdk wrote one frame per datagram (no IP fragments; those are tested below)
    assert (stats.frames, stats.datagrams, stats.reassembled, stats.incomplete) == (74, 74, 0, 0)
    stamps = [d.stamp_ns for d in datagrams]
    assert stamps == sorted(stamps) and stamps[0] > 10**18


@pytest.mark.parametrize("big", [False, True])
def test_pcapng_gives_the_same_datagrams(tmp_path: Path, big: bool) -> None:
    link, records = _classic_records(DATA / f"{OS0}.pcap")
    path = tmp_path / "x.pcapng"
    _write_pcapng(path, link, [(s * 10**9 + u * 1000, f) for s, u, f in records], big=big)
    assert list(pcap.read_pcap(path)) == list(pcap.read_pcap(DATA / f"{OS0}.pcap"))
    expected = list(ouster.scans_from_pcap(DATA / f"{OS0}.pcap", DATA / f"{OS0}.json",
                                           as_dataclass=True))
    got = list(ouster.scans_from_pcap(path, DATA / f"{OS0}.json", as_dataclass=True))
    assert _scan_bytes(got) == _scan_bytes(expected)


@pytest.mark.parametrize("link,wrap", [
    (1, lambda ip: _ethernet(ip)),
    (1, lambda ip: _ethernet(ip, vlan=True)),
    (101, lambda ip: ip),
    (0, lambda ip: struct.pack("<I", 2) + ip),
    (113, lambda ip: b"\x00" * 14 + b"\x08\x00" + ip),
    (276, lambda ip: b"\x08\x00" + b"\x00" * 18 + ip),
])
@pytest.mark.parametrize("big,nanos", [(False, False), (True, True)])
def test_link_types_byte_orders_and_shuffled_fragments(tmp_path: Path, link: int, wrap: Any,
                                                       big: bool, nanos: bool) -> None:
    packets = _packets(OS0)
    frames = []
    for k, (ns, payload) in enumerate(packets):
        parts = _ipv4_udp(payload, 7502, 1000 + k, mtu=1400)
        parts = parts[1:] + parts[:1] if k % 2 else parts[::-1]   # out of order
        frames += [(ns, wrap(p)) for p in parts]
    frames.insert(5, (0, wrap(b"\x45" + b"\x00" * 8 + b"\x06" + b"\x00" * 10)))  # a TCP frame
    path = tmp_path / "x.pcap"
    _write_classic(path, link, frames, big=big, nanos=nanos)
    stats = pcap.PcapStats()
    got = [d.payload for d in pcap.read_pcap(path, stats)]
    assert got == [p for _, p in packets]
    assert stats.reassembled == 64 and stats.skipped == 1


def test_missing_fragment_drops_the_datagram(tmp_path: Path) -> None:
    packets = _packets(OS0)[:3]
    frames = []
    for k, (ns, payload) in enumerate(packets):
        parts = _ipv4_udp(payload, 7502, k)
        if k == 1:
            del parts[2]
        frames += [(ns, _ethernet(p)) for p in parts]
    path = tmp_path / "x.pcap"
    _write_classic(path, 1, frames)
    stats = pcap.PcapStats()
    assert [d.payload for d in pcap.read_pcap(path, stats)] == [packets[0][1], packets[2][1]]
    assert stats.incomplete == 1


def test_lidar_port_from_metadata_or_by_size(tmp_path: Path) -> None:
    packets = _packets(OS0)
    frames = []
    for k, (ns, payload) in enumerate(packets):
        frames += [(ns, _ethernet(p)) for p in _ipv4_udp(payload, 7777, k)]
        frames += [(ns, _ethernet(p)) for p in _ipv4_udp(b"\x00" * 48, 7503, 5000 + k)]
    path = tmp_path / "x.pcap"
    _write_classic(path, 1, frames)
    meta = DATA / f"{OS0}.json"         # says port 7502: not in this capture -> by size
    assert [p for _, p in ouster.lidar_packets(path, meta)] == [p for _, p in packets]
    assert list(ouster.lidar_packets(path, meta, port=7502)) == []
    assert len(list(ouster.lidar_packets(path, meta, port=7777))) == 64


def test_not_a_capture(tmp_path: Path) -> None:
    path = tmp_path / "x.pcap"
    path.write_bytes(b"hello world, not a pcap")
    with pytest.raises(Exception, match="pcap"):
        list(pcap.read_pcap(path))


# --------------------------------------------------------------------------- ouster-ros bags

def _typestore() -> Any:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg("uint8[] buf\n", PACKET_TYPE))
    return store


def _cdr(store: Any, msgtype: str, **fields: Any) -> bytes:
    msg = store.types[msgtype](**fields)
    return bytes(store.serialize_cdr(msg, msgtype))


def _recording_rows(name: str, with_metadata: bool = True) -> list[tuple[str, str, int, bytes]]:
    store = _typestore()
    rows = []
    if with_metadata:
        text = (DATA / f"{name}.json").read_text()
        rows.append(("/ouster/metadata", "std_msgs/msg/String", 10**18,
                     _cdr(store, "std_msgs/msg/String", data=text)))
    for k, (ns, payload) in enumerate(_packets(name)):
        rows.append(("/ouster/lidar_packets", PACKET_TYPE, 10**18 + 1000 * (k + 1),
                     _cdr(store, PACKET_TYPE, buf=np.frombuffer(payload, np.uint8))))
        if k % 8 == 0:       # ouster-ros's IMU packets: the same type, never decoded
            rows.append(("/ouster/imu_packets", PACKET_TYPE, 10**18 + 1000 * (k + 1) + 1,
                         _cdr(store, PACKET_TYPE, buf=np.zeros(48, np.uint8))))
    return rows


def _write_mcap(path: Path, rows: list[tuple[str, str, int, bytes]]) -> None:
    from lidarscan.mcap import McapWriter

    bags.register_packet_types()
    with McapWriter(path) as writer:
        for topic, msgtype, t, cdr in rows:
            writer.write(topic, cdr, msgtype=msgtype, log_time_ns=t)


def _write_db3(path: Path, rows: list[tuple[str, str, int, bytes]]) -> None:
    topics: dict[str, tuple[int, str]] = {}
    for topic, msgtype, _, _ in rows:
        topics.setdefault(topic, (len(topics) + 1, msgtype))
    write_db3(path, [(i, t, k, "cdr", "") for t, (i, k) in topics.items()],
              [(topics[t][0], ts, cdr) for t, _, ts, cdr in rows])


@pytest.mark.parametrize("storage", ["mcap", "db3"])
@pytest.mark.parametrize("name", [OS2, OS0])
def test_ouster_ros_recording_gives_the_pcap_scans(tmp_path: Path, storage: str,
                                                   name: str) -> None:
    path = tmp_path / f"rec.{storage}"
    (_write_mcap if storage == "mcap" else _write_db3)(path, _recording_rows(name))
    got = list(ouster.scans_from_bag(path, as_dataclass=True))
    expected = list(ouster.scans_from_pcap(DATA / f"{name}.pcap", DATA / f"{name}.json",
                                           as_dataclass=True))
    assert len(got) == 1 and _scan_bytes(got) == _scan_bytes(expected)
    assert got[0][1].vendor_metadata == (DATA / f"{name}.json").read_text()


def test_recording_is_decoded_in_bounded_batches(tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """scans_from_bag hands the packets to the decoder's batch entry (push_many) in runs of at
    most decoder._RUN packets, read as they come (never the whole recording at once): the
    scans are the pcap's, bit for bit."""
    from converters.sources.ouster import decoder as ouster_decoder

    path = tmp_path / "rec.mcap"
    _write_mcap(path, _recording_rows(OS0))
    expected = _scan_bytes(list(ouster.scans_from_pcap(DATA / f"{OS0}.pcap",
                                                       DATA / f"{OS0}.json", as_dataclass=True)))
    sizes: list[int] = []
    push_many = ouster_decoder.PacketDecoder.push_many

    def spy(self: Any, stamps: Any, payloads: Any, errors: Any = None) -> Any:
        sizes.append(payloads.shape[0])
        return push_many(self, stamps, payloads, errors)

    monkeypatch.setattr(ouster_decoder.PacketDecoder, "push_many", spy)
    monkeypatch.setattr(ouster_decoder, "_RUN", 10)
    got = list(ouster.scans_from_bag(path, as_dataclass=True))
    assert len(got) == 1 and _scan_bytes(got) == expected
    assert sizes == [10] * 6 + [4]                  # the recording's 64 lidar packets


def test_recording_without_metadata_needs_it(tmp_path: Path) -> None:
    path = tmp_path / "rec.mcap"
    _write_mcap(path, _recording_rows(OS0, with_metadata=False))
    with pytest.raises(ConfigError, match="metadata"):
        list(ouster.scans_from_bag(path))
    got = list(ouster.scans_from_bag(path, DATA / f"{OS0}.json", as_dataclass=True))
    assert len(got) == 1


def test_packet_msg_cdr_is_rosbags() -> None:
    from converters.sources.ouster.bag import string_payload

    store = _typestore()
    raw = bytes(range(256)) * 3 + b"\x07"
    scan = bags.ouster_packets(_cdr(store, PACKET_TYPE, buf=np.frombuffer(raw, np.uint8)))
    assert scan.data.shape == (1, len(raw)) and scan.data.tobytes() == raw
    assert scan.payloads.tobytes() == raw and not scan.data.flags.writeable
    assert string_payload(_cdr(store, "std_msgs/msg/String", data="{\"a\": 1}")) == "{\"a\": 1}"
    with pytest.raises(Exception, match="PacketMsg"):
        bags.ouster_packets(b"\x00\x01\x00\x00\xff\x00\x00\x00abc")


# ----------------------------------------------------------------------------------- CLI

@pytest.mark.parametrize("extra,outputs", [
    ([], {"/lidar/info", "/lidar/scan"}),
    (["--pointcloud2"], {"/lidar/info", "/lidar/scan", "/lidar/points"}),
    (["--compress"], {"/lidar/info", "/lidar/scan"}),
    (["--slice", "low:-0.5:0.5"], {"/lidar/info", "/lidar/scan", "/lidar/slices/low"}),
])
def test_cli_convert_pcap(tmp_path: Path, extra: list[str], outputs: set[str]) -> None:
    out = tmp_path / "out.mcap"
    assert cli.main(["convert", str(DATA / f"{OS2}.pcap"), str(out), "--metadata",
                     str(DATA / f"{OS2}.json"), "-q", *extra]) == 0
    topics = messages_by_topic(out)
    assert set(topics) == outputs
    (expected, _), = ouster.scans_from_pcap(DATA / f"{OS2}.pcap", DATA / f"{OS2}.json",
                                            as_dataclass=True)
    if "--compress" not in extra:
        assert topics["/lidar/scan"][0].payload == _encoded(expected)


def _encoded(scan: Any) -> bytes:
    import lidarscan
    return bytes(lidarscan.encode(scan))


def test_cli_convert_pcap_needs_metadata(tmp_path: Path, capsys: Any) -> None:
    src = tmp_path / "x.pcapng"
    link, records = _classic_records(DATA / f"{OS0}.pcap")
    _write_pcapng(src, link, [(s * 10**9 + u * 1000, f) for s, u, f in records])
    assert cli.main(["convert", str(src), str(tmp_path / "o.mcap")]) == 2
    assert "--metadata" in capsys.readouterr().err
    (tmp_path / "x.json").write_text((DATA / f"{OS0}.json").read_text())
    assert cli.main(["convert", str(src), str(tmp_path / "o.mcap"), "-q"]) == 0  # x.json


@pytest.mark.parametrize("storage", ["mcap", "db3"])
def test_cli_convert_ouster_ros_recording(tmp_path: Path, storage: str, capsys: Any) -> None:
    src = tmp_path / f"rec.{storage}"
    (_write_mcap if storage == "mcap" else _write_db3)(src, _recording_rows(OS0))
    out = tmp_path / "out.mcap"
    assert cli.main(["convert", str(src), str(out), "--pointcloud2", "-q"]) == 0
    topics = messages_by_topic(out)
    prefix = "/ouster/lidar_packets"
    assert {f"{prefix}/lidar_info", f"{prefix}/lidar_scan", f"{prefix}/points",
            "/ouster/metadata", "/ouster/imu_packets"} == set(topics)
    assert len(topics["/ouster/imu_packets"]) == 8           # copied like any other topic
    (expected, _), = ouster.scans_from_pcap(DATA / f"{OS0}.pcap", DATA / f"{OS0}.json",
                                            as_dataclass=True)
    assert topics[f"{prefix}/lidar_scan"][0].payload == _encoded(expected)
    # without the recorded metadata: exit 2 naming --metadata, then fine with it
    bare = tmp_path / f"bare.{storage}"
    (_write_mcap if storage == "mcap" else _write_db3)(bare, _recording_rows(OS0, False))
    capsys.readouterr()
    assert cli.main(["convert", str(bare), str(tmp_path / "o2.mcap")]) == 2
    assert "--metadata" in capsys.readouterr().err
    assert cli.main(["convert", str(bare), str(tmp_path / "o2.mcap"), "--metadata",
                     str(DATA / f"{OS0}.json"), "-q", "--keep-packets"]) == 0
    kept = messages_by_topic(tmp_path / "o2.mcap")
    assert len(kept["/ouster/lidar_packets"]) == 64
