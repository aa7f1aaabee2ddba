"""Benchmark: the whole ``lidarscan convert`` of a long raw-packet recording, vs real time.

Run: ``.venv/bin/python bench/bench_convert.py [--seconds S] [--profile N]``. Prints, per
recording, the convert time as a multiple of real time (sensor seconds / wall seconds) beside a
baseline measured in the same run, and optionally the cProfile top entries. No assertions.
Target (issue "Real sensors in"): >= 20x real time.

Input: the real VLS-128 (single return, 6 250 packets/s) and Pandar64 (dual return) recordings of
``tests/data/nebula`` (0.3-0.4 s each, see their NOTICE files) repeated into one rosbag2 .db3
directory per sensor of about ``--seconds`` of sensor time: a copy of the recording's own .db3
(its schema: topics, metadata tables) whose ``messages`` rows are replaced by the recorded
messages over and over, every copy shifted in time by the recording's length: the bag stamps,
each message's ``header.stamp`` and packet stamps, and the packets' own clocks (Velodyne
microseconds past the hour; Hesai UTC date-time + microseconds) so the decoders see one
continuous recording (with an azimuth jump at each seam). An empty ``serialization_format``
(the VLS-128 bag) is written as "cdr" (rosbags refuses the empty one; ``converters.bags`` reads
both).

Candidates (the bag already on disk, page cache warm), timed in interleaved rounds (CPU time,
median of ``--repeat`` rounds; ratios against ``convert`` in the same round):

- ``convert``: ``converters.cli.main(["convert", BAG, OUT.mcap, "--calibration", FILE, "-q"])``
  in this process (no interpreter start-up), the default options: read the .db3, parse the packet
  messages, decode every rotation to LidarScan + LidarInfo, write the MCAP file (zstd chunks at
  the default level).
- ``zstd:1`` / ``zstd:3`` / ``lz4`` / ``none``: the same with ``--zstd-level 1`` /
  ``--zstd-level 3`` (the ``mcap`` package's level, the default before) /
  ``--chunk-compression lz4`` / ``none``.
- ``--compress``: the default chunks with every LidarScan compressed by lidarscan.codec.
- ``decode``: the decoder alone (``PacketDecoder.push_many`` on the parsed packets of every
  message, no output): the part of ``convert`` the decoders own; the rest is reading, parsing,
  serialising and writing.
- ``rosbags``: read the same bag with rosbags and deserialise every message into Python objects
  (what a Python tool does before any decoding): no decode, no output.

The output size is printed beside each convert candidate.
"""

from __future__ import annotations

import argparse
import calendar
import cProfile
import io
import os
import pstats
import shutil
import sqlite3
import statistics
import struct
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data" / "nebula"

#: name -> (folder, calibration, payload bytes in the message, message carries data[:size])
RECORDINGS = {
    "VLS-128": ("velodyne_vls128", "VLS128.yaml", 1206, False),
    "Pandar64 dual": ("hesai_pandar64", "Pandar64.csv", 1500, True),
}


def _shift_time(buf: bytearray, pos: int, shift_ns: int) -> None:
    sec, nsec = struct.unpack_from("<iI", buf, pos)
    total = sec * 1_000_000_000 + nsec + shift_ns
    struct.pack_into("<iI", buf, pos, total // 1_000_000_000, total % 1_000_000_000)


def _shift_velodyne_clock(buf: bytearray, data: int, shift_ns: int) -> None:
    toh = struct.unpack_from("<I", buf, data + 1200)[0]
    struct.pack_into("<I", buf, data + 1200, (toh + shift_ns // 1000) % 3_600_000_000)


def _shift_hesai_clock(buf: bytearray, data: int, size: int, shift_ns: int) -> None:
    from converters.hesai import detect_format
    fmt = detect_format(bytes(buf[data:data + size]))
    y, mo, d, h, mi, s = buf[data + fmt.datetime_at:data + fmt.datetime_at + 6]
    us = struct.unpack_from("<I", buf, data + fmt.timestamp_at)[0]
    total_us = (calendar.timegm((1900 + y, mo, d, h, mi, s, 0, 0, 0)) * 1_000_000 + us
                + shift_ns // 1000)
    when = time.gmtime(total_us // 1_000_000)
    buf[data + fmt.datetime_at:data + fmt.datetime_at + 6] = bytes(
        (when.tm_year - 1900, when.tm_mon, when.tm_mday, when.tm_hour, when.tm_min,
         when.tm_sec))
    struct.pack_into("<I", buf, data + fmt.timestamp_at, total_us % 1_000_000)


def shift_message(cdr: bytes, shift_ns: int, payload: int, sized: bool) -> tuple[bytes, int]:
    """(A VelodyneScan / PandarScan CDR message (little-endian) moved ``shift_ns`` later:
    header stamp, packet stamps and the packets' own clocks (``shift_ns``: whole us), number
    of packets)."""
    if cdr[:2] != b"\x00\x01":
        raise ValueError("expected little-endian CDR")
    buf = bytearray(cdr)
    _shift_time(buf, 4, shift_ns)
    pos = 12
    pos += 4 + struct.unpack_from("<I", buf, pos)[0]             # frame_id
    pos += -(pos - 4) % 4
    count = struct.unpack_from("<I", buf, pos)[0]
    pos += 4
    for _ in range(count):
        pos += -(pos - 4) % 4
        _shift_time(buf, pos, shift_ns)
        data = pos + 8
        pos = data + payload
        if sized:
            pos += -(pos - 4) % 4
            size = struct.unpack_from("<I", buf, pos)[0]
            pos += 4
            _shift_hesai_clock(buf, data, size, shift_ns)
        else:
            _shift_velodyne_clock(buf, data, shift_ns)
    return bytes(buf), count


def build_bag(name: str, seconds: float, where: Path) -> tuple[Path, float, int, int]:
    """(bag directory, sensor seconds, messages, packets) of a repeated recording."""
    import yaml
    folder, _, payload, sized = RECORDINGS[name]
    source = DATA / folder / "bag"
    bag = where / folder
    bag.mkdir()
    meta = yaml.safe_load((source / "metadata.yaml").read_text())
    info = meta["rosbag2_bagfile_information"]
    db_name = info["relative_file_paths"][0]
    shutil.copy(source / db_name, bag / db_name)
    con = sqlite3.connect(bag / db_name)
    rows = con.execute("SELECT topic_id, timestamp, data FROM messages ORDER BY timestamp"
                       ).fetchall()
    stamps = [r[1] for r in rows]
    period = (stamps[-1] - stamps[0]) // (len(stamps) - 1)
    length = (stamps[-1] - stamps[0] + period) // 1000 * 1000       # whole microseconds
    copies = max(1, round(seconds * 1e9 / length))
    con.execute("DELETE FROM messages")
    # the VLS-128 bag leaves serialization_format empty; rosbags (the baseline) refuses that
    con.execute("UPDATE topics SET serialization_format='cdr' WHERE serialization_format=''")
    packets = 0
    for k in range(copies):
        shift = k * length
        batch = []
        for topic_id, stamp, data in rows:
            moved, count = shift_message(bytes(data), shift, payload, sized)
            batch.append((topic_id, stamp + shift, moved))
            packets += count
        con.executemany("INSERT INTO messages (topic_id, timestamp, data) VALUES (?, ?, ?)",
                        batch)
    con.commit()
    con.close()
    total = copies * length
    count = copies * len(rows)
    info["duration"] = {"nanoseconds": total - period}
    info["message_count"] = count
    for entry in info["topics_with_message_count"]:
        entry["message_count"] = count
        entry["topic_metadata"]["serialization_format"] = "cdr"
    for entry in info.get("files", []):
        entry["duration"] = {"nanoseconds": total - period}
        entry["message_count"] = count
    (bag / "metadata.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
    return bag, total / 1e9, count, packets


#: candidate -> extra ``convert`` options
CONVERTS = {"convert": [], "zstd:1": ["--zstd-level", "1"], "zstd:3": ["--zstd-level", "3"],
            "lz4": ["--chunk-compression", "lz4"], "none": ["--chunk-compression", "none"],
            "--compress": ["--compress"]}


def run_convert(bag: Path, calibration: Path, out: Path, extra: list[str] | None = None) -> None:
    from converters import cli
    out.unlink(missing_ok=True)
    status = cli.main(["convert", str(bag), str(out), "--calibration", str(calibration), "-q",
                       *(extra or [])])
    if status != 0:
        raise RuntimeError(f"lidarscan convert {bag} exited with {status}")


def run_decode(bag: Path, calibration: Path) -> int:
    """The decoder alone on every packet message of the bag (parsed beforehand): scans made."""
    from converters.bags import PACKET_TYPES, open_bag
    batches = [(PACKET_TYPES[m.msgtype][1](m.payload)) for m in open_bag(bag).messages()
               if getattr(m, "msgtype", "") in PACKET_TYPES]
    module = __import__(PACKET_TYPES[_packet_type(bag)][0], fromlist=["PacketDecoder"])
    decoder = module.PacketDecoder(str(calibration), frame_id="lidar")
    count = 0
    with _clock() as spent:
        for packets in batches:
            count += len(decoder.push_many(packets.stamps, packets.payloads))
        count += len(decoder.flush())
    _DECODE_CPU.append(spent[0])
    return count


_DECODE_CPU: list[float] = []


def _packet_type(bag: Path) -> str:
    from converters.bags import PACKET_TYPES, open_bag
    return next(t.msgtype for t in open_bag(bag).topics.values() if t.msgtype in PACKET_TYPES)


class _clock:
    """CPU seconds of the block, in ``[0]`` of the value of ``with``."""

    def __enter__(self) -> list[float]:
        self.spent = [0.0]
        self.t0 = time.process_time()
        return self.spent

    def __exit__(self, *exc: object) -> None:
        self.spent[0] = time.process_time() - self.t0


def run_rosbags(bag: Path) -> int:
    """Read with rosbags and deserialise every message (the Python baseline)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    store = get_typestore(Stores.ROS2_HUMBLE)
    for text, name in (("builtin_interfaces/Time stamp\nuint8[1206] data",
                        "velodyne_msgs/msg/VelodynePacket"),
                       ("std_msgs/Header header\nvelodyne_msgs/VelodynePacket[] packets",
                        "velodyne_msgs/msg/VelodyneScan"),
                       ("builtin_interfaces/Time stamp\nuint8[1500] data\nuint32 size",
                        "pandar_msgs/msg/PandarPacket"),
                       ("std_msgs/Header header\npandar_msgs/PandarPacket[] packets",
                        "pandar_msgs/msg/PandarScan")):
        store.register(get_types_from_msg(text, name))
    count = 0
    with AnyReader([bag], default_typestore=store) as reader:
        for conn, _, raw in reader.messages():
            count += len(reader.deserialize(raw, conn.msgtype).packets)
    return count


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=30.0, help="sensor time per bag")
    parser.add_argument("--repeat", type=int, default=3, help="timed rounds (median)")
    parser.add_argument("--profile", type=int, default=0, metavar="N",
                        help="print the N top cProfile entries (cumulative) of one convert")
    parser.add_argument("--only", choices=sorted(RECORDINGS), action="append")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench_convert_") as tmp:
        where = Path(tmp)
        for name in args.only or RECORDINGS:
            folder, calib, _, _ = RECORDINGS[name]
            start = time.perf_counter()
            bag, sensor_s, messages, packets = build_bag(name, args.seconds, where)
            mb = sum(p.stat().st_size for p in bag.iterdir()) / 1e6
            print(f"{name}: {sensor_s:.1f} s of sensor time, {messages} messages, {packets} "
                  f"packets, {mb:.0f} MB bag (built in {time.perf_counter() - start:.1f} s)")
            out = where / f"{folder}.mcap"
            cal = DATA / folder / calib
            labels = [*CONVERTS, "decode", "rosbags"]
            cpu: dict[str, list[float]] = {label: [] for label in labels}
            sizes: dict[str, int] = {}

            def convert(label: str) -> None:
                run_convert(bag, cal, out, CONVERTS[label])
                sizes[label] = out.stat().st_size

            def decode() -> None:
                run_decode(bag, cal)

            runs = [(label, lambda label=label: convert(label)) for label in CONVERTS] + \
                [("decode", decode), ("rosbags", lambda: run_rosbags(bag))]
            for _ in range(args.repeat):  # interleaved: the machine's load hits all alike
                for label, fn in runs:
                    _DECODE_CPU.clear()
                    c0 = time.process_time()
                    fn()
                    # decode: the decoder's own CPU only (not the parsing before it)
                    cpu[label].append(_DECODE_CPU[0] if label == "decode"
                                      else time.process_time() - c0)
            base = statistics.median(cpu["convert"])
            for label in labels:
                proc = statistics.median(cpu[label])
                size = f"; output {sizes[label] / 1e6:6.1f} MB" if label in sizes else ""
                print(f"  {label:11s} CPU {proc:6.2f} s = {sensor_s / proc:5.1f}x real time "
                      f"(/ convert {proc / base:4.2f}){size}")
            decode_share = statistics.median(cpu["decode"]) / base
            print(f"  split of convert: decode {100 * decode_share:.0f} %, the rest (read, parse, "
                  f"serialise, write) {100 * (1 - decode_share):.0f} %; load average "
                  f"{os.getloadavg()[0]:.1f}")
            if args.profile:
                prof = cProfile.Profile()
                prof.runcall(run_convert, bag, cal, out)
                text = io.StringIO()
                pstats.Stats(prof, stream=text).sort_stats("cumulative").print_stats(args.profile)
                print("\n".join(line for line in text.getvalue().splitlines()[6:] if line))
            shutil.rmtree(bag)
    return 0


if __name__ == "__main__":
    sys.exit(main())
