"""Soak test of the converter and merger nodes over real Fast DDS, with restarts.

Processes (each its own python, all on a private ROS_DOMAIN_ID):

* ``publisher``: LidarInfo once at start on a latched topic (reliable, transient local), then
  LidarScans of H x W (default 128 x 2048, range float32 + intensity uint16) at ``--rate`` Hz
  (default 40 Hz: twice a 128 x 2048 sensor at 20 Hz) on ``/lidar_scan`` (sensor data QoS), and
  a 2D LaserScan with the same stamp on ``/laser``. Stamps are the wall clock at publication.
* ``converter``: ``python -m converters.edge.nodes.converter_node`` -> ``/points`` (PointCloud2) and
  ``/slices/mid`` (LaserScan slice).
* ``merger``: ``python -m converters.edge.nodes.merger_node`` merging ``/slices/mid`` and ``/laser``
  -> ``/scan_merged``.
* ``monitor``: raw subscriptions to the three outputs; latency = receive wall clock - header
  stamp (same machine, same clock).

Timeline (fractions of ``--seconds``): at 50 % the publisher is killed (SIGINT) and a new one
started (its LidarInfo is published again with the same stamp); at 65 % the merger node is
restarted; at 80 % the converter node is restarted: it must get the LidarInfo from the
publisher's latched topic (the publisher does not publish it again) and resume without manual
action. Throughout, ``--inject-bad`` (2 %) of the scan slots carry a malformed LidarScan
(truncated, junk bytes, or naming a LidarInfo that never comes) and a malformed LaserScan (NaN
angles) instead of good ones: the nodes must drop them and stay alive (checked at the end).

Prints, per output: published vs received scans (drops), latency p50/p99/max, the outage after
each restart; per process: CPU (% of one core), peak RSS, and RSS growth after warm-up (flat
memory check). Usage::

    .venv/bin/python bench/soak.py                    # 60 s, 128 x 2048 at 40 Hz
    .venv/bin/python bench/soak.py --seconds 20 --width 1024 --rate 20
"""

from __future__ import annotations

import argparse
import array
import itertools
import json
import math
import os
import platform
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PY = sys.executable
INFO_STAMP_NS = 1_700_000_000_000_000_000
OUTPUTS = ("/points", "/slices/mid", "/scan_merged")
INPUTS = ("/lidar_scan",)  # also received by the monitor: separates transport loss from node loss


# ------------------------------------------------------------------------------- publisher

def _room_ranges(info: Any, frames: int, rng: np.random.Generator) -> list[np.ndarray[Any, Any]]:
    """Ranges of a 16 x 10 x 3 m box room seen from (1, 0.5, 1.2) m, with a little noise."""
    import lidarscan as ls
    d = ls.make_projector(info).directions.astype(np.float64)          # (H, W, 3)
    origin = np.array([1.0, 0.5, 1.2])
    low, high = np.array([-8.0, -5.0, 0.0]), np.array([8.0, 5.0, 3.0])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d > 0, (high - origin) / d, np.where(d < 0, (low - origin) / d, np.inf))
    base = t.min(axis=-1).astype(np.float32)
    return [(base + rng.normal(0, 0.01, base.shape)).astype(np.float32) for _ in range(frames)]


def run_publisher(args: argparse.Namespace) -> int:
    import rclpy
    from lidarscan_msgs.msg import LidarInfo, LidarScan
    from sensor_msgs.msg import LaserScan

    import lidarscan as ls
    from converters.edge.nodes.params import qos_profile

    height, width = args.height, args.width
    info = ls.make_info(stamp_ns=INFO_STAMP_NS, frame_id="lidar",
                        vertical_angles=np.radians(np.linspace(22.5, -22.5, height)),
                        horizontal_angles=2 * np.pi * (1 - np.arange(width) / width),
                        pixel_shift_by_row=np.tile([12, 8, 4, 0], height // 4 + 1)[:height],
                        column_time_increment=int(1e9 / (20 * width)), range_min=0.3,
                        range_max=200.0)
    info_dc = ls.decode_info(ls.encode(info))
    rng = np.random.default_rng(1)
    frames = []
    for ranges in _room_ranges(info_dc, 4, rng):
        intensity = rng.integers(0, 4000, (height, width), dtype=np.uint16)
        frames.append(ls.make_scan(info_dc, {"range": ranges, "intensity": intensity},
                                   INFO_STAMP_NS))
    laser = LaserScan()
    laser.header.frame_id = "lidar"
    laser.angle_min, laser.angle_increment = -math.pi, math.radians(0.5)
    laser.angle_max = laser.angle_min + 719 * laser.angle_increment
    laser.range_min, laser.range_max, laser.scan_time = 0.1, 30.0, 1.0 / args.rate
    laser.ranges = array.array("f", np.full(720, 7.5, np.float32).tobytes())
    # malformed messages injected in place of some scans (counted apart, never "expected")
    good_cdr = ls.encode(ls.decode_scan(ls.encode(frames[0])))
    orphan_info = ls.make_info(stamp_ns=INFO_STAMP_NS + 1, frame_id="lidar",
                               vertical_angles=np.asarray(info_dc.vertical_angles),
                               horizontal_angles=np.asarray(info_dc.horizontal_angles),
                               as_dataclass=True)
    bad_scans = [
        good_cdr[:4096],                                                  # truncated
        b"\x00\x01\x00\x00" + rng.integers(0, 256, 3000, np.uint8).tobytes(),  # junk
        ls.encode(ls.make_scan(orphan_info, {"range": np.ones((height, width), np.float32)},
                               INFO_STAMP_NS, as_dataclass=True)),      # its info never comes
    ]
    from lidarscan import types as lt
    bad_laser = ls.encode(lt.message_class("sensor_msgs/msg/LaserScan")(
        header=lt.Header(lt.Time(0, 0), "lidar"), angle_min=math.nan, angle_max=1.0,
        angle_increment=math.nan, time_increment=0.0, scan_time=0.0, range_min=0.1,
        range_max=30.0, ranges=np.ones(10, np.float32), intensities=np.ones(3, np.float32)))

    rclpy.init()
    node = rclpy.create_node("soak_publisher")
    info_pub = node.create_publisher(LidarInfo, "lidar_info", qos_profile("latched"))
    scan_pub = node.create_publisher(LidarScan, "lidar_scan", qos_profile(args.qos))
    laser_pub = node.create_publisher(LaserScan, "laser", qos_profile(args.qos))
    info_pub.publish(info)  # once: late joiners get it from the latched topic
    stamps: list[int] = []
    injected = 0
    period = 1.0 / args.rate
    stop = {"now": False}
    signal.signal(signal.SIGINT, lambda *_: stop.update(now=True))
    signal.signal(signal.SIGTERM, lambda *_: stop.update(now=True))
    next_t = time.monotonic()
    k = 0
    late = 0
    while not stop["now"]:
        now_ns = time.time_ns()
        sec, nanosec = divmod(now_ns, 10**9)
        if rng.random() < args.inject_bad:
            bad = bytearray(bad_scans[injected % len(bad_scans)])
            if len(bad) >= 12:
                bad[4:12] = np.array([sec], "<i4").tobytes() + np.array([nanosec], "<u4").tobytes()
            scan_pub.publish(bytes(bad))
            if injected % 2:  # NaN angles, current stamp
                bad2 = bytearray(bad_laser)
                bad2[4:12] = np.array([sec], "<i4").tobytes() + \
                    np.array([nanosec], "<u4").tobytes()
                laser_pub.publish(bytes(bad2))
            else:  # NaN angles and a zero stamp (a driver that does not stamp)
                laser_pub.publish(bad_laser)
            injected += 1
        else:
            msg = frames[k % len(frames)]
            msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
            laser.header.stamp.sec, laser.header.stamp.nanosec = sec, nanosec
            scan_pub.publish(msg)
            laser_pub.publish(laser)
            stamps.append(now_ns)
        k += 1
        next_t += period
        delay = next_t - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        else:
            late += 1
            if delay < -period:  # cannot keep up: do not burst, resynchronise
                next_t = time.monotonic()
    Path(args.out).write_text(json.dumps({"stamps": stamps, "late": late,
                                          "injected": injected}))
    node.destroy_node()  # type: ignore[no-untyped-call]
    rclpy.try_shutdown()  # type: ignore[attr-defined]
    return 0


# --------------------------------------------------------------------------------- monitor

def _stamp_of(raw: bytes) -> int:
    """header.stamp of a CDR message whose first field is a std_msgs/Header (LE)."""
    sec = int.from_bytes(raw[4:8], "little", signed=True)
    nanosec = int.from_bytes(raw[8:12], "little")
    return sec * 10**9 + nanosec


def run_monitor(args: argparse.Namespace) -> int:
    import rclpy
    from sensor_msgs.msg import LaserScan, PointCloud2

    from converters.edge.nodes.params import qos_profile

    rclpy.init()
    node = rclpy.create_node("soak_monitor")
    from lidarscan_msgs.msg import LidarScan

    records: dict[str, list[tuple[int, int]]] = {t: [] for t in OUTPUTS + INPUTS}

    def callback(topic: str) -> Any:
        rows = records[topic]
        return lambda raw: rows.append((_stamp_of(raw), time.time_ns()))

    for topic, cls in zip(OUTPUTS + INPUTS, (PointCloud2, LaserScan, LaserScan, LidarScan)):
        node.create_subscription(cls, topic, callback(topic), qos_profile(args.qos), raw=True)
    stop = {"now": False}
    signal.signal(signal.SIGINT, lambda *_: stop.update(now=True))
    while not stop["now"]:
        rclpy.spin_once(node, timeout_sec=0.1)
    Path(args.out).write_text(json.dumps(records))
    node.destroy_node()  # type: ignore[no-untyped-call]
    rclpy.try_shutdown()  # type: ignore[attr-defined]
    return 0


# ------------------------------------------------------------------------------ orchestrator

def _node_cmd(kind: str, qos: str) -> list[str]:
    if kind == "converter":
        return [PY, "-m", "converters.edge.nodes.converter_node", "--ros-args",
                "-p", "slice_names:=[mid]", "-p", "slices.mid.min_height:=-0.3",
                "-p", "slices.mid.max_height:=0.3", "-p", f"scan_qos:={qos}",
                "-p", f"output_qos:={qos}", "--log-level", "warn"]
    return [PY, "-m", "converters.edge.nodes.merger_node", "--ros-args",
            "-p", f"inputs.mid.qos:={qos}", "-p", f"inputs.laser.qos:={qos}",
            "-p", f"output_qos:={qos}",
            "-p", "input_names:=[mid, laser]", "-p", "inputs.mid.topic:=/slices/mid",
            "-p", "inputs.laser.topic:=/laser", "-p", "frame_id:=lidar", "-p", "use_tf:=false",
            "-p", "motion_compensation:=false", "-p", "angle_increment:=0.00872664626",
            "--log-level", "warn"]


class Watched:
    """A child process with CPU and RSS samples (psutil)."""

    def __init__(self, name: str, cmd: list[str], env: dict[str, str], log: Path) -> None:
        import psutil
        self.name = name
        self.log = open(log, "ab")  # noqa: SIM115
        self.proc = subprocess.Popen(cmd, env=env, stdout=self.log, stderr=subprocess.STDOUT,
                                     cwd=ROOT)
        self.ps = psutil.Process(self.proc.pid)
        self.started = time.monotonic()
        self.rss: list[tuple[float, float]] = []  # (seconds since soak start, MiB)
        self.cpu_s = 0.0

    def sample(self, t: float) -> None:
        import psutil
        try:
            rss = self.ps.memory_info().rss / 2**20
            times = self.ps.cpu_times()
        except psutil.Error:  # the process has just exited
            return
        self.rss.append((t, rss))
        self.cpu_s = times.user + times.system

    def stop(self, sig: int = signal.SIGINT, timeout: float = 15.0) -> float:
        """Stop; returns the seconds it ran."""
        ran = time.monotonic() - self.started
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()
        return ran


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def run_soak(args: argparse.Namespace) -> int:
    workdir = Path(tempfile.mkdtemp(prefix="soak-"))
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(args.domain if args.domain >= 0 else 100 + os.getpid() % 100)
    env.setdefault("RCUTILS_LOGGING_BUFFERED_STREAM", "1")
    if args.transport != "default":
        env["FASTDDS_BUILTIN_TRANSPORTS"] = args.transport.upper()
    me = [PY, str(Path(__file__).resolve())]
    common = ["--height", str(args.height), "--width", str(args.width), "--rate", str(args.rate),
              "--qos", args.qos, "--inject-bad", str(args.inject_bad)]
    t0 = time.monotonic()
    load0 = os.getloadavg()[0]
    events: list[tuple[float, str]] = []

    def now() -> float:
        return time.monotonic() - t0

    def start(name: str, cmd: list[str]) -> Watched:
        events.append((now(), f"start {name}"))
        return Watched(name, cmd, env, workdir / f"{name}.log")

    monitor = start("monitor", me + ["monitor", "--qos", args.qos,
                                     "--out", str(workdir / "monitor.json")])
    converters = [start("converter", _node_cmd("converter", args.qos))]
    merger = start("merger", _node_cmd("merger", args.qos))
    mergers = [merger]
    time.sleep(args.startup)  # nodes up before data flows (their start-up is not measured)
    pub_files = [workdir / "pub0.json"]
    publishers = [start("publisher", me + ["publisher", "--out", str(pub_files[0])] + common)]
    measure_start = now()
    restarts = {"publisher": measure_start + 0.5 * args.seconds,
                "merger": measure_start + 0.65 * args.seconds,
                "converter": measure_start + 0.8 * args.seconds}
    end = measure_start + args.seconds
    done: set[str] = set()
    cpu_runs: dict[str, list[tuple[float, float]]] = {}  # name -> [(cpu s, wall s)]

    exits: list[str] = []

    def finish(w: Watched) -> None:
        w.sample(now())
        alive = w.proc.poll() is None  # a node that crashed on bad input is dead by now
        ran = w.stop()
        cpu_runs.setdefault(w.name, []).append((w.cpu_s, ran))
        exits.append(f"{w.name} {'alive' if alive else 'DIED'} until stopped, exit status "
                     f"{w.proc.returncode}")

    while now() < end:
        t = now()
        for w in [monitor, merger, converters[-1], publishers[-1]]:
            w.sample(t)
        if "publisher" not in done and t >= restarts["publisher"] and not args.no_restart:
            done.add("publisher")
            events.append((now(), "stop publisher"))
            finish(publishers[-1])
            pub_files.append(workdir / f"pub{len(pub_files)}.json")
            publishers.append(start("publisher", me + ["publisher", "--out", str(pub_files[-1])]
                                    + common))
        if "merger" not in done and t >= restarts["merger"] and not args.no_restart:
            done.add("merger")
            events.append((now(), "stop merger"))
            finish(merger)
            mergers.append(start("merger", _node_cmd("merger", args.qos)))
            merger = mergers[-1]
        if "converter" not in done and t >= restarts["converter"] and not args.no_restart:
            done.add("converter")
            events.append((now(), "stop converter"))
            finish(converters[-1])
            converters.append(start("converter", _node_cmd("converter", args.qos)))
        time.sleep(0.5)
    events.append((now(), "stop all"))
    finish(publishers[-1])
    time.sleep(1.0)  # let the last messages through
    for w in (converters[-1], mergers[-1]):
        finish(w)
    finish(monitor)

    published: list[int] = []
    late = injected = 0
    for path in pub_files:
        data = json.loads(path.read_text())
        published += data["stamps"]
        late += data["late"]
        injected += data["injected"]
    received = json.loads((workdir / "monitor.json").read_text())
    wall0_ns = time.time_ns() - int(now() * 1e9)  # wall clock of the orchestrator's t0

    def at(stamp_ns: int) -> float:
        return (stamp_ns - wall0_ns) / 1e9

    print(f"soak: {args.height}x{args.width} LidarScan + 720-ray LaserScan at {args.rate:g} Hz, "
          f"{args.seconds:g} s measured; {platform.node()}, {platform.machine()}, "
          f"{os.cpu_count()} cpu, python {platform.python_version()}, "
          f"RMW {env.get('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp (default)')}, transports "
          f"{env.get('FASTDDS_BUILTIN_TRANSPORTS', 'default (UDPv4 + SHM)')}, QoS {args.qos}")
    print("events: " + "; ".join(f"{t:.1f} s {what}" for t, what in events))
    print(f"machine load average (1 min) at start {load0:.2f}, at end {os.getloadavg()[0]:.2f} "
          "(other work on the machine shows here)")
    print(f"published {len(published)} good scans + {injected} malformed ones ({late} "
          f"publication slots late: the publisher could not keep {args.rate:g} Hz)")
    print("processes: " + "; ".join(exits))
    pub_set = set(published)
    results: dict[str, Any] = {"published": len(published)}
    for topic in INPUTS + OUTPUTS:
        rows = received.get(topic, [])
        got = {s for s, _ in rows if s in pub_set}
        lat = [(r - s) / 1e6 for s, r in rows if s in pub_set]
        # outages: gaps in the received stamps longer than 5 periods, in orchestrator seconds
        stamps = sorted(got)
        gaps = [(at(a), (b - a) / 1e9) for a, b in itertools.pairwise(stamps)
                if b - a > 5e9 / args.rate]
        first = at(stamps[0]) if stamps else float("nan")
        drops = len(published) - len(got)
        steady = [s for s in published if not any(
            0 <= at(s) - t < args.settle for t, what in events if what.startswith("start"))]
        steady_drops = len([s for s in steady if s not in got])
        print(f"{topic:13s} received {len(got):5d}/{len(published)} "
              f"(drops {drops}, {100.0 * drops / max(len(published), 1):.1f} %; steady state "
              f"{steady_drops}/{len(steady)}, "
              f"{100.0 * steady_drops / max(len(steady), 1):.1f} %), latency ms "
              f"p50 {_pct(lat, 50):.1f} p99 {_pct(lat, 99):.1f} max "
              f"{max(lat) if lat else float('nan'):.1f}; first output at {first:.1f} s; "
              f"{len(gaps)} outages > 5 periods"
              + (", longest: " + ", ".join(f"{g:.2f} s at {t:.1f} s" for t, g in
                                           sorted(gaps, key=lambda x: -x[1])[:4])
                 if gaps else ""))
        results[topic] = {"received": len(got), "drops": drops,
                          "steady_drops": steady_drops, "steady_published": len(steady),
                          "p50_ms": round(_pct(lat, 50), 1), "p99_ms": round(_pct(lat, 99), 1),
                          "outages": [(round(t, 1), round(g, 2)) for t, g in gaps]}
    # recovery after each restart: first output whose stamp is after the new process started
    restarted: list[tuple[float, str]] = []
    seen: set[str] = set()
    for t_start, what in events:
        if what in ("start publisher", "start converter", "start merger"):
            if what in seen:
                restarted.append((t_start, what))
            seen.add(what)
    for t_start, what in restarted:
        pieces = []
        for topic in OUTPUTS:
            after = sorted(at(st) for st, _ in received.get(topic, [])
                           if at(st) >= t_start and st in pub_set)
            pieces.append(f"{topic} after {after[0] - t_start:.2f} s" if after
                          else f"{topic} NEVER")
        note = {"start converter": " (LidarInfo only from the latched topic)",
                "start merger": "",
                "start publisher": " (a new publisher process, LidarInfo published again)"}[what]
        print(f"recovery after '{what}' at {t_start:.1f} s{note}: first output " +
              ", ".join(pieces))
        results[f"recovery {what}"] = pieces
    for w_list in ([monitor], mergers, converters, publishers):
        name = w_list[0].name
        runs = cpu_runs.get(name, [])
        cpu = 100.0 * sum(c for c, _ in runs) / max(sum(r for _, r in runs), 1e-9)
        peak = max((m for w in w_list for _, m in w.rss), default=float("nan"))
        line = f"{name:10s} CPU {cpu:5.1f} % of one core, peak RSS {peak:6.1f} MiB"
        # flat memory: RSS of each run after warm-up (first sample after args.warmup s of it)
        for i, w in enumerate(w_list):
            samples = [(t, m) for t, m in w.rss if t - w.rss[0][0] >= args.warmup] \
                if w.rss else []
            if len(samples) >= 4:
                times, mib = np.array(samples).T
                slope = np.polyfit(times, mib, 1)[0] * 60.0
                line += (f"; run {i + 1}: after warm-up {mib[0]:.1f} -> {mib[-1]:.1f} MiB "
                         f"({mib[-1] - mib[0]:+.1f}), slope {slope:+.1f} MiB/min")
        print(line)
        results[name] = {"cpu_pct": round(cpu, 1), "peak_rss_mib": round(peak, 1)}
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps({"args": vars(args), "events": events,
                                           "results": results}, indent=1))
    print(f"logs in {workdir}; summary {args.json}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("role", nargs="?", default="soak",
                        choices=("soak", "publisher", "monitor"))
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--rate", type=float, default=40.0)
    parser.add_argument("--height", type=int, default=128)
    parser.add_argument("--width", type=int, default=2048)
    parser.add_argument("--warmup", type=float, default=10.0)
    parser.add_argument("--startup", type=float, default=4.0,
                        help="seconds for the nodes to start before data flows")
    parser.add_argument("--no-restart", action="store_true")
    parser.add_argument("--inject-bad", type=float, default=0.02,
                        help="fraction of scan slots replaced by a malformed scan (truncated, "
                             "junk, unknown info) and a malformed LaserScan (NaN angles)")
    parser.add_argument("--settle", type=float, default=5.0,
                        help="seconds after a (re)start excluded from the steady-state drops")
    parser.add_argument("--qos", default="sensor_data", choices=("sensor_data", "reliable"),
                        help="QoS of scans, laser, slices, clouds and merged scans")
    parser.add_argument("--transport", default="default",
                        choices=("default", "large_data", "shm", "udpv4"),
                        help="Fast DDS builtin transports (FASTDDS_BUILTIN_TRANSPORTS)")
    parser.add_argument("--domain", type=int, default=-1, help="ROS_DOMAIN_ID (default private)")
    parser.add_argument("--out", default="")
    parser.add_argument("--json", default=str(ROOT / "build" / "soak" / "summary.json"))
    args = parser.parse_args(argv)
    if args.role == "publisher":
        return run_publisher(args)
    if args.role == "monitor":
        return run_monitor(args)
    return run_soak(args)


if __name__ == "__main__":
    sys.exit(main())
