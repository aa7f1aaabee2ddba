"""Long fuzz run over every decoder and validator: only the project's own exceptions may escape.

Each target turns a seeded random generator into one malformed input (mutated CDR bytes, a
message dataclass with inconsistent fields, a mutated MCAP file, mutated Ouster metadata, ...)
and drives it through the code a user would run on it (decode, validate, project, convert).
A case FAILS when it

* raises anything that is not a :class:`lidarscan.errors.LidarScanError` ("crash"),
* runs longer than ``--timeout`` CPU seconds ("hang", interrupted with SIGPROF: CPU time, so a
  busy machine does not fake a hang; a warm-up runs first so imports are not counted), or
* allocates more than ``--max-alloc-mb`` at its peak (tracemalloc; numpy reports its buffers)
  ("memory": e.g. a declared size larger than the payload that got allocated).

Every case is reproducible from (``--seed``, target, case number): ``--target T --case N``
replays one case and prints its traceback. Failing inputs are saved to ``--out``.

Usage::

    .venv/bin/python bench/fuzz.py                        # 100k cases over all targets
    .venv/bin/python bench/fuzz.py --cases 20000 --targets scan_cdr,mcap,mcap_chunks
    .venv/bin/python bench/fuzz.py --target mcap --case 1234   # replay one case

Prints, per target: cases, cases accepted (no exception), the exception types seen with counts,
the failures, the slowest case and the largest per-case allocation; then the max RSS.

This file is the runner; the targets live beside it, one module per input family:
``fuzz_messages.py`` (CDR bytes, message fields), ``fuzz_recordings.py`` (MCAP files and chunks,
packets, rosbag2), ``fuzz_converters.py`` (Ouster metadata, PointCloud2, sweeps, merger, linkage),
with the seeds, mutators and :class:`Target` in ``fuzz_common.py`` (whose ``ROOT`` sets where
scratch files go).
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import math
import os
import platform
import random
import resource
import signal
import sys
import time
import traceback
import tracemalloc
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from lidarscan.errors import LidarScanError

sys.path.insert(0, str(Path(__file__).resolve().parent))
import fuzz_common  # noqa: E402
from fuzz_common import (  # noqa: E402, F401 - the shared parts, re-exported
    CONV,
    DEEP,
    MISSING,
    CaseTimeout,
    Target,
    exercise_info,
    exercise_scan,
    mutate_bytes,
    seed_info,
    seed_scan,
    _converters,
)
from fuzz_converters import (  # noqa: E402, F401 - the converter targets, re-exported
    _MERGER_ADAPTER,
    LaserScanSweep,
    LinkageEviction,
    MergerInputs,
    OusterJson,
    PointCloud2Input,
    WrongGeometry,
    _laser,
    make_merger,
    merger_merge,
    merger_push,
    mutate_json,
)
from fuzz_messages import InfoCdr, InfoFields, ScanCdr, ScanFields  # noqa: E402
from fuzz_recordings import BagDb3, CheckFailed, McapChunks, McapFile, PacketCdr  # noqa: E402,F401

TARGETS: dict[str, type[Target]] = {t.name: t for t in (
    ScanCdr, InfoCdr, ScanFields, InfoFields, McapFile, McapChunks, PacketCdr, BagDb3,
    OusterJson, PointCloud2Input, LaserScanSweep, MergerInputs, LinkageEviction)}


# ----------------------------------------------------------------------------------- runner

@dataclasses.dataclass
class Stats:
    cases: int = 0
    accepted: int = 0
    rejected: collections.Counter[str] = dataclasses.field(default_factory=collections.Counter)
    failures: list[tuple[int, str, str]] = dataclasses.field(default_factory=list)
    failure_kinds: collections.Counter[str] = dataclasses.field(
        default_factory=collections.Counter)
    slowest: tuple[float, int] = (0.0, -1)
    max_alloc: tuple[int, int] = (0, -1)
    seconds: float = 0.0


def _alarm(signum: int, frame: Any) -> None:
    raise CaseTimeout()


def case_rng(seed: int, target: str, index: int) -> random.Random:
    return random.Random(f"{seed}:{target}:{index}")


def run_case(target: Target, seed: int, index: int, timeout: float
             ) -> tuple[str, str, int, float, bytes | str]:
    """(outcome, detail, peak bytes, seconds, input). outcome: accepted/rejected/crash/hang."""
    rnd = case_rng(seed, target.name, index)
    try:
        data, call = target.case(rnd)
    except Exception as err:  # noqa: BLE001 - a bug of this fuzzer, reported, not fatal
        return "generator", "".join(traceback.format_exception(err)), 0, 0.0, b""
    DEEP["on"] = rnd.random() < 0.25
    tracemalloc.reset_peak()
    base = tracemalloc.get_traced_memory()[0]
    start = time.perf_counter()
    signal.setitimer(signal.ITIMER_PROF, timeout)  # CPU time: immune to a busy machine
    try:
        call()
        outcome, detail = "accepted", ""
    except LidarScanError as err:
        outcome, detail = "rejected", type(err).__name__
    except CaseTimeout:
        outcome, detail = "hang", f"> {timeout} s"
    except Exception as err:  # noqa: BLE001 - the point of the fuzzer
        outcome, detail = "crash", "".join(traceback.format_exception(err))
    finally:
        signal.setitimer(signal.ITIMER_PROF, 0)
    elapsed = time.perf_counter() - start
    peak = tracemalloc.get_traced_memory()[1] - base
    return outcome, detail, peak, elapsed, data


def _warm_up(targets: list[Target], seed: int, timeout: float) -> None:
    """First calls build caches and import modules (rclpy messages, converters): run a full
    conversion and a few uncounted cases per target so the per-case timeout measures cases."""
    DEEP["on"] = True
    import lidarscan_msgs.msg  # noqa: F401 - the ROS message modules outputs are built from
    import sensor_msgs.msg  # noqa: F401
    info = seed_info()
    try:
        exercise_scan(seed_scan(info), info)
        if "merger" in CONV:
            merger = make_merger(CONV["merger"])
            for i in range(3):
                for name in ("front", "rear"):
                    scan = _laser(random.Random(i), 1_000_000_000 + i * 50_000_000)
                    merger_push(merger, name, dataclasses.replace(
                        scan, angle_min=-1.0, angle_max=1.0, angle_increment=0.1,
                        ranges=np.ones(21, np.float32), intensities=np.ones(0, np.float32),
                        range_min=0.1, range_max=30.0, scan_time=0.1, time_increment=0.0))
    except LidarScanError:
        pass
    for target in targets:
        for index in range(5):
            run_case(target, seed + 1, index, max(timeout, 60.0))


def _crash_key(detail: str) -> str:
    lines = [ln for ln in detail.strip().splitlines() if ln.strip()]
    where = [ln.strip() for ln in lines if ln.strip().startswith("File ")]
    return f"{lines[-1][:120]} @ {where[-1] if where else '?'}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", type=int, default=0,
                        help="cases per target (default: 100000 split evenly over the targets)")
    parser.add_argument("--total", type=int, default=100_000)
    parser.add_argument("--targets", default="", help="comma-separated subset")
    parser.add_argument("--target", default="", help="replay one case of this target")
    parser.add_argument("--case", type=int, default=-1)
    parser.add_argument("--start", type=int, default=0, help="first case number (split runs)")
    parser.add_argument("--seed", type=int, default=20241122)
    parser.add_argument("--timeout", type=float, default=5.0,
                        help="CPU seconds per case (SIGPROF), after a warm-up")
    parser.add_argument("--max-alloc-mb", type=float, default=64.0)
    parser.add_argument("--max-vm-gb", type=float, default=8.0,
                        help="address-space limit of this process (RLIMIT_AS), 0 = none")
    parser.add_argument("--out", default=str(fuzz_common.ROOT / "build" / "fuzz"))
    args = parser.parse_args(argv)

    if args.max_vm_gb > 0:  # a huge allocation fails (MemoryError, reported) instead of the
        limit = int(args.max_vm_gb * 2**30)  # kernel's OOM killer ending the whole run
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    warnings.simplefilter("ignore")  # overflow warnings from numpy on extreme floats are fine
    signal.signal(signal.SIGPROF, _alarm)
    CONV.update(_converters())
    _bind_merger()
    tracemalloc.start()

    if args.target:
        target = TARGETS[args.target]()
        target.setup()
        outcome, detail, peak, elapsed, data = run_case(target, args.seed, args.case,
                                                        args.timeout)
        print(f"{args.target} case {args.case}: {outcome} {elapsed * 1e3:.1f} ms "
              f"peak {peak / 1e6:.2f} MB")
        print(detail or "")
        print("input:", repr(data)[:2000])
        return 0 if outcome in ("accepted", "rejected") else 1

    names = [n for n in (args.targets.split(",") if args.targets else TARGETS) if n]
    active, skipped = [], []
    for name in names:
        target = TARGETS[name]()
        missing = [need for need in target.needs if need not in CONV]
        if missing:
            skipped.append(f"{name} (missing {', '.join(missing)}: "
                           f"{'; '.join(MISSING.get(m, '?') for m in missing)})")
            continue
        target.setup()
        active.append(target)
    _warm_up(active, args.seed, args.timeout)
    per = args.cases or max(1, args.total // max(len(active), 1))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    limit = int(args.max_alloc_mb * 1e6)
    print(f"fuzz: seed {args.seed}, {per} cases per target from case {args.start}, "
          f"timeout {args.timeout} s, alloc limit {args.max_alloc_mb:g} MB; "
          f"python {platform.python_version()}, numpy {np.__version__}, "
          f"{platform.machine()} {os.cpu_count()} cpu")
    if skipped:
        print("skipped (not yet available):", "; ".join(skipped))
    total_fail = 0
    all_stats: dict[str, Stats] = {}
    for target in active:
        stats = Stats()
        t0 = time.perf_counter()
        for index in range(args.start, args.start + per):
            outcome, detail, peak, elapsed, data = run_case(target, args.seed, index,
                                                            args.timeout)
            stats.cases += 1
            if outcome == "accepted":
                stats.accepted += 1
            elif outcome == "rejected":
                stats.rejected[detail] += 1
            if peak > limit and outcome in ("accepted", "rejected"):
                outcome, detail = "memory", f"peak allocation {peak / 1e6:.1f} MB"
            if outcome in ("crash", "hang", "memory", "generator"):
                key = f"{outcome}: " + (_crash_key(detail) if outcome in ("crash", "generator")
                                        else detail)
                if stats.failure_kinds[key] == 0:
                    stats.failures.append((index, key, detail))
                    suffix = "bin" if isinstance(data, bytes) else "txt"
                    path = out / f"{target.name}-{index}.{suffix}"
                    path.write_bytes(data if isinstance(data, bytes) else data.encode())
                    print(f"  FAIL {target.name} case {index}: {key}\n    saved {path}; "
                          f"replay: bench/fuzz.py --target {target.name} --case {index} "
                          f"--seed {args.seed}", flush=True)
                stats.failure_kinds[key] += 1
            if elapsed > stats.slowest[0]:
                stats.slowest = (elapsed, index)
            if peak > stats.max_alloc[0]:
                stats.max_alloc = (peak, index)
        stats.seconds = time.perf_counter() - t0
        all_stats[target.name] = stats
        total_fail += sum(stats.failure_kinds.values())
        kinds = ", ".join(f"{k} {v}" for k, v in stats.rejected.most_common())
        print(f"{target.name:16s} {stats.cases:7d} cases in {stats.seconds:6.1f} s "
              f"({stats.cases / max(stats.seconds, 1e-9):6.0f}/s): accepted {stats.accepted}, "
              f"rejected {sum(stats.rejected.values())} [{kinds}], "
              f"failures {sum(stats.failure_kinds.values())}; slowest "
              f"{stats.slowest[0] * 1e3:.1f} ms (case {stats.slowest[1]}), max alloc "
              f"{stats.max_alloc[0] / 1e6:.2f} MB (case {stats.max_alloc[1]})", flush=True)
        for key, count in stats.failure_kinds.items():
            print(f"    {count:6d} x {key}")
        if hasattr(target, "summary"):
            print(f"    {target.summary()}")
    maxrss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    total = sum(s.cases for s in all_stats.values())
    print(f"total {total} cases, {total_fail} failures, max RSS {maxrss:.0f} MiB")
    summary = {name: {"cases": s.cases, "accepted": s.accepted, "rejected": dict(s.rejected),
                      "failures": dict(s.failure_kinds), "seconds": round(s.seconds, 1),
                      "max_alloc_mb": round(s.max_alloc[0] / 1e6, 2),
                      "slowest_ms": round(s.slowest[0] * 1e3, 1)}
               for name, s in all_stats.items()}
    (out / f"summary-{args.seed}-{args.start}.json").write_text(json.dumps(
        {"skipped": skipped, "max_rss_mib": round(maxrss), "targets": summary}, indent=1))
    return 1 if total_fail else 0


def _bind_merger() -> None:
    """Adapter to converters.merger's API: LaserScanMerger({name: MergerInput}), push(name,
    scan) -> merged scan or None."""
    mod = CONV.get("merger")
    if mod is None:
        return

    def make(mod: Any) -> Any:
        inputs = {"front": mod.MergerInput(),
                  "rear": mod.MergerInput(extrinsics=np.diag([-1.0, -1.0, 1.0, 1.0]),
                                          range_min=0.2, angle_min=-1.0, angle_max=1.0)}
        return mod.LaserScanMerger(inputs, frame_id="base_link", policy="timeout",
                                   timeout_ns=200_000_000, angle_increment=math.radians(2.0))

    _MERGER_ADAPTER["make"] = make
    _MERGER_ADAPTER["push"] = lambda merger, name, scan: merger.push(name, scan)
    _MERGER_ADAPTER["merge"] = lambda merger, now_ns: None


if __name__ == "__main__":
    sys.exit(main())
