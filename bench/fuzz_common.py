"""Shared parts of ``bench/fuzz.py``: seed inputs, mutators, the code each case exercises and
the :class:`Target` base class. ``ROOT`` (scratch files go under ``ROOT/build/fuzz``) and
``CONV`` (the converter entry points found at start) are read at run time by every target module.
"""

from __future__ import annotations

import importlib
import math
import random
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

import lidarscan as ls

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
    "to_pointcloud2": ("converters.pointcloud2.converter", "to_pointcloud2"),
    "from_pointcloud2": ("converters.pointcloud2.converter", "from_pointcloud2"),
    "to_laserscan": ("converters.slices.converter", "to_laserscan"),
    "merger": ("converters.merger", None),
    "info_from_metadata": ("converters.sources.ouster.metadata", "info_from_metadata"),
    "from_laserscan_sweep": ("converters.sources.sweep", "from_laserscan_sweep"),
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


def use_scan(scan: Any, info: Any) -> None:
    """What a consumer does with a (possibly bad) scan: validate, then read every channel,
    project, time (also the oracle of ``tests/test_fuzz.py``, which imports it)."""
    ls.validate(scan)
    for desc in scan.channels:
        ls.channel(scan, desc.name)
    ls.validate(scan, info)
    ls.range_m(scan, info)
    projector = ls.make_projector(info)
    projector.project(scan, info)
    projector.pixel_times(scan)


def exercise_scan(scan: Any, info: Any) -> str:
    """:func:`use_scan`, then (``DEEP``) convert to PointCloud2 and back, and to LaserScan."""
    use_scan(scan, info)
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
