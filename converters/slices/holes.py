"""Holes (negative obstacles) of LaserScan slices: the rule, its static per-ray tables and the
packed plan the compiled row kernel reads.

The grid, band and fusion conventions these tables feed are those of :mod:`converters.slices.spec`
(a hole edge is classified and fused like a point there).

**Holes** (negative obstacles, slices only, off unless a slice enables them). The floor is the
plane ``z = floor_height`` of the output frame. A ray whose origin is above it (``Oz >
floor_height``) and that points down (``Dz < 0``) crosses it at ``r_f = (floor_height - Oz) / Dz``;
that crossing ``p(r_f)`` is the *edge*, where the floor should have been seen. The ray reports a
hole when its measurement went below the floor: a finite ``r > 0`` with ``z(r) = r*Dz + Oz <=
floor_height - hole_depth`` (inclusive; ``hole_depth > 0`` is the tolerance for floor noise), or
a ``+Inf`` (no return) when ``no_return`` is set (nothing answered where the floor should
be). ``NaN``, ``0``, negative and ``-Inf`` ranges never do. A hole is an obstacle at the edge,
classified like a point at the edge's planar range ``rho_f`` (finite in ``[range_min,
range_max]``, ``-Inf`` below, ``+Inf`` above) in the exact bin of ``atan2(y_f, x_f)``, and only
when ``rho_f <= hole_range_max`` (inclusive); the band ``[min_z, max_z]`` is not applied to it
(the edge lies on the floor, usually below the band). It fuses with the ray's other codes by the
same minimum with the ray's tie key, so a hole edge closer than every obstacle wins its bin.
Everything but the height test is static per ray (:func:`hole_edges`, once per table version).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from converters.slices.spec import AngleGrid, rho_codes

__all__ = ["HoleEdges", "HoleOptions", "HolePlan", "hole_edges", "hole_hits"]


@dataclass(frozen=True)
class HoleOptions:
    """Hole detection of one slice (module docstring, **Holes**).

    Attributes:
        floor_height: z of the floor plane in the output frame, metres.
        hole_depth: > 0, metres: a measured point at ``z <= floor_height - hole_depth``
            (inclusive) is below the floor.
        range_max: largest planar range of a reported edge, metres (inclusive; may be inf).
        no_return: a ray with no return (+Inf) that crosses the floor also reports a hole.
    """

    floor_height: float
    hole_depth: float
    range_max: float
    no_return: bool

    @property
    def below(self) -> float:
        """The height at or under which a measured point is in a hole (float64)."""
        return self.floor_height - self.hole_depth


@dataclass(frozen=True)
class HoleEdges:
    """Static hole tables of one slice: the rays that can report a hole, and what they report.

    Attributes:
        index: (m,) int64 ray indices (ascending).
        dz, oz: (m,) float64 z of their direction and origin (the height test per scan).
        bins: (m,) int64 bin of each ray's edge.
        codes: (m,) int64 code of each edge's planar range.
        below: ``floor_height - hole_depth``.
        no_return: whether +Inf ranges report holes.
    """

    index: np.ndarray[Any, np.dtype[np.int64]]
    dz: np.ndarray[Any, np.dtype[np.float64]]
    oz: np.ndarray[Any, np.dtype[np.float64]]
    bins: np.ndarray[Any, np.dtype[np.int64]]
    codes: np.ndarray[Any, np.dtype[np.int64]]
    below: float
    no_return: bool


def hole_edges(d: np.ndarray[Any, Any], o: np.ndarray[Any, Any], holes: HoleOptions,
               grid: AngleGrid, range_min: float, range_max: float) -> HoleEdges:
    """Where each ray would report a hole, computed once per table version.

    Args:
        d, o: (n, 3) float64 ray directions and origins in the output frame.
        holes: the slice's hole options.
        grid: the slice's grid.
        range_min, range_max: the slice's planar limits (classify the edge's range).

    Returns:
        :class:`HoleEdges` of the rays pointing down from above the floor whose edge lies in
        the grid and within ``holes.range_max``.
    """
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    ox, oy, oz = o[:, 0], o[:, 1], o[:, 2]
    floor = holes.floor_height
    down = np.flatnonzero((dz < 0) & (oz > floor))
    r_f = (floor - oz[down]) / dz[down]
    x = r_f * dx[down] + ox[down]
    y = r_f * dy[down] + oy[down]
    rho = np.sqrt(x * x + y * y)
    near = rho <= holes.range_max
    down, x, y, rho = down[near], x[near], y[near], rho[near]
    bins = grid.bins(np.arctan2(y, x))
    inside = bins >= 0
    down, bins, rho = down[inside], bins[inside], rho[inside]
    return HoleEdges(index=down.astype(np.int64), dz=dz[down].astype(np.float64),
                     oz=oz[down].astype(np.float64), bins=bins.astype(np.int64),
                     codes=rho_codes(rho, range_min, range_max), below=holes.below,
                     no_return=holes.no_return)


def hole_hits(r: np.ndarray[Any, Any], edges: HoleEdges) -> np.ndarray[Any, np.dtype[np.bool_]]:
    """(m,) bool: which rays of ``edges`` report a hole for their ranges ``r`` ((m,) metres,
    any float dtype; evaluated in float64)."""
    r64 = np.asarray(r, np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        z = r64 * edges.dz + edges.oz
        hit = (r64 > 0) & (r64 < np.inf) & (z <= edges.below)
    if edges.no_return:
        hit |= r64 == np.inf
    return hit


@dataclass(frozen=True)
class HolePlan:
    """The hole edges of all slices, as the compiled row kernel takes them
    (:func:`converters._kernels.slices_numba._row_convert`; the rule of :func:`hole_hits`,
    then :func:`merge_min`). Compact (24 bytes per edge; the pass is memory-bound), and slices
    whose edges are identical (same rays, bins, codes and hole options: usually all slices
    sharing a grid and range limits) form one group, tested once per scan.

    Attributes:
        start: (k + 1,) int64 first edge of each group; below: (k,) float64; no_return: (k,)
            bool; slice_start: (k + 1,) int64 first entry of each group in ``slice``.
        slice: (s,) int64 the slices with holes, group by group.
        pixel: (m,) int32 ray (pixel index) of each edge; bin: (m,) int32 its bin;
        value: (m,) int64 ``code << 32 | key`` of the edge (code of its planar range, tie key
            of its ray).
        dz, oz: (m,) float32 the ray's z direction and origin (the slices' tables are float32,
            so these are exact; the test is evaluated in float64).
    """

    start: np.ndarray[Any, np.dtype[np.int64]]
    below: np.ndarray[Any, np.dtype[np.float64]]
    no_return: np.ndarray[Any, np.dtype[np.bool_]]
    slice_start: np.ndarray[Any, np.dtype[np.int64]]
    slice: np.ndarray[Any, np.dtype[np.int64]]
    pixel: np.ndarray[Any, np.dtype[np.int32]]
    bin: np.ndarray[Any, np.dtype[np.int32]]
    value: np.ndarray[Any, np.dtype[np.int64]]
    dz: np.ndarray[Any, np.dtype[np.float32]]
    oz: np.ndarray[Any, np.dtype[np.float32]]

    @classmethod
    def create(cls, holes: Sequence[tuple[int, HoleEdges]], key: Any) -> HolePlan:
        """From (slice index, :class:`HoleEdges`) per slice with holes (none: an empty plan)
        and ``key``: pixel indices -> (m,) int64 tie keys.

        Raises:
            ValueError: ray tables that are not float32 values (a programming error).
        """
        groups: list[tuple[HoleEdges, list[int]]] = []
        for i, edges in holes:
            same = next((g for e, g in groups if e.below == edges.below
                         and e.no_return == edges.no_return
                         and all(np.array_equal(getattr(e, f), getattr(edges, f))
                                 for f in ("index", "bins", "codes", "dz", "oz"))), None)
            if same is None:
                groups.append((edges, [i]))
            else:
                same.append(i)
        e = [edges for edges, _ in groups]

        def cat(parts: list[Any], dtype: Any) -> np.ndarray[Any, Any]:
            return np.ascontiguousarray(np.concatenate(parts) if parts else np.zeros(0), dtype)

        dz, oz = cat([x.dz for x in e], np.float32), cat([x.oz for x in e], np.float32)
        if not (np.array_equal(dz, cat([x.dz for x in e], np.float64))
                and np.array_equal(oz, cat([x.oz for x in e], np.float64))):
            raise ValueError("hole edges: dz, oz must be float32 values")
        return cls(start=np.cumsum([0] + [x.index.size for x in e]).astype(np.int64),
                   below=np.array([x.below for x in e], np.float64),
                   no_return=np.array([x.no_return for x in e], np.bool_),
                   slice_start=np.cumsum([0] + [len(g) for _, g in groups]).astype(np.int64),
                   slice=np.array([i for _, g in groups for i in g], np.int64),
                   pixel=cat([x.index for x in e], np.int32),
                   bin=cat([x.bins for x in e], np.int32),
                   value=cat([(x.codes << 32) | key(x.index) for x in e], np.int64),
                   dz=dz, oz=oz)
