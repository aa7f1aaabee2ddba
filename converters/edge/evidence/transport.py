"""Question 2: CPU per frame through real rclpy, and the receiver's conversion costs.

The real frames (OS-2-128 single return, OS-0-32 dual return) are published as a LidarScan and
as the PointCloud2s ouster-ros publishes (``ouster`` preset, 48 B/pt, one cloud per return) and
the minimal x,y,z,intensity cloud (16 B/pt), through rclpy on Fast DDS (one process, its own
Context and domain id, discovery limited to localhost). Per frame: ``serialize_message``,
``deserialize_message``, publish -> subscription callback (wall time) and the process CPU time of
that whole cycle (both ends run in this process). The receiver-side table times what a consumer
of LidarScan runs to get a PointCloud2 or LaserScan slices, against the per-point pipeline from a
PointCloud2. All numbers are the best of repeated runs (the least disturbed by other processes on
a shared machine) on the machine printed with them; the ratio columns compare figures of the
same run.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from converters.edge.evidence._common import (
    Block,
    fmt_int,
    have,
    load_frame,
    ouster_files,
    pending,
    short_name,
    table,
    time_call,
)

__all__ = ["SLICES", "blocks", "slices_from_cloud"]

#: Height bands (metres, sensor frame) of the slices: floor obstacles, robot body, overhead.
SLICES = {"low": (-1.0, -0.2), "mid": (-0.2, 0.3), "high": (0.3, 1.5)}
N_MESSAGES = 30


def slices_from_cloud(cloud: Any, bands: dict[str, tuple[float, float]], n: int,
                      range_min: float, range_max: float) -> dict[str, np.ndarray[Any, Any]]:
    """Per-point pipeline: LaserScan ranges from a PointCloud2's x, y, z (float32).

    The grid and classes are those of :mod:`converters.slices.spec` (full circle from -pi, n bins,
    nearest bin with the half-bin to the lower index, inclusive band and range limits, min
    planar range wins, below range_min -> -Inf, above range_max -> +Inf, empty -> +Inf), so the
    result can be compared bin for bin with :class:`converters.slices.converter.SliceConverter`.
    Points without a return (NaN) carry no information here: a point cloud has no rays.

    Returns:
        band name -> (n,) float32 ranges.
    """
    from converters.pointcloud2.converter import read_points
    pts = read_points(cloud).reshape(-1)
    x = pts["x"].astype(np.float64)
    y = pts["y"].astype(np.float64)
    z = pts["z"].astype(np.float64)
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(z)
    x, y, z = x[ok], y[ok], z[ok]
    rho = np.sqrt(x * x + y * y).astype(np.float32)
    inc = 2 * np.pi / n
    k = np.ceil((np.arctan2(y, x) + np.pi) / inc - 0.5).astype(np.int64) % n
    out = {}
    for name, (lo, hi) in bands.items():
        band = (z >= lo) & (z <= hi)
        r = rho[band]
        kb = k[band]
        value = np.where(r < np.float32(range_min), -np.inf,
                         np.where(r > np.float32(range_max), np.inf, r)).astype(np.float32)
        # classes: finite < -Inf < +Inf (order for the min): encode -Inf above every finite
        code = np.where(np.isfinite(value), value.astype(np.float64),
                        np.where(value < 0, 1e30, 2e30))
        best = np.full(n, 3e30)
        np.minimum.at(best, kb, code)
        ranges = np.where(best < 1e30, best, np.where(best < 1.5e30, -np.inf, np.inf))
        out[name] = ranges.astype(np.float32)
    return out


def _frames() -> list[tuple[str, Any, Any]]:
    """(label, rclpy LidarInfo, rclpy LidarScan) of the real frames."""
    from converters.sources.ouster.metadata import info_from_metadata, scan_from_frame
    out = []
    for meta, frame_path in ouster_files():
        if frame_path is None:
            continue
        info = info_from_metadata(meta, stamp_ns=1_000_000_000)
        frame = load_frame(frame_path)
        scan = scan_from_frame(frame, info)
        out.append((short_name(meta) + (" dual" if "range2_mm" in frame else ""), info, scan))
    return out


def _clouds(scan: Any, info: Any) -> dict[str, list[Any]]:
    """The PointCloud2 messages a driver publishes for this frame (one per return)."""
    from converters.pointcloud2.converter import to_pointcloud2
    names = [c.name for c in scan.channels]
    ranges = ["range"] + (["range2"] if "range2" in names else [])
    return {
        "PointCloud2 ouster-ros (48 B/pt)": [to_pointcloud2(scan, info, preset="ouster",
                                                            range_channel=r) for r in ranges],
        "PointCloud2 x,y,z,i (16 B/pt)": [to_pointcloud2(scan, info, preset="xyzi",
                                                         range_channel=r) for r in ranges],
    }


class _Ros:
    """A node with one publisher/subscription pair per message type, on a private Context."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        os.environ.pop("ROS_LOCALHOST_ONLY", None)
        self.rclpy = rclpy
        self.context = Context()
        rclpy.init(context=self.context, domain_id=150 + os.getpid() % 70)
        self.node = rclpy.create_node(f"lidarscan_evidence_{os.getpid()}", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def roundtrip(self, msgs: list[Any], repeat: int, depth: int = 4) -> tuple[float, float]:
        """(best wall s, best process CPU s) over ``repeat`` rounds, from publishing ``msgs``
        until every one of them has been received and deserialised by the subscription
        (``depth``: the QoS history depth, at least ``len(msgs)`` for a burst)."""
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        qos = QoSProfile(depth=depth,  # type: ignore[no-untyped-call]
                         reliability=ReliabilityPolicy.RELIABLE)
        topic = f"/evidence/t{id(msgs)}"
        got: list[Any] = []
        pub = self.node.create_publisher(type(msgs[0]), topic, qos)
        sub = self.node.create_subscription(type(msgs[0]), topic, got.append, qos)
        try:
            deadline = time.monotonic() + 10.0
            while pub.get_subscription_count() < 1 and time.monotonic() < deadline:
                self.executor.spin_once(timeout_sec=0.01)
            walls, cpus = [], []
            for i in range(repeat + 1):
                got.clear()
                w0, c0 = time.perf_counter(), time.process_time()
                for msg in msgs:
                    pub.publish(msg)
                deadline = time.monotonic() + 10.0
                while len(got) < len(msgs) and time.monotonic() < deadline:
                    self.executor.spin_once(timeout_sec=0.05)
                if len(got) < len(msgs):
                    raise RuntimeError(f"rclpy round trip on {topic} timed out")
                if i:  # the first round warms up
                    walls.append(time.perf_counter() - w0)
                    cpus.append(time.process_time() - c0)
            return min(walls), min(cpus)
        finally:
            self.node.destroy_subscription(sub)
            self.node.destroy_publisher(pub)

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=2.0)
        self.node.destroy_node()  # type: ignore[no-untyped-call]
        self.rclpy.shutdown(context=self.context)


def _wire(msgs: list[Any]) -> tuple[int, float, float]:
    """(bytes, serialize s, deserialize s) for a list of messages (summed)."""
    from rclpy.serialization import deserialize_message, serialize_message
    blobs = [serialize_message(m) for m in msgs]
    ser = time_call(lambda: [serialize_message(m) for m in msgs], repeat=5)
    des = time_call(lambda: [deserialize_message(b, type(m)) for b, m in zip(blobs, msgs)],
                    repeat=5)
    return sum(len(b) for b in blobs), ser, des


def _transport_table(ros: _Ros) -> str:
    rows = []
    for label, info, scan in _frames():
        candidates: dict[str, list[Any]] = {"LidarScan": [scan]}
        candidates.update(_clouds(scan, info))
        base: dict[str, float] = {}
        for name, msgs in candidates.items():
            size, ser, des = _wire(msgs)
            wall, cpu = ros.roundtrip(msgs, N_MESSAGES)
            if name == "LidarScan":
                base = {"cpu": cpu, "wall": wall}
            rows.append([label, name + (f" ×{len(msgs)}" if len(msgs) > 1 else ""),
                         fmt_int(size), f"{ser * 1e3:.2f}", f"{des * 1e3:.2f}",
                         f"{wall * 1e3:.2f}", f"{cpu * 1e3:.2f}",
                         f"{cpu / base['cpu']:.1f}×", f"{wall / base['wall']:.1f}×"])
    return table(["frame", "message", "bytes", "serialize ms", "deserialize ms",
                  "publish→callback ms (wall)", "CPU ms per frame (both ends)",
                  "CPU ÷ LidarScan", "wall ÷ LidarScan"], rows,
                 ["l", "l"] + ["r"] * 7)


def _receiver_table() -> str:
    from rclpy.serialization import serialize_message

    import lidarscan as ls
    from converters.slices.converter import SliceConverter
    from converters.pointcloud2.converter import to_pointcloud2
    rows = []
    for label, info, scan in _frames():
        cdr = bytes(serialize_message(scan))
        proj = ls.make_projector(info)
        slicer = SliceConverter(info, {k: {"min_height": lo, "max_height": hi}
                                       for k, (lo, hi) in SLICES.items()},
                                intensity_channel=None)
        first = next(iter(slicer.convert(scan).values()))
        n = len(first.ranges)
        cloud = to_pointcloud2(scan, info, preset="ouster")
        rmin, rmax = float(first.range_min), float(first.range_max)
        cases: list[tuple[str, Callable[[], Any]]] = [
            ("LidarScan CDR → numpy views (lidarscan.decode_scan, zero-copy)",
             lambda: ls.channel(ls.decode_scan(cdr), "range")),
            ("LidarScan → x,y,z (projector, float32)", lambda: proj.project(scan, info)),
            ("LidarScan → PointCloud2 ouster-ros layout (to_pointcloud2)",
             lambda: to_pointcloud2(scan, info, preset="ouster")),
            ("LidarScan → PointCloud2 x,y,z,i (to_pointcloud2)",
             lambda: to_pointcloud2(scan, info, preset="xyzi")),
            (f"LidarScan → {len(SLICES)} LaserScan slices (SliceConverter)",
             lambda: slicer.convert(scan)),
            (f"PointCloud2 (ouster-ros) → {len(SLICES)} slices, per point (numpy)",
             lambda: slices_from_cloud(cloud, SLICES, n, rmin, rmax)),
        ]
        times = [(name, time_call(fn, repeat=5)) for name, fn in cases]
        base = next(t for name, t in times if "SliceConverter" in name)
        rows += [[label, name, f"{t * 1e3:.2f}", f"{t / base:.2f}"] for name, t in times]
    return table(["frame", "receiver step", "ms per frame", "÷ SliceConverter"], rows,
                 ["l", "l", "r", "r"])


def blocks() -> list[Block]:
    """``timing-transport`` and ``timing-receiver`` blocks (placeholders if a part is missing)."""
    ok, why = have("converters.pointcloud2.converter", "to_pointcloud2", "read_points")
    ok2, why2 = have("converters.slices.converter", "SliceConverter")
    try:
        import lidarscan_msgs.msg  # noqa: F401
        import rclpy  # noqa: F401
    except ImportError as err:
        return [pending("timing-transport", "CPU per frame through rclpy", str(err), False),
                pending("timing-receiver", "receiver-side conversions", str(err), False)]
    out = []
    if not ok:
        out.append(pending("timing-transport", "CPU per frame through rclpy", why, False))
    else:
        ros = _Ros()
        try:
            out.append(Block("timing-transport", _transport_table(ros), deterministic=False))
        finally:
            ros.close()
    if not (ok and ok2):
        out.append(pending("timing-receiver", "receiver-side conversions", why or why2, False))
    else:
        out.append(Block("timing-receiver", _receiver_table(), deterministic=False))
    return out
