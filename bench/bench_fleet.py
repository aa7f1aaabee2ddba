"""``lidarscan convert`` over many recordings (issue 31): scaling, Dask's overhead, memory.

    python bench/bench_fleet.py scaling --data DIR [--count 6] [--grow MB] [--dask]
    python bench/bench_fleet.py memory [--sizes 128,512] [--seed DB3]
    python bench/bench_fleet.py malloc [--size 256]
    python bench/bench_fleet.py dask [--workers 2] [--size 128]

``scaling``: ``--data`` (or $LIDARSCAN_FLEET_DATA) is a folder of raw-packet recordings laid out
as tests/data/nebula (``<model>/bag`` + its calibration file beside it); ``--count`` recordings
are made from them in a temporary folder (copies, cycling through the models; ``--grow``: each
.db3 repeated to about MB megabytes), each with its calibration beside it (``<name>.yaml`` /
``.csv``, the fleet rule). Timed, wall clock: the serial shell loop of one ``lidarscan convert``
process per recording (the baseline), the fleet command with ``--jobs 1 .. cores`` and with
``--dask`` (a LocalCluster of as many workers); every output is compared with the loop's, byte
for byte. ``memory``: peak RSS of one ``convert`` process for synthetic VLS-128 .db3 bags of the
given sizes (the real tests/data recording's rows repeated). ``malloc``: user and system CPU of
one conversion with glibc's default malloc, Dask's ``MALLOC_TRIM_THRESHOLD_=65536`` and the
fleet's :data:`converters.edge.cli.fleet.WORKER_ENV`. ``dask``: a LocalCluster's start time, a
worker's RSS idle, the round trip of a trivial task, a worker's peak RSS after one conversion.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parents[1]))   # this checkout, not an installed one
from _synthetic_bag import grow_db3

ROOT = Path(__file__).parents[1]
NEBULA = ROOT / "tests" / "data" / "nebula"
CLI = [sys.executable, "-m", "converters.edge.cli", "convert"]


def _run(command: list[str], env: dict[str, str] | None = None) -> tuple[float, int, float, float]:
    """(wall s, peak RSS kB, user s, sys s) of a child process."""
    start = time.perf_counter()
    process = subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE)
    _, status, usage = os.wait4(process.pid, 0)
    wall = time.perf_counter() - start
    err = process.stderr.read().decode() if process.stderr else ""
    code = os.waitstatus_to_exitcode(status)
    if code != 0:
        raise SystemExit(f"{' '.join(command)}: exit {code}\n{err}")
    return wall, usage.ru_maxrss, usage.ru_utime, usage.ru_stime


def _make_fleet(data: Path, folder: Path, count: int, grow: int) -> list[tuple[Path, Path]]:
    models = sorted(p for p in data.iterdir() if (p / "bag").is_dir())
    out = []
    for k in range(count):
        model = models[k % len(models)]
        calibration = next(p for p in model.iterdir()
                           if p.suffix.lower() in (".yaml", ".csv") and p.is_file())
        bag = folder / f"{k:02d}_{model.name}"
        shutil.copytree(model / "bag", bag)
        if grow:
            for db3 in bag.glob("*.db3"):
                tmp = db3.with_suffix(".tmp")
                grow_db3(db3, tmp, grow << 20)
                tmp.replace(db3)
            (bag / "metadata.yaml").unlink()   # counts from the grown .db3
        cal = folder / f"{bag.name}{calibration.suffix}"
        shutil.copy(calibration, cal)
        out.append((bag, cal))
    return out


def scaling(args: argparse.Namespace) -> None:
    data = Path(args.data or os.environ.get("LIDARSCAN_FLEET_DATA", ""))
    if not data.is_dir():
        raise SystemExit("scaling: give --data DIR or $LIDARSCAN_FLEET_DATA (a folder laid out "
                         "as tests/data/nebula)")
    cores = os.cpu_count() or 1
    with tempfile.TemporaryDirectory(prefix="bench_fleet_") as tmp:
        root = Path(tmp)
        recordings = _make_fleet(data, root / "in", args.count, args.grow)
        size = sum(f.stat().st_size for b, _ in recordings for f in b.rglob("*") if f.is_file())
        print(f"{len(recordings)} recordings, {size / 1e6:.1f} MB, {cores} cores, load "
              f"{os.getloadavg()[0]:.1f}")
        rows = []
        for round_ in range(args.rounds):
            loop = root / f"loop{round_}"
            loop.mkdir()
            start, cpu = time.perf_counter(), 0.0
            for bag, cal in recordings:
                _, _, user, system = _run([*CLI, str(bag), str(loop / f"{bag.name}.mcap"),
                                           "--calibration", str(cal), "-q"])
                cpu += user + system
            rows.append(("serial loop of processes", time.perf_counter() - start, cpu,
                         os.getloadavg()[0]))
            variants = [(f"--jobs {n}", ["--jobs", str(n)]) for n in range(1, cores + 1)]
            if args.dask:
                variants.append((f"--dask (LocalCluster, {cores} workers)", ["--dask"]))
            for name, extra in variants:
                out = root / f"{name.split()[0].strip('-')}{extra[-1]}_{round_}"
                wall, _, user, system = _run([*CLI, str(root / "in"), str(out), "-q", *extra])
                for bag, _ in recordings:
                    a, b = (loop / f"{bag.name}.mcap").read_bytes(), \
                        (out / f"{bag.name}.mcap").read_bytes()
                    if a != b:
                        raise SystemExit(f"{name}: {bag.name}.mcap differs from the loop's")
                rows.append((name, wall, user + system, os.getloadavg()[0]))
                shutil.rmtree(out)
            shutil.rmtree(loop)
        print(f"{'candidate':38s} {'wall s':>7s} {'vs loop':>8s} {'CPU s':>7s} {'load':>5s}  "
              "(every output byte-identical to the loop's)")
        per = len(rows) // args.rounds
        for round_ in range(args.rounds):
            part = rows[round_ * per:(round_ + 1) * per]
            base = part[0][1]
            for name, wall, cpu, load in part:
                print(f"{name:38s} {wall:7.2f} {base / wall:7.2f}x {cpu:7.2f} {load:5.1f}")


def memory(args: argparse.Namespace) -> None:
    seed = Path(args.seed) if args.seed else next((NEBULA / "velodyne_vls128" / "bag").glob("*.db3"))
    calibration = args.calibration or str(NEBULA / "velodyne_vls128" / "VLS128.yaml")
    with tempfile.TemporaryDirectory(prefix="bench_fleet_") as tmp:
        print(f"{'input':>12s} {'peak RSS':>10s} {'wall s':>8s} {'user s':>7s} {'sys s':>6s}")
        for mb in (int(s) for s in args.sizes.split(",")):
            db3 = grow_db3(seed, Path(tmp) / f"vls128_{mb}.db3", mb << 20)
            wall, rss, user, system = _run([*CLI, str(db3), str(Path(tmp) / "out.mcap"),
                                            "--calibration", calibration, "-q"])
            print(f"{db3.stat().st_size / 1e6:9.0f} MB {rss / 1024:7.0f} MB {wall:8.2f} "
                  f"{user:7.2f} {system:6.2f}")
            db3.unlink()


def malloc(args: argparse.Namespace) -> None:
    from converters.edge.cli.fleet import WORKER_ENV

    seed = next((NEBULA / "velodyne_vls128" / "bag").glob("*.db3"))
    calibration = str(NEBULA / "velodyne_vls128" / "VLS128.yaml")
    base = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    variants = {"glibc default": {}, "Dask default (TRIM 65536)": {
        "MALLOC_TRIM_THRESHOLD_": "65536"}, "fleet WORKER_ENV": WORKER_ENV}
    with tempfile.TemporaryDirectory(prefix="bench_fleet_") as tmp:
        db3 = grow_db3(seed, Path(tmp) / "in.db3", args.size << 20)
        times: dict[str, list[tuple[float, float]]] = {k: [] for k in variants}
        for _ in range(args.rounds):
            for name, env in variants.items():
                _, _, user, system = _run([*CLI, str(db3), str(Path(tmp) / "out.mcap"),
                                           "--calibration", calibration, "-q", "--threads",
                                           "1"], env={**base, **env})
                times[name].append((user, system))
        print(f"{db3.stat().st_size / 1e6:.0f} MB VLS-128 .db3, --threads 1, medians of "
              f"{args.rounds} interleaved rounds")
        for name, values in times.items():
            user = sorted(u for u, _ in values)[len(values) // 2]
            system = sorted(s for _, s in values)[len(values) // 2]
            print(f"{name:30s} user {user:6.2f} s  sys {system:6.2f} s")


def _rss() -> int:
    with open("/proc/self/status") as status:
        return int(status.read().split("VmRSS:")[1].split()[0]) * 1024


def dask_overhead(args: argparse.Namespace) -> None:
    """LocalCluster start, a worker's RSS idle, per-task round trip of trivial tasks, and a
    worker's RSS after converting a synthetic VLS-128 .db3 of --size MB."""
    import logging

    import dask
    from distributed import Client, LocalCluster, as_completed

    from converters.edge.cli import fleet

    environ = {**dask.config.get("distributed.nanny.pre-spawn-environ", {}), **fleet.WORKER_ENV}
    start = time.perf_counter()
    with dask.config.set({"distributed.nanny.pre-spawn-environ": environ}), \
            LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True,
                         dashboard_address=None, silence_logs=logging.ERROR) as cluster, \
            Client(cluster) as client:
        started = time.perf_counter() - start
        idle = client.run(_rss)
        for _ in range(2):
            start = time.perf_counter()
            futures = [client.submit(abs, -k, pure=False) for k in range(args.tasks)]
            for _ in as_completed(futures):
                pass
            per_task = (time.perf_counter() - start) / args.tasks
        with tempfile.TemporaryDirectory(prefix="bench_fleet_") as tmp:
            seed = next((NEBULA / "velodyne_vls128" / "bag").glob("*.db3"))
            db3 = grow_db3(seed, Path(tmp) / "in.db3", args.size << 20)
            options = dict(vars(fleet_args(str(db3), str(Path(tmp) / "out"))))
            options["calibration"] = str(NEBULA / "velodyne_vls128" / "VLS128.yaml")
            options["threads"] = 1
            job = fleet.Job(0, str(db3), str(Path(tmp) / "out.mcap"), "out.mcap",
                            db3.stat().st_size, options)
            result = client.submit(fleet.convert_job, job, pure=False).result()
            after = client.run(_peak)
    print(f"LocalCluster of {args.workers} workers: started in {started:.2f} s; worker RSS "
          f"idle {', '.join(f'{v / 1e6:.0f}' for v in idle.values())} MB; trivial task round "
          f"trip {per_task * 1e3:.1f} ms ({args.tasks} tasks, as_completed)")
    print(f"after converting a {args.size} MB VLS-128 .db3 ({result.status}, {result.seconds:.1f} "
          f"s): worker peak RSS {', '.join(f'{v / 1e6:.0f}' for v in after.values())} MB")


def _peak() -> int:
    with open("/proc/self/status") as status:
        return int(status.read().split("VmHWM:")[1].split()[0]) * 1024


def fleet_args(source: str, out: str) -> argparse.Namespace:
    from converters.edge.cli._parser import build_parser

    return build_parser().parse_args(["convert", source, out])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="what", required=True)
    p = sub.add_parser("scaling")
    p.add_argument("--data", default=None)
    p.add_argument("--count", type=int, default=6)
    p.add_argument("--grow", type=int, default=0, metavar="MB")
    p.add_argument("--rounds", type=int, default=1)
    p.add_argument("--dask", action="store_true")
    p.set_defaults(func=scaling)
    p = sub.add_parser("memory")
    p.add_argument("--sizes", default="128,512")
    p.add_argument("--seed", default=None, help="a VLS-128 rosbag2 .db3 (default: tests/data)")
    p.add_argument("--calibration", default=None)
    p.set_defaults(func=memory)
    p = sub.add_parser("malloc")
    p.add_argument("--size", type=int, default=256, metavar="MB")
    p.add_argument("--rounds", type=int, default=3)
    p.set_defaults(func=malloc)
    p = sub.add_parser("dask")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--tasks", type=int, default=200)
    p.add_argument("--size", type=int, default=128, metavar="MB")
    p.set_defaults(func=dask_overhead)
    args = parser.parse_args()
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    args.func(args)


if __name__ == "__main__":
    main()
