"""Benchmark: 4 height slices of a 128 x 1024 LidarScan from a moving mount (issue 15).

Run: ``.venv/bin/python bench/bench_moving_slices.py [--repeat N] [--beam-times]
[--t-channel]``. Prints
medians, minima and ratios of CPU time (``time.process_time``) of candidates interleaved in a
new random order every round (``bench/_timing.py``), measured in the same run, and the load
average; no assertions. Target: a moving mount costs no more than ~3x the fixed mount.

Scene: the OS-1-128-like sensor and room of ``bench_slices.py`` at 1024 columns (100 ms
sweep), on a pan-tilt head 0.5 m above ``base_link``: yawing at one turn per second and
nodding 0.2 rad at 5 Hz, its pose sampled every 5 ms in a
:class:`converters.TransformTrack` (the ranges are the room seen from the mid-sweep pose: the
speed does not depend on them). ``--beam-times``: every beam fires 0.2 us after the previous
one (``beam_time_offsets``), so every pixel has its own time (one pose per pixel).
``--t-channel``: a per-pixel ``t`` channel of irregular delays (0-50 us, fixed seed, as a
sensor with irregular pixel timing), a pose per pixel too.

Candidates (all 4 slices, the 4 rclpy LaserScans included):

* ``fixed mount``: the same converter with the mid-sweep pose as fixed extrinsics (default
  backend: the C kernel or the numba row kernel, tables precomputed once): the baseline of the
  target;
* ``moving, track``: ``extrinsics=TransformTrack`` (default backend), poses looked up per scan;
* ``moving, per time (before)``: with a pose per pixel (``--beam-times``, ``--t-channel``),
  the same converter looking up one pose per distinct pixel time (``np.unique`` of the pixel
  times, ``TransformTrack.lookup_many``, then the compiled transform) instead of
  interpolating each ray's pose in the compiled pass: the path before that pass, and its
  oracle;
* ``moving, callable``: ``extrinsics=head``, the head's pose as a Python function of the
  stamp (one call per distinct pixel time, each result checked);
* ``moving, full tables``: the path before issue 15's change, every table of the fixed mount
  rebuilt per scan (kept as the tests' oracle);
* ``per-point loop``: the poses of the scan's distinct times, then, compiled with numba, every
  sensor-frame point moved by its pose and pointcloud_to_laserscan's per-point loop once per
  slice (``bench_slices._p2l_loop``); the sensor-frame cloud is built outside the timing.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import statistics
import sys
import time
from typing import Any

import numpy as np

import bench_slices as scene
import lidarscan
from _timing import interleaved_times
from converters import TransformTrack
from converters.slices.converter import SliceConverter, SliceSpec

scene.H, scene.W = 128, 1024
STAMP = 10**9
MS = 1_000_000


def head(t: int) -> np.ndarray:
    """base_link <- sensor of the pan-tilt head at ``t`` ns."""
    s = (t - STAMP) * 1e-9
    yaw, pitch = 2 * math.pi * s, 0.2 * math.sin(2 * math.pi * 5 * s)
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    m = np.eye(4)
    m[:3, :3] = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ np.array(
        [[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    m[:3, 3] = (0.0, 0.0, 0.5)
    return m


def _move_points(xyz: Any, rows: Any, index: Any, x: Any, y: Any, z: Any) -> None:
    """Every point moved by its pose (``rows[index[i]]``: top 3x4, row-major)."""
    for i in range(xyz.shape[0]):
        m = rows[index[i]]
        a, b, c = np.float64(xyz[i, 0]), np.float64(xyz[i, 1]), np.float64(xyz[i, 2])
        x[i] = m[0] * a + m[1] * b + m[2] * c + m[3]
        y[i] = m[4] * a + m[5] * b + m[6] * c + m[7]
        z[i] = m[8] * a + m[9] * b + m[10] * c + m[11]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeat", type=int, default=40)
    parser.add_argument("--beam-times", action="store_true",
                        help="beam_time_offsets 0.2 us apart: one pose per pixel")
    parser.add_argument("--t-channel", action="store_true",
                        help="a per-pixel t channel of irregular delays: one pose per pixel")
    args = parser.parse_args()

    info = scene.make_info()
    if args.beam_times:
        info = dataclasses.replace(info, beam_time_offsets=np.arange(scene.H, dtype=np.int64)
                                   * 200)
    mid = head(STAMP + 50 * MS)
    r = scene.room_ranges(info, mid)
    rng = np.random.default_rng(1)
    channels = {"range": r, "intensity": rng.integers(0, 4000, r.shape).astype(np.uint16)}
    if args.t_channel:
        channels["t"] = rng.integers(0, 50_000, r.shape).astype(np.uint32)
    scan = lidarscan.make_scan(info, channels, STAMP, as_dataclass=True)
    track = TransformTrack(name="base_link <- os_sensor")
    for t in range(STAMP - 20 * MS, STAMP + 125 * MS, 5 * MS):
        track.add(t, head(t))
    specs = {k: SliceSpec(*v) for k, v in scene.BANDS.items()}

    fixed = SliceConverter(info, specs, extrinsics=mid, frame_id="base_link")
    moving = SliceConverter(info, specs, extrinsics=track, frame_id="base_link")
    by_call = SliceConverter(info, specs, extrinsics=head, frame_id="base_link")
    full = SliceConverter(info, specs, extrinsics=track, frame_id="base_link")
    full._reference_tables = True
    candidates: dict[str, Any] = {
        "fixed mount": lambda: fixed.convert(scan),
        "moving, track": lambda: moving.convert(scan),
    }
    if args.beam_times or args.t_channel:
        per_time = SliceConverter(info, specs, extrinsics=track, frame_id="base_link")
        per_time._per_pixel = False
        candidates["moving, per time (before)"] = lambda: per_time.convert(scan)
        for name, got in moving.convert(scan).items():     # the same slices (up to rounding)
            want = per_time.convert(scan)[name]
            a, b = np.asarray(got.ranges), np.asarray(want.ranges)
            same = np.mean((a == b) | (np.isnan(a) & np.isnan(b))) * 100
            print(f"  {name}: {same:.3f} % of the ranges identical to the per-time path")
    candidates.update({
        "moving, callable": lambda: by_call.convert(scan),
        "moving, full tables (before)": lambda: full.convert(scan),
    })
    try:
        import numba
    except ImportError:
        numba = None
    if numba is not None:
        loop = numba.njit(cache=False)(scene._p2l_loop)
        move = numba.njit(cache=False)(_move_points)
        proj = lidarscan.make_projector(info)
        xyz = proj.xyz(r).reshape(-1, 3)                  # sensor frame, NaN: no return
        rel = proj.pixel_times(scan).reshape(-1)
        n = xyz.shape[0]
        x, y, z = np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, np.float32)
        inc = 2 * math.pi / scene.W
        out = np.empty(scene.W, np.float32)

        def per_point() -> None:
            unique, index = np.unique(STAMP + rel, return_inverse=True)
            rows = track.lookup_many(unique)[:, :3, :].reshape(-1, 12)
            move(xyz, np.ascontiguousarray(rows), index.reshape(-1), x, y, z)
            for zmin, zmax in scene.BANDS.values():
                loop(x, y, z, zmin, zmax, -math.pi, math.pi, inc, 0.1, 120.0, out)
        candidates["per-point loop (numba)"] = per_point

    times = interleaved_times(candidates, args.repeat, clock=time.process_time)
    med = {k: statistics.median(v) * 1e3 for k, v in times.items()}
    low = {k: min(v) * 1e3 for k, v in times.items()}
    poses = len(moving.mount_poses(scan)[0])
    print(f"4 slices of a {scene.H}x{scene.W} scan from a pan-tilt head ({poses} poses per "
          f"scan); CPU time, median of {args.repeat} interleaved rounds, python "
          f"{sys.version.split()[0]}, load average {os.getloadavg()[0]:.1f}")
    for name, ms in med.items():
        print(f"  {name:30s} median {ms:7.2f} ms   min {low[name]:7.2f} ms   "
              f"{med[name] / med['fixed mount']:5.2f}x the fixed mount (medians), "
              f"{low[name] / low['fixed mount']:5.2f}x (minima)")
    for base in [k for k in candidates if k.startswith(("per-point", "moving, full",
                                                          "moving, per time"))]:
        print(f"  ratio {base} / moving, track: {med[base] / med['moving, track']:.1f}x "
              f"(medians), {low[base] / low['moving, track']:.1f}x (minima)")


if __name__ == "__main__":
    main()
