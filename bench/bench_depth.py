"""Benchmark: depth image -> LidarScan (converters.sources.depth) at 640x480 and 1280x720.

Run: ``.venv/bin/python bench/bench_depth.py [--repeat N]``. Prints medians and ratios measured in
one run (no assertions).

Cases, per size, for a raw image (K + plumb_bob, undistorted by Newton) and a rectified one (P):

* first call: ``DepthImageConverter(camera_info)`` (rays, LidarInfo) + one ``convert``;
* steady state: ``convert`` of a ``sensor_msgs/Image`` (rclpy message when available, else the
  dataclass), 16UC1 and 32FC1 (about 2 % zeros / NaN);
* baselines: the same work as plain per-pixel Python loops (rays: pinhole, undistortion by
  fixed-point iteration to 1e-12, azimuth/altitude, 1/cos; frame: REP 118 checks and z * 1/cos),
  timed on 16 rows (best of 3) and scaled to the image height; and a numpy depth_image_proc-style point cloud
  (``x = (u - cx) z / fx``, ``y = (v - cy) z / fy``, ``z``), the usual vectorised consumer.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _timing import interleaved_times  # noqa: E402

from converters.sources.depth import DepthImageConverter  # noqa: E402
from lidarscan import types  # noqa: E402

D = [-0.21, 0.05, 0.0012, -0.0008, -0.004]
LOOP_ROWS = 16


def camera_info(w: int, h: int, distorted: bool) -> Any:
    ci_cls = types.message_class("sensor_msgs/msg/CameraInfo")
    roi = types.message_class("sensor_msgs/msg/RegionOfInterest")(0, 0, 0, 0, False)
    f = 0.9 * w
    k = [f, 0.0, w / 2 - 0.5, 0.0, f, h / 2 - 0.5, 0.0, 0.0, 1.0]
    p = [f, 0.0, w / 2 - 0.5, 0.0, 0.0, f, h / 2 - 0.5, 0.0, 0.0, 0.0, 1.0, 0.0]
    return ci_cls(header=types.Header(types.Time(1, 0), "cam"), height=h, width=w,
                  distortion_model="plumb_bob", d=np.array(D if distorted else [0.0] * 5),
                  k=np.array(k), r=np.eye(3).reshape(-1), p=np.array(p), binning_x=0,
                  binning_y=0, roi=roi)


def image(values: np.ndarray, encoding: str) -> Any:
    h, w = values.shape
    try:
        import array

        from sensor_msgs.msg import Image
        msg = Image(height=h, width=w, encoding=encoding, is_bigendian=0,
                    step=w * values.itemsize)
        msg.data = array.array("B", values.tobytes())
        msg.header.frame_id = "cam"
        return msg
    except ImportError:
        cls = types.message_class("sensor_msgs/msg/Image")
        return cls(header=types.Header(types.Time(2, 0), "cam"), height=h, width=w,
                   encoding=encoding, is_bigendian=0, step=w * values.itemsize,
                   data=values.tobytes())


def loop_rays(ci: Any, rows: int) -> list[list[tuple[float, float, float]]]:
    """Per-pixel loop: pinhole, fixed-point undistortion, azimuth/altitude and 1/cos."""
    fx, cx, fy, cy = ci.k[0], ci.k[2], ci.k[4], ci.k[5]
    k1, k2, p1, p2, k3 = (float(c) for c in ci.d)
    out = []
    for v in range(rows):
        row = []
        for u in range(int(ci.width)):
            xd, yd = (u - cx) / fx, (v - cy) / fy
            x, y = xd, yd
            for _ in range(100):
                r2 = x * x + y * y
                g = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
                nx = (xd - 2 * p1 * x * y - p2 * (r2 + 2 * x * x)) / g
                ny = (yd - p1 * (r2 + 2 * y * y) - 2 * p2 * x * y) / g
                done = abs(nx - x) < 1e-12 and abs(ny - y) < 1e-12
                x, y = nx, ny
                if done:
                    break
            n = math.sqrt(x * x + y * y + 1)
            row.append((math.atan2(-x, 1.0), math.atan2(-y, math.hypot(1.0, x)), n))
        out.append(row)
    return out


def loop_frame(depth: list[list[float]], scale: list[list[float]], unit: float) -> list[float]:
    """Per-pixel loop: REP 118 checks and range = z * unit * |ray|."""
    out = []
    for zrow, srow in zip(depth, scale):
        for z, s in zip(zrow, srow):
            if z > 0 and z != math.inf:
                out.append(z * unit * s)
            elif z == math.inf or z == -math.inf:
                out.append(z)
            else:
                out.append(math.nan)
    return out


def best_of(fn: Any, factor: float, runs: int = 3) -> float:
    """Shortest of ``runs`` timings of ``fn`` in seconds, times ``factor``."""
    best = math.inf
    for _ in range(runs):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best * factor


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeat", type=int, default=30)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    for w, h in ((640, 480), (1280, 720)):
        z_mm = rng.integers(300, 10000, (h, w)).astype(np.uint16)
        z_mm[rng.random((h, w)) < 0.02] = 0
        z_m = (z_mm * 0.001).astype(np.float32)
        z_m[z_mm == 0] = np.nan
        msgs = {"16UC1": image(z_mm, "16UC1"), "32FC1": image(z_m, "32FC1")}
        raw, rect = camera_info(w, h, True), camera_info(w, h, False)
        print(f"\n{w}x{h} ({w * h} pixels), {args.repeat} rounds")

        first: dict[str, list[float]] = {}
        for name, ci, opt in (("raw (K + plumb_bob)", raw, False), ("rectified (P)", rect, True)):
            ts = []
            for _ in range(max(3, args.repeat // 10)):
                t = time.perf_counter()
                DepthImageConverter(ci, rectified=opt).convert(msgs["16UC1"])
                ts.append(time.perf_counter() - t)
            first[name] = ts
        loop_first = best_of(lambda: loop_rays(raw, LOOP_ROWS), h / LOOP_ROWS)
        print(f"  first call (rays + info + 1 frame): loop baseline {loop_first * 1e3:9.1f} ms "
              f"(raw model, {LOOP_ROWS} rows timed, scaled)")
        for name, ts in first.items():
            med = statistics.median(ts)
            print(f"    {name:24s} median {med * 1e3:7.1f} ms   "
                  f"{loop_first / med:6.0f}x faster than the loop")

        conv = DepthImageConverter(raw, rectified=False)
        scale = conv.scale.tolist()
        depth_f = z_m.astype(np.float64).tolist()
        depth_u = z_mm.astype(np.float64).tolist()
        fx, cx, fy, cy = rect.p[0], rect.p[2], rect.p[5], rect.p[6]
        uu = (np.arange(w, dtype=np.float32) - np.float32(cx)) / np.float32(fx)
        vv = (np.arange(h, dtype=np.float32) - np.float32(cy)) / np.float32(fy)

        def cloud() -> np.ndarray:
            z = z_m
            return np.stack([uu[None, :] * z, vv[:, None] * z, z], -1)

        cases = {
            "convert 16UC1": lambda: conv.convert(msgs["16UC1"]),
            "convert 32FC1": lambda: conv.convert(msgs["32FC1"]),
            "numpy xyz cloud (depth_image_proc-like)": cloud,
        }
        times = interleaved_times(cases, args.repeat)
        loop_u = best_of(lambda: loop_frame(depth_u[:LOOP_ROWS], scale[:LOOP_ROWS], 0.001),
                         h / LOOP_ROWS)
        loop_f = best_of(lambda: loop_frame(depth_f[:LOOP_ROWS], scale[:LOOP_ROWS], 1.0),
                         h / LOOP_ROWS)
        print(f"  steady state per frame: loop baseline 16UC1 {loop_u * 1e3:7.1f} ms, "
              f"32FC1 {loop_f * 1e3:7.1f} ms ({LOOP_ROWS} rows timed, scaled)")
        cloud_med = statistics.median(times["numpy xyz cloud (depth_image_proc-like)"])
        for name, ts in times.items():
            med, low = statistics.median(ts), min(ts)
            loop = loop_u if "16UC1" in name else loop_f
            print(f"    {name:40s} median {med * 1e3:6.2f} ms  min {low * 1e3:6.2f} ms  "
                  f"{loop / med:6.0f}x the loop  {med / cloud_med:5.2f}x the numpy cloud")


if __name__ == "__main__":
    main()
