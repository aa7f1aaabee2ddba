"""Benchmark: 4 height slices of a 128 x 2048 LidarScan vs a pointcloud_to_laserscan-style loop.

Run: ``.venv/bin/python bench/bench_slices.py [--repeat N] [--offset]``. Prints medians, minima
and ratios of CPU time (``time.process_time``) measured in the same run (the timings of the
candidates are interleaved, in a new random order every round, so machine load and cache
leftovers hit all alike) and the load average; no assertions.
Target: >= 5x the baseline.

Scene: an OS-1-128-like sensor (2048 columns, +-22.5 deg, 15.8 mm beam origins, +-4.2 deg beam
azimuth offsets) 0.5 m above ``base_link`` in an 8 x 6 m room with a table and a pillar, 5 % of
the pixels without return. Four slices: floor-to-knee 0.05-0.5 m, knee-to-table 0.5-0.8 m,
table-to-head 0.8-1.8 m, low obstacles 0.02-0.3 m.

Candidates:

* ``SliceConverter.convert`` (ours): all 4 slices in one pass, including building the 4 rclpy
  LaserScan messages; the default backend (the C kernel converters/_slicekernel.c when built),
  the numba kernel when numba is installed, and the numpy backend (same algorithm with
  ``minimum.reduceat``). All use tables precomputed once per LidarInfo version (outside the
  timing, like the JIT).
* baseline ``p2l``: pointcloud_to_laserscan's per-point algorithm on the equivalent organised
  cloud (x, y, z float32 in base_link, NaN where no return), one pass per slice as four nodes
  would run it: NaN check, height test, hypot, range test, atan2, angle test, bin = trunc, keep
  the min. Written as a plain loop compiled with numba when numba is installed (the fastest form
  available here), and also as a vectorised numpy version of the same per-point algorithm
  (atan2 recomputed every scan). The cloud is built outside the timing (free for the baseline).
* holes (issue 15): the same 4 slices with ``holes=True`` (floor at z = 0) by the numba
  row-ordered kernel (what "auto" takes with holes on) and, forced, the path it replaced
  (bin-ordered kernel, then the numpy hole pass).
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from typing import Any

import numpy as np

import lidarscan
from _timing import interleaved_times
from converters.slices.converter import SliceConverter, SliceSpec

H, W = 128, 2048
BANDS = {"floor_to_knee": (0.05, 0.5), "knee_to_table": (0.5, 0.8),
         "table_to_head": (0.8, 1.8), "low": (0.02, 0.3)}


def pose(x: float = 0.0, y: float = 0.0, z: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    m = np.eye(4)
    m[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    m[:3, 3] = (x, y, z)
    return m


def make_info() -> Any:
    beta = np.radians(np.tile([4.2, 1.4, -1.4, -4.2], H // 4))
    n = 0.015806
    return lidarscan.make_info(
        stamp_ns=1, frame_id="os_sensor",
        vertical_angles=np.radians(np.linspace(22.5, -22.5, H)),
        horizontal_angles=2 * np.pi * (1 - np.arange(W) / W), beam_azimuth_offsets=-beta,
        beam_origins=np.stack([n * np.cos(-beta), -n * np.sin(-beta), np.zeros(H)], 1).ravel(),
        beam_range_offsets=np.full(H, -n),
        lidar_to_sensor_transform=pose(z=0.036, yaw=math.pi).ravel(),
        range_min=0.1, range_max=120.0, column_time_increment=48828, as_dataclass=True)


def room_ranges(info: Any, ext: np.ndarray) -> np.ndarray:
    """Ranges (H, W) float32 of an 8 x 6 x 2.5 m room with a table and a pillar."""
    proj = lidarscan.make_projector(info)
    d = proj.directions.reshape(-1, 3).astype(np.float64) @ ext[:3, :3].T
    o = proj.offsets.reshape(-1, 3).astype(np.float64) @ ext[:3, :3].T + ext[:3, 3]
    room = (np.array([-4.0, -3.0, 0.0]), np.array([4.0, 3.0, 2.5]))
    solids = [(np.array([1.0, -0.5, 0.70]), np.array([2.0, 0.5, 0.75])),
              (np.array([-2.0, 1.0, 0.0]), np.array([-1.7, 1.3, 2.5]))]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        best = np.nanmin(np.maximum((room[0] - o) * inv, (room[1] - o) * inv), axis=1)
        for lo, hi in solids:
            a, b = (lo - o) * inv, (hi - o) * inv
            t_in, t_out = np.nanmax(np.minimum(a, b), 1), np.nanmin(np.maximum(a, b), 1)
            best = np.where((t_in <= t_out) & (t_in > 0) & (t_in < best), t_in, best)
    r = best.astype(np.float32).reshape(H, W)
    r[np.random.default_rng(0).random((H, W)) < 0.05] = np.inf
    return r


# ------------------------------------------------------------------------------- baselines

def p2l_numpy(x: np.ndarray, y: np.ndarray, z: np.ndarray, zmin: float, zmax: float,
              amin: float, amax: float, inc: float, rmin: float, rmax: float
              ) -> np.ndarray:
    """pointcloud_to_laserscan's per-point algorithm, vectorised (one slice)."""
    n = math.ceil((amax - amin) / inc)
    ranges = np.full(n, np.inf, np.float32)
    ok = ~(np.isnan(x) | np.isnan(y) | np.isnan(z))
    ok &= (z >= zmin) & (z <= zmax)
    xs, ys = x[ok], y[ok]
    rng = np.hypot(xs, ys)
    keep = (rng >= rmin) & (rng <= rmax)
    xs, ys, rng = xs[keep], ys[keep], rng[keep]
    ang = np.arctan2(ys, xs)
    keep = (ang >= amin) & (ang <= amax)
    idx = ((ang[keep] - amin) / inc).astype(np.int64)
    idx = np.minimum(idx, n - 1)                 # the C++ writes out of bounds here (#14)
    np.minimum.at(ranges, idx, rng[keep])
    return ranges


def _p2l_loop(x: Any, y: Any, z: Any, zmin: float, zmax: float, amin: float, amax: float,
              inc: float, rmin: float, rmax: float, ranges: Any) -> None:
    """pointcloud_to_laserscan's per-point loop (one slice), as plainly as the C++."""
    n = ranges.shape[0]
    for i in range(n):
        ranges[i] = np.inf
    for i in range(x.shape[0]):
        if math.isnan(x[i]) or math.isnan(y[i]) or math.isnan(z[i]):
            continue
        if z[i] > zmax or z[i] < zmin:
            continue
        rng = math.hypot(x[i], y[i])
        if rng < rmin or rng > rmax:
            continue
        angle = math.atan2(y[i], x[i])
        if angle < amin or angle > amax:
            continue
        index = int((angle - amin) / inc)
        if index >= n:                           # the C++ writes out of bounds here (#14)
            continue
        ranges[index] = min(ranges[index], rng)


def variants(info: Any, specs: Any, common: Any, scan: Any, have_numba: bool
             ) -> dict[str, Any]:
    """Every compiled variant forced on the same scene (the converter's tables are edited
    after they are built so that the dispatch takes the variant)."""
    from converters._kernels import slices as cslices
    out: dict[str, Any] = {}

    def forced(edit: Any, **kw: Any) -> Any:
        conv = SliceConverter(info, specs, **common, **kw)
        conv.convert(scan)
        edit(conv, next(iter(conv._tables.values())))
        conv.convert(scan)                                # JIT of the variant
        return lambda: conv.convert(scan)

    if have_numba:
        def bin_ordered(conv: Any, t: Any) -> None:
            t.sorted.rows = None

        def general(conv: Any, t: Any) -> None:
            t.sorted = None
        out["variant: numba bin-ordered"] = forced(bin_ordered, backend="numba")
        out["variant: numba general 3-pass"] = forced(general, backend="numba")
    if cslices.available():
        def scalar_c(conv: Any, t: Any) -> None:
            conv._c_kernel = True
        run = forced(scalar_c)

        def scalar() -> None:
            simd, cslices.SIMD = cslices.SIMD, 0
            try:
                run()
            finally:
                cslices.SIMD = simd
        out["variant: C kernel, scalar path"] = scalar
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeat", type=int, default=40)
    parser.add_argument("--offset", action="store_true",
                        help="mount the sensor 0.3 m in front of base_link (most in-band "
                             "points then need atan2)")
    parser.add_argument("--variants", action="store_true",
                        help="also time every compiled variant on this scene, each forced: "
                             "numba bin-ordered and general kernels, the C "
                             "kernel's scalar path")
    args = parser.parse_args()

    info = make_info()
    ext = pose(x=0.3 if args.offset else 0.0, z=0.5)
    r = room_ranges(info, ext)
    rng = np.random.default_rng(1)
    scan = lidarscan.make_scan(info, {"range": r, "intensity": rng.integers(
        0, 4000, (H, W)).astype(np.uint16)}, 10**9, as_dataclass=True)
    specs = {k: SliceSpec(*v) for k, v in BANDS.items()}
    common = {"extrinsics": ext, "frame_id": "base_link"}

    # the equivalent organised cloud in base_link (as a driver + TF would publish it)
    proj = lidarscan.make_projector(info)
    xyz = proj.xyz(r).reshape(-1, 3).astype(np.float64)
    xyz = (xyz @ ext[:3, :3].T + ext[:3, 3]).astype(np.float32)
    x, y, z = (np.ascontiguousarray(xyz[:, k]) for k in range(3))
    inc = 2 * math.pi / W
    grid = (-math.pi, math.pi, inc, 0.1, 120.0)

    candidates: dict[str, Any] = {}
    try:
        import numba
        loop = numba.njit(cache=False)(_p2l_loop)
        out = np.empty(math.ceil(2 * math.pi / inc), np.float32)

        def p2l_numba() -> None:
            for zmin, zmax in BANDS.values():
                loop(x, y, z, zmin, zmax, grid[0], grid[1], grid[2], grid[3], grid[4], out)
        p2l_numba()
        candidates["p2l loop (numba)"] = p2l_numba
        have_numba = True
    except ImportError:
        have_numba = False

    def p2l_np() -> None:
        for zmin, zmax in BANDS.values():
            p2l_numpy(x, y, z, zmin, zmax, *grid)
    candidates["p2l vectorised numpy"] = p2l_np

    ours: dict[str, Any] = {}
    conv_auto = SliceConverter(info, specs, **common)
    if conv_auto._c_kernel:
        ours["ours, one pass (C kernel)"] = lambda: conv_auto.convert(scan)
    if have_numba:
        conv = SliceConverter(info, specs, backend="numba", **common)
        ours["ours, one pass (numba kernel)"] = lambda: conv.convert(scan)
    conv_np = SliceConverter(info, specs, backend="numpy", **common)
    ours["ours, one pass (numpy backend)"] = lambda: conv_np.convert(scan)
    if have_numba:
        # holes on in every slice (floor z = 0, no drop in the room: every edge is tested; the
        # no-return pixels looking down report holes): "auto" takes the numba row kernel
        conv_holes = SliceConverter(info, specs, holes=True, **common)
        ours["ours, holes on (numba row kernel)"] = lambda: conv_holes.convert(scan)
        conv_before = SliceConverter(info, specs, holes=True, backend="numba", **common)
        conv_before.convert(scan)
        next(iter(conv_before._tables.values())).sorted.rows = None
        ours["ours, holes on (bin-ordered + numpy holes)"] = lambda: conv_before.convert(scan)
    for fn in ours.values():
        fn()                                              # tables + JIT outside the timing
    if args.variants:
        ours.update(variants(info, specs, common, scan, have_numba))
    candidates.update(ours)

    times = interleaved_times(candidates, args.repeat, clock=time.process_time)
    med = {k: statistics.median(v) * 1e3 for k, v in times.items()}
    low = {k: min(v) * 1e3 for k, v in times.items()}

    print(f"4 slices of a {H}x{W} scan, sensor {'0.3 m in front of' if args.offset else 'on'} "
          f"the z axis of base_link; CPU time, median of {args.repeat} runs, python "
          f"{sys.version.split()[0]}, load average {os.getloadavg()[0]:.1f}")
    for name, ms in med.items():
        print(f"  {name:34s} median {ms:7.2f} ms   min {low[name]:7.2f} ms")
    for mine in ours:
        for base in (k for k in candidates if k.startswith("p2l")):
            print(f"  ratio {base} / {mine}: {med[base] / med[mine]:.1f}x (medians), "
                  f"{low[base] / low[mine]:.1f}x (minima)")
    in_band = [float(np.mean((z >= a) & (z <= b))) for a, b in BANDS.values()]
    print("  fraction of pixels in each band:", ", ".join(f"{f:.2f}" for f in in_band))
    tables = next(iter(conv_np._tables.values()))
    rr = r.reshape(-1).astype(np.float64)
    near = [tables.near_fraction(rr, i) for i in range(len(tables.r_thr))]
    print("  fraction of finite pixels needing atan2 (r < r_thr), per grid:",
          ", ".join(f"{f:.3f}" for f in near))
    if have_numba:
        srt = next(iter(conv._tables.values())).sorted
        path = ("per-pixel passes" if srt is None else "bin-ordered kernel" if srt.rows is None
                else "row-ordered kernel (per-row float32 band intervals)")
        print("  numba path:", path)
    if conv_auto._c_kernel:
        t = next(iter(conv_auto._tables.values()))
        rows = None if t.sorted is None else t.sorted.rows
        used = rows is not None and rows.c_plan(t, conv_auto.slices) is not None
        print("  C kernel:", "row-ordered, streamed in pixel order" if used
              else "does not apply here (the numba / numpy path runs)")


if __name__ == "__main__":
    main()
