"""Plain-loop reference code shared by the slice and merger tests (the documented grid rules).

Written from the conventions in converters/slices/spec.py's docstring, not from its code.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

import lidarscan

TWO_PI = 2 * math.pi


def ref_grid(amin: float, amax: float, inc: float) -> tuple[float, float, int, bool]:
    """(angle_min, increment, N, full) from the documented rule."""
    span = amax - amin
    n_full = round(TWO_PI / inc)
    n_sector = round(span / inc) + 1
    if n_sector >= n_full:
        return amin, TWO_PI / n_full, n_full, True
    return amin, inc, n_sector, False


def ref_bin(theta: float, grid: tuple[float, float, int, bool]) -> int | None:
    amin, inc, n, full = grid
    if full:
        return math.ceil((theta - amin) / inc - 0.5) % n
    d = theta - amin
    d = d - TWO_PI * math.floor((d + inc / 2) / TWO_PI)
    k = math.ceil(d / inc - 0.5)
    return k if 0 <= k < n else None


def ray_interval(dz: float, oz: float, zmin: float, zmax: float) -> tuple[float, float]:
    if dz == 0:
        return (0.0, math.inf) if zmin <= oz <= zmax else (math.inf, -math.inf)
    a, b = (zmin - oz) / dz, (zmax - oz) / dz
    return max(min(a, b), 0.0), max(a, b)


def ref_qualify(d: tuple[float, ...], o: tuple[float, ...], zmin: float, zmax: float,
                rmin: float, rmax: float, near: float) -> tuple[bool, bool]:
    lo, hi = ray_interval(d[2], o[2], zmin, zmax)
    if lo > hi:
        return False, False

    def rho(r: float) -> float:
        if math.isinf(r):
            return math.inf if (d[0] or d[1]) else math.hypot(o[0], o[1])
        x, y = r * d[0] + o[0], r * d[1] + o[1]
        return math.sqrt(x * x + y * y)

    a2 = d[0] * d[0] + d[1] * d[1]
    r_star = -(d[0] * o[0] + d[1] * o[1]) / a2 if a2 > 0 else 0.0
    r_star = min(max(r_star, lo), max(hi, lo))
    return rho(r_star) <= rmax and max(rho(lo), rho(hi)) >= rmin, lo <= near


RANK = {"finite": 0, "neg": 1, "pos": 2, "nan": 3}
F32 = np.float32


def pose(x: float = 0.0, y: float = 0.0, z: float = 0.0, yaw: float = 0.0, roll: float = 0.0,
         pitch: float = 0.0) -> np.ndarray:
    """4x4 pose from translation and ZYX Euler angles."""
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))
    m = np.eye(4)
    m[:3, :3] = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]]) @ \
        np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]]) @ \
        np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    m[:3, 3] = (x, y, z)
    return m


def ref_slice(scan: Any, info: Any, *, zmin: float, zmax: float, ext: Any = None,
              amin: float = -math.pi, amax: float | None = None, inc: float | None = None,
              rmin: float | None = None, rmax: float | None = None, use_inf: bool = True,
              eps: float = 1.0, fill: float | None = None, holes: dict[str, Any] | None = None,
              intensity: str | None = "intensity") -> tuple[np.ndarray, np.ndarray]:
    """One slice of a LidarScan, pixel by pixel, from the documented rules (float32 ranges and
    the winners' intensities per bin); ``holes``: floor_height, hole_depth, hole_range_max
    (None = rmax), hole_no_return."""
    height, width = int(info.height), int(info.width)
    # ext: a fixed 4x4, or a callable (u, v) -> 4x4: the pose of pixel (row, stored column)
    m = np.eye(4) if ext is None or callable(ext) else np.asarray(ext, float)
    inc = TWO_PI / width if inc is None else inc
    amax = amin + TWO_PI if amax is None else amax
    rmin = max(float(info.range_min), 0.0) if rmin is None else rmin
    if rmax is None:
        rmax = float(info.range_max) if float(info.range_max) > 0 else math.inf
    near = max(float(info.range_min), 0.0)
    grid = ref_grid(amin, amax, inc)
    proj = lidarscan.make_projector(info)
    dirs, offs = proj.tables_for(scan)
    ranges = lidarscan.range_m(scan, info)
    values = lidarscan.channel(scan, intensity) if intensity else None
    cands: dict[int, tuple[Any, ...]] = {}

    def offer(b: int | None, cand: tuple[Any, ...]) -> None:
        if b is not None and (b not in cands or cand[:3] < cands[b][:3]):
            cands[b] = cand

    def rank_of(rho: float) -> tuple[int, float]:
        cls = "neg" if rho < rmin else "pos" if rho > rmax else "finite"
        return RANK[cls], float(F32(rho)) if cls == "finite" else 0.0

    for u in range(height):
        for v in range(width):
            c = (v - int(proj.shifts[u])) % width if scan.is_destaggered else v
            key = u * width + c
            if callable(ext):
                m = np.asarray(ext(u, v), float)
            d0 = [float(x) for x in dirs[u, v]]
            o0 = [float(x) for x in offs[u, v]]
            d = tuple(float(F32(m[i, 0] * d0[0] + m[i, 1] * d0[1] + m[i, 2] * d0[2]))
                      for i in range(3))
            o = tuple(float(F32(m[i, 0] * o0[0] + m[i, 1] * o0[1] + m[i, 2] * o0[2] + m[i, 3]))
                      for i in range(3))
            r = float(ranges[u, v])
            inten = float(values[u, v]) if values is not None else 0.0
            if math.isfinite(r) and r > 0:
                x, y, z = (r * d[i] + o[i] for i in range(3))
                if zmin <= z <= zmax:
                    offer(ref_bin(math.atan2(y, x), grid),
                          (*rank_of(math.sqrt(x * x + y * y)), key, inten))
            elif d[0] != 0 or d[1] != 0:
                cls = "pos" if r == math.inf else "neg" if r == -math.inf else "nan"
                far, near_ok = ref_qualify(d, o, zmin, zmax, rmin, rmax, near)
                if near_ok if cls == "neg" else far:
                    offer(ref_bin(math.atan2(d[1], d[0]), grid), (RANK[cls], 0.0, key, inten))
            if holes is None:
                continue
            floor = holes["floor_height"]
            if not (d[2] < 0 and o[2] > floor):
                continue                               # the ray never meets the floor
            below = (math.isfinite(r) and r > 0
                     and r * d[2] + o[2] <= floor - holes["hole_depth"]) or (
                r == math.inf and holes["hole_no_return"])
            if not below:
                continue
            r_f = (floor - o[2]) / d[2]
            x_f, y_f = r_f * d[0] + o[0], r_f * d[1] + o[1]
            rho_f = math.sqrt(x_f * x_f + y_f * y_f)
            edge_max = rmax if holes["hole_range_max"] is None else holes["hole_range_max"]
            if rho_f <= edge_max:
                offer(ref_bin(math.atan2(y_f, x_f), grid), (*rank_of(rho_f), key, inten))
    return ref_output(cands, grid[2], rmax, use_inf=use_inf, eps=eps, fill=fill)


def ref_output(cands: dict[int, tuple[Any, ...]], size: int, rmax: float, *,
               use_inf: bool = True, eps: float = 1.0, fill: float | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """The published (ranges, intensities) of ``size`` bins from each bin's winning candidate
    (rank, float32 range, tie key, intensity): REP 117 values, ``fill`` where nothing won."""
    inf_value = math.inf if use_inf else rmax + eps
    out = np.full(size, inf_value if fill is None else fill, np.float32)
    ints = np.zeros(size, np.float32)
    for b, (rank, v32, _key, inten) in cands.items():
        out[b] = [v32, -math.inf, inf_value, math.nan][rank]
        ints[b] = inten
    return out, ints
