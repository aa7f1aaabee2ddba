"""Harness: the Velodyne C fill kernel alone (``vdk_fill`` of converters/_kernels/_velokernel.c).

Run: ``.venv/bin/python bench/velokernel_harness.py [--so other.so ...] [--rounds N]``.

Captures the kernel calls that ``PacketDecoder.push_many`` makes for one rotation of the bench's
VLS-128 dual-return packets (bench/bench_velodyne.py: 1 s of data, default
``azimuth_model="nebula"``), then replays that rotation's calls on warm (already written) views
and, separately, on fresh ``np.zeros`` views (first-touch page faults included, as a decoder
that allocates a ScanBuffer per rotation pays), for the installed kernel and for every extra
shared object given with ``--so`` (built from a variant of the source; the same exported
functions). Prints CPU-time (``time.process_time``) medians of interleaved rounds, per rotation
and per second of data, the ratio to the installed kernel and the load average; checks that
every shared object writes the same bytes (no assertions on speed).
"""

from __future__ import annotations

import argparse
import ctypes
import importlib.util
import os
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent


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
    from converters.velodyne import PacketDecoder

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
        views_seen: list[int] = []
        for i in range(0, len(rows), per):
            dec.push_many(stamps[i:i + per], rows[i:i + per])
            views_seen.append(len(calls))
    finally:
        kv.fill = original
    # the calls of the second rotation (the first may start mid-rotation)
    groups: dict[int, list[tuple[Any, ...]]] = {}
    for call in calls:
        groups.setdefault(id(call[5]["range"]), []).append(call)
    rotation = max(groups.values(), key=lambda g: sum(c[3] for c in g))
    width = rotation[0][5]["range"].shape[1]
    return rotation, width * bench.SEQUENCE_S


def _bind(path: str | None) -> Any:
    if path is None:
        import converters._kernels.velodyne as kv
        lib = kv.library()
        if lib is None:
            raise SystemExit("the installed kernel is not built or is disabled")
        return lib
    lib = ctypes.CDLL(path)
    from converters._kernels.velodyne import _load  # noqa: F401  (argtypes as the module sets)
    i64, ptr = ctypes.c_int64, ctypes.c_void_p
    lib.vdk_fill.restype = i64
    lib.vdk_fill.argtypes = [ptr, i64, i64, i64, i64, i64, i64, i64,
                             ptr, ptr, ptr, ptr, i64, i64, i64,
                             ptr, ptr, ptr, ptr, ptr, ptr]
    return lib


def _fresh(views: dict[str, np.ndarray[Any, Any]]) -> dict[str, np.ndarray[Any, Any]]:
    """New views like ``views`` in one zeroed block (as a ScanBuffer lays them out)."""
    size = sum(v.nbytes for v in views.values())
    block = np.zeros(size, np.uint8)
    out, at = {}, 0
    for name, v in views.items():
        out[name] = block[at:at + v.nbytes].view(v.dtype).reshape(v.shape)
        at += v.nbytes
    return out


def replay(lib: Any, calls: list[tuple[Any, ...]], views: dict[str, np.ndarray[Any, Any]]
           ) -> None:
    import converters._kernels.velodyne as kv
    for plan, run, begin, count, column, _ in calls:
        kv.fill(lib, plan, run, begin, count, column, views)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--so", action="append", default=[], help="a variant's shared object")
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--inner", type=int, default=10, help="rotations per timed sample")
    args = parser.parse_args()
    calls, seconds = capture()
    libs = {"installed": _bind(None)} | {Path(p).name: _bind(p) for p in args.so}
    template = {k: v for k, v in calls[0][5].items()}
    warm = {name: _fresh(template) for name in libs}
    reference = None
    for name, lib in libs.items():
        replay(lib, calls, warm[name])
        got = b"".join(v.tobytes() for v in warm[name].values())
        reference = reference or got
        print(f"{name}: {'same bytes' if got == reference else 'DIFFERENT BYTES'}")
    load0 = os.getloadavg()[0]
    times: dict[tuple[str, str], list[float]] = {}
    for _ in range(args.rounds):
        for name, lib in libs.items():
            start = time.process_time()
            for _ in range(args.inner):
                replay(lib, calls, warm[name])
            times.setdefault((name, "warm"), []).append(
                (time.process_time() - start) / args.inner)
            fresh = [_fresh(template) for _ in range(args.inner)]
            start = time.process_time()
            for v in fresh:
                replay(lib, calls, v)
            times.setdefault((name, "fresh"), []).append(
                (time.process_time() - start) / args.inner)
            del fresh
    print(f"one rotation = {seconds:.4f} s of data, {sum(c[3] for c in calls)} columns; load "
          f"average {load0:.2f} -> {os.getloadavg()[0]:.2f}; CPU medians of {args.rounds} rounds")
    for mode in ("warm", "fresh"):
        base = statistics.median(times[("installed", mode)])
        for name in libs:
            med = statistics.median(times[(name, mode)])
            print(f"  {mode:5s} {name:28s} {med * 1e3:7.3f} ms/rotation = {med / seconds * 1e3:6.2f}"
                  f" ms per second of data, {med / base:5.2f}x installed")


if __name__ == "__main__":
    main()
