"""Fuzz targets of ``bench/fuzz.py`` for single messages: LidarScan / LidarInfo CDR bytes and
message dataclasses with inconsistent fields."""

from __future__ import annotations

import copy
import dataclasses
import random
from collections.abc import Callable
from typing import Any, ClassVar

import numpy as np

import lidarscan as ls
from lidarscan import types as lt

from fuzz_common import (  # bench/ is on sys.path: see fuzz.py
    exercise_info,
    exercise_scan,
    H,
    INTERESTING_F64,
    INTERESTING_INTS,
    mutate_bytes,
    seed_info,
    seed_scan,
    Target,
    W,
)

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
