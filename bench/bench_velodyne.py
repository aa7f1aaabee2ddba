"""Benchmark: Velodyne packet decoding (converters.sources.velodyne.decode_packets) vs real time.

Run: ``.venv/bin/python bench/bench_velodyne.py [--seconds S] [--repeat N]``. Prints CPU-time
medians of interleaved rounds (the machine may be shared: wall times only beside them), the
multiple of real time on one core and the load average (no assertions). Target: >= 50x real
time (<= 20 ms of CPU per second of data).

Input: a VLS-128 in dual-return mode at 600 rpm (one firing sequence of 128 lasers x 2 returns
per packet, 18 761 packets per second of sensor time), random returns with 20 % no-return,
built in memory with numpy (the manual's layout). Candidates: the decoder (LidarScan + LidarInfo
dataclasses, one per rotation) fed (stamp, bytes) pairs through ``decode_packets`` (with the C
kernel the payloads are read where they are, through a table of their addresses); the batch
API ``PacketDecoder.push_many`` fed (N, 1206) uint8 arrays of one rotation's packets (what a bag
reader gives for a VelodyneScan message, zero-copy), with the C kernel
(``converters/_kernels/_velokernel.c``, built by ``pip install``), with ``LIDARSCAN_NO_KERNEL=1``'s
numpy path, and with ``azimuth_model="manual"`` (no per-pixel azimuth channel: what the
default's Nebula azimuths cost); and a plain per-point
Python loop that unpacks each point and computes x, y, z with the manual's formula (measured on
a slice of the packets in the same run, scaled to the same number of packets). For the C
kernel's candidates it also prints the CPU time spent inside the kernel's fill calls and the
rest (the decoder's Python and numpy work around them, the header check included).
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import struct
import time

import numpy as np

from converters.sources.velodyne import MODELS, PacketDecoder, decode_packets

SEQUENCE_S = 53.3e-6                                # one VLS-128 firing sequence


def make_packets(seconds: float, seed: int = 0) -> list[tuple[int, bytes]]:
    """VLS-128 dual-return packets: blocks EE EE DD DD CC CC BB BB + 4 padding blocks."""
    rng = np.random.default_rng(seed)
    count = int(seconds / SEQUENCE_S)
    packets = np.zeros((count, 1206), np.uint8)
    blocks = packets[:, :1200].reshape(count, 12, 100)
    azimuth = np.round(np.arange(count) * SEQUENCE_S * 3600.0 * 100).astype(np.int64) % 36000
    for b, flag in enumerate((0xEE, 0xEE, 0xDD, 0xDD, 0xCC, 0xCC, 0xBB, 0xBB)):
        blocks[:, b, 0], blocks[:, b, 1] = 0xFF, flag
        blocks[:, b, 2], blocks[:, b, 3] = azimuth & 0xFF, azimuth >> 8
        dist = rng.integers(1, 50000, (count, 32))
        dist[rng.random((count, 32)) < 0.2] = 0
        points = blocks[:, b, 4:].reshape(count, 32, 3)
        points[..., 0], points[..., 1] = dist & 0xFF, dist >> 8
        points[..., 2] = rng.integers(0, 256, (count, 32))
    toh = (np.arange(count) * SEQUENCE_S * 1e6).astype(np.int64) % 3_600_000_000
    packets[:, 1200:1204] = toh.astype("<u4").view(np.uint8).reshape(count, 4)
    packets[:, 1204], packets[:, 1205] = 0x39, 0xA1
    stamp = 1_700_000_000_000_000_000
    return [(stamp + int(t) * 1000, packets[i].tobytes()) for i, t in enumerate(toh)]


def calibration() -> dict[str, object]:
    rng = np.random.default_rng(1)
    return {"lasers": [{"laser_id": k, "vert_correction": float(rng.uniform(-0.4, 0.3)),
                        "rot_correction": float(rng.uniform(-0.1, 0.1))} for k in range(128)]}


def loop_baseline(packets: list[tuple[int, bytes]], calib: dict[str, object]) -> int:
    """Per-point loop: unpack each point, x y z by the manual's formula (the work a naive
    decoder does); returns the number of points."""
    lasers = calib["lasers"]
    assert isinstance(lasers, list)
    cos_v = [math.cos(las["vert_correction"]) for las in lasers]
    sin_v = [math.sin(las["vert_correction"]) for las in lasers]
    rot = [las["rot_correction"] for las in lasers]
    laser_ns = MODELS[0xA1].laser_ns
    omega = math.radians(3600.0) * 1e-9
    point = struct.Struct("<HB")
    n = 0
    for _, data in packets:
        for b in range(8):
            bank = (b // 2) * 32
            azimuth = math.radians((data[100 * b + 2] | data[100 * b + 3] << 8) / 100.0)
            for k in range(32):
                raw, _refl = point.unpack_from(data, 100 * b + 4 + 3 * k)
                if raw == 0:
                    continue
                laser = bank + k
                d = raw * 0.004
                a = azimuth + omega * laser_ns[laser] - rot[laser]
                xy = d * cos_v[laser]
                _ = (xy * math.cos(a), -xy * math.sin(a), d * sin_v[laser])
                n += 1
    return n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=1.0, help="sensor time to decode")
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    packets = make_packets(args.seconds)
    calib = calibration()
    span = args.seconds
    print(f"VLS-128 dual return, 600 rpm: {len(packets)} packets = {span:.2f} s of data; load "
          f"average at the start {os.getloadavg()[0]:.1f}")

    rows = np.frombuffer(b"".join(p for _, p in packets), np.uint8).reshape(-1, 1206)
    stamps = np.array([s for s, _ in packets], np.int64)
    per_message = int(round(0.1 / SEQUENCE_S))                 # one rotation per message

    def decoder() -> int:
        return sum(1 for _ in decode_packets(packets, calib, as_dataclass=True))

    def batch(azimuth_model: str = "nebula") -> int:
        dec = PacketDecoder(calib, as_dataclass=True, azimuth_model=azimuth_model)
        count = 0
        for i in range(0, len(rows), per_message):
            count += len(dec.push_many(stamps[i:i + per_message], rows[i:i + per_message]))
        return count + len(dec.flush())

    def numpy_batch() -> int:
        saved = os.environ.get("LIDARSCAN_NO_KERNEL")
        os.environ["LIDARSCAN_NO_KERNEL"] = "1"                  # the numpy reference path
        try:
            return batch()
        finally:
            if saved is None:
                del os.environ["LIDARSCAN_NO_KERNEL"]
            else:
                os.environ["LIDARSCAN_NO_KERNEL"] = saved

    def loop() -> int:
        return loop_baseline(subset, calib)

    subset = packets[: max(1, len(packets) // 20)]
    def manual_batch() -> int:
        return batch("manual")

    candidates = {"decode_packets (bytes)": decoder, "push_many (arrays), C": batch,
                  "push_many, numpy path": numpy_batch, "push_many, manual": manual_batch,
                  "per-point loop": loop}
    wall: dict[str, list[float]] = {name: [] for name in candidates}
    cpu: dict[str, list[float]] = {name: [] for name in candidates}
    fills: dict[str, list[float]] = {name: [] for name in candidates}
    from converters._kernels import velodyne as kernel
    fill, spent = kernel.fill, [0.0]

    def timed_fill(*args: object, **kw: object) -> None:
        start = time.process_time()
        fill(*args, **kw)                                       # type: ignore[arg-type]
        spent[0] += time.process_time() - start

    kernel.fill = timed_fill                                    # type: ignore[assignment]
    rotations = decoder()                                      # warm-up (and compile)
    batch()
    numpy_batch()
    manual_batch()
    for _ in range(args.repeat):
        for name, run in candidates.items():
            scale = len(packets) / len(subset) if run is loop else 1.0
            spent[0] = 0.0
            start, start_cpu = time.perf_counter(), time.process_time()
            run()
            wall[name].append((time.perf_counter() - start) * scale)
            cpu[name].append((time.process_time() - start_cpu) * scale)
            fills[name].append(spent[0])
    from converters._kernels import select
    kernel = select("velodyne").c is not None
    print(f"{rotations} rotations; kernel: {'C' if kernel else 'none (numpy)'}; load average "
          f"{os.getloadavg()[0]:.1f} at the end (2 cores shared: the CPU times are the figures)")
    loop_cpu = statistics.median(cpu["per-point loop"])
    for name in candidates:
        med, low = statistics.median(wall[name]), min(wall[name])
        cpu_med = statistics.median(cpu[name])
        print(f"{name:24s}: {cpu_med * 1e3:8.1f} ms CPU median = {span / cpu_med:5.1f}x real time "
              f"on one core (target 50x); wall {med * 1e3:.1f} ms ({low * 1e3:.1f} min), "
              f"{cpu_med / len(packets) * 1e6:.2f} us CPU/packet, {loop_cpu / cpu_med:.0f}x the "
              "loop")
        if statistics.median(fills[name]) > 0:
            rest = statistics.median([c - f for c, f in zip(cpu[name], fills[name])])
            print(f"{'':26s}of which the C fill {statistics.median(fills[name]) * 1e3:.1f} ms, "
                  f"the rest {rest * 1e3:.1f} ms")


if __name__ == "__main__":
    main()
