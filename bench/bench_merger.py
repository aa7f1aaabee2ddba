"""Benchmark: LaserScanMerger.merge of 4 inputs x 1440 rays into a 1440-bin full circle.

Run: ``.venv/bin/python bench/bench_merger.py [--repeat N]``. Prints medians, minima and merge
rates measured in one run (no assertions). Target: >= 2 kHz.

Inputs: four 270-degree lidars at the corners of a 1 x 0.6 m robot, each turned outwards
(yaw 45/135/-135/-45 deg), 1440 rays at 0.1875 deg, ranges 0.1..30 m with 3 % +Inf, 1 % NaN and
1 % zeros, float32 intensities; as rclpy ``sensor_msgs.msg.LaserScan`` messages (array.array
fields, what a node receives). Cases: static extrinsics (cached rays, no atan2), the same with
odometry motion compensation (rays moved every merge), the numpy backend, and ``push`` of the
four streams (synchronisation included).
"""

from __future__ import annotations

import argparse
import array
import math
import statistics
import time
from typing import Any

import numpy as np

from converters.merger import LaserScanMerger, MergerInput


def pose(x: float, y: float, yaw: float) -> np.ndarray:
    m = np.eye(4)
    m[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    m[:2, 3] = (x, y)
    return m


def make_scan(rng: np.random.Generator, stamp: int, n: int = 1440) -> Any:
    from builtin_interfaces.msg import Time
    from sensor_msgs.msg import LaserScan
    from std_msgs.msg import Header
    r = rng.uniform(0.1, 30.0, n).astype(np.float32)
    kind = rng.random(n)
    r[kind < 0.03] = np.inf
    r[(kind >= 0.03) & (kind < 0.04)] = np.nan
    r[(kind >= 0.04) & (kind < 0.05)] = 0.0
    inc = math.radians(270.0) / n
    msg = LaserScan(header=Header(stamp=Time(sec=stamp // 10**9, nanosec=stamp % 10**9),
                                  frame_id="laser"),
                    angle_min=-math.radians(135.0), angle_max=-math.radians(135.0) + (n - 1) * inc,
                    angle_increment=inc, time_increment=0.0, scan_time=0.05, range_min=0.05,
                    range_max=30.0)
    msg.ranges = array.array("f", r.tobytes())
    msg.intensities = array.array("f", rng.uniform(0, 1000, n).astype(np.float32).tobytes())
    return msg


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeat", type=int, default=2000)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    corners = {"front_left": (0.5, 0.3, math.pi / 4), "rear_left": (-0.5, 0.3, 3 * math.pi / 4),
               "rear_right": (-0.5, -0.3, -3 * math.pi / 4),
               "front_right": (0.5, -0.3, -math.pi / 4)}
    inputs = {k: MergerInput(extrinsics=pose(*v), range_min=0.1) for k, v in corners.items()}
    t0 = 1_700_000_000_000_000_000
    scans = {k: make_scan(rng, t0 + 1_000_000 * i) for i, k in enumerate(inputs)}

    from lidarscan.types import Header, Time, message_class
    odom_cls = message_class("nav_msgs/msg/Odometry")
    pose_cls = message_class("geometry_msgs/msg/Pose")

    def odom(t: int, x: float, yaw: float) -> Any:
        pt = message_class("geometry_msgs/msg/Point")(x=x, y=0.0, z=0.0)
        q = message_class("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=math.sin(yaw / 2),
                                                          w=math.cos(yaw / 2))
        pwc = message_class("geometry_msgs/msg/PoseWithCovariance")(
            pose=pose_cls(position=pt, orientation=q), covariance=np.zeros(36))
        return odom_cls(header=Header(Time(t // 10**9, t % 10**9), "odom"),
                        child_frame_id="base_link", pose=pwc, twist=None)

    cases: dict[str, Any] = {}
    try:
        import numba  # noqa: F401
        fast = LaserScanMerger(inputs, backend="numba")
        cases["merge, static extrinsics (numba kernel)"] = lambda: fast.merge(scans)
        moving = LaserScanMerger(inputs, backend="numba")
        for k in range(10):
            moving.push_odometry(odom(t0 - 5_000_000 + 2_000_000 * k, 0.01 * k, 0.02 * k))
        cases["merge + motion compensation (numba)"] = lambda: moving.merge(scans)
    except ImportError:
        pass
    slow = LaserScanMerger(inputs, backend="numpy")
    cases["merge, static extrinsics (numpy)"] = lambda: slow.merge(scans)

    streamer = LaserScanMerger(inputs, slop_ns=10_000_000)
    names = list(inputs)
    state = {"t": t0}
    stream = [{k: make_scan(rng, 0) for k in names} for _ in range(4)]

    def push_all() -> Any:
        state["t"] += 50_000_000
        batch = stream[(state["t"] // 50_000_000) % 4]
        out = None
        for i, k in enumerate(names):
            msg = batch[k]
            t = state["t"] + 1_000_000 * i
            msg.header.stamp.sec, msg.header.stamp.nanosec = t // 10**9, t % 10**9
            out = streamer.push(k, msg)
        return out
    cases["push x4 (sync + merge)"] = push_all

    for fn in cases.values():
        fn()
    times: dict[str, list[float]] = {k: [] for k in cases}
    for _ in range(args.repeat):
        for name, fn in cases.items():
            t = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t)
    print(f"4 inputs x 1440 rays -> 1440 bins, {args.repeat} runs each (interleaved)")
    for name, ts in times.items():
        med, low = statistics.median(ts), min(ts)
        print(f"  {name:40s} median {med * 1e6:7.1f} us ({1 / med:7.0f} Hz)   "
              f"min {low * 1e6:7.1f} us ({1 / low:7.0f} Hz)")
    print("  target: >= 2000 Hz;", "merged sets while pushing:", streamer.stats["merged"])


if __name__ == "__main__":
    main()
