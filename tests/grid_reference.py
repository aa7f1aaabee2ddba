"""Plain-loop reference code shared by the slice and merger tests (the documented grid rules).

Written from the conventions in converters/_grid.py's docstring, not from its code.
"""

from __future__ import annotations

import math

import numpy as np

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
