"""Harness: the Velodyne C fill kernel alone (``vdk_fill`` of converters/_kernels/_velokernel.c).

Run: ``.venv/bin/python bench/velokernel_harness.py [--so X.so[:0] ...] [--rounds N]
[--push-many]``.

Captures the kernel calls that ``PacketDecoder.push_many`` makes for one rotation of the bench's
VLS-128 dual-return packets (bench/bench_velodyne.py, default ``azimuth_model="nebula"``), then
replays that rotation's calls on warm (already written) views and, separately, on fresh
``np.zeros`` views (first-touch page faults included, as a decoder that allocates a ScanBuffer
per rotation pays). Candidates: the installed kernel on its portable path
(``converters._kernels.velodyne.SIMD = 0``) and on its default path, and every extra shared
object given with ``--so`` (built from a variant of the source, e.g. main's, with the same
exported functions and ABI; ``PATH:0`` runs its portable path). With ``--push-many``, also
``PacketDecoder.push_many`` on 1 s of the same packets (one rotation per call, as
bench_velodyne.py) with each candidate as the decoder's kernel, in the same interleaved rounds
(``bench/_timing.py``, in a new random order each round). Prints CPU-time
(``time.process_time``) medians per second of data, ratios to the portable path and the load
average; checks that every candidate writes the same bytes (no assertions on speed).
"""

from __future__ import annotations

import argparse
import ctypes
import functools
import importlib.util
import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _timing import interleaved_times  # noqa: E402


def _bench_module() -> Any:
    spec = importlib.util.spec_from_file_location("bench_velodyne", HERE / "bench_velodyne.py")
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def capture() -> tuple[list[tuple[Any, ...]], float]:
    """The fill calls of one full rotation (arguments, views) and the seconds of data a
    rotation is."""
    import converters._kernels.velodyne as kv
    from converters.sources.velodyne import PacketDecoder

    bench = _bench_module()
    packets = bench.make_packets(0.35)
    rows = np.frombuffer(b"".join(p for _, p in packets), np.uint8).reshape(-1, 1206)
    stamps = np.array([s for s, _ in packets], np.int64)
    calls: list[tuple[Any, ...]] = []
    original = kv.fill

    def spy(lib: Any, plan: Any, run: Any, begin: int, count: int, column: int,
            views: Any) -> None:
        calls.append((plan, run.copy(), begin, count, column, views))
        original(lib, plan, run, begin, count, column, views)

    kv.fill = spy
    try:
        dec = PacketDecoder(bench.calibration(), as_dataclass=True)
        per = int(round(0.1 / bench.SEQUENCE_S))
        for i in range(0, len(rows), per):
            dec.push_many(stamps[i:i + per], rows[i:i + per])
    finally:
        kv.fill = original
    rotations: list[list[tuple[Any, ...]]] = []      # a rotation's calls start at column 0
    for call in calls:
        if call[4] == 0:
            rotations.append([])
        if rotations:
            rotations[-1].append(call)
    rotation = max(rotations, key=lambda g: sum(c[3] for c in g))   # a whole one
    width = rotation[0][5]["range"].shape[1]
    return rotation, width * bench.SEQUENCE_S


def _bind(path: str | None) -> Any:
    import converters._kernels.velodyne as kv
    if path is None:
        lib = kv.library()
        if lib is None:
            raise SystemExit("the installed kernel is not built or is disabled")
        return lib
    return kv.bind(ctypes.CDLL(path))                # the argument types the module sets


def _fresh(views: dict[str, np.ndarray[Any, Any]]) -> dict[str, np.ndarray[Any, Any]]:
    """New views like ``views`` in one zeroed block (as a ScanBuffer lays them out)."""
    size = sum(v.nbytes for v in views.values())
    block = np.zeros(size, np.uint8)
    out, at = {}, 0
    for name, v in views.items():
        out[name] = block[at:at + v.nbytes].view(v.dtype).reshape(v.shape)
        at += v.nbytes
    return out


def replay(candidate: tuple[Any, int], calls: list[tuple[Any, ...]],
           views: dict[str, np.ndarray[Any, Any]]) -> None:
    import converters._kernels.velodyne as kv
    lib, kv.SIMD = candidate
    for plan, run, begin, count, column, _ in calls:
        kv.fill(lib, plan, run, begin, count, column, views)


def push_many_runner() -> Callable[[tuple[Any, int]], None]:
    """A function that decodes 1 s of the bench's packets with ``push_many`` (one rotation per
    call, a new decoder each time) with a candidate (library, simd flag) as the kernel."""
    import converters._kernels.velodyne as kv
    from converters._kernels import _loader
    from converters.sources.velodyne import PacketDecoder

    bench = _bench_module()
    packets = bench.make_packets(1.0)
    rows = np.frombuffer(b"".join(p for _, p in packets), np.uint8).reshape(-1, 1206)
    stamps = np.array([s for s, _ in packets], np.int64)
    per, calib = int(round(0.1 / bench.SEQUENCE_S)), bench.calibration()
    installed = kv._library

    def run(candidate: tuple[Any, int]) -> None:
        lib, kv.SIMD = candidate
        kv._library = _loader.LoadOnce(lambda: lib)        # the decoder's kernel
        try:
            dec = PacketDecoder(calib, as_dataclass=True)
            for i in range(0, len(rows), per):
                dec.push_many(stamps[i:i + per], rows[i:i + per])
            dec.flush()
        finally:
            kv._library = installed

    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--so", action="append", default=[],
                        help="a variant's shared object, PATH or PATH:0 (its portable path)")
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--inner", type=int, default=10, help="rotations per timed sample")
    parser.add_argument("--push-many", action="store_true", help="also time push_many")
    args = parser.parse_args()
    calls, seconds = capture()
    installed = _bind(None)
    libs = {"portable (SIMD=0)": (installed, 0), "default (AVX2)": (installed, 1)}
    for spec in args.so:
        path, _, simd = spec.partition(":")
        libs[Path(path).name + (" (SIMD=0)" if simd == "0" else "")] = (_bind(path),
                                                                       int(simd != "0"))
    template = dict(calls[0][5])
    warm = {name: _fresh(template) for name in libs}
    reference = None
    for name, lib in libs.items():
        replay(lib, calls, warm[name])
        got = b"".join(v.tobytes() for v in warm[name].values())
        reference = reference or got
        print(f"{name}: {'same bytes' if got == reference else 'DIFFERENT BYTES'}")
    push_many = push_many_runner() if args.push_many else None
    inner = args.inner
    candidates: dict[str, Callable[[], Any]] = {}        # "mode|name" -> one timed sample
    for name, lib in libs.items():
        candidates[f"warm|{name}"] = functools.partial(
            lambda lib, views: [replay(lib, calls, views) for _ in range(inner)], lib, warm[name])
        candidates[f"fresh|{name}"] = functools.partial(     # np.zeros: pages faulted in the fill
            lambda lib: [replay(lib, calls, _fresh(template)) for _ in range(inner)], lib)
        if push_many is not None:
            candidates[f"push_many|{name}"] = functools.partial(push_many, lib)   # 1 s of data
    load0 = os.getloadavg()[0]
    times = interleaved_times(candidates, args.rounds, clock=time.process_time)
    print(f"one rotation = {seconds:.4f} s of data, {sum(c[3] for c in calls)} columns; load "
          f"average {load0:.2f} -> {os.getloadavg()[0]:.2f}; CPU medians of {args.rounds} rounds")
    for mode in ("warm", "fresh", "push_many"):
        if f"{mode}|portable (SIMD=0)" not in times:
            continue
        per = 1.0 if mode == "push_many" else inner * seconds      # seconds of data per sample
        base = statistics.median(times[f"{mode}|portable (SIMD=0)"]) / per
        what = "push_many, 1 s of data" if mode == "push_many" else f"kernel, {mode} views"
        for name in libs:
            med = statistics.median(times[f"{mode}|{name}"]) / per
            print(f"  {what:22s} {name:20s} {med * 1e3:7.2f} ms per second of data "
                  f"= {1 / med:5.1f}x real time, {med / base:5.2f}x the portable path")

if __name__ == "__main__":
    main()
