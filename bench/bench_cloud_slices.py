"""Benchmark: 4 height slices of an unstructured cloud (the real OS-2-128 frame) in one pass vs
four runs of a compiled per-point loop for one slice.

Run: ``.venv/bin/python bench/bench_cloud_slices.py [--repeat N]``. Prints medians, minima and
ratios of CPU time (``time.process_time``) measured in the same run (candidates interleaved, in
a new random order every round) and the load average; no assertions. Target (issue 15): 4
slices >= 3x faster than four runs of the baseline.

Cloud: the real OS-2-128 frame of tests/data/ouster (128 x 1024, 8.7 % of the pixels without
return, NaN points there), converted with :func:`converters.pointcloud2.converter.to_pointcloud2`
(x, y, z, intensity float32, 16-byte points) and then treated as an unstructured cloud
(``height = 1``, ``width = 131072``: no grid, no ray tables). Target frame ``base_link``: the
sensor 1.8 m above it (the ground of the frame lies about 1.8 m below the sensor). Four slices
(metres in base_link): floor-to-knee 0.05-0.5, knee-to-table 0.5-0.8, table-to-head 0.8-1.8,
low 0.02-0.3; full circle at 2*pi/1024.

Candidates:

* ``ours``: :meth:`converters.slices.cloud.CloudSliceConverter.convert`, all 4 slices in one
  pass including the 4 rclpy LaserScan messages (the C kernel, its AVX2 build where the CPU has
  it, and its scalar build; also the numpy reference);
* baseline: the plain per-point loop for one slice, compiled with numba, run once per slice as
  four ``cloud_to_laserscan`` calls would: read x, y, z (the same strided fields of the cloud),
  skip non-finite, transform into base_link, band test, planar range, ``math.atan2``, nearest
  bin, range classes, keep the minimum (``code << 32 | index``, the same tie rule). Its outputs
  are checked equal to ours. Fields are extracted and messages built outside its timing (free
  for the baseline);
* for the decomposition: ours with one slice per converter, four converters (what the
  polynomial atan2 gains without the one pass), and the kernel alone
  (:meth:`CloudSliceConverter.fuse`: no decoding, no messages).
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _timing import interleaved_times  # noqa: E402

from converters.slices.spec import CODE_NEG_INF, CODE_POS_INF, EMPTY  # noqa: E402
from converters.slices.cloud import CloudSliceConverter, cloud_points  # noqa: E402

BANDS = {"floor_to_knee": (0.05, 0.5), "knee_to_table": (0.5, 0.8),
         "table_to_head": (0.8, 1.8), "low": (0.02, 0.3)}
WIDTH = 1024
MOUNT_Z = 1.8


def make_cloud() -> Any:
    """The real OS-2-128 frame as a height-1 (unstructured) PointCloud2 in os_sensor."""
    from converters.edge.evidence._common import load_frame, ouster_files, ouster_info
    from converters.sources.ouster.metadata import scan_from_frame
    from converters.pointcloud2.converter import to_pointcloud2

    meta, path = next((m, p) for m, p in ouster_files() if p is not None and "OS-2" in m.name)
    info = ouster_info(meta)
    scan = scan_from_frame(load_frame(path), info, as_dataclass=True)
    cloud = to_pointcloud2(scan, info)
    n = int(cloud.height) * int(cloud.width)
    cloud.height, cloud.width, cloud.row_step = 1, n, n * int(cloud.point_step)
    cloud.is_dense = False
    return cloud


def _loop_one_slice(xs: Any, ys: Any, zs: Any, m: Any, zlo: float, zhi: float, rlo: float,
                    rhi: float, amin: float, inc: float, size: int,
                    best: Any) -> None:  # pragma: no cover - compiled
    """The per-point loop for one slice (full circle), as plainly as possible."""
    for i in range(size):
        best[i] = EMPTY
    for i in range(xs.shape[0]):
        x, y, z = float(xs[i]), float(ys[i]), float(zs[i])
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            continue
        pz = m[6] * x + m[7] * y + m[8] * z + m[11]
        if pz < zlo or pz > zhi:
            continue
        px = m[0] * x + m[1] * y + m[2] * z + m[9]
        py = m[3] * x + m[4] * y + m[5] * z + m[10]
        rho = math.sqrt(px * px + py * py)
        k = int(math.ceil((math.atan2(py, px) - amin) / inc - 0.5)) % size
        code = np.int64(np.float32(rho).view(np.int32))
        if rho < rlo:
            code = CODE_NEG_INF
        elif rho > rhi:
            code = CODE_POS_INF
        v = (code << 32) | i
        if v < best[k]:
            best[k] = v


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeat", type=int, default=40)
    args = parser.parse_args()

    cloud = make_cloud()
    ext = np.eye(4)
    ext[2, 3] = MOUNT_Z
    specs = {k: {"min_height": a, "max_height": b} for k, (a, b) in BANDS.items()}
    common = {"extrinsics": ext, "frame_id": "base_link", "angle_increment": 2 * math.pi / WIDTH}
    inc = 2 * math.pi / WIDTH

    candidates: dict[str, Any] = {}
    try:
        import numba
        loop = numba.njit(cache=False, error_model="numpy")(_loop_one_slice)
        have_numba = True
    except ImportError:
        have_numba = False
    x, y, z = cloud_points(cloud)
    m = np.r_[ext[:3, :3].reshape(-1), ext[:3, 3]]
    outs = {name: np.empty(WIDTH, np.int64) for name in BANDS}
    if have_numba:
        def baseline() -> None:
            for name, (zlo, zhi) in BANDS.items():
                loop(x, y, z, m, zlo, zhi, 0.0, math.inf, -math.pi, inc, WIDTH, outs[name])
        baseline()
        candidates["baseline: 4 x one-slice loop (numba)"] = baseline

    from converters._kernels import cloud_slices as kernel

    ours: dict[str, Any] = {}
    conv = CloudSliceConverter(specs, **common)
    if kernel.available():
        def scalar() -> Any:
            kernel.SIMD = 0
            try:
                return conv.convert(cloud)
            finally:
                kernel.SIMD = 1
        build = "AVX2" if kernel.vectorised() else "scalar"
        ours[f"ours, one pass (C kernel, {build})"] = lambda: conv.convert(cloud)
        if kernel.vectorised():
            ours["ours, one pass (C kernel, scalar build)"] = scalar
        singles = [CloudSliceConverter({k: v}, **common) for k, v in specs.items()]
        ours["ours, 4 x one slice (C kernel)"] = lambda: [c.convert(cloud) for c in singles]
        ours["ours, kernel alone (fuse, no messages)"] = lambda: conv.fuse(cloud)
    conv_np = CloudSliceConverter(specs, backend="numpy", **common)
    ours["ours, one pass (numpy reference)"] = lambda: conv_np.convert(cloud)
    candidates.update(ours)

    ref = conv_np.fuse(cloud)
    if kernel.available():
        got = conv.fuse(cloud)
        print(f"  outputs: C kernel == numpy reference: {np.array_equal(got, ref)}")
    if have_numba:
        base = np.concatenate([outs[k] for k in BANDS])
        print(f"  baseline == numpy reference: {np.array_equal(base, ref)} "
              f"({int(np.sum(base != ref))} bins differ)")

    times = interleaved_times(candidates, args.repeat, clock=time.process_time)
    med = {k: statistics.median(v) * 1e3 for k, v in times.items()}
    low = {k: min(v) * 1e3 for k, v in times.items()}
    n = int(cloud.width)
    zz = z.astype(np.float64) + MOUNT_Z
    print(f"4 slices of the OS-2-128 frame as an unstructured cloud ({n} points), sensor "
          f"{MOUNT_Z} m above base_link; CPU time, median of {args.repeat} runs, python "
          f"{sys.version.split()[0]}, load average {os.getloadavg()[0]:.1f}")
    for name, ms in med.items():
        print(f"  {name:42s} median {ms:7.2f} ms   min {low[name]:7.2f} ms")
    for mine in ours:
        for base_name in (k for k in candidates if k.startswith("baseline")):
            print(f"  ratio {base_name} / {mine}: {med[base_name] / med[mine]:.1f}x "
                  f"(medians), {low[base_name] / low[mine]:.1f}x (minima)")
    fractions = [float(np.mean((zz >= a) & (zz <= b))) for a, b in BANDS.values()]
    union = float(np.mean((zz >= 0.02) & (zz <= 1.8)))
    print("  fraction of points in each band:", ", ".join(f"{f:.3f}" for f in fractions),
          f"(union {union:.3f})")


if __name__ == "__main__":
    main()
