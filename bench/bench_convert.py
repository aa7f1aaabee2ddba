"""Benchmark: the whole ``lidarscan convert`` of a long raw-packet recording, vs real time.

Run: ``.venv/bin/python bench/bench_convert.py [--seconds S] [--repeat N] [--threads N]
[--base DIR] [--profile N] [--timeline]``. Prints, per recording, the convert time as a
multiple of real time (sensor seconds / seconds) beside baselines measured in the same run,
and optionally the cProfile top entries (of ``--threads 1``). No assertions.
Target (issue "Real sensors in"): >= 20x real time.

Input: the real VLS-128 (single return, 6 250 packets/s) and Pandar64 (dual return) recordings of
``tests/data/nebula`` (0.3-0.4 s each, see their NOTICE files) repeated into one rosbag2 .db3
directory per sensor of about ``--seconds`` of sensor time: a copy of the recording's own .db3
(its schema: topics, metadata tables) whose ``messages`` rows are replaced by the recorded
messages over and over, every copy shifted in time by the recording's length: the bag stamps,
each message's ``header.stamp`` and packet stamps, and the packets' own clocks (Velodyne
microseconds past the hour; Hesai UTC date-time + microseconds) so the decoders see one
continuous recording (with an azimuth jump at each seam). An empty ``serialization_format``
(the VLS-128 bag) is written as "cdr" (rosbags refuses the empty one; ``converters.sources.bags`` reads
both).

Candidates (the bag already on disk, page cache warm, one untimed convert of the small
recording first), timed in interleaved rounds (medians of ``--repeat`` rounds; ratios against
``convert`` in the same round). Each is timed three ways: process CPU (every thread), the main
thread's CPU (``time.thread_time``) and wall; from these the **2-core bound**: sensor seconds /
max(main-thread CPU, CPU / 2, the other threads' CPU / the number of output threads), the
real-time factor the run would reach on 2 free cores (the wall time of a shared machine says
little; the other threads are the output threads and the thread reading the bag ahead):

- ``main``: with ``--base DIR``, the default ``convert`` of the source tree DIR (e.g.
  ``git archive main | tar -x -C DIR`` with the compiled modules copied in) in a child process
  that hides this environment's editable install (start-up and a warm-up run excluded).
- ``convert``: ``converters.edge.cli.main(["convert", BAG, OUT.mcap, "--calibration", FILE, "-q"])``
  in this process (no interpreter start-up), the default options: read the .db3, parse the packet
  messages, decode every rotation to LidarScan + LidarInfo, write the MCAP file (zstd chunks at
  the default level, compressed by two threads beside the main one: ``--threads 3``).
- ``threads:1`` / ``threads:2``: the same in one thread / with one writer thread.
- ``lz4`` / ``none`` / ``none,threads:1``: ``--chunk-compression lz4`` / ``none`` (and in one
  thread).
- with ``--more``: ``zstd:1`` / ``zstd:3`` / ``--compress`` (``--zstd-level 1`` / ``3``, every
  LidarScan compressed by lidarscan.codec).
- ``decode``: the decoder alone (``PacketDecoder.push_many`` on the parsed packets of every
  message, no output): the part of ``convert`` the decoders own; the rest is reading, parsing,
  serialising, compressing and writing.
- ``rosbags``: read the same bag with rosbags and deserialise every message into Python objects
  (what a Python tool does before any decoding): no decode, no output.

Printed after them: the split decode / the rest of ``--threads 1`` and the decoder CPU that 20x
would need, on one core and on 2 free cores with the default threads; then the chunk compression
alone (one thread, medians of 3 interleaved rounds): the records of every chunk of the default
output compressed with the parameters the writer chose for it (level 2, its hash table smaller
for chunks of single-return scans) vs level 2's own parameters for every chunk.

The output size is printed beside each convert candidate. The last round's output file is
removed before a candidate's timing starts (freeing 70 MB of page cache is not part of a
convert; ``--base`` children write a new file too).

With ``--timeline``: one more default ``convert``, its stages timed in whichever thread runs
them (:data:`_STAGES`: reading the rows, waiting for the reading thread, decoder set-up, decode,
writing a message, handing a chunk over, packing and writing a chunk, closing): per thread its
CPU, per stage its wall and CPU; wall above CPU is waiting (a lock, the GIL, the disk, or the
machine's other processes).
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
    from converters.sources.hesai.decoder import detect_format
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
CONVERTS = {"convert": [], "threads:1": ["--threads", "1"], "threads:2": ["--threads", "2"],
            "lz4": ["--chunk-compression", "lz4"],
            "none": ["--chunk-compression", "none"],
            "none,threads:1": ["--chunk-compression", "none", "--threads", "1"]}
#: more candidates with ``--more``
MORE = {"zstd:1": ["--zstd-level", "1"], "zstd:3": ["--zstd-level", "3"],
        "--compress": ["--compress"]}


#: ``convert --threads`` default
DEFAULT_THREADS = 3


def _threads(options: list[str]) -> int:
    return int(options[options.index("--threads") + 1]) if "--threads" in options \
        else DEFAULT_THREADS


def run_convert(bag: Path, calibration: Path, out: Path, extra: list[str] | None = None) -> None:
    from converters.edge import cli
    out.unlink(missing_ok=True)
    status = cli.main(["convert", str(bag), str(out), "--calibration", str(calibration), "-q",
                       *(extra or [])])
    if status != 0:
        raise RuntimeError(f"lidarscan convert {bag} exited with {status}")


#: the child that times another tree's ``convert`` (``--base``): its editable install is
#: hidden so that the tree given wins; one untimed run on the small recording first (imports,
#: cached kernels), then the timed one; prints [process CPU, main-thread CPU, wall]
_BASE_CHILD = """
import json, sys, time
sys.meta_path[:] = [f for f in sys.meta_path if "editable" not in repr(f)]
sys.path.insert(0, sys.argv[1])
from converters.edge import cli
warm, timed = json.loads(sys.argv[2]), json.loads(sys.argv[3])
assert cli.main(["convert", *warm, "-q"]) == 0
c0, t0, w0 = time.process_time(), time.thread_time(), time.perf_counter()
assert cli.main(["convert", *timed, "-q"]) == 0
print(json.dumps([time.process_time() - c0, time.thread_time() - t0, time.perf_counter() - w0]))
"""


def run_base(base: Path, folder: str, bag: Path, calibration: Path, out: Path
             ) -> tuple[float, float, float]:
    """(process CPU, main-thread CPU, wall) of the default ``convert`` of the tree ``base``
    (e.g. ``git archive main``), in a child process, start-up excluded."""
    import json
    import subprocess
    out.unlink(missing_ok=True)
    small = [str(DATA / folder / "bag"), str(out.with_suffix(".warm.mcap")),
             "--calibration", str(calibration)]
    timed = [str(bag), str(out), "--calibration", str(calibration)]
    done = subprocess.run([sys.executable, "-c", _BASE_CHILD, str(base), json.dumps(small),
                           json.dumps(timed)], check=True, capture_output=True, text=True,
                          cwd=tempfile.gettempdir())
    cpu, main_cpu, wall = json.loads(done.stdout.strip().splitlines()[-1])
    return float(cpu), float(main_cpu), float(wall)


def run_decode(bag: Path, calibration: Path) -> int:
    """The decoder alone on every packet message of the bag (parsed beforehand): scans made
    (dataclasses, as ``convert`` asks for)."""
    from converters.sources.bags import PACKET_TYPES, open_bag
    batches = [(PACKET_TYPES[m.msgtype][1](m.payload)) for m in open_bag(bag).messages()
               if getattr(m, "msgtype", "") in PACKET_TYPES]
    module = __import__(PACKET_TYPES[_packet_type(bag)][0], fromlist=["PacketDecoder"])
    decoder = module.PacketDecoder(str(calibration), frame_id="lidar", as_dataclass=True)
    count = 0
    with _clock() as spent:
        for packets in batches:
            count += len(decoder.push_many(packets.stamps, packets.payloads))
        count += len(decoder.flush())
    _DECODE_CPU.append(spent[0])
    return count


_DECODE_CPU: list[float] = []


def _packet_type(bag: Path) -> str:
    from converters.sources.bags import PACKET_TYPES, open_bag
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


def chunk_compression(out: Path, bag: Path, calibration: Path, rounds: int = 3) -> None:
    """Print the CPU and bytes of the default output's chunks compressed as the writer chose
    (told by which compressor gives the stored frame) vs with level 2's own parameters."""
    import zstandard
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    from lidarscan._mcapfile import _compressor

    run_convert(bag, calibration, out)
    with open(out, "rb") as stream:
        frames = [r.data for r in StreamReader(stream, emit_chunks=True).records
                  if isinstance(r, Chunk) and r.compression == "zstd"]
    records = [zstandard.ZstdDecompressor().decompress(f) for f in frames]
    level2, small = _compressor("zstd", 2)[1], _compressor("zstd", None, True)[1]
    chosen = [small if small(r) == f else level2 for r, f in zip(records, frames)]
    spent: dict[str, list[float]] = {"chosen": [], "level 2": []}
    size: dict[str, int] = {}
    for _ in range(rounds):
        for label, fns in (("chosen", chosen), ("level 2", [level2] * len(records))):
            c0 = time.process_time()
            size[label] = sum(len(fn(r)) for fn, r in zip(fns, records))
            spent[label].append(time.process_time() - c0)
    cpu = {label: statistics.median(v) for label, v in spent.items()}
    print(f"  chunk compression alone ({len(records)} chunks, "
          f"{sum(map(len, records)) / 1e6:.1f} MB, {sum(c is small for c in chosen)} with the "
          f"small hash table): as chosen {cpu['chosen']:.2f} s, {size['chosen'] / 1e6:.1f} MB; "
          f"level 2's own {cpu['level 2']:.2f} s, {size['level 2'] / 1e6:.1f} MB "
          f"(chosen / level 2: CPU {cpu['chosen'] / cpu['level 2']:.2f}, bytes "
          f"{size['chosen'] / size['level 2']:.3f})")


#: (module, attribute, stage) timed by ``--timeline``: where each thread spends its time
_STAGES = [
    ("converters.sources.bags.Bag", "messages", "read (sqlite rows)"),
    ("converters.edge.cli._common._Input", "items", "wait for the reading thread"),
    ("converters.sources.velodyne.decoder.PacketDecoder", "__init__", "decoder set-up"),
    ("converters.sources.velodyne.decoder.PacketDecoder", "push_many", "decode"),
    ("converters.sources.hesai.decoder.PacketDecoder", "__init__", "decoder set-up"),
    ("converters.sources.hesai.decoder.PacketDecoder", "push_many", "decode"),
    ("lidarscan.mcap.McapWriter", "write", "write (serialise, queue)"),
    ("lidarscan.mcap.McapWriter", "close", "close (drain, summary)"),
    ("lidarscan._mcapfile.ChunkedMcapWriter", "_finish_chunk", "hand a chunk over"),
    ("lidarscan._mcapfile.ChunkedMcapWriter", "_pack", "pack (join, CRC, compress)"),
    ("lidarscan._mcapfile.ChunkedMcapWriter", "_write_chunk", "write a chunk to the file"),
]


def timeline(bag: Path, calibration: Path, out: Path, sensor_s: float) -> None:
    """One default ``convert`` with the stages of :data:`_STAGES` timed in whichever thread
    runs them (wall by ``perf_counter``, CPU by ``thread_time``; generators per item): per
    thread its CPU and per stage its wall and CPU. Wall well above CPU in a stage is waiting
    (a lock, the GIL, I/O, or this machine's other processes)."""
    import collections
    import contextlib
    import importlib
    import inspect
    import threading

    spent: dict[tuple[str, str], list[float]] = collections.defaultdict(lambda: [0, 0.0, 0.0])
    threads: dict[str, float] = collections.defaultdict(float)
    lock = threading.Lock()

    def account(stage: str, w0: float, c0: float) -> None:
        name = threading.current_thread().name.rstrip("0123456789_").removesuffix("-")
        with lock:
            entry = spent[(name, stage)]
            entry[0] += 1
            entry[1] += time.perf_counter() - w0
            entry[2] += time.thread_time() - c0

    def timed(fn, stage):  # type: ignore[no-untyped-def]
        if inspect.isgeneratorfunction(fn):
            def each(*a, **k):  # type: ignore[no-untyped-def]
                items = fn(*a, **k)
                while True:
                    w0, c0 = time.perf_counter(), time.thread_time()
                    try:
                        item = next(items)
                    except StopIteration:
                        return
                    finally:
                        account(stage, w0, c0)
                    yield item
            return each

        def call(*a, **k):  # type: ignore[no-untyped-def]
            w0, c0 = time.perf_counter(), time.thread_time()
            try:
                return fn(*a, **k)
            finally:
                account(stage, w0, c0)
        return call

    run = threading.Thread.run

    def counted(self):  # type: ignore[no-untyped-def]
        c0 = time.thread_time()
        try:
            run(self)
        finally:
            with lock:
                threads[self.name.rstrip("0123456789_").removesuffix("-")] += \
                    time.thread_time() - c0

    with contextlib.ExitStack() as undo:
        for where, attr, stage in _STAGES:
            module, _, cls = where.rpartition(".")
            try:
                owner = getattr(importlib.import_module(module), cls)
            except (ImportError, AttributeError):
                continue
            original = owner.__dict__[attr]
            undo.callback(setattr, owner, attr, original)
            setattr(owner, attr, timed(original, stage))
        undo.callback(setattr, threading.Thread, "run", run)
        threading.Thread.run = counted  # type: ignore[method-assign]
        out.unlink(missing_ok=True)
        c0, t0, w0 = time.process_time(), time.thread_time(), time.perf_counter()
        run_convert(bag, calibration, out)
        cpu, main_cpu, wall = (time.process_time() - c0, time.thread_time() - t0,
                               time.perf_counter() - w0)
    print(f"  timeline of one convert (load {os.getloadavg()[0]:.1f}): wall {wall:.3f} s = "
          f"{sensor_s / wall:.1f}x, CPU {cpu:.3f} s; per thread CPU: MainThread {main_cpu:.3f} s"
          + "".join(f", {name} {value:.3f} s" for name, value in sorted(threads.items())))
    for (name, stage), (count, stage_wall, stage_cpu) in sorted(spent.items()):
        print(f"    {name:18s} {stage:30s} x{count:<5d} wall {stage_wall:6.3f} s, "
              f"CPU {stage_cpu:6.3f} s")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=30.0, help="sensor time per bag")
    parser.add_argument("--repeat", type=int, default=3, help="timed rounds (median)")
    parser.add_argument("--profile", type=int, default=0, metavar="N",
                        help="print the N top cProfile entries (cumulative) of one convert "
                             "--threads 1")
    parser.add_argument("--only", choices=sorted(RECORDINGS), action="append")
    parser.add_argument("--threads", type=int, action="append", metavar="N",
                        help="only convert --threads N (repeatable; N = 3 is the default "
                             "'convert'); default: every candidate")
    parser.add_argument("--timeline", action="store_true",
                        help="also time the stages of one default convert per thread")
    parser.add_argument("--more", action="store_true",
                        help="also --zstd-level 1 and 3 and --compress")
    parser.add_argument("--base", type=Path, metavar="DIR",
                        help="also time the default convert of the source tree DIR (e.g. "
                             "`git archive main | tar -x -C DIR`, compiled modules copied in) "
                             "in a child process: the 'before' of a change")
    args = parser.parse_args(argv)
    converts = {**CONVERTS, **(MORE if args.more else {})}
    if args.threads:
        converts = {"convert" if t == DEFAULT_THREADS else f"threads:{t}":
                    ["--threads", str(t)] for t in args.threads}
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
            labels = [*(["main"] if args.base else []), *converts, "decode", "rosbags"]
            # label -> [(process CPU, main-thread CPU, wall)] per round
            times: dict[str, list[tuple[float, float, float]]] = {label: [] for label in labels}
            sizes: dict[str, int] = {}

            def convert(label: str) -> None:
                run_convert(bag, cal, out, converts[label])
                sizes[label] = out.stat().st_size

            runs = [(label, lambda label=label: convert(label)) for label in converts] + \
                [("decode", lambda: run_decode(bag, cal)), ("rosbags", lambda: run_rosbags(bag))]
            run_convert(DATA / folder / "bag", cal, out)   # imports, cached kernels: untimed
            loads = []
            for _ in range(args.repeat):  # interleaved: the machine's load hits all alike
                if args.base:
                    times["main"].append(run_base(args.base, folder, bag, cal, out))
                    sizes["main"] = out.stat().st_size
                for label, fn in runs:
                    _DECODE_CPU.clear()
                    out.unlink(missing_ok=True)  # freeing the last output: not timed (as main's)
                    c0, t0, w0 = time.process_time(), time.thread_time(), time.perf_counter()
                    fn()
                    cpu, main_cpu = time.process_time() - c0, time.thread_time() - t0
                    if label == "decode":   # the decoder's own CPU only (not the parsing)
                        cpu = main_cpu = _DECODE_CPU[0]
                    times[label].append((cpu, main_cpu, time.perf_counter() - w0))
                loads.append(os.getloadavg()[0])
            med = {label: [statistics.median(t[k] for t in times[label]) for k in range(3)]
                   for label in labels}
            base = med["convert" if "convert" in med else labels[0]][0]
            print(f"  load average {min(loads):.1f}-{max(loads):.1f} on {os.cpu_count()} cores; "
                  f"medians of {args.repeat} interleaved rounds; x = sensor seconds / seconds")
            for label in labels:
                cpu, main_cpu, wall = med[label]
                size = f"; {sizes[label] / 1e6:6.1f} MB" if label in sizes else ""
                # on 2 free cores a run takes at least its CPU / 2, its main thread's CPU,
                # and its output threads' CPU / their number
                # (main: the base tree's default convert, 3 threads too since e404878)
                helpers = _threads(converts.get(label, [])) - 1
                bound = max(main_cpu, cpu / 2, (cpu - main_cpu) / max(helpers, 1))
                print(f"  {label:15s} CPU {cpu:6.2f} s = {sensor_s / cpu:5.1f}x (/ convert "
                      f"{cpu / base:4.2f}); main thread {main_cpu:5.2f} s; 2-core bound "
                      f"{sensor_s / bound:5.1f}x; wall {wall:6.2f} s = {sensor_s / wall:5.1f}x"
                      f"{size}")
            if "threads:1" in med and "decode" in med:
                one, dec = med["threads:1"][0], med["decode"][0]
                print(f"  split of convert --threads 1: decode {100 * dec / one:.0f} %, the rest "
                      f"(read, parse, serialise, compress, write) {100 * (1 - dec / one):.0f} %; "
                      f"20x on one core needs decode <= {sensor_s / 20 - (one - dec):.2f} s")
            if "convert" in med and "decode" in med:
                cpu, main_cpu, _ = med["convert"]
                dec = med["decode"][0]
                # the 2-core bound of convert is 20x when main <= T/20 and CPU / 2 <= T/20
                need = min(sensor_s / 20 - (main_cpu - dec), sensor_s / 10 - (cpu - dec))
                print(f"  convert ({DEFAULT_THREADS} threads): main thread {main_cpu:.2f} s "
                      f"(decode {dec:.2f} s, the rest {main_cpu - dec:.2f} s), output threads "
                      f"{cpu - main_cpu:.2f} s; 20x on 2 free cores needs decode <= "
                      f"{need:.2f} s ({dec / max(need, 1e-9):.1f}x faster)" if need > 0 else
                      "  convert: 20x on 2 free cores is out of reach whatever the decoder")
            chunk_compression(out, bag, cal)
            if args.timeline:
                timeline(bag, cal, out, sensor_s)
            if args.profile:
                prof = cProfile.Profile()
                prof.runcall(run_convert, bag, cal, out, ["--threads", "1"])
                text = io.StringIO()
                pstats.Stats(prof, stream=text).sort_stats("cumulative").print_stats(args.profile)
                print("\n".join(line for line in text.getvalue().splitlines()[6:] if line))
            shutil.rmtree(bag)
    return 0


if __name__ == "__main__":
    sys.exit(main())
