"""First scans of a freshly started converter node, as a driver-side system starts it.

The ``lidarscan-converter`` node is started as a process (one slice, the mount of
``bench_startup.py``, reliable input and output QoS); a driver-like publisher in this process
latches the real OS-2-128 LidarInfo (``tests/data/ouster``, 128 x 1024) and starts publishing
the real frame at 10 Hz, stamped with the wall clock, as soon as the node's scan subscription
matches. Every PointCloud2 and LaserScan the node publishes is received raw (the stamp read from
the CDR header); latency = receive time - scan stamp.

Cases: numba's cache cold (``NUMBA_CACHE_DIR`` an empty temporary directory: a plain ``pip
install``, a new CPU) and warm (the same directory after the first run's background fill has
finished).

Goal (issue 30): no scan lost, and each of the first ten scans' latency <= 2 x the steady state
(median of scans 20 and later) + 50 ms, cold and warm. Figures: bench/README.md.

Run: ``.venv/bin/python bench/bench_first_scans.py [--scans N] [--root CHECKOUT]`` (``--root``:
the node's code from another checkout, e.g. to measure a commit before a change).
"""

from __future__ import annotations

import json
import os
import re
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data" / "ouster"
META = DATA / "OS-2-128-U1_v2.3.0_1024x10.json"
FRAME = DATA / "OS-2-128-U1_v2.3.0_1024x10_frame1259.npz"
PARAMS = {"scan_qos": "reliable", "output_qos": "reliable", "slice_names": "[knee]",
          "slices.knee.min_height": "0.05", "slices.knee.max_height": "0.5",
          "target_frame": "base_link", "extrinsics": "[0.0, 0.0, 0.4, 0.0, 0.0, 0.0]"}
FIRST = 10          # scans held to the goal
STEADY_FROM = 20    # scans from this index on make the steady state


def _stamp_ns(raw: bytes) -> int:
    """The header stamp of a raw CDR message (PointCloud2, LaserScan: header first)."""
    sec, nanosec = struct.unpack_from("<iI" if raw[1] == 1 else ">iI", raw, 4)
    return sec * 1_000_000_000 + nanosec


def node_command() -> list[str]:
    """The console script of the converter node (its module when the script is missing)."""
    script = Path(sys.executable).parent / "lidarscan-converter"
    return [str(script)] if script.exists() else [sys.executable, "-m",
                                                  "converters.edge.nodes.converter_node"]


def measure(cache_dir: str, scans: int = 60, rate_hz: float = 10.0, domain: int | None = None,
            timeout: float = 120.0, root: Path = ROOT, drain_s: float = 10.0) -> dict[str, Any]:
    """Start the node with ``NUMBA_CACHE_DIR=cache_dir`` (the code of checkout ``root``),
    publish ``scans`` scans as soon as its subscription matches, and return what came back
    within ``drain_s`` seconds after the last one.

    Returns:
        ``sent`` (stamps), ``clouds`` / ``slices`` (stamps in arrival order), ``cloud_ms`` /
        ``slice_ms`` (stamp -> latency, ms), ``start_s`` (process start to the match),
        ``ready_s`` (process start to its ``ready`` line), ``log`` (the node's output).
    """
    import numpy as np
    import rclpy
    from converters.ouster import info_from_metadata, scan_from_frame
    from lidarscan_msgs.msg import LidarInfo, LidarScan
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import LaserScan, PointCloud2

    import lidarscan

    domain = 1 + (os.getpid() + 37) % 100 if domain is None else domain
    info = info_from_metadata(META, stamp_ns=1, frame_id="os_lidar", as_dataclass=True)
    frame = dict(np.load(FRAME))
    raw = bytearray(lidarscan.encode(scan_from_frame(frame, info, stamp_ns=1,
                                                     as_dataclass=True)))
    env = {k: v for k, v in os.environ.items() if not k.startswith("_ROS_WHEELS")}
    env.update(NUMBA_CACHE_DIR=cache_dir, PYTHONPATH=str(root), ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED="1",
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", RCUTILS_LOGGING_BUFFERED_STREAM="0")
    env.pop("ROS_LOCALHOST_ONLY", None)
    args = [a for k, v in PARAMS.items() for a in ("-p", f"{k}:={v}")]
    reliable = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain)
    arrivals: dict[str, list[tuple[int, int]]] = {"clouds": [], "slices": []}
    log = tempfile.TemporaryFile(mode="w+")  # noqa: SIM115 - read after the node stops
    proc = None
    executor = SingleThreadedExecutor(context=context)
    spinner = None
    try:
        node = rclpy.create_node("driver", context=context)
        executor.add_node(node)
        info_pub = node.create_publisher(LidarInfo, "lidar_info", latched)
        scan_pub = node.create_publisher(LidarScan, "lidar_scan", reliable)
        for name, (kind, topic) in {"clouds": (PointCloud2, "points"),
                                    "slices": (LaserScan, "slices/knee")}.items():
            box = arrivals[name]
            node.create_subscription(kind, topic, lambda raw, box=box: box.append(
                (_stamp_ns(raw), time.time_ns())), reliable, raw=True)
        info_pub.publish(lidarscan.encode(info))
        spinner = threading.Thread(target=executor.spin, daemon=True)
        spinner.start()
        start, start_wall = time.monotonic(), time.time()
        proc = subprocess.Popen([*node_command(), "--ros-args", *args], env=env,
                                stdout=log, stderr=subprocess.STDOUT)
        while scan_pub.get_subscription_count() == 0:     # the driver waits for the match
            if proc.poll() is not None or time.monotonic() - start > timeout:
                log.seek(0)
                raise RuntimeError(f"the node did not subscribe:\n{log.read()[-3000:]}")
            time.sleep(0.002)
        matched = time.monotonic() - start
        sent = []
        period = 1.0 / rate_hz
        t0 = time.monotonic()
        for k in range(scans):
            time.sleep(max(0.0, t0 + k * period - time.monotonic()))
            stamp = time.time_ns()
            struct.pack_into("<iI" if raw[1] == 1 else ">iI", raw, 4,
                             *divmod(stamp, 1_000_000_000))       # the header's stamp
            scan_pub.publish(bytes(raw))
            sent.append(stamp)
        end = time.monotonic() + drain_s
        while time.monotonic() < end and (len(arrivals["clouds"]) < scans
                                          or len(arrivals["slices"]) < scans):
            time.sleep(0.05)
    finally:
        if proc is not None and proc.poll() is None:
            proc.send_signal(2)
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        executor.shutdown(timeout_sec=2.0)
        if spinner is not None:
            spinner.join(timeout=5.0)
        rclpy.try_shutdown(context=context)
    log.seek(0)
    out: dict[str, Any] = {"sent": sent, "start_s": round(matched, 3), "log": log.read()}
    log.close()
    ready = re.search(r"\[(\d+\.\d+)\] \[[^]]*\]: ready:", out["log"])
    out["ready_s"] = round(float(ready.group(1)) - start_wall, 3) if ready else None
    for name, box in arrivals.items():
        out[name] = [s for s, _ in box]
        out[name[:-1] + "_ms"] = {s: (t - s) / 1e6 for s, t in box}
    return out


def goal(result: dict[str, Any]) -> dict[str, Any]:
    """Losses, the steady state and the first scans' latencies of a :func:`measure`."""
    sent = result["sent"]
    row: dict[str, Any] = {"start_s": result["start_s"], "ready_s": result["ready_s"]}
    ok = True
    for kind in ("cloud", "slice"):
        got = result[kind + "_ms"]
        lost = [k for k, s in enumerate(sent) if s not in got]
        late = [got[s] for s in sent[STEADY_FROM:] if s in got]
        steady = statistics.median(late) if late else float("nan")
        first = [round(got.get(s, float("inf")), 1) for s in sent[:FIRST]]
        row[kind] = {"lost": len(lost), "steady_ms": round(steady, 1), "first_ms": first}
        ok &= bool(late) and not lost and max(first) <= 2 * steady + 50
    row["met"] = ok
    return row


def main() -> int:
    argv = sys.argv
    scans = int(argv[argv.index("--scans") + 1]) if "--scans" in argv else 60
    root = Path(argv[argv.index("--root") + 1]) if "--root" in argv else ROOT
    failed = 0
    with tempfile.TemporaryDirectory() as cache:
        for case in ("cold", "warm"):
            if case == "warm":        # the cold start's background fill, or fill it here
                subprocess.run([sys.executable, "-m", "converters.warmup", "--config",
                                json.dumps({"tasks": ["cloud", "slices"], "moving": False,
                                            "slices": {"knee": {"min_height": 0.05,
                                                                "max_height": 0.5}}})],
                               env={**os.environ, "NUMBA_CACHE_DIR": cache,
                                    "PYTHONPATH": str(root)}, check=False, capture_output=True)
            result = measure(cache, scans, root=root)
            row = goal(result)
            ready = [line for line in result["log"].splitlines() if "ready:" in line]
            failed += not row["met"]
            print(f"{case}: process start->ready {row['ready_s']} s, ->subscribed "
                  f"{row['start_s']:.2f} s; "
                  + "; ".join(f"{k}: lost {row[k]['lost']}, steady {row[k]['steady_ms']} ms, "
                              f"first ten {row[k]['first_ms']} ms" for k in ("cloud", "slice"))
                  + f"; goal {'met' if row['met'] else 'MISSED'}", flush=True)
            print("   node: " + (ready[0].split("ready:", 1)[1].strip() if ready else "?"),
                  flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
