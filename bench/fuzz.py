"""Long fuzz run over every decoder and validator: only the project's own exceptions may escape.

Each target turns a seeded random generator into one malformed input (mutated CDR bytes, a
message dataclass with inconsistent fields, a mutated MCAP file, mutated Ouster metadata, ...)
and drives it through the code a user would run on it (decode, validate, project, convert).
A case FAILS when it

* raises anything that is not a :class:`lidarscan.errors.LidarScanError` ("crash"),
* runs longer than ``--timeout`` CPU seconds ("hang", interrupted with SIGPROF: CPU time, so a
  busy machine does not fake a hang; a warm-up runs first so imports are not counted), or
* allocates more than ``--max-alloc-mb`` at its peak (tracemalloc; numpy reports its buffers)
  ("memory": e.g. a declared size larger than the payload that got allocated).

Every case is reproducible from (``--seed``, target, case number): ``--target T --case N``
replays one case and prints its traceback. Failing inputs are saved to ``--out``.

Usage::

    .venv/bin/python bench/fuzz.py                        # 100k cases over all targets
    .venv/bin/python bench/fuzz.py --cases 20000 --targets scan_cdr,mcap,mcap_chunks
    .venv/bin/python bench/fuzz.py --target mcap --case 1234   # replay one case

Prints, per target: cases, cases accepted (no exception), the exception types seen with counts,
the failures, the slowest case and the largest per-case allocation; then the max RSS.
"""

from __future__ import annotations

import argparse
import collections
import copy
import dataclasses
import functools
import importlib
import io
import json
import math
import os
import platform
import random
import resource
import signal
import struct
import sys
import time
import traceback
import tracemalloc
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

import lidarscan as ls
from lidarscan import types as lt
from lidarscan.errors import LidarScanError

ROOT = Path(__file__).resolve().parents[1]
H, W = 4, 8


class CaseTimeout(BaseException):
    """Raised by SIGPROF inside a case that ran too long (BaseException: not caught by code)."""


# ---------------------------------------------------------------------------- seed inputs

def seed_info() -> Any:
    """A small valid LidarInfo using every optional array (so mutations reach every field)."""
    return ls.make_info(
        stamp_ns=1_500_000_000, frame_id="lidar",
        vertical_angles=np.radians([15.0, 5.0, -5.0, -15.0]),
        horizontal_angles=2 * np.pi * (1 - np.arange(W) / W),
        beam_azimuth_offsets=np.radians([1.0, -1.0, 1.0, -1.0]),
        beam_origins=np.tile([0.015, 0.0, 0.0], H), beam_range_offsets=np.full(H, -0.015),
        pixel_shift_by_row=[3, 2, 1, 0], beam_time_offsets=[0, 10, 20, 30],
        beam_ids=[3, 2, 1, 0], column_time_increment=1000, range_multiplier=0.001,
        range_min=0.1, range_max=100.0, vendor="v", model="m", as_dataclass=True)


def seed_scan(info: Any, stamp_ns: int = 2_000_000_000, value: float = 5.0) -> Any:
    """A valid scan for ``info`` with float, integer and multi-count channels."""
    rng = np.random.default_rng(int(stamp_ns) % 1000)
    return ls.make_scan(info, {
        "range": rng.uniform(0.5, value * 2, (H, W)).astype(np.float32),
        "intensity": rng.integers(0, 2**16, (H, W), dtype=np.uint16),
        "range2": rng.integers(0, 2**20, (H, W), dtype=np.uint32),
        "flags": rng.integers(0, 255, (H, W, 2), dtype=np.uint8),
    }, stamp_ns, column_time_offsets=np.arange(W) * 1000,
        column_azimuth_angles=2 * np.pi * (1 - np.arange(W) / W), as_dataclass=True)


INTERESTING_U32 = [0, 1, 2, 3, 4, 7, 8, 0x7F, 0x80, 0xFF, 0x100, 0xFFFF, 0x10000, 0x7FFFFFFF,
                   0x80000000, 0xFFFFFFFE, 0xFFFFFFFF]
INTERESTING_F64 = [math.nan, math.inf, -math.inf, 0.0, -0.0, 1e308, -1e308, 5e-324, 1e-300]
INTERESTING_INTS = [0, -1, 1, 2, 3, 7, 8, 255, 256, 65535, 2**31 - 1, 2**31, -(2**31), 2**32 - 1,
                    2**32, 2**63 - 1, -(2**63), 10**12]


def mutate_bytes(rnd: random.Random, data: bytes) -> bytes:
    """One of: truncate, bit flips, byte overwrite, interesting u32/f64 at random/aligned
    offsets, insert or delete a range, duplicate a range, append junk."""
    buf = bytearray(data)
    kind = rnd.randrange(9)
    if kind == 0 or not buf:
        return bytes(buf[:rnd.randrange(len(buf) + 1)])
    if kind == 1:
        for _ in range(rnd.randint(1, 8)):
            pos = rnd.randrange(len(buf))
            buf[pos] ^= 1 << rnd.randrange(8)
    elif kind == 2:
        for _ in range(rnd.randint(1, 4)):
            buf[rnd.randrange(len(buf))] = rnd.randrange(256)
    elif kind in (3, 4) and len(buf) >= 8:
        for _ in range(rnd.randint(1, 3)):
            pos = rnd.randrange(len(buf) - 4)
            if kind == 3:
                pos -= pos % 4
            struct.pack_into("<I", buf, pos, rnd.choice(INTERESTING_U32))
    elif kind == 5 and len(buf) >= 12:
        pos = rnd.randrange(len(buf) - 8)
        pos -= pos % 8
        struct.pack_into("<d", buf, min(pos + 4, len(buf) - 8), rnd.choice(INTERESTING_F64))
    elif kind == 6:
        start = rnd.randrange(len(buf))
        del buf[start:start + rnd.randint(1, 16)]
    elif kind == 7:
        start = rnd.randrange(len(buf))
        piece = buf[start:start + rnd.randint(1, 32)]
        at = rnd.randrange(len(buf) + 1)
        buf[at:at] = piece
    else:
        buf += bytes(rnd.randrange(256) for _ in range(rnd.randint(1, 64)))
    return bytes(buf)


# --------------------------------------------------------------------------- exercise code

_ENTRY_POINTS = {
    "to_pointcloud2": ("converters.pointcloud2", "to_pointcloud2"),
    "from_pointcloud2": ("converters.pointcloud2", "from_pointcloud2"),
    "to_laserscan": ("converters.laserscan", "to_laserscan"),
    "merger": ("converters.merger", None),
    "info_from_metadata": ("converters.ouster", "info_from_metadata"),
    "from_laserscan_sweep": ("converters.sweep", "from_laserscan_sweep"),
}
MISSING: dict[str, str] = {}


def _converters() -> dict[str, Any]:
    """Converter entry points that exist now (the converters are written in parallel)."""
    found: dict[str, Any] = {}
    for key, (module_name, attr) in _ENTRY_POINTS.items():
        try:
            module = importlib.import_module(module_name)
        except Exception as err:  # noqa: BLE001 - absent or broken module: target skipped
            MISSING[key] = f"{type(err).__name__}: {err}"
            continue
        value = module if attr is None else getattr(module, attr, None)
        if value is None:
            MISSING[key] = f"{module_name}.{attr} not found"
        else:
            found[key] = value
    return found


CONV: dict[str, Any] = {}


DEEP = {"on": True}  # run the converters too (set per case: they are slow)


def exercise_scan(scan: Any, info: Any) -> str:
    """Validate a (possibly bad) scan; if it passes, read every channel, project, convert."""
    ls.validate(scan)
    for desc in scan.channels:
        ls.channel(scan, desc.name)
    ls.validate(scan, info)
    ls.range_m(scan, info)
    projector = ls.make_projector(info)
    projector.project(scan, info)
    projector.pixel_times(scan)
    if not DEEP["on"]:
        return "projected"
    if "to_pointcloud2" in CONV:
        cloud = CONV["to_pointcloud2"](scan, info)
        if "from_pointcloud2" in CONV:
            CONV["from_pointcloud2"](cloud)
    if "to_laserscan" in CONV:
        CONV["to_laserscan"](scan, info, min_height=-0.5, max_height=0.5)
    return "converted"


def exercise_info(info: Any) -> str:
    ls.validate_info(info)
    projector = ls.make_projector(info)
    projector.xyz(np.ones((int(info.height), int(info.width)), np.float32))
    return "projected"


# ---------------------------------------------------------------------------------- targets

class Target:
    name = ""
    needs: tuple[str, ...] = ()

    def setup(self) -> None:
        pass

    def case(self, rnd: random.Random) -> tuple[bytes | str, Callable[[], str]]:
        """(input to save if it fails, the call to run)."""
        raise NotImplementedError


class ScanCdr(Target):
    """LidarScan CDR bytes: truncated at every length, bit flips, huge counts, NaN angles."""
    name = "scan_cdr"

    def setup(self) -> None:
        self.info = seed_info()
        self.payload = ls.encode(seed_scan(self.info))

    def case(self, rnd: random.Random) -> tuple[bytes, Callable[[], str]]:
        if rnd.random() < 0.1:  # every truncation length gets visited over a long run
            data = self.payload[:rnd.randrange(len(self.payload))]
        else:
            data = mutate_bytes(rnd, self.payload)
            if rnd.random() < 0.3:
                data = mutate_bytes(rnd, data)
        return data, lambda: exercise_scan(ls.decode_scan(data), self.info)


class InfoCdr(Target):
    """LidarInfo CDR bytes, mutated the same way, then validated and projected."""
    name = "info_cdr"

    def setup(self) -> None:
        self.payload = ls.encode(seed_info())

    def case(self, rnd: random.Random) -> tuple[bytes, Callable[[], str]]:
        if rnd.random() < 0.1:
            data = self.payload[:rnd.randrange(len(self.payload))]
        else:
            data = mutate_bytes(rnd, self.payload)
            if rnd.random() < 0.3:
                data = mutate_bytes(rnd, data)

        def run() -> str:
            info = ls.decode_info(data)
            exercise_info(info)
            return exercise_scan(seed_scan(info) if _fits(info) else seed_scan(seed_info()), info)
        return data, run


def _fits(info: Any) -> bool:
    return (int(info.height), int(info.width)) == (H, W)


def _rand_array(rnd: random.Random, n: int, dtype: Any) -> np.ndarray[Any, Any]:
    kind = np.dtype(dtype).kind
    if kind == "f":
        arr = np.array([rnd.uniform(-10, 10) for _ in range(n)], dtype)
        for _ in range(rnd.randint(0, 2)):
            if n:
                arr[rnd.randrange(n)] = rnd.choice(INTERESTING_F64)
        return arr
    info = np.iinfo(dtype)
    return np.array([rnd.choice([0, 1, info.max, info.min, rnd.randint(info.min, info.max)])
                     for _ in range(n)], dtype)


class ScanFields(Target):
    """LidarScan dataclasses with inconsistent fields: zero/negative/huge sizes, overlapping or
    out-of-range channels, unknown datatypes, wrong per-column array lengths, NaN azimuths."""
    name = "scan_fields"

    def setup(self) -> None:
        self.info = seed_info()
        self.scan = seed_scan(self.info)

    def case(self, rnd: random.Random) -> tuple[str, Callable[[], str]]:
        scan = self.scan
        changes: dict[str, Any] = {}
        for _ in range(rnd.randint(1, 3)):
            what = rnd.randrange(8)
            if what == 0:
                changes[rnd.choice(["height", "width"])] = rnd.choice(INTERESTING_INTS)
            elif what in (1, 2, 3):
                chans = list(changes.get("channels", scan.channels))
                i = rnd.randrange(len(chans))
                field = rnd.choice(["offset", "datatype", "count", "name"])
                value: Any = {"offset": rnd.choice(INTERESTING_INTS + [8, 24, 40, 64]),
                              "datatype": rnd.choice([0, 9, 255, -1, 1, 2, 7, 8]),
                              "count": rnd.choice([0, -1, 1, 2, 3, 2**31]),
                              "name": rnd.choice(["", "range", "intensity", "x" * 300])}[field]
                if field == "offset" and rnd.random() < 0.5:  # overlap another block
                    value = int(chans[rnd.randrange(len(chans))].offset) + rnd.choice([0, 1, 4])
                chans[i] = dataclasses.replace(chans[i], **{field: value})
                if rnd.random() < 0.2:
                    chans.append(copy.copy(chans[i]))
                changes["channels"] = tuple(chans)
            elif what == 4:
                data = np.asarray(scan.data)
                cut = rnd.randrange(len(data) + 16)
                changes["data"] = np.concatenate([data, np.zeros(16, np.uint8)])[:cut].copy()
            elif what == 5:
                changes["column_time_offsets"] = _rand_array(rnd, rnd.choice([0, 1, W - 1, W,
                                                                              W + 1]), np.int64)
            elif what == 6:
                changes["column_azimuth_angles"] = _rand_array(rnd, rnd.choice([0, 1, W, W + 1]),
                                                               np.float64)
            else:
                changes[rnd.choice(["header", "lidar_info_time"])] = \
                    lt.Header(lt.Time(rnd.choice(INTERESTING_INTS), rnd.choice(INTERESTING_INTS)),
                              "lidar") if rnd.random() < 0.5 else \
                    lt.Time(rnd.choice(INTERESTING_INTS), rnd.choice(INTERESTING_INTS))
        if "header" in changes and not isinstance(changes["header"], lt.Header):
            changes["header"] = lt.Header(changes["header"], "lidar")
        if "lidar_info_time" in changes and isinstance(changes["lidar_info_time"], lt.Header):
            changes["lidar_info_time"] = changes["lidar_info_time"].stamp
        bad = dataclasses.replace(scan, **changes)

        def run() -> str:
            result = exercise_scan(bad, self.info)
            payload = ls.encode(bad)  # EncodeError for values that do not fit their CDR type
            exercise_scan(ls.decode_scan(payload), self.info)
            return result
        return repr(changes)[:4000], run


class InfoFields(Target):
    """LidarInfo dataclasses with NaN/Inf angles, wrong lengths, zero/huge sizes, bad transforms,
    negative multipliers or limits."""
    name = "info_fields"

    ARRAYS: ClassVar[dict[str, Any]] = {"vertical_angles": np.float64, "horizontal_angles": np.float64,
              "beam_azimuth_offsets": np.float64, "pixel_azimuth_angles": np.float64,
              "pixel_altitude_angles": np.float64, "beam_origins": np.float64,
              "beam_range_offsets": np.float64, "lidar_to_sensor_transform": np.float64,
              "pixel_shift_by_row": np.int32, "beam_time_offsets": np.int64,
              "beam_ids": np.uint16}

    def setup(self) -> None:
        self.info = seed_info()

    def case(self, rnd: random.Random) -> tuple[str, Callable[[], str]]:
        changes: dict[str, Any] = {}
        for _ in range(rnd.randint(1, 3)):
            what = rnd.randrange(5)
            if what == 0:
                changes[rnd.choice(["height", "width"])] = rnd.choice([0, 1, 3, 5, 2**31, 2**32 - 1,
                                                                       -1])
            elif what in (1, 2):
                name = rnd.choice(list(self.ARRAYS))
                current = np.asarray(getattr(self.info, name))
                n = rnd.choice([0, 1, current.size, current.size - 1, current.size + 1, H * W,
                                3 * H, 16])
                changes[name] = _rand_array(rnd, max(n, 0), self.ARRAYS[name])
                if rnd.random() < 0.5 and n == current.size:
                    arr = np.array(current, dtype=self.ARRAYS[name])
                    if arr.size and arr.dtype.kind == "f":
                        arr[rnd.randrange(arr.size)] = rnd.choice(INTERESTING_F64)
                    changes[name] = arr
            elif what == 3:
                changes[rnd.choice(["range_multiplier", "range_offset", "range_min",
                                    "range_max"])] = rnd.choice(INTERESTING_F64 + [-1.0, 1.0])
            else:
                changes["column_time_increment"] = rnd.choice(INTERESTING_INTS)
        bad = dataclasses.replace(self.info, **changes)

        def run() -> str:
            exercise_info(bad)
            exercise_scan(seed_scan(bad) if _fits(bad) else seed_scan(self.info), bad)
            payload = ls.encode(bad)
            return exercise_info(ls.decode_info(payload))
        return repr(changes)[:4000], run


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
        self.tmp = ROOT / "build" / "fuzz" / f"mcap-case-{os.getpid()}.mcap"
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
    """VelodyneScan / PandarScan CDR (converters.bags): mutated, truncated, huge counts; only
    DecodeError may escape and every payload lies inside the message."""
    name = "packet_cdr"

    def setup(self) -> None:
        from converters import bags
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
        path = ROOT / "build" / "fuzz" / f"bag-seed-{os.getpid()}.db3"
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
        self.tmp = ROOT / "build" / "fuzz" / f"bag-case-{os.getpid()}.db3"

    def case(self, rnd: random.Random) -> tuple[bytes, Callable[[], str]]:
        from converters import bags
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


def _metadata_seed() -> dict[str, Any]:
    path = ROOT / "converters" / "data" / "2_0_0_os1-992008000494-128_col_win_legacy.json"
    meta: dict[str, Any] = json.loads(path.read_text())
    return meta


def _json_paths(node: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    out = [prefix] if prefix else []
    if isinstance(node, dict):
        for key, value in node.items():
            out += _json_paths(value, prefix + (key,))
    elif isinstance(node, list) and len(node) <= 16:
        for i, value in enumerate(node):
            out += _json_paths(value, prefix + (i,))
    return out


def mutate_json(rnd: random.Random, data: Any) -> Any:
    """Delete a key, change a value's type, length or value (NaN, Inf, huge, negative)."""
    data = copy.deepcopy(data)
    paths = _json_paths(data)
    for _ in range(rnd.randint(1, 3)):
        path = rnd.choice(paths)
        parent = data
        try:
            for key in path[:-1]:
                parent = parent[key]
            value = parent[path[-1]]
        except (KeyError, IndexError, TypeError):
            continue
        if not isinstance(parent, (dict, list)):  # an earlier mutation replaced a container
            continue
        kind = rnd.randrange(6)
        if kind == 0 and isinstance(parent, dict):
            del parent[path[-1]]
            continue
        if kind == 1:
            new: Any = rnd.choice([None, "", "x", "1024x10", "0x0", "99999999x1", [], {}, True,
                                   -1, 0, 2**31, 10**12, 1e308, math.nan, math.inf, 0.5])
        elif kind == 2 and isinstance(value, list):
            new = value[:rnd.randrange(len(value) + 1)] if rnd.random() < 0.5 else value + value
        elif kind == 3 and isinstance(value, list) and value:
            new = list(value)
            new[rnd.randrange(len(new))] = rnd.choice([math.nan, math.inf, -math.inf, None, "a",
                                                       [1, 2], 1e308])
        elif kind == 4 and isinstance(value, (int, float)) and not isinstance(value, bool):
            new = rnd.choice([value * -1, value * 1000, 0, value + 1, 2**40, math.nan])
        else:
            new = rnd.choice([str(value), [value], {"v": value}])
        parent[path[-1]] = new
    return data


class OusterJson(Target):
    """Ouster metadata: structural mutations of the shipped JSON, or byte mutations of its text."""
    name = "ouster_json"
    needs = ("info_from_metadata",)

    def setup(self) -> None:
        self.meta = _metadata_seed()
        self.text = json.dumps(self.meta)

    def case(self, rnd: random.Random) -> tuple[str, Callable[[], str]]:
        convert = CONV["info_from_metadata"]
        if rnd.random() < 0.75:
            text = json.dumps(mutate_json(rnd, self.meta))  # NaN/Infinity stay valid JSON here
        else:
            raw = mutate_bytes(rnd, self.text.encode())
            text = raw.decode("utf-8", errors="replace")
            if not text.lstrip().startswith("{"):
                text = "{" + text  # a str not starting with "{" is taken as a path

        def run() -> str:
            info = convert(text, stamp_ns=1, as_dataclass=True)
            ls.validate_info(info)
            return "converted"
        return text, run


class PointCloud2Input(Target):
    """PointCloud2 dataclasses with inconsistent fields into from_pointcloud2."""
    name = "pointcloud2"
    needs = ("from_pointcloud2",)

    def setup(self) -> None:
        self.cls = lt.message_class("sensor_msgs/msg/PointCloud2")
        self.field_cls = lt.message_class("sensor_msgs/msg/PointField")

    def case(self, rnd: random.Random) -> tuple[str, Callable[[], str]]:
        rows = rnd.choice([1, 2, 4, 16])
        n = rnd.choice([0, 1, 2, 7, 64])
        organized = rnd.random() < 0.5
        height, width = (rows, n) if organized else (1, rows * n)
        fields = [self.field_cls(name=name, offset=off, datatype=dt, count=1)
                  for name, off, dt in (("x", 0, 7), ("y", 4, 7), ("z", 8, 7),
                                        ("intensity", 12, 7), ("ring", 16, 4), ("t", 20, 6))]
        if rnd.random() < 0.3:
            fields.pop(rnd.choice([3, 4, 5]))
        point_step = 24
        pts = np.zeros((rows, n), np.dtype({"names": ["x", "y", "z", "i", "ring", "t"],
                                           "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<u4"],
                                           "offsets": [0, 4, 8, 12, 16, 20], "itemsize": 24}))
        az = np.linspace(0, 2 * np.pi, max(n, 1), endpoint=False)[:n]
        el = np.linspace(0.2, -0.2, rows)[:, None]
        r = np.array([[rnd.uniform(1, 50) for _ in range(n)] for _ in range(rows)])
        pts["x"] = r * np.cos(el) * np.cos(az)
        pts["y"] = r * np.cos(el) * np.sin(az)
        pts["z"] = r * np.sin(el)
        pts["ring"] = np.arange(rows)[:, None]
        pts["t"] = np.arange(n)[None, :] * 1000
        flat = pts.reshape(-1)
        for _ in range(rnd.randint(0, 4)):
            if flat.size:
                flat[rnd.choice("xyz")][rnd.randrange(flat.size)] = rnd.choice(
                    [np.nan, np.inf, -np.inf, 0.0, 1e30])
        if not organized:
            flat = flat[np.argsort(pts["t"].reshape(-1), kind="stable")]
        data = flat.tobytes()
        row_step = width * point_step
        for _ in range(rnd.randint(0, 3)):
            kind = rnd.randrange(9)
            if kind == 0:
                point_step = rnd.choice([0, 1, 4, 12, 23, 2**31, 2**32 - 1])
            elif kind == 1:
                row_step = rnd.choice([0, row_step - 1, row_step + 1, 2**32 - 1])
            elif kind == 2:
                data = data[:rnd.randrange(len(data) + 1)]
            elif kind == 3:
                i = rnd.randrange(len(fields))
                fields[i] = dataclasses.replace(fields[i], offset=rnd.choice([13, 22, 24, 2**31,
                                                                               2**32 - 1]))
            elif kind == 4:
                i = rnd.randrange(len(fields))
                fields[i] = dataclasses.replace(fields[i], datatype=rnd.choice([0, 9, 255, 1, 8]))
            elif kind == 5:
                i = rnd.randrange(len(fields))
                fields[i] = dataclasses.replace(fields[i], count=rnd.choice([0, 2, 2**31]))
            elif kind == 6:
                fields.pop(rnd.randrange(len(fields)))
            elif kind == 7:
                width = rnd.choice([0, 2**31, 2**32 - 1, width + 1])
                height = rnd.choice([0, 2**31, 2**32 - 1, height])
            else:
                fields.append(dataclasses.replace(fields[rnd.randrange(len(fields))]))
        msg = self.cls(header=lt.Header(lt.Time(1, 0), "lidar"), height=height, width=width,
                       fields=tuple(fields), is_bigendian=rnd.random() < 0.05,
                       point_step=point_step, row_step=row_step,
                       data=np.frombuffer(data, np.uint8), is_dense=rnd.random() < 0.5)
        convert = CONV["from_pointcloud2"]
        layout = rnd.choice(["auto", "auto", "organized", "ring"])

        def run() -> str:
            scan, info = convert(msg, layout=layout, as_dataclass=True)
            exercise_scan(scan, info)
            return "converted"
        return repr(msg)[:4000], run


def _laser(rnd: random.Random, stamp_ns: int, frame: str = "laser") -> Any:
    cls = lt.message_class("sensor_msgs/msg/LaserScan")
    n = rnd.choice([0, 1, 2, 5, 360])
    ranges = np.array([rnd.uniform(0, 20) for _ in range(n)], np.float32)
    for _ in range(rnd.randint(0, 3)):
        if n:
            ranges[rnd.randrange(n)] = rnd.choice([np.nan, np.inf, -np.inf, 0.0, -1.0])
    inc = rnd.choice([2 * math.pi / max(n, 1), 0.0, -0.01, math.nan, math.inf, 1e-300, 10.0])
    amin = rnd.choice([-math.pi, 0.0, math.nan, -math.inf, 1e308])
    amax = rnd.choice([amin + inc * max(n - 1, 0), amin, math.nan, amin - 1])
    inten_n = rnd.choice([n, n, 0, n + 1, max(n - 1, 0)])
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    return cls(header=lt.Header(lt.Time(sec, nsec), frame), angle_min=amin, angle_max=amax,
               angle_increment=inc, time_increment=rnd.choice([0.0, 1e-5, -1e-5, math.nan]),
               scan_time=rnd.choice([0.1, 0.0, math.nan]),
               range_min=rnd.choice([0.1, 0.0, -1.0, math.nan, 30.0]),
               range_max=rnd.choice([30.0, 0.0, math.inf, math.nan, 0.05]),
               ranges=ranges, intensities=np.ones(inten_n, np.float32))


class LaserScanSweep(Target):
    """LaserScan inputs with inconsistent fields into sweep.from_laserscan_sweep."""
    name = "laserscan_sweep"
    needs = ("from_laserscan_sweep",)

    def case(self, rnd: random.Random) -> tuple[str, Callable[[], str]]:
        scans = [_laser(rnd, 1_000_000_000 + i) for i in range(rnd.choice([0, 1, 2, 5]))]
        if scans and rnd.random() < 0.7:  # mostly consistent geometry, so the deep code runs
            scans = [dataclasses.replace(s, angle_min=scans[0].angle_min,
                                         angle_increment=scans[0].angle_increment,
                                         ranges=np.resize(s.ranges, len(scans[0].ranges)),
                                         intensities=np.resize(s.intensities,
                                                               len(scans[0].ranges)))
                     for s in scans]
        joints = rnd.choice([np.linspace(-0.5, 0.5, len(scans)), np.full(len(scans), np.nan),
                             np.zeros(len(scans) + 1), np.zeros((len(scans), 2))])
        convert = CONV["from_laserscan_sweep"]
        return repr(scans)[:4000], lambda: (convert(scans, joints, as_dataclass=True),
                                            "converted")[1]


class MergerInputs(Target):
    """LaserScan inputs (bad fields, odd stamps) into LaserScanMerger: push then merge."""
    name = "merger"
    needs = ("merger",)

    def setup(self) -> None:
        self.mod = CONV["merger"]

    def case(self, rnd: random.Random) -> tuple[str, Callable[[], str]]:
        scans = [(rnd.choice(["front", "rear"] * 8 + ["nope"]),
                  _laser(rnd, rnd.choice([0, 1_000_000_000, 1_000_000_000 + i * 50_000_000,
                                          2**62, 5])))
                 for i in range(rnd.randint(1, 6))]

        def run() -> str:
            merger = make_merger(self.mod)
            for name, scan in scans:
                merger_push(merger, name, scan)
            merger_merge(merger, 1_000_000_000 + 300_000_000)
            return "merged"
        return repr(scans)[:4000], run


class WrongGeometry(Exception):
    """A scan released with an info that is not the one true geometry of its stamp (a failure:
    not a LidarScanError, so the runner counts it as a crash)."""


class LinkageEviction(Target):
    """Reconfiguring LidarInfo streams through InfoResolver with tiny bounds (1-3 infos kept,
    0-3 digests remembered): new versions, identical and conflicting republishes (also under
    evicted and forgotten stamps), stragglers naming old stamps, clock ticks. Each stamp has one
    true geometry (its first publication); a release with any other info, or under a stamp that
    carried two contents, raises WrongGeometry. Every scan must be released or dropped once."""
    name = "linkage_eviction"

    def setup(self) -> None:
        from lidarscan.geometry import info_key
        from lidarscan.linkage import InfoResolver

        self.resolver_class = InfoResolver
        self.key = info_key
        self.geometries = [self._info(0, g) for g in range(4)]
        self.digests = [info_key(g)[1] for g in self.geometries]
        self.totals: collections.Counter[str] = collections.Counter()

    @staticmethod
    @functools.lru_cache(maxsize=4096)
    def _info(stamp: int, g: int) -> Any:
        return ls.make_info(stamp_ns=stamp, frame_id="lidar",
                            vertical_angles=np.radians([15.0, 5.0, -5.0, -15.0]) + 0.03 * g,
                            horizontal_angles=2 * np.pi * (1 - np.arange(W) / W),
                            as_dataclass=True)

    def case(self, rnd: random.Random) -> tuple[str, Callable[[], str]]:
        bounds = {"max_infos": rnd.randint(1, 3), "max_digests": rnd.randint(0, 3),
                  "max_pending": rnd.randint(0, 4),
                  "max_wait_ns": rnd.choice([None, 5, 50])}
        ops = []
        newest = 0
        for _ in range(rnd.randint(5, 60)):
            r = rnd.random()
            if r < 0.25:  # a new version, usually later than the newest
                newest += rnd.randint(1, 3)
                ops.append(("info", 100 * newest, rnd.randrange(4), False))
            elif r < 0.4:  # republish any stamp: identical or not
                ops.append(("info", 100 * rnd.randint(1, newest + 2), rnd.randrange(4),
                            rnd.random() < 0.5))
            elif r < 0.9:  # a scan naming a recent stamp or a straggler
                back = 0 if rnd.random() < 0.6 else rnd.randint(1, 12)
                ops.append(("scan", 100 * max(1, newest - back), rnd.randrange(4), False))
            else:
                ops.append(("tick", rnd.randint(0, 30), 0, False))

        def run() -> str:
            clock = [0]
            resolver = self.resolver_class(clock=lambda: clock[0], **bounds)
            true: dict[int, int] = {}
            published: dict[int, set[int]] = {}
            outcome: dict[int, str] = {}
            scans = 0

            def check(pairs: list[tuple[Any, Any]]) -> None:
                for scan, info in pairs:
                    stamp = ls.to_ns(scan.lidar_info_time)
                    if (ls.to_ns(info.header.stamp) != stamp
                            or self.key(info)[1] != self.digests[true[stamp]]
                            or len(published.get(stamp, ())) != 1):
                        raise WrongGeometry(f"scan naming {stamp} paired wrongly")
                    sid = ls.to_ns(scan.header.stamp)
                    if sid in outcome:
                        raise WrongGeometry(f"scan {sid} released twice")
                    outcome[sid] = "released"
                for d in resolver.take_dropped():
                    if d.stamp_ns in outcome:
                        raise WrongGeometry(f"scan {d.stamp_ns} reported twice")
                    outcome[d.stamp_ns] = "dropped"

            for kind, a, g, same in ops:
                if kind == "info":
                    if a in true and (same or a not in published):
                        g = true[a]
                    true.setdefault(a, g)
                    published.setdefault(a, set()).add(g)
                    check(resolver.add_info(self._info(a, g)))
                elif kind == "scan":
                    g = true.setdefault(a, g)
                    scans += 1
                    check(resolver.add_scan(ls.make_scan(
                        self._info(a, g), {"range": np.ones((H, W), np.float32)}, scans,
                        as_dataclass=True)))
                else:
                    clock[0] += a
                    resolver.expire()
                    check([])
            resolver.flush()
            check([])
            if len(outcome) != scans:
                raise WrongGeometry(f"{scans - len(outcome)} scans lost silently")
            counts = collections.Counter(outcome.values())
            self.totals.update(counts)
            self.totals["scans"] += scans
            self.totals["conflicts"] += resolver.conflicts
            self.totals["forgotten"] += resolver.forgotten_ns is not None
            return "linked"
        return repr((bounds, ops))[:4000], run

    def summary(self) -> str:
        t = self.totals
        return (f"{t['scans']} scans: released {t['released']}, dropped {t['dropped']}, "
                f"0 wrong-geometry pairs unless reported as failures above; conflicts "
                f"{t['conflicts']}; cases past the digest bound {t['forgotten']}")


# The merger's API is bound once known (see _bind_merger); kept as module functions so the
# fault tests can reuse the same adapter.
def make_merger(mod: Any) -> Any:
    return _MERGER_ADAPTER["make"](mod)


def merger_push(merger: Any, name: str, scan: Any) -> Any:
    return _MERGER_ADAPTER["push"](merger, name, scan)


def merger_merge(merger: Any, now_ns: int) -> Any:
    return _MERGER_ADAPTER["merge"](merger, now_ns)


_MERGER_ADAPTER: dict[str, Callable[..., Any]] = {}


TARGETS: dict[str, type[Target]] = {t.name: t for t in (
    ScanCdr, InfoCdr, ScanFields, InfoFields, McapFile, McapChunks, PacketCdr, BagDb3,
    OusterJson, PointCloud2Input, LaserScanSweep, MergerInputs, LinkageEviction)}


# ----------------------------------------------------------------------------------- runner

@dataclasses.dataclass
class Stats:
    cases: int = 0
    accepted: int = 0
    rejected: collections.Counter[str] = dataclasses.field(default_factory=collections.Counter)
    failures: list[tuple[int, str, str]] = dataclasses.field(default_factory=list)
    failure_kinds: collections.Counter[str] = dataclasses.field(
        default_factory=collections.Counter)
    slowest: tuple[float, int] = (0.0, -1)
    max_alloc: tuple[int, int] = (0, -1)
    seconds: float = 0.0


def _alarm(signum: int, frame: Any) -> None:
    raise CaseTimeout()


def case_rng(seed: int, target: str, index: int) -> random.Random:
    return random.Random(f"{seed}:{target}:{index}")


def run_case(target: Target, seed: int, index: int, timeout: float
             ) -> tuple[str, str, int, float, bytes | str]:
    """(outcome, detail, peak bytes, seconds, input). outcome: accepted/rejected/crash/hang."""
    rnd = case_rng(seed, target.name, index)
    try:
        data, call = target.case(rnd)
    except Exception as err:  # noqa: BLE001 - a bug of this fuzzer, reported, not fatal
        return "generator", "".join(traceback.format_exception(err)), 0, 0.0, b""
    DEEP["on"] = rnd.random() < 0.25
    tracemalloc.reset_peak()
    base = tracemalloc.get_traced_memory()[0]
    start = time.perf_counter()
    signal.setitimer(signal.ITIMER_PROF, timeout)  # CPU time: immune to a busy machine
    try:
        call()
        outcome, detail = "accepted", ""
    except LidarScanError as err:
        outcome, detail = "rejected", type(err).__name__
    except CaseTimeout:
        outcome, detail = "hang", f"> {timeout} s"
    except Exception as err:  # noqa: BLE001 - the point of the fuzzer
        outcome, detail = "crash", "".join(traceback.format_exception(err))
    finally:
        signal.setitimer(signal.ITIMER_PROF, 0)
    elapsed = time.perf_counter() - start
    peak = tracemalloc.get_traced_memory()[1] - base
    return outcome, detail, peak, elapsed, data


def _warm_up(targets: list[Target], seed: int, timeout: float) -> None:
    """First calls build caches and import modules (rclpy messages, converters): run a full
    conversion and a few uncounted cases per target so the per-case timeout measures cases."""
    DEEP["on"] = True
    import lidarscan_msgs.msg  # noqa: F401 - the ROS message modules outputs are built from
    import sensor_msgs.msg  # noqa: F401
    info = seed_info()
    try:
        exercise_scan(seed_scan(info), info)
        if "merger" in CONV:
            merger = make_merger(CONV["merger"])
            for i in range(3):
                for name in ("front", "rear"):
                    scan = _laser(random.Random(i), 1_000_000_000 + i * 50_000_000)
                    merger_push(merger, name, dataclasses.replace(
                        scan, angle_min=-1.0, angle_max=1.0, angle_increment=0.1,
                        ranges=np.ones(21, np.float32), intensities=np.ones(0, np.float32),
                        range_min=0.1, range_max=30.0, scan_time=0.1, time_increment=0.0))
    except LidarScanError:
        pass
    for target in targets:
        for index in range(5):
            run_case(target, seed + 1, index, max(timeout, 60.0))


def _crash_key(detail: str) -> str:
    lines = [ln for ln in detail.strip().splitlines() if ln.strip()]
    where = [ln.strip() for ln in lines if ln.strip().startswith("File ")]
    return f"{lines[-1][:120]} @ {where[-1] if where else '?'}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", type=int, default=0,
                        help="cases per target (default: 100000 split evenly over the targets)")
    parser.add_argument("--total", type=int, default=100_000)
    parser.add_argument("--targets", default="", help="comma-separated subset")
    parser.add_argument("--target", default="", help="replay one case of this target")
    parser.add_argument("--case", type=int, default=-1)
    parser.add_argument("--start", type=int, default=0, help="first case number (split runs)")
    parser.add_argument("--seed", type=int, default=20241122)
    parser.add_argument("--timeout", type=float, default=5.0,
                        help="CPU seconds per case (SIGPROF), after a warm-up")
    parser.add_argument("--max-alloc-mb", type=float, default=64.0)
    parser.add_argument("--max-vm-gb", type=float, default=8.0,
                        help="address-space limit of this process (RLIMIT_AS), 0 = none")
    parser.add_argument("--out", default=str(ROOT / "build" / "fuzz"))
    args = parser.parse_args(argv)

    if args.max_vm_gb > 0:  # a huge allocation fails (MemoryError, reported) instead of the
        limit = int(args.max_vm_gb * 2**30)  # kernel's OOM killer ending the whole run
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    warnings.simplefilter("ignore")  # overflow warnings from numpy on extreme floats are fine
    signal.signal(signal.SIGPROF, _alarm)
    CONV.update(_converters())
    _bind_merger()
    tracemalloc.start()

    if args.target:
        target = TARGETS[args.target]()
        target.setup()
        outcome, detail, peak, elapsed, data = run_case(target, args.seed, args.case,
                                                        args.timeout)
        print(f"{args.target} case {args.case}: {outcome} {elapsed * 1e3:.1f} ms "
              f"peak {peak / 1e6:.2f} MB")
        print(detail or "")
        print("input:", repr(data)[:2000])
        return 0 if outcome in ("accepted", "rejected") else 1

    names = [n for n in (args.targets.split(",") if args.targets else TARGETS) if n]
    active, skipped = [], []
    for name in names:
        target = TARGETS[name]()
        missing = [need for need in target.needs if need not in CONV]
        if missing:
            skipped.append(f"{name} (missing {', '.join(missing)}: "
                           f"{'; '.join(MISSING.get(m, '?') for m in missing)})")
            continue
        target.setup()
        active.append(target)
    _warm_up(active, args.seed, args.timeout)
    per = args.cases or max(1, args.total // max(len(active), 1))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    limit = int(args.max_alloc_mb * 1e6)
    print(f"fuzz: seed {args.seed}, {per} cases per target from case {args.start}, "
          f"timeout {args.timeout} s, alloc limit {args.max_alloc_mb:g} MB; "
          f"python {platform.python_version()}, numpy {np.__version__}, "
          f"{platform.machine()} {os.cpu_count()} cpu")
    if skipped:
        print("skipped (not yet available):", "; ".join(skipped))
    total_fail = 0
    all_stats: dict[str, Stats] = {}
    for target in active:
        stats = Stats()
        t0 = time.perf_counter()
        for index in range(args.start, args.start + per):
            outcome, detail, peak, elapsed, data = run_case(target, args.seed, index,
                                                            args.timeout)
            stats.cases += 1
            if outcome == "accepted":
                stats.accepted += 1
            elif outcome == "rejected":
                stats.rejected[detail] += 1
            if peak > limit and outcome in ("accepted", "rejected"):
                outcome, detail = "memory", f"peak allocation {peak / 1e6:.1f} MB"
            if outcome in ("crash", "hang", "memory", "generator"):
                key = f"{outcome}: " + (_crash_key(detail) if outcome in ("crash", "generator")
                                        else detail)
                if stats.failure_kinds[key] == 0:
                    stats.failures.append((index, key, detail))
                    suffix = "bin" if isinstance(data, bytes) else "txt"
                    path = out / f"{target.name}-{index}.{suffix}"
                    path.write_bytes(data if isinstance(data, bytes) else data.encode())
                    print(f"  FAIL {target.name} case {index}: {key}\n    saved {path}; "
                          f"replay: bench/fuzz.py --target {target.name} --case {index} "
                          f"--seed {args.seed}", flush=True)
                stats.failure_kinds[key] += 1
            if elapsed > stats.slowest[0]:
                stats.slowest = (elapsed, index)
            if peak > stats.max_alloc[0]:
                stats.max_alloc = (peak, index)
        stats.seconds = time.perf_counter() - t0
        all_stats[target.name] = stats
        total_fail += sum(stats.failure_kinds.values())
        kinds = ", ".join(f"{k} {v}" for k, v in stats.rejected.most_common())
        print(f"{target.name:16s} {stats.cases:7d} cases in {stats.seconds:6.1f} s "
              f"({stats.cases / max(stats.seconds, 1e-9):6.0f}/s): accepted {stats.accepted}, "
              f"rejected {sum(stats.rejected.values())} [{kinds}], "
              f"failures {sum(stats.failure_kinds.values())}; slowest "
              f"{stats.slowest[0] * 1e3:.1f} ms (case {stats.slowest[1]}), max alloc "
              f"{stats.max_alloc[0] / 1e6:.2f} MB (case {stats.max_alloc[1]})", flush=True)
        for key, count in stats.failure_kinds.items():
            print(f"    {count:6d} x {key}")
        if hasattr(target, "summary"):
            print(f"    {target.summary()}")
    maxrss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    total = sum(s.cases for s in all_stats.values())
    print(f"total {total} cases, {total_fail} failures, max RSS {maxrss:.0f} MiB")
    summary = {name: {"cases": s.cases, "accepted": s.accepted, "rejected": dict(s.rejected),
                      "failures": dict(s.failure_kinds), "seconds": round(s.seconds, 1),
                      "max_alloc_mb": round(s.max_alloc[0] / 1e6, 2),
                      "slowest_ms": round(s.slowest[0] * 1e3, 1)}
               for name, s in all_stats.items()}
    (out / f"summary-{args.seed}-{args.start}.json").write_text(json.dumps(
        {"skipped": skipped, "max_rss_mib": round(maxrss), "targets": summary}, indent=1))
    return 1 if total_fail else 0


def _bind_merger() -> None:
    """Adapter to converters.merger's API: LaserScanMerger({name: MergerInput}), push(name,
    scan) -> merged scan or None."""
    mod = CONV.get("merger")
    if mod is None:
        return

    def make(mod: Any) -> Any:
        inputs = {"front": mod.MergerInput(),
                  "rear": mod.MergerInput(extrinsics=np.diag([-1.0, -1.0, 1.0, 1.0]),
                                          range_min=0.2, angle_min=-1.0, angle_max=1.0)}
        return mod.LaserScanMerger(inputs, frame_id="base_link", policy="timeout",
                                   timeout_ns=200_000_000, angle_increment=math.radians(2.0))

    _MERGER_ADAPTER["make"] = make
    _MERGER_ADAPTER["push"] = lambda merger, name, scan: merger.push(name, scan)
    _MERGER_ADAPTER["merge"] = lambda merger, now_ns: None


if __name__ == "__main__":
    sys.exit(main())
