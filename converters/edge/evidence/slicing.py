"""Question 6: slices from the structured scan vs from a point cloud; merger vs per-point pipeline.

Slices: the real frames go through :class:`converters.slices.converter.SliceConverter` (three height
bands, the sensor's column resolution, the grid rules of :mod:`converters.slices.spec`) and through a
per-point pipeline on the PointCloud2 that ouster-ros publishes for the same frame
(:func:`converters.edge.evidence.transport.slices_from_cloud`, same grid and rules, float32 x, y, z).
The table counts bins that agree, and says why the others do not.

Merger: the two real frames as two lidars on one robot (OS-2-128 at the front, 0.5 m high; the
OS-0-32 at the back, 0.4 m high, turned 180°), one band 0.3..0.8 m in ``base_link``, output grid at the lidars' column resolution (360°/1024), and 0.25° (finer than the inputs: output bins
that no input ray lands in stay empty, in both pipelines). Reference = every 3D return of both sensors in the band, binned directly on the output
grid in float64 (min planar range per bin). Compared with it:

* project: SliceConverter per lidar (into ``base_link``, at the lidar's column resolution), then
  :class:`converters.merger.LaserScanMerger`;
* per-point pipeline as deployed today: pointcloud_to_laserscan rules per lidar (bin =
  floor((θ − angle_min)/inc), N = ceil(2π/inc), θ = +π falls outside and is dropped, a point
  cloud has no rays so no +Inf), then the scans projected back to points (laser_geometry: keep
  range_min ≤ r < range_max), concatenated and binned again with the same rules (ira_laser_tools).
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Any

import numpy as np

from converters.edge.evidence._common import Block, fmt_int, have, pending, table, time_call

__all__ = ["blocks", "merger_quality", "slice_agreement"]

BAND = (0.3, 0.8)
MOUNTS = {"front OS-2-128": ((0.25, 0.0, 0.5), 0.0), "back OS-0-32": ((-0.25, 0.0, 0.4), math.pi)}
OUT_INC = 2 * math.pi / 1024  # both lidars have 1024 columns: no up-sampling


def _pose(xyz: tuple[float, float, float], yaw: float) -> np.ndarray[Any, Any]:
    m = np.eye(4)
    m[:3, :3] = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0],
                          [0, 0, 1]])
    m[:3, 3] = xyz
    return m


def _frames() -> list[tuple[str, Any, Any]]:
    """(label, rclpy info, rclpy scan) of the real frames, OS-2-128 first."""
    from converters.edge.evidence.transport import _frames as frames
    return sorted(frames(), key=lambda f: "OS-2" not in f[0])


@lru_cache(maxsize=1)
def slice_agreement() -> list[list[str]]:
    """Rows: per frame and band, bins compared between SliceConverter and the per-point path."""
    from converters.edge.evidence.transport import SLICES, slices_from_cloud
    from converters.slices.converter import SliceConverter
    from converters.pointcloud2.converter import to_pointcloud2
    rows = []
    for label, info, scan in _frames():
        slicer = SliceConverter(info, {k: {"min_height": lo, "max_height": hi}
                                       for k, (lo, hi) in SLICES.items()},
                                intensity_channel=None)
        scans = slicer.convert(scan)
        # the same with empty bins = NaN: +Inf then means "a ray crossed the band, no return"
        free_scan = SliceConverter(info, {k: {"min_height": lo, "max_height": hi}
                                          for k, (lo, hi) in SLICES.items()},
                                   intensity_channel=None, fill=math.nan).convert(scan)
        first = next(iter(scans.values()))
        n = len(first.ranges)
        cloud = to_pointcloud2(scan, info, preset="ouster")
        ref = slices_from_cloud(cloud, SLICES, n, float(first.range_min), float(first.range_max))
        for name, (lo, hi) in SLICES.items():
            a = np.asarray(scans[name].ranges, np.float32)
            b = ref[name]
            same = (a == b) | (np.isnan(a) & np.isnan(b))
            both = np.isfinite(a) & np.isfinite(b)
            with np.errstate(invalid="ignore"):
                close = both & ~same & (np.abs(a - b) <= 1e-4)
            far = both & ~same & ~close
            cls = ~same & ~both
            free = int(np.sum(np.isposinf(np.asarray(free_scan[name].ranges, np.float32))))
            diff = np.abs(a[both] - b[both])
            rows.append([label, f"{name} [{lo:g}, {hi:g}] m", fmt_int(n), fmt_int(int(same.sum())),
                         fmt_int(int(close.sum())), fmt_int(int(far.sum())),
                         fmt_int(int(cls.sum())),
                         f"{diff.max() * 1e3:.3f}" if diff.size else "—",
                         fmt_int(int(np.isfinite(a).sum())), fmt_int(free)])
    return rows


# ------------------------------------------------------------------------------ merger

def _p2l(x: np.ndarray[Any, Any], y: np.ndarray[Any, Any], inc: float, rmin: float,
         rmax: float) -> np.ndarray[Any, Any]:
    """pointcloud_to_laserscan binning of planar points (f32 fields): floor bins, N = ceil."""
    n = (math.ceil(np.float32(2 * math.pi) / np.float32(inc)))
    r = np.hypot(x, y)
    theta = np.arctan2(y, x)
    k = np.floor((theta + math.pi) / inc).astype(np.int64)
    keep = (r >= rmin) & (r <= rmax) & (k >= 0) & (k < n)  # k == n (+pi) would be OOB: dropped
    out = np.full(n, np.inf)
    np.minimum.at(out, k[keep], r[keep])
    return out


def _project_laser(ranges: np.ndarray[Any, Any], inc: float, rmin: float, rmax: float
                   ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """laser_geometry.projectLaser: points of rays with range_min <= r < range_max."""
    i = np.arange(ranges.size)
    angle = -math.pi + i * inc
    keep = np.isfinite(ranges) & (ranges >= rmin) & (ranges < rmax)
    r = ranges[keep]
    return r * np.cos(angle[keep]), r * np.sin(angle[keep])


def _points_in_base(info: Any, scan: Any, pose: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    from lidarscan import range_m
    from lidarscan.geometry import exact_xyz
    p = exact_xyz(info, range_m(scan, info)).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1)]
    out: np.ndarray[Any, Any] = p @ pose[:3, :3].T + pose[:3, 3]
    return out


def _reference(points: list[np.ndarray[Any, Any]], n: int, rmin: float, rmax: float,
               inc: float) -> np.ndarray[Any, Any]:
    p = np.concatenate(points)
    p = p[(p[:, 2] >= BAND[0]) & (p[:, 2] <= BAND[1])]
    rho = np.hypot(p[:, 0], p[:, 1])
    k = np.ceil((np.arctan2(p[:, 1], p[:, 0]) + math.pi) / inc - 0.5).astype(np.int64) % n
    keep = (rho >= rmin) & (rho <= rmax)
    out = np.full(n, np.inf)
    np.minimum.at(out, k[keep], rho[keep])
    return out


@lru_cache(maxsize=4)
def merger_quality(timing: bool = False, out_inc: float = OUT_INC
                   ) -> tuple[list[list[str]], dict[str, float]]:
    """Rows comparing the project's merger and the per-point pipeline with the reference."""
    from converters.slices.converter import SliceConverter
    from converters.merger import LaserScanMerger, MergerInput
    from converters.pointcloud2.converter import read_points, to_pointcloud2
    frames = _frames()[:2]
    rmin, rmax = 0.3, 100.0
    slices, clouds_xy, points, incs = {}, [], [], []
    for (label, info, scan), (name, (xyz, yaw)) in zip(frames, MOUNTS.items()):
        pose = _pose(xyz, yaw)
        inc = 2 * math.pi / int(info.width)
        conv = SliceConverter(info, {"band": {"min_height": BAND[0], "max_height": BAND[1]}},
                              extrinsics=pose, frame_id="base_link", angle_increment=inc,
                              range_min=rmin, range_max=rmax, intensity_channel=None)
        slices[name] = conv.convert(scan)["band"]
        points.append(_points_in_base(info, scan, pose))
        cloud = read_points(to_pointcloud2(scan, info, preset="ouster")).reshape(-1)
        xyz32 = np.stack([cloud["x"], cloud["y"], cloud["z"]], -1).astype(np.float32)
        xyz32 = xyz32[np.all(np.isfinite(xyz32), axis=1)]
        # tf of the f32 cloud into base_link (float32 arithmetic, as PCL does)
        base = (xyz32 @ pose[:3, :3].T.astype(np.float32)) + pose[:3, 3].astype(np.float32)
        clouds_xy.append((base, inc))
        incs.append(inc)
    merger = LaserScanMerger({n: MergerInput() for n in slices}, frame_id="base_link",
                             angle_increment=out_inc, range_min=rmin, range_max=rmax,
                             intensities=False, motion_compensation=False)
    merged = np.asarray(merger.merge(slices).ranges, np.float64)
    n = merged.size

    def per_point() -> np.ndarray[Any, Any]:
        xs, ys = [], []
        for base, inc in clouds_xy:
            band = base[(base[:, 2] >= BAND[0]) & (base[:, 2] <= BAND[1])]
            scan_r = _p2l(band[:, 0].astype(np.float64), band[:, 1].astype(np.float64), inc,
                          rmin, rmax)
            x, y = _project_laser(scan_r, inc, rmin, rmax)
            xs.append(x)
            ys.append(y)
        return _p2l(np.concatenate(xs), np.concatenate(ys), out_inc, rmin, rmax)

    naive = per_point()
    ref = _reference(points, n, rmin, rmax, out_inc)
    rows = []
    for name, out in (("project: SliceConverter → LaserScanMerger", merged),
                      ("per-point: pointcloud_to_laserscan → laser_geometry → "
                       "pointcloud_to_laserscan", naive)):
        m = min(out.size, n)
        o, r = out[:m], ref[:m]
        fin_r = np.isfinite(r)
        both = fin_r & np.isfinite(o)
        with np.errstate(invalid="ignore"):
            near = both & (np.abs(o - r) <= 0.01)
        err = np.abs(o[both] - r[both])
        rows.append([name, f"{math.degrees(out_inc):.4f}°", fmt_int(out.size), fmt_int(int(fin_r.sum())),
                     fmt_int(int(near.sum())),
                     fmt_int(int((fin_r & ~np.isfinite(o)).sum()) + max(n - out.size, 0)),
                     fmt_int(int((~fin_r & np.isfinite(o)).sum())),
                     f"{np.median(err) * 1e3:.1f}" if err.size else "—",
                     f"{np.percentile(err, 99) * 1e3:.0f}" if err.size else "—"])
    times: dict[str, float] = {}
    if timing:
        times["project merge (2 slices → 1)"] = time_call(lambda: merger.merge(slices))
        times["per-point merge (from the two band clouds)"] = time_call(per_point)
    return rows, times


def blocks(timing: bool = True) -> list[Block]:
    """``slicing`` and ``merger`` (deterministic) and ``timing-slicing`` blocks."""
    ok, why = have("converters.slices.converter", "SliceConverter")
    ok2, why2 = have("converters.pointcloud2.converter", "to_pointcloud2", "read_points")
    ok3, why3 = have("converters.merger", "LaserScanMerger", "MergerInput")
    out: list[Block] = []
    if ok and ok2:
        rows = slice_agreement()
        out.append(Block("slicing", table(
            ["frame", "slice (band, sensor frame)", "bins", "identical",
             "finite, \\|Δ\\| ≤ 0.1 mm", "finite, \\|Δ\\| > 0.1 mm", "different class",
             "max \\|Δ\\| finite (mm)", "finite bins",
             "free-space bins (+Inf with fill = NaN), from the scan only"], rows,
            ["l", "l"] + ["r"] * 8)))
    else:
        out.append(pending("slicing", "slices from the scan vs from a point cloud", why or why2))
    merger_times: dict[str, float] = {}
    if ok and ok2 and ok3:
        first, merger_times = merger_quality(timing)
        rows = list(first) + list(merger_quality(False, math.radians(0.25))[0])
        out.append(Block("merger", table(
            ["pipeline", "output grid", "bins", "reference finite bins", "within 1 cm of reference",
             "missing (reference finite, output not)", "spurious", "median \\|Δ\\| (mm)",
             "99th percentile \\|Δ\\| (mm)"], rows, ["l"] + ["r"] * 8)))
    else:
        out.append(pending("merger", "merger output vs a per-point pipeline", why or why2 or why3))
    if timing:
        if ok and ok2:
            out.append(Block("timing-slicing", _timing_table(merger_times), deterministic=False))
        else:
            out.append(pending("timing-slicing", "slicing time", why or why2, False))
    return out


def _timing_table(merger_times: dict[str, float]) -> str:
    from converters.edge.evidence.transport import SLICES, slices_from_cloud
    from converters.slices.converter import SliceConverter
    from converters.pointcloud2.converter import to_pointcloud2
    rows = []
    for label, info, scan in _frames():
        slicer = SliceConverter(info, {k: {"min_height": lo, "max_height": hi}
                                       for k, (lo, hi) in SLICES.items()},
                                intensity_channel=None)
        first = next(iter(slicer.convert(scan).values()))
        n, rmin, rmax = len(first.ranges), float(first.range_min), float(first.range_max)
        t_scan = time_call(lambda: slicer.convert(scan))
        t_cloud = time_call(lambda: slices_from_cloud(
            to_pointcloud2(scan, info, preset="ouster"), SLICES, n, rmin, rmax))
        rows.append([label, f"{len(SLICES)} slices", f"{t_scan * 1e3:.2f}",
                     f"{t_cloud * 1e3:.2f}", f"{t_cloud / t_scan:.2f}"])
    text = table(["frame", "output", "from LidarScan (SliceConverter) ms",
                  "via PointCloud2 (to_pointcloud2 + per-point numpy) ms",
                  "via PointCloud2 ÷ from LidarScan"], rows, ["l", "l", "r", "r", "r"])
    if merger_times:
        text += "\n\n" + table(["merge step", "ms"], [[k, f"{v * 1e3:.2f}"]
                                                    for k, v in merger_times.items()],
                               ["l", "r"])
    return text
