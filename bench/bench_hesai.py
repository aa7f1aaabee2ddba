"""Benchmark: Hesai packet decoding (Pandar64, dual return) as a multiple of real time, one core.

Run: ``.venv/bin/python bench/bench_hesai.py [--rounds N]``. Prints medians and ratios measured
in one run (no assertions). Target: >= 50x real time.

Input: the real Pandar64 recording of ``tests/data/nebula/hesai_pandar64`` (2400 packets of
1198 bytes in 25 PandarScan messages, 0.4 s of sensor time at 600 rpm, dual return 0x39), read
once with ``rosbags`` (by ``tests/test_hesai.py``'s reader).
Candidates, interleaved round after round, all producing (LidarScan, LidarInfo) dataclasses
unless said otherwise:

* ``push``: ``PacketDecoder.push`` packet by packet, then ``flush``;
* ``push_many``: ``PacketDecoder.push_many`` once per bag message, on the (N, 1198) view
  ``data[:, :size]`` of the message's (N, 1500) packet array (as a bag reader gives it;
  the arrays are built before timing);
* ``decode_packets``: ``converters.hesai.decode_packets`` on the (stamp, bytes) list (it
  joins runs of equal-size payloads and calls push_many);
* ``decode_packets+msg``: the same, built as rclpy messages (what a node publishes);
* ``loop``: a plain per-point loop (struct.unpack per channel, math.sin/cos per point) that
  writes x, y, z, intensity and time of every return to preallocated lists: what a decoder
  without vectorisation does. It runs on the first 300 packets; its time is scaled to all.

Besides wall-clock medians it prints the CPU time (``time.process_time``) of the same calls:
on a shared, overloaded machine the process is often descheduled, and the CPU time is what one
core spends on the work. The load average is printed with the figures. The compiled units
kernel is used when numba is installed (``LIDARSCAN_NUMBA=0``: the numpy reference).
"""

from __future__ import annotations

import argparse
import calendar
import math
import os
import statistics
import struct
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).parent))
from _timing import interleaved_times  # noqa: E402

import numpy as np  # noqa: E402

from converters import hesai  # noqa: E402

DATA = Path(__file__).resolve().parent.parent / "tests" / "data" / "nebula" / "hesai_pandar64"


def read_packets() -> tuple[list[tuple[int, bytes]], list[tuple[np.ndarray, np.ndarray]]]:
    """(stamp ns, payload) of every packet, read with rosbags by the tests' reader, and per bag
    message its (N,) stamps and (N, size) view of an (N, 1500) uint8 array."""
    sys.path.insert(0, str(DATA.parents[2]))
    from test_hesai import _bag, _packets

    messages = []
    for _, msg in _bag("hesai_pandar64"):
        size = len(msg[0][1])
        wide = np.zeros((len(msg), 1500), np.uint8)
        for i, (_, p) in enumerate(msg):
            wide[i, :size] = np.frombuffer(p, np.uint8)
        messages.append((np.array([t for t, _ in msg], np.int64), wide[:, :size]))
    return _packets("hesai_pandar64"), messages


def loop_decode(packets: list[tuple[int, bytes]], elevation: list[float],
                azimuth: list[float]) -> int:
    """Per-point Pandar64 decoding in plain Python; returns the number of points."""
    xs: list[float] = []
    ys: list[float] = []
    zs: list[float] = []
    intens: list[int] = []
    times: list[int] = []
    before_end = hesai._P64_BEFORE_END_NS
    cos_e = [math.cos(math.radians(e)) for e in elevation]
    sin_e = [math.sin(math.radians(e)) for e in elevation]
    unit = struct.Struct("<HB")
    for _, p in packets:
        y, mo, d, h, mi, s = p[1188:1194]
        t0 = (calendar.timegm((1900 + y, mo, d, h, mi, s, 0, 0, 0)) * 10**9
              + struct.unpack_from("<I", p, 1182)[0] * 1000)
        returns = 2 if p[1186] == 0x39 else 1
        for b in range(6):
            base = 8 + b * 194
            az = struct.unpack_from("<H", p, base)[0] * 0.01
            end = t0 - 42580 - 55560 * ((5 - b) // returns)
            for laser in range(64):
                dist, refl = unit.unpack_from(p, base + 2 + 3 * laser)
                if dist == 0:
                    continue
                r = dist * 0.004
                a = math.radians(az + azimuth[laser])
                xy = r * cos_e[laser]
                xs.append(xy * math.sin(a))
                ys.append(xy * math.cos(a))
                zs.append(r * sin_e[laser])
                intens.append(refl)
                times.append(end - before_end[laser])
    return len(xs)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=7)
    args = parser.parse_args()
    packets, messages = read_packets()
    csv = DATA / "Pandar64.csv"
    cal = hesai.load_calibration(csv)
    firings = len(packets) * 3                            # dual return: 3 firings a packet
    real_s = firings * 55.56e-6
    subset = packets[:300]

    def decode(as_dataclass: bool = True) -> list[Any]:
        return list(hesai.decode_packets(packets, cal, as_dataclass=as_dataclass))

    def push() -> list[Any]:
        dec = hesai.PacketDecoder(cal, as_dataclass=True)
        return [r for t, p in packets for r in dec.push(t, p)] + dec.flush()

    def push_many() -> list[Any]:
        dec = hesai.PacketDecoder(cal, as_dataclass=True)
        return [r for stamps, rows in messages for r in dec.push_many(stamps, rows)
                ] + dec.flush()

    candidates = {
        "push": push,
        "push_many": push_many,
        "decode_packets": decode,
        "decode_packets+msg": lambda: decode(False),
        "loop (300 packets)": lambda: loop_decode(subset, list(cal.elevation_deg),
                                                  list(cal.azimuth_deg)),
    }
    load = os.getloadavg()
    times = interleaved_times(candidates, args.rounds)
    med = {k: statistics.median(v) for k, v in times.items()}
    cpu = {}
    for name, fn in candidates.items():
        runs = []
        for _ in range(args.rounds):
            start = time.process_time()
            fn()
            runs.append(time.process_time() - start)
        cpu[name] = statistics.median(runs)
    load = max(load[0], os.getloadavg()[0])
    loop_cpu = cpu["loop (300 packets)"] * len(packets) / len(subset)
    loop_all = med["loop (300 packets)"] * len(packets) / len(subset)
    kernel = "numba kernel" if hesai._kernel() is not None else "numpy (no compiled path)"
    print(f"Pandar64 dual return: {len(packets)} packets, {real_s:.3f} s of sensor time, "
          f"{len(decode())} scans; medians of {args.rounds} interleaved rounds, one core, "
          f"units by {kernel}; load average {load:.1f} on {os.cpu_count()} cores")
    for name in ("push", "push_many", "decode_packets", "decode_packets+msg"):
        print(f"  {name:<18} wall {med[name] * 1e3:7.2f} ms {real_s / med[name]:6.1f}x real "
              f"time {loop_all / med[name]:5.1f}x the loop | cpu {cpu[name] * 1e3:7.2f} ms "
              f"{real_s / cpu[name]:6.1f}x real time {loop_cpu / cpu[name]:5.1f}x the loop")
    print(f"  {'loop':<18} wall {loop_all * 1e3:7.2f} ms {real_s / loop_all:6.1f}x real time "
          f"(300 packets, scaled) | cpu {loop_cpu * 1e3:7.2f} ms "
          f"{real_s / loop_cpu:6.1f}x real time")


if __name__ == "__main__":
    main()
