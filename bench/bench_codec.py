"""Benchmark: LidarScan CDR decode/encode against rclpy, as ratios measured in one run.

Scan: 128 x 2048, six channels (range f32, intensity u16, reflectivity u8, ambient u16, flags u8,
range2 f32; 3.67 MB of data) plus per-column times.

* decode: ``lidarscan.decode_scan`` + ``lidarscan.channel`` for every channel (numpy views of the
  payload) vs ``rclpy.serialization.deserialize_message`` + the same numpy views of the rclpy
  message's buffers. Target: >= 50x faster (decode is O(1) in the data size).
* encode: ``lidarscan.encode`` of the rclpy message vs ``serialize_message``. Target: no slower.

Usage: ``.venv/bin/python bench/bench_codec.py [--runs N]``. Prints medians and ratios; exits 1
when a target is missed.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np

import lidarscan

CHANNELS = ("range", "intensity", "reflectivity", "ambient", "flags", "range2")


def make_scan(height: int, width: int) -> tuple[Any, Any]:
    """(rclpy LidarScan, its LidarInfo) with six random channels."""
    rng = np.random.default_rng(0)
    info = lidarscan.make_info(stamp_ns=1_700_000_000_000_000_000, frame_id="os_sensor",
                               vertical_angles=np.linspace(0.4, -0.4, height),
                               horizontal_angles=2 * np.pi * (1 - np.arange(width) / width))
    channels = {
        "range": rng.random((height, width), np.float32) * 100,
        "intensity": rng.integers(0, 2**16, (height, width), dtype=np.uint16),
        "reflectivity": rng.integers(0, 256, (height, width), dtype=np.uint8),
        "ambient": rng.integers(0, 2**16, (height, width), dtype=np.uint16),
        "flags": rng.integers(0, 256, (height, width), dtype=np.uint8),
        "range2": rng.random((height, width), np.float32) * 100,
    }
    scan = lidarscan.make_scan(info, channels, 1_700_000_000_050_000_000,
                               column_time_offsets=np.arange(width, dtype=np.int64) * 48_828)
    return scan, info


def median_s(func: Callable[[], Any], runs: int) -> float:
    """Median wall time of one call, in seconds (after two warm-up calls)."""
    func()
    func()
    times = []
    for _ in range(runs):
        start = time.perf_counter_ns()
        func()
        times.append(time.perf_counter_ns() - start)
    return statistics.median(times) / 1e9


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=60, help="timed runs per measurement")
    args = parser.parse_args(argv)

    from lidarscan_msgs.msg import LidarScan
    from rclpy.serialization import deserialize_message, serialize_message

    scan, _info = make_scan(128, 2048)
    payload = lidarscan.encode(scan)
    assert payload[:4] == b"\x00\x01\x00\x00"

    def ours_decode() -> list[np.ndarray]:
        msg = lidarscan.decode_scan(payload)
        return [lidarscan.channel(msg, name) for name in CHANNELS]

    def rclpy_decode() -> list[np.ndarray]:
        msg = deserialize_message(payload, LidarScan)
        return [lidarscan.channel(msg, name) for name in CHANNELS]

    # same numbers from both before timing anything
    for a, b in zip(ours_decode(), rclpy_decode(), strict=True):
        assert np.array_equal(a, b)
    dataclass_scan = lidarscan.decode_scan(payload)

    runs = args.runs
    t_dec = median_s(ours_decode, runs)
    t_dec_only = median_s(lambda: lidarscan.decode_scan(payload), runs)
    t_rdec = median_s(rclpy_decode, max(10, runs // 3))
    t_enc = median_s(lambda: lidarscan.encode(scan), runs)
    t_enc_dc = median_s(lambda: lidarscan.encode(dataclass_scan), runs)
    t_renc = median_s(lambda: serialize_message(scan), max(10, runs // 3))
    small, _ = make_scan(16, 512)
    small_payload = lidarscan.encode(small)

    def ours_decode_small() -> list[np.ndarray]:
        msg = lidarscan.decode_scan(small_payload)
        return [lidarscan.channel(msg, name) for name in CHANNELS]

    t_dec_small = median_s(ours_decode_small, runs)

    mb = len(payload) / 1e6
    print(f"LidarScan 128x2048, {len(CHANNELS)} channels, CDR payload {mb:.2f} MB, "
          f"median of {runs} runs")
    rows = [
        ("decode + 6 channel views (lidarscan)", t_dec),
        ("  decode_scan alone", t_dec_only),
        ("  same on a 16x512 scan (O(1) check)", t_dec_small),
        ("deserialize_message + 6 views (rclpy)", t_rdec),
        ("encode rclpy msg (lidarscan)", t_enc),
        ("encode decoded dataclass (lidarscan)", t_enc_dc),
        ("serialize_message (rclpy)", t_renc),
    ]
    for label, seconds in rows:
        print(f"  {label:<42s} {seconds * 1e6:10.1f} us")
    dec_ratio = t_rdec / t_dec
    enc_ratio = t_renc / t_enc
    print(f"decode speed-up vs rclpy: {dec_ratio:7.1f}x  (target >= 50x)  "
          f"{'OK' if dec_ratio >= 50 else 'MISSED'}")
    print(f"encode speed-up vs rclpy: {enc_ratio:7.1f}x  (target >= 1x)   "
          f"{'OK' if enc_ratio >= 1 else 'MISSED'}")
    return 0 if dec_ratio >= 50 and enc_ratio >= 1 else 1


if __name__ == "__main__":
    sys.exit(main())
