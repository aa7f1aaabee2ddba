"""Fuzz targets of ``bench/fuzz.py`` for recordings and packets: mutated MCAP files, damaged MCAP
chunks, packet messages and rosbag2 ``.db3`` files (scratch files under
``fuzz_common.ROOT/build/fuzz``)."""

from __future__ import annotations

import io
import os
import random
import struct
from collections.abc import Callable
from typing import Any

import numpy as np

from lidarscan import types as lt
from lidarscan.errors import LidarScanError

import fuzz_common
from fuzz_common import (  # bench/ is on sys.path: see fuzz.py
    exercise_scan,
    mutate_bytes,
    seed_info,
    seed_scan,
    Target,
)

class McapFile(Target):
    """Small MCAP files (info + scans + a foreign type, chunked or not), truncated or damaged;
    read with read_messages (every record decoded) and read_scans."""
    name = "mcap"

    def setup(self) -> None:
        from lidarscan.mcap import McapWriter
        info = seed_info()
        self.files = []
        laser = lt.message_class("sensor_msgs/msg/LaserScan")(
            header=lt.Header(lt.Time(0, 5), "laser"), angle_min=-1.0, angle_max=1.0,
            angle_increment=0.5, time_increment=0.0, scan_time=0.1, range_min=0.1, range_max=30.0,
            ranges=np.array([1, 2, 3, 4, 5], np.float32), intensities=np.zeros(0, np.float32))
        for compression, chunk in (("zstd", 1024), ("lz4", 2048), ("none", 1 << 20)):
            buf = io.BytesIO()
            with McapWriter(buf, compression=compression, chunk_size=chunk) as writer:
                writer.write("/scan", seed_scan(info, 1_000_000_000))  # before its info
                writer.write("/info", info)
                for i in range(3):
                    writer.write("/scan", seed_scan(info, 2_000_000_000 + i))
                writer.write("/laser", laser, log_time_ns=5)
            self.files.append(buf.getvalue())
        self.tmp = fuzz_common.ROOT / "build" / "fuzz" / f"mcap-case-{os.getpid()}.mcap"
        self.tmp.parent.mkdir(parents=True, exist_ok=True)

    def case(self, rnd: random.Random) -> tuple[bytes, Callable[[], str]]:
        from lidarscan.mcap import BadMessage, read_messages, read_scans
        data = rnd.choice(self.files)
        if rnd.random() < 0.15:
            data = data[:rnd.randrange(len(data))]
        else:
            data = mutate_bytes(rnd, data)
        on_disk = rnd.random() < 0.3  # buffered file reads allocate what is asked for

        def run() -> str:
            source: Any = data
            if on_disk:
                self.tmp.write_bytes(data)
                source = self.tmp
            good = 0
            for item in read_messages(source):
                if isinstance(item, BadMessage):
                    if not isinstance(item.error, LidarScanError):
                        raise TypeError(f"BadMessage.error is {type(item.error).__name__}")
                    continue
                try:
                    item.decode()
                    good += 1
                except LidarScanError:
                    pass
            errors: list[Any] = []
            for scan, info in read_scans(source, on_error=errors.append):
                exercise_scan(scan, info)
            return f"{good} decoded"
        return data, run


class CheckFailed(Exception):
    """A fuzz case broke a promise of the reader (not an exception type the code may raise)."""


def _string_cdr(text: str) -> bytes:
    raw = text.encode() + b"\x00"
    return b"\x00\x01\x00\x00" + struct.pack("<I", len(raw)) + raw


class McapChunks(Target):
    """Chunk damage in multi-chunk MCAP files (zstd, lz4, none): bytes altered inside a chunk
    (after its time fields), the file cut anywhere, the summary dropped or altered, a chunk's
    record length damaged (with or without the summary). Beyond "only LidarScanError": every
    message of a chunk that is intact and on disk is read byte-identical, nothing that was not
    written is returned, and a chunk that lost messages is reported at its offset."""
    name = "mcap_chunks"

    def setup(self) -> None:
        from mcap.reader import make_reader

        from lidarscan.mcap import McapWriter
        self.files = []
        for compression in ("zstd", "lz4", "none"):
            buf = io.BytesIO()
            with McapWriter(buf, compression=compression, chunk_size=700) as writer:
                for k in range(40):
                    writer.write(f"/t{k % 3}", _string_cdr(f"message {k} " * (1 + k % 7)),
                                 msgtype="std_msgs/msg/String", log_time_ns=1000 + k)
            data = buf.getvalue()
            reader = make_reader(io.BytesIO(data))
            messages = [(ch.topic, m.log_time, bytes(m.data))
                        for _, ch, m in reader.iter_messages()]
            summary = reader.get_summary()
            chunks = sorted((c.chunk_start_offset, c.chunk_length, c.message_start_time,
                             c.message_end_time) for c in summary.chunk_indexes)
            summary_start = struct.unpack_from("<Q", data, len(data) - 8 - 20)[0]
            self.files.append((data, messages, chunks, summary_start))

    def case(self, rnd: random.Random) -> tuple[bytes, Callable[[], str]]:
        from lidarscan.mcap import BadMessage, McapMessage, read_messages
        data, messages, chunks, summary_start = rnd.choice(self.files)
        buf = bytearray(data)
        kind = rnd.choice(["flip", "flip", "flip", "truncate", "drop_summary", "summary",
                           "length"])
        damaged: set[int] = set()
        strict = True
        if kind == "flip":
            for _ in range(rnd.randint(1, 3)):
                k = rnd.randrange(len(chunks))
                start, length = chunks[k][:2]
                buf[rnd.randrange(start + 25, start + length)] ^= rnd.randrange(1, 256)
                damaged.add(k)
        elif kind == "truncate":
            del buf[rnd.randrange(len(buf)):]
        elif kind == "drop_summary":
            del buf[summary_start:]
        elif kind == "summary":
            buf[rnd.randrange(summary_start, len(buf) - 8 - 29)] ^= rnd.randrange(1, 256)
        else:
            k = rnd.randrange(len(chunks))
            start = chunks[k][0]
            struct.pack_into("<Q", buf, start + 1, rnd.choice(
                [0, 1, 30, chunks[k][1] // 2, chunks[k][1] + 50, 2**40, 2**64 - 1]))
            damaged.add(k)
            strict = False  # a wrong length can frame bytes as records: only the basics hold
            if rnd.random() < 0.5:
                del buf[summary_start:]
        data_out = bytes(buf)

        def run() -> str:
            got: list[tuple[str, int, bytes]] = []
            reports: list[Any] = []
            for item in read_messages(data_out):
                if isinstance(item, BadMessage):
                    if not isinstance(item.error, LidarScanError) or not item.reason.strip():
                        raise CheckFailed(f"report without a LidarScanError or reason: {item}")
                    reports.append(item)
                elif isinstance(item, McapMessage):
                    got.append((item.topic, item.log_time_ns, item.payload))
            changed = data_out != data
            if changed and not reports and got != messages:
                raise CheckFailed("messages lost without a report")
            if not strict:
                if not reports:
                    raise CheckFailed("a damaged chunk length was not reported")
                return f"{len(got)} read, {len(reports)} reports"
            extra = [m for m in got if m not in messages]
            if extra:
                raise CheckFailed(f"{len(extra)} message(s) returned that were never written")
            offsets = {r.offset for r in reports}
            for start, length, first, last in chunks:
                inside = [m for m in messages if first <= m[1] <= last]
                intact = start + length <= len(data_out) and chunks.index(
                    (start, length, first, last)) not in damaged
                missing = [m for m in inside if m not in got]
                if intact and missing:
                    raise CheckFailed(f"chunk at {start} is intact but lost {len(missing)}")
                if missing and start < len(data_out) and start not in offsets:
                    raise CheckFailed(f"chunk at {start} lost {len(missing)} unreported")
            if len(data_out) < len(data) and not reports:
                raise CheckFailed("a truncated file was not reported")
            return f"{len(got)} read, {len(reports)} reports"
        return data_out, run


def _packet_scan_cdr(kind: str, count: int, frame: str = "velo") -> bytes:
    """A VelodyneScan / PandarScan in little-endian CDR (alignment from the payload start)."""
    out = bytearray(b"\x00\x01\x00\x00")

    def align(n: int) -> None:
        out.extend(bytes(-(len(out) - 4) % n))
    raw = frame.encode() + b"\x00"
    out += struct.pack("<iII", 5, 6, len(raw)) + raw
    align(4)
    out += struct.pack("<I", count)
    for k in range(count):
        align(4)
        out += struct.pack("<iI", k, 1000 * k)
        size = 1206 if kind == "velodyne" else 1500
        out += bytes((k + i) % 256 for i in range(size))
        if kind == "pandar":
            align(4)
            out += struct.pack("<I", 1000 + k)
    return bytes(out)


class PacketCdr(Target):
    """VelodyneScan / PandarScan CDR (converters.sources.bags): mutated, truncated, huge counts; only
    DecodeError may escape and every payload lies inside the message."""
    name = "packet_cdr"

    def setup(self) -> None:
        from converters.sources import bags
        self.seeds = [(bags.velodyne_packets, _packet_scan_cdr("velodyne", 3, "v")),
                      (bags.pandar_packets, _packet_scan_cdr("pandar", 3, "hesai_x"))]

    def case(self, rnd: random.Random) -> tuple[bytes, Callable[[], str]]:
        parse, seed = rnd.choice(self.seeds)
        data = mutate_bytes(rnd, seed)

        def run() -> str:
            scan = parse(data)
            total = sum(len(bytes(p)) for _, p in scan.packets)
            if total > len(data):
                raise CheckFailed(f"{total} payload bytes from a {len(data)}-byte message")
            return f"{len(scan.packets)} packets"
        return data, run


class BagDb3(Target):
    """A small rosbag2 .db3 (packets and strings) with its file bytes mutated: open_bag,
    every message read and parsed; only LidarScanError may escape."""
    name = "bag_db3"

    def setup(self) -> None:
        import sqlite3
        path = fuzz_common.ROOT / "build" / "fuzz" / f"bag-seed-{os.getpid()}.db3"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.unlink(missing_ok=True)
        con = sqlite3.connect(path)
        con.execute("CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT, type TEXT, "
                    "serialization_format TEXT, offered_qos_profiles TEXT)")
        con.executemany("INSERT INTO topics VALUES (?,?,?,?,?)", [
            (1, "/packets", "pandar_msgs/msg/PandarScan", "cdr", ""),
            (2, "/chatter", "std_msgs/msg/String", "cdr", "- depth: 5\n")])
        con.execute("CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER, "
                    "timestamp INTEGER, data BLOB)")
        con.executemany("INSERT INTO messages(topic_id, timestamp, data) VALUES (?,?,?)",
                        [(1 + k % 2, 100 - k, _packet_scan_cdr("pandar", 1) if k % 2 == 0
                          else _string_cdr(f"m{k}")) for k in range(8)])
        con.commit()
        con.close()
        self.seed = path.read_bytes()
        path.unlink()
        self.tmp = fuzz_common.ROOT / "build" / "fuzz" / f"bag-case-{os.getpid()}.db3"

    def case(self, rnd: random.Random) -> tuple[bytes, Callable[[], str]]:
        from converters.sources import bags
        from lidarscan.mcap import McapMessage
        data = mutate_bytes(rnd, self.seed)
        if rnd.random() < 0.5:
            data = mutate_bytes(rnd, data)

        def run() -> str:
            self.tmp.write_bytes(data)
            bag = bags.open_bag(self.tmp)
            good = 0
            for item in bag.messages():
                if isinstance(item, McapMessage):
                    good += 1
                    if item.msgtype in bags.PACKET_TYPES:
                        try:
                            bags.PACKET_TYPES[item.msgtype][1](item.payload)
                        except LidarScanError:
                            pass
                elif not isinstance(item.error, LidarScanError):
                    raise CheckFailed(f"BadMessage.error is {type(item.error).__name__}")
            return f"{good} read"
        return data, run
