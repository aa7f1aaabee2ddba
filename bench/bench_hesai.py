"""Benchmark: Hesai packet decoding (Pandar64, dual return) as a multiple of real time, one core.

Run: ``.venv/bin/python bench/bench_hesai.py [--rounds N] [--baseline FILE]``. Prints medians and
ratios measured in one run (no assertions). Target: >= 50x real time. ``--baseline`` times
another version of ``converters/sources/hesai/decoder.py`` beside this one, interleaved in the same run (e.g.
``git show main:converters/sources/hesai/decoder.py > /tmp/hesai_main.py``; it runs against this tree's
``lidarscan``); ``--baseline-kernel FILE`` gives it its own version of
``converters/_kernels/hesai.py`` (needed when the kernel's arguments changed, e.g.
``git show main:converters/_kernels/hesai.py > /tmp/hesai_kernel_main.py``).

Input: the real Pandar64 recording of ``tests/data/nebula/hesai_pandar64`` (2400 packets of
1198 bytes in 25 PandarScan messages, 0.4 s of sensor time at 600 rpm, dual return 0x39), read
once with ``rosbags`` (by ``tests/test_hesai.py``'s reader).
Candidates, interleaved round after round, all producing (LidarScan, LidarInfo) dataclasses
unless said otherwise:

* ``push``: ``PacketDecoder.push`` packet by packet, then ``flush``;
* ``push_many``: ``PacketDecoder.push_many`` once per bag message, on the (N, 1198) view
  ``data[:, :size]`` of the message's (N, 1500) packet array (as a bag reader gives it;
  the arrays are built before timing);
* ``decode_packets``: ``converters.sources.hesai.decoder.decode_packets`` on the (stamp, bytes) list (it
  joins runs of equal-size payloads and calls push_many);
* ``decode_packets+msg``: the same, built as rclpy messages (what a node publishes);
* ``loop``: a plain per-point loop (struct.unpack per channel, math.sin/cos per point) that
  writes x, y, z, intensity and time of every return to preallocated lists: what a decoder
  without vectorisation does. It runs on the first 300 packets; its time is scaled to all.

Besides wall-clock medians it prints the median CPU time (``time.process_time``) of a second
set of rounds, interleaved the same way: on a shared, overloaded machine the process is often
descheduled, and the CPU time is what one core spends on the work. The load average is printed
with the figures. The compiled units kernel is used when numba is installed
(``LIDARSCAN_NUMBA=0``: the numpy reference).
"""

from __future__ import annotations

import argparse
import calendar
import importlib.util
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

from converters.sources.hesai import decoder as hesai  # noqa: E402

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


def load_baseline(path: Path, kernel: Path | None = None) -> Any:
    """``path`` (another version of converters/sources/hesai/decoder.py) imported as a separate module; with
    ``kernel`` (another version of converters/_kernels/hesai.py), using that kernel."""
    module = _load(path, "hesai_baseline")
    if kernel is not None and module._kernel() is not None:
        module._KERNEL = _load(kernel, "hesai_baseline_kernel").kernel()
    return module


def _load(path: Path, name: str) -> Any:
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module            # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def decoders(mod: Any, packets: list[tuple[int, bytes]],
             messages: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, Any]:
    """The four decoding candidates of module ``mod`` (converters.sources.hesai.decoder or a baseline)."""
    cal = mod.load_calibration(DATA / "Pandar64.csv")

    def decode(as_dataclass: bool = True) -> list[Any]:
        return list(mod.decode_packets(packets, cal, as_dataclass=as_dataclass))

    def push() -> list[Any]:
        dec = mod.PacketDecoder(cal, as_dataclass=True)
        return [r for t, p in packets for r in dec.push(t, p)] + dec.flush()

    def push_many() -> list[Any]:
        dec = mod.PacketDecoder(cal, as_dataclass=True)
        return [r for stamps, rows in messages for r in dec.push_many(stamps, rows)
                ] + dec.flush()

    return {"push": push, "push_many": push_many, "decode_packets": decode,
            "decode_packets+msg": lambda: decode(False)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--baseline", type=Path, default=None,
                        help="another version of converters/sources/hesai/decoder.py to time beside this one")
    parser.add_argument("--baseline-kernel", type=Path, default=None,
                        help="the baseline's version of converters/_kernels/hesai.py")
    args = parser.parse_args()
    packets, messages = read_packets()
    cal = hesai.load_calibration(DATA / "Pandar64.csv")
    firings = len(packets) * 3                            # dual return: 3 firings a packet
    real_s = firings * 55.56e-6
    subset = packets[:300]
    candidates = decoders(hesai, packets, messages)
    names = list(candidates)
    if args.baseline is not None:
        base = decoders(load_baseline(args.baseline, args.baseline_kernel), packets, messages)
        candidates.update({f"{name} (baseline)": fn for name, fn in base.items()})
        names = [n for name in names for n in (f"{name} (baseline)", name)]
    candidates["loop (300 packets)"] = lambda: loop_decode(
        subset, list(cal.elevation_deg), list(cal.azimuth_deg))
    load = os.getloadavg()
    times = interleaved_times(candidates, args.rounds)
    med = {k: statistics.median(v) for k, v in times.items()}
    cpu: dict[str, list[float]] = {name: [] for name in candidates}
    order = list(candidates)
    shuffle = np.random.default_rng(1).shuffle
    for _ in range(args.rounds):                          # CPU time, interleaved too
        shuffle(order)
        for name in order:
            start = time.process_time()
            candidates[name]()
            cpu[name].append(time.process_time() - start)
    cpu_med = {k: statistics.median(v) for k, v in cpu.items()}
    load = max(load[0], os.getloadavg()[0])
    loop_cpu = cpu_med["loop (300 packets)"] * len(packets) / len(subset)
    loop_all = med["loop (300 packets)"] * len(packets) / len(subset)
    kernel = "numba kernel" if hesai._kernel() is not None else "numpy (no compiled path)"
    print(f"Pandar64 dual return: {len(packets)} packets, {real_s:.3f} s of sensor time, "
          f"{len(candidates['decode_packets']())} scans; medians of {args.rounds} interleaved "
          f"rounds, one core, units by {kernel}; load average {load:.1f} on {os.cpu_count()} "
          "cores")
    for name in names:
        c = cpu_med[name]
        print(f"  {name:<29} wall {med[name] * 1e3:7.2f} ms {real_s / med[name]:6.1f}x real "
              f"time {loop_all / med[name]:5.1f}x the loop | cpu {c * 1e3:7.2f} ms "
              f"{real_s / c:6.1f}x real time {loop_cpu / c:5.1f}x the loop")
    print(f"  {'loop':<29} wall {loop_all * 1e3:7.2f} ms {real_s / loop_all:6.1f}x real time "
          f"(300 packets, scaled) | cpu {loop_cpu * 1e3:7.2f} ms "
          f"{real_s / loop_cpu:6.1f}x real time")


if __name__ == "__main__":
    main()
