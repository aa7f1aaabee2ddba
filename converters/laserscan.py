"""Height-filtered LaserScan slices of a LidarScan, several in one pass.

A slice keeps the points whose height ``z`` in the target frame lies in ``[min_height,
max_height]`` (inclusive) and publishes, per bin of an angle grid, the minimum planar range
``sqrt(x*x + y*y)`` (inclusive ``[range_min, range_max]``). Grid, binning, value classes (REP 117)
and fusion rules are those of :mod:`converters._grid` (read its docstring); in short:

* default grid: full circle ``[-pi, pi)`` at the sensor's column resolution ``2*pi / W``;
  nearest bin in float64, half-bin to the lower index, +pi and -pi share a bin;
* a finite in-range value beats ``-Inf`` (too close) beats ``+Inf`` (no return / beyond
  ``range_max``) beats ``NaN`` (invalid pixel) beats an empty bin (``fill``); min range wins and
  carries its intensity; equal ranges go to the first pixel in *measurement* order
  (row-major, row ``u`` then measurement column ``c``), so staggered and destaggered scans give
  identical slices;
* a pixel with no return (+Inf) whose ray crosses the band within the range limits keeps ``+Inf``
  in its bin, so costmaps can clear; an invalid pixel (NaN, or a float range <= 0) gives ``NaN``.

**Holes** (negative obstacles: a stair down, a drop, a pit), off by default, per slice
(``holes=True``): a pixel whose ray points down from above the floor plane ``z =
floor_height`` (target frame) and whose measurement lies at or below ``floor_height -
hole_depth`` (or, with ``hole_no_return``, got no return at all) reports an obstacle at the
*edge*: the point where its ray crosses the floor plane, at that point's planar range and bin,
when that range is ``<= hole_range_max`` (default: the slice's ``range_max``). The edge is a point
like any other for the REP 117 classes, the limits and the ties (it carries the pixel's tie key
and intensity); the height band does not apply to it. Exact rules: :mod:`converters._holes`.
This is the cliff detection of the multi-laserscan toolbox's depth converter (its
``cliff_height`` is ``floor_height - hole_depth``), for any LidarScan: a lidar or a depth image
(:func:`converters.from_depth_image`).

Tables: with a fixed mount every pixel is a ray ``p = r*D + O`` whose direction ``D`` and
origin ``O`` in the target frame (float32 components, like the projector's tables; arithmetic in
float64) are computed once per LidarInfo version and column order (:func:`lidarscan.make_projector`,
then the extrinsics, :func:`converters.frames.transform_rays`). Per distinct grid and pixel the
far-field bin and the range ``r_thr`` above which the point's bin *is* the far-field bin are
precomputed (:func:`converters._grid.far_field`), so ``atan2`` runs only for in-band points
closer than their ``r_thr`` (a sensor far off the target's z axis makes most points need it:
prefer a target frame below the sensor); per slice, which pixels may report +Inf/NaN/-Inf.
Scans carrying ``column_azimuth_angles`` or a per-pixel ``azimuth`` channel
(:func:`lidarscan.geometry.pixel_azimuths`) rebuild the tables for every scan (correct, not fast).

**Moving mounts.** ``extrinsics`` may also be a :class:`converters.TransformTrack` (stamped
poses, interpolated: linear translation, shortest-arc slerp) or any callable ``stamp_ns (int) ->
4x4``: a lidar on a pan unit, an arm or a nodding mount that moves during its sweep. Every pixel's
ray is then moved by the mount's pose at *that pixel's* time: ``header.stamp +
column_time_offsets[c] + beam_time_offsets[u]`` (+ the per-pixel ``t`` channel when the scan has
one; :meth:`lidarscan.geometry.Projector.pixel_times`), so the sweep is de-skewed pixel by pixel
(with per-column times only, as most lidars, the pose is per column). The slicing that follows
is the same in every respect (grid, band, classes, ties, holes, backends); only the rays are
moved per scan (:meth:`SliceConverter._moving_tables`). What does not depend on the pose is kept:
the sensor-frame rays per geometry, the distinct pixel times and each pixel's one per column
timing (a scan with a ``t`` channel computes its own). A track computes the poses of the distinct
times in one batch; a callable is called once per distinct pixel time and its result checked (a
finite rigid 4x4, else :class:`lidarscan.errors.ValidationError`). With the compiled kernels
the rays are moved by a compiled loop (the bits of :func:`converters.frames.transform_rays`) and
fused by the general kernel with atan2 for every in-band point; far-field bins and
+Inf/NaN/-Inf qualifiers are computed for the pixels without a finite range only
(:class:`_MovingRays`); the numpy backend builds the full per-scan tables (the reference; the
same slices bit for bit, tests/test_moving_slices.py). A mount that holds still over a whole
scan gets the fixed-mount tables at that pose (every kernel), kept for the next scan. A pose
that cannot be found -- a time outside the track's span
(:class:`converters.transforms.OutOfSpanError`, the track never extrapolates) or any
:class:`~converters.transforms.TransformLookupError` the callable raises -- is raised by
:meth:`SliceConverter.convert`; nothing falls back to another pose. The fixed-mount path is
unchanged (same tables, same kernels).

Backends (:func:`converters._kernels.select`, table in :mod:`converters._kernels`): the numpy
reference here (:meth:`SliceConverter._fuse`, then :func:`converters._grid.decode`); the numba
kernels of :mod:`converters._kernels.slices_numba` (bin-ordered when all slices share one grid
and their range limits; row-ordered, with exact per-row float32 band intervals, when that grid
is a full circle at the sensor's column resolution seen by an upright or upside-down sensor;
else the per-pixel passes); the C kernel of :mod:`converters._kernels.slices` for the
row-ordered case (streams the scan in pixel order). All give identical slices (up to points
within an ulp of a bin edge, where numpy's SIMD ``atan2`` may differ from libm's in the last
bit). Inputs reach the kernels in native byte order (:func:`lidarscan.channel`, ``native=True``).
With holes enabled in any slice the C kernel is not used: the numba row-ordered kernel adds the
hole edges in the same call (static per-pixel tables, :class:`converters._holes.HolePlan`: only
the height test runs per scan); elsewhere the bands are fused by the other kernels (or numpy),
the holes are then added to the same reduction array by numpy
(:meth:`SliceConverter._add_holes`), and the result is decoded.

Time fields: ``header.stamp`` is the scan's stamp (measurement column 0), identical for all slices
of a scan; ``scan_time`` is ``W * column_time_increment`` (or from ``column_time_offsets``);
``time_increment`` is ``+-scan_time * angle_increment / 2pi``, positive for a counter-clockwise
sweep, negative for a clockwise one (Ouster). Since a grid generally does not start at column 0's
azimuth, the time of ray ``i`` is *not* ``stamp + i * time_increment``; it is the time of the
column that looked at that azimuth (use the LidarScan for per-point time).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from converters import _grid, _holes, _kernels, options
from converters._kernels import slices as _cslices
from converters._kernels.slices_numba import Bands, Rays
from converters._grid import AngleGrid, OutputOptions
from converters._holes import HoleOptions
from converters.frames import check_extrinsics, check_poses, transform_rays
from converters.options import IfPresent, resolve_channel
from converters.transforms import TransformTrack
from lidarscan.errors import ConfigError, InfoMismatchError, LinkageError
from lidarscan.geometry import azimuth_channel, info_key, make_projector, pixel_delays
from lidarscan.scan import as_array, channel, channel_names, range_m
from lidarscan.stamps import to_ns

__all__ = ["SliceConverter", "SliceSpec", "check_extrinsics", "to_laserscan"]

_NO_VALUES = np.zeros(0, np.float32)
_NO_KEYS = np.zeros(0, np.int64)


@dataclass(frozen=True)
class SliceSpec:
    """One slice: a height band plus optional overrides of the converter's common options.

    Attributes:
        min_height, max_height: inclusive band in metres, in the target frame (``-inf``/``inf``
            allowed for an open side; no default on purpose: pointcloud_to_laserscan's
            ``DBL_MIN`` default silently dropped everything at z <= 0).
        angle_min, angle_max, angle_increment, range_min, range_max, use_inf, inf_epsilon, fill,
        holes, floor_height, hole_depth, hole_range_max, hole_no_return:
            None = the converter's common value (see :class:`SliceConverter`).
    """

    min_height: float
    max_height: float
    angle_min: float | None = None
    angle_max: float | None = None
    angle_increment: float | None = None
    range_min: float | None = None
    range_max: float | None = None
    use_inf: bool | None = None
    inf_epsilon: float | None = None
    fill: float | None = None
    holes: bool | None = None
    floor_height: float | None = None
    hole_depth: float | None = None
    hole_range_max: float | None = None
    hole_no_return: bool | None = None


_OVERRIDES = ("angle_min", "angle_max", "angle_increment", "range_min", "range_max", "use_inf",
              "inf_epsilon", "fill", *options.HOLE_KEYS)


@dataclass(frozen=True)
class _Slice:
    name: str
    min_z: float
    max_z: float
    grid: AngleGrid
    options: OutputOptions
    holes: HoleOptions | None = None


class _Tables:
    """Static per-pixel tables of one column order (per LidarInfo version and extrinsics).

    Rays ``p = r*D + O`` in the target frame (float32 components, arithmetic in float64); per
    distinct grid the far-field bin and ``r_thr``; per slice the +Inf/NaN/-Inf qualifiers and,
    for slices with holes, their :class:`converters._holes.HoleEdges`.
    """

    def __init__(self, d: np.ndarray[Any, Any], o: np.ndarray[Any, Any],
                 keys: np.ndarray[Any, Any] | None, slices: list[_Slice],
                 grids: list[AngleGrid], slice_grid: list[int], near: float,
                 width: int) -> None:
        self.n = d.shape[0]
        self.rays = np.ascontiguousarray(np.concatenate([d, o], axis=1))     # (n, 6) f4
        self.dx, self.dy, self.dz = (np.ascontiguousarray(d[:, k]) for k in range(3))
        self.ox, self.oy, self.oz = (np.ascontiguousarray(o[:, k]) for k in range(3))
        self.keys = keys                     # measurement-order tie key per pixel, None = index
        if keys is None:
            self.key_to_pos: np.ndarray[Any, Any] | None = None
        else:
            self.key_to_pos = np.empty(self.n, np.int64)
            self.key_to_pos[keys] = np.arange(self.n)
        d64, o64 = d.astype(np.float64), o.astype(np.float64)
        self.bin_far: list[np.ndarray[Any, Any]] = []
        self.r_thr: list[np.ndarray[Any, Any]] = []
        for grid in grids:
            bin_far, r_thr = _grid.far_field(d64, o64, grid)
            self.bin_far.append(bin_far)
            self.r_thr.append(r_thr)
        self.q_far: list[np.ndarray[Any, Any]] = []
        self.q_near: list[np.ndarray[Any, Any]] = []
        for s, g in zip(slices, slice_grid):
            q_far, q_near = _grid.qualify(d64, o64, s.min_z, s.max_z, s.options.range_min,
                                          s.options.range_max, near)
            ok = self.bin_far[g] >= 0
            self.q_far.append(q_far & ok)
            self.q_near.append(q_near & ok)
        #: (slice index, edges) of the slices with holes
        self.holes = [(i, _holes.hole_edges(d64, o64, s.holes, s.grid, s.options.range_min,
                                           s.options.range_max))
                      for i, s in enumerate(slices) if s.holes is not None]
        self.hole_plan = _holes.HolePlan.create(self.holes, self.key)
        self.k_r_thr = np.ascontiguousarray(np.stack([_grid.round_up_f32(t) for t in self.r_thr]))
        #: the tables as the general compiled kernels take them
        self.kernel_rays = Rays(
            self.dx, self.dy, self.dz, self.ox, self.oy, self.oz,
            keys=np.zeros(0, np.int32) if keys is None else keys.astype(np.int32),
            qual=np.ascontiguousarray(np.stack(
                [qf.astype(np.uint8) | (qn.astype(np.uint8) << 1)
                 for qf, qn in zip(self.q_far, self.q_near)])),
            bin_far=np.ascontiguousarray(np.stack(self.bin_far).astype(np.int32)),
            r_thr=self.k_r_thr)
        self.sorted: _Sorted | None = None
        if len(grids) == 1 and len(slices) <= 60 and len(
                {(s.options.range_min, s.options.range_max) for s in slices}) == 1:
            self.sorted = _Sorted(self, grids[0].size, slices, width)

    def key(self, index: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        """Tie keys of pixel indices."""
        return index.astype(np.int64) if self.keys is None else self.keys[index]

    def position(self, key: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        """Pixel indices of tie keys."""
        return key if self.key_to_pos is None else self.key_to_pos[key]

    def near_fraction(self, r: np.ndarray[Any, Any], index: int = 0) -> float:
        """Fraction of finite pixels that need atan2 on grid ``index`` (diagnostics)."""
        ok = np.isfinite(r) & (r > 0)
        return float(np.mean(r[ok] < self.r_thr[index][ok])) if ok.any() else 0.0


class _MovingRays:
    """One scan's rays seen by a moving mount, as the general compiled kernel takes them
    (:meth:`converters._kernels.slices_numba.Compiled.fuse`), built per scan from the cached
    sensor-frame rays and the per-pixel poses (:meth:`SliceConverter._moving_tables`).

    Unlike :class:`_Tables` nothing is precomputed for reuse: the far-field thresholds are
    +inf (every in-band point takes atan2, which gives the bin the far-field tables would:
    they are exact), and the far-field bins and +Inf/NaN/-Inf qualifiers are computed only
    for this scan's pixels without a finite positive range (the only ones that read them,
    :func:`converters._kernels.slices_numba._pass_others`), compiled
    (:func:`converters._kernels.slices_numba._special_tables`: the float64 operations of
    :func:`converters._grid.far_field` and :func:`converters._grid.qualify`; libm's atan2 may
    differ from numpy's in the last bit, which moves a far-field bin only for a ray within an
    ulp of a bin edge). Hole edges (slices with holes) are computed per scan by numpy.
    Same slices, bit for bit, as the full tables on the tests' scenes
    (tests/test_moving_slices.py).
    """

    sorted = None                      # no bin-ordered / row-ordered layout

    def __init__(self, rays: tuple[np.ndarray[Any, Any], ...], keys: np.ndarray[Any, Any] | None,
                 r: np.ndarray[Any, Any], conv: SliceConverter) -> None:
        dx, dy, dz, ox, oy, oz = rays
        self.n = n = dx.shape[0]
        self.keys = keys
        self.key_to_pos: np.ndarray[Any, Any] | None = None
        if keys is not None:
            self.key_to_pos = np.empty(n, np.int64)
            self.key_to_pos[keys] = np.arange(n)
        with np.errstate(invalid="ignore"):
            special = np.flatnonzero(~((r > 0) & (r < np.inf)))
        n_grids, n_slices = len(conv._grids), len(conv.slices)
        bin_far = np.full((n_grids, n), -1, np.int32)
        qual = np.zeros((n_slices, n), np.uint8)
        if special.size:
            conv._kernel.special_tables(special, rays, conv._bands, conv._near, bin_far, qual)
        #: (slice index, edges) of the slices with holes (as :attr:`_Tables.holes`)
        self.holes: list[tuple[int, Any]] = []
        if conv._holes:
            d64 = np.array([dx, dy, dz], np.float64).T
            o64 = np.array([ox, oy, oz], np.float64).T
            self.holes = [(i, _holes.hole_edges(d64, o64, s.holes, s.grid, s.options.range_min,
                                                s.options.range_max))
                          for i, s in enumerate(conv.slices) if s.holes is not None]
        self.kernel_rays = Rays(
            dx, dy, dz, ox, oy, oz,
            keys=np.zeros(0, np.int32) if keys is None else keys.astype(np.int32),
            qual=qual, bin_far=bin_far, r_thr=conv._no_thresholds(n))

    def key(self, index: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        """Tie keys of pixel indices."""
        return index.astype(np.int64) if self.keys is None else self.keys[index]

    def position(self, key: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        """Pixel indices of tie keys."""
        return key if self.key_to_pos is None else self.key_to_pos[key]


class _Sorted:
    """The tables of :class:`_Tables` permuted into the order of the (single) grid's far-field
    bins, then pixel index, for the bin-ordered compiled kernel
    :func:`converters._kernels.slices_numba._sorted_fuse`."""

    def __init__(self, t: _Tables, size: int, slices: list[_Slice], width: int) -> None:
        n_slices = len(slices)
        far = t.bin_far[0]
        sort_key = np.where(far < 0, size, far)
        order = np.argsort(sort_key, kind="stable")
        self.src = order.astype(np.int32)
        self.bin_start = np.searchsorted(sort_key[order], np.arange(size + 2)).astype(np.int64)
        # tie key = pixel index unless destaggered: then the same array (read once)
        self.keys = self.src if t.keys is None else t.keys[order].astype(np.int32)
        #: dz, oz, dx, dy, ox, oy, r_thr, float32 in bin order
        self.cols = tuple(np.ascontiguousarray(a[order])
                          for a in (t.dz, t.oz, t.dx, t.dy, t.ox, t.oy, t.k_r_thr[0]))
        self.mask_dtype: Any = np.uint8 if n_slices <= 8 else np.uint64
        qf = np.zeros(t.n, np.uint64)
        qn = np.zeros(t.n, np.uint64)
        for s, (far_ok, near_ok) in enumerate(zip(t.q_far, t.q_near)):
            qf |= far_ok[order].astype(np.uint64) << np.uint64(s)
            qn |= near_ok[order].astype(np.uint64) << np.uint64(s)
        #: bit s: slice s may report +Inf/NaN (qf) or -Inf (qn), bin order
        self.qf, self.qn = qf.astype(self.mask_dtype), qn.astype(self.mask_dtype)
        self.max_width = int(np.diff(self.bin_start).max(initial=0))
        #: (size + 1,) float32 largest r_thr per bin (0 for an empty bin)
        thr = self.cols[6]
        self.bin_thr = np.zeros(size + 1, np.float32)
        filled = np.flatnonzero(np.diff(self.bin_start[:size + 2]) > 0)
        if filled.size:
            self.bin_thr[filled] = np.maximum.reduceat(thr, self.bin_start[filled])
        self.rows = _RowLayout.create(t, self, size, slices, width)


class _RowLayout:
    """Extra tables of the row-ordered kernels (numba's
    :func:`converters._kernels.slices_numba._row_convert` and the C kernel's plan), when it
    applies: every bin holds exactly one pixel of every row, in row order (a full circle at
    the sensor's column resolution), and ``dz``, ``oz`` are bitwise constant along every row
    (an upright sensor), so each band is an exact float32 range interval per row."""

    def __init__(self, src: np.ndarray[Any, Any], keys: np.ndarray[Any, Any],
                 lo: np.ndarray[Any, Any], hi: np.ndarray[Any, Any], q_rows: bool,
                 qf: np.ndarray[Any, Any], qn: np.ndarray[Any, Any]) -> None:
        self.src, self.keys = src, keys           # uint32 views: no negative-index checks
        #: (S, H) float32 band intervals per row (S padded to a multiple of four)
        self.lo, self.hi = lo, hi
        #: qualifiers per row ((H,), the same in every bin) or per position ((n,), bin order)
        self.q_rows, self.qf, self.qn = q_rows, qf, qn
        self._c_plan: _cslices.SlicePlan | None = None
        self._c_plan_tried = False

    def c_plan(self, t: _Tables, slices: list[_Slice]) -> _cslices.SlicePlan | None:
        """Arguments of the compiled kernel (converters/_slicekernel.c), built at the first
        call; None when its extra condition fails: bins and tie keys of every row affine in
        the column (``start + step*c mod W``), at most 32 slices."""
        if self._c_plan_tried:
            return self._c_plan
        self._c_plan_tried = True
        height = self.lo.shape[1]
        width = t.n // height
        cols = np.arange(width)
        keys = (np.broadcast_to(cols, (height, width)) if t.keys is None
                else t.keys.reshape(height, width) - np.arange(height)[:, None] * width)
        bin_rows = _grid.aligned_rows(t.bin_far[0], width, width)
        key_rows = _grid.aligned_rows(keys, width, width)
        if bin_rows is None or key_rows is None or len(slices) > _cslices.MAX_SLICES:
            return None
        if self.q_rows:
            qf, qn = self.qf, self.qn
        else:                                     # per pixel, in pixel order
            qf = np.zeros(t.n, np.uint32)
            qn = np.zeros(t.n, np.uint32)
            for s, (far_ok, near_ok) in enumerate(zip(t.q_far, t.q_near)):
                qf |= far_ok.astype(np.uint32) << np.uint32(s)
                qn |= near_ok.astype(np.uint32) << np.uint32(s)
        grid, options = slices[0].grid, slices[0].options
        self._c_plan = _cslices.SlicePlan(
            height=height, width=width, n_slices=len(slices), dx=t.dx, dy=t.dy, ox=t.ox,
            oy=t.oy, r_thr=t.k_r_thr[0], bins=bin_rows, keys=key_rows, qf=qf, qn=qn,
            lo=self.lo, hi=self.hi, lim_lo=float(options.range_min),
            lim_hi=float(options.range_max), g_min=grid.angle_min, g_inc=grid.increment,
            g_full=grid.full_circle,
            inf_value=np.array([s.options.inf_value for s in slices], np.float32),
            fill_value=np.array([s.options.fill_value for s in slices], np.float32),
            key_to_pos=t.key_to_pos)
        return self._c_plan

    @classmethod
    def create(cls, t: _Tables, st: _Sorted, size: int, slices: list[_Slice], width: int
               ) -> _RowLayout | None:
        """The layout, or None when the tables do not have that structure."""
        n = t.n
        if len(slices) > 32:                  # the kernel keeps qualifier bits in int32
            return None
        if size < 1 or width < 1 or n % size or n % width:
            return None
        height = n // size
        if height != n // width or not np.array_equal(st.bin_start[:size + 1],
                                                      np.arange(size + 1) * height):
            return None
        if not np.array_equal(st.src.reshape(size, height) // width, np.broadcast_to(
                np.arange(height), (size, height))):
            return None
        dz = t.dz.reshape(height, width).view(np.int32)
        oz = t.oz.reshape(height, width).view(np.int32)
        if not (np.all(dz == dz[:, :1]) and np.all(oz == oz[:, :1])):
            return None
        pad = -len(slices) % 4                    # empty bands up to a multiple of four
        zmin = np.r_[[s.min_z for s in slices], np.full(pad, np.inf)]
        zmax = np.r_[[s.max_z for s in slices], np.full(pad, -np.inf)]
        lo, hi = _grid.band_intervals_f32(t.dz[::width], t.oz[::width], zmin, zmax)
        q_rows = bool(np.all(st.qf.reshape(size, height) == st.qf[:height])
                      and np.all(st.qn.reshape(size, height) == st.qn[:height]))
        qf, qn = (st.qf[:height].copy(), st.qn[:height].copy()) if q_rows else (st.qf, st.qn)
        return cls(st.src.view(np.uint32), st.keys.view(np.uint32), np.ascontiguousarray(lo),
                   np.ascontiguousarray(hi), q_rows, qf, qn)


class SliceConverter:
    """Several height slices of one lidar, computed together from each LidarScan.

    Args:
        info: the LidarInfo (rclpy or dataclass) of the scans to convert.
        slices: name -> :class:`SliceSpec` (or a dict of its fields); order is kept.
        extrinsics: 4x4 pose of the scan's frame (``info.header.frame_id``) in the target frame;
            None = the scan's frame is the target frame. Heights and ranges are measured in the
            target frame, so a tilted or upside-down sensor works. A moving mount: a
            :class:`converters.TransformTrack` or a callable ``stamp_ns (int) -> 4x4``, looked
            up at every pixel's time (module docstring, **Moving mounts**).
        frame_id: header.frame_id of the slices (required with ``extrinsics``; default: the
            scan's frame).
        angle_min, angle_max, angle_increment: grid (radians); default full circle from -pi at
            2*pi/W.
        range_min, range_max: inclusive planar limits, metres; default the info's (0 / inf when
            unknown).
        intensity_channel: channel whose value at the winning pixel becomes the intensity (any
            dtype, cast to float32), or None for an empty ``intensities``. The default,
            ``IfPresent("intensity")``, uses the scan's ``intensity`` channel when it has one
            (empty ``intensities`` for a range-only scan); a plain name is required.
        use_inf, inf_epsilon, fill: output values (see :class:`converters._grid.OutputOptions`).
        holes: report negative obstacles (module docstring, **Holes**); off by default.
        floor_height: z of the floor in the target frame, metres (0: a target frame on the
            floor, such as ``base_footprint``).
        hole_depth: metres (> 0): a measured point at or below ``floor_height - hole_depth``
            is in a hole (the tolerance for floor noise and a slightly tilted floor).
        hole_range_max: largest planar range of a reported hole edge, metres (inclusive; None =
            the slice's ``range_max``): beyond it the floor is seen too obliquely to judge.
        hole_no_return: a pixel with no return (+Inf) whose ray crosses the floor also reports
            a hole (nothing answered where the floor should be); set False for sensors that
            lose returns on dark or wet floors.
        range_channel: the range channel (float metres or integer with the info's multiplier).
        backend: ``"auto"``, ``"numba"`` or ``"numpy"``, as :func:`converters._kernels.select`
            chooses them (the C kernel where it applies, numba, numpy). All give the same
            slices (up to points within an ulp of a bin edge).

    Raises:
        ConfigError: a bad option (empty band set, inverted band, increment <= 0, ...).
    """

    def __init__(self, info: Any, slices: Mapping[str, SliceSpec | Mapping[str, Any]], *,
                 extrinsics: Any = None, frame_id: str | None = None,
                 angle_min: float | None = None, angle_max: float | None = None,
                 angle_increment: float | None = None, range_min: float | None = None,
                 range_max: float | None = None,
                 intensity_channel: str | None = IfPresent("intensity"),
                 use_inf: bool = True, inf_epsilon: float = 1.0, fill: float | None = None,
                 holes: bool = False, floor_height: float = 0.0, hole_depth: float = 0.05,
                 hole_range_max: float | None = None, hole_no_return: bool = True,
                 range_channel: str = "range", backend: str = "auto") -> None:
        if not isinstance(slices, Mapping):
            raise ConfigError("slices", slices, "a non-empty dict of name -> SliceSpec")
        specs = {name: _as_spec(name, spec) for name, spec in slices.items()}
        common = {"angle_min": angle_min, "angle_max": angle_max,
                  "angle_increment": angle_increment, "range_min": range_min,
                  "range_max": range_max, "use_inf": use_inf, "inf_epsilon": inf_epsilon,
                  "fill": fill, "holes": holes, "floor_height": floor_height,
                  "hole_depth": hole_depth, "hole_range_max": hole_range_max,
                  "hole_no_return": hole_no_return}
        #: a moving mount: TransformTrack or callable stamp_ns -> 4x4 (None: a fixed mount)
        self.moving: Any = extrinsics if callable(extrinsics) else None
        options.slice_options(specs, {
            **common, "extrinsics": _checkable(extrinsics), "frame_id": frame_id,
            "intensity_channel": intensity_channel, "range_channel": range_channel,
            "backend": backend})
        chosen = _kernels.select("slices", backend=backend)
        self._kernel = chosen.numba
        self._c_kernel = bool(chosen.c)
        self._common = common
        self._specs: dict[str, SliceSpec] = specs
        self.extrinsics = check_extrinsics(_checkable(extrinsics))
        self._frame_id = frame_id
        self.intensity_channel = intensity_channel
        self.range_channel = range_channel
        self._tables: dict[Any, _Tables] = {}
        self._moving_cache: tuple[Any, _Tables] | None = None
        self._time_cache: tuple[Any, tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]] | None
        self._rays_cache: tuple[Any, tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]] | None
        #: moving mount: build the full per-scan tables even with the compiled kernels (the
        #: path before :class:`_MovingRays`; tests compare both)
        self._reference_tables = False
        self._set_info(info)

    # ------------------------------------------------------------------------- configuration
    def _set_info(self, info: Any) -> None:
        self.info = info
        self.projector = make_projector(info)
        self._info_key = info_key(info)
        self._info_stamp = to_ns(info.header.stamp)
        self.frame_id = self._frame_id or info.header.frame_id
        self._tables.clear()
        self._moving_cache = None
        self._time_cache = None
        self._rays_cache = None
        self._inf_thr: np.ndarray[Any, Any] | None = None
        width = int(info.width)
        self.slices = [self._build_slice(name, spec, info, width)
                       for name, spec in self._specs.items()]
        self._holes = any(s.holes is not None for s in self.slices)
        self._size, self._offsets, self._grids, self._slice_grid = _grid.output_layout(
            [s.grid for s in self.slices])
        self._near = max(float(info.range_min), 0.0)
        self._sweep = self._sweep_sign(info)
        self._bands = Bands.create([(s.min_z, s.max_z, s.options, g)
                                    for s, g in zip(self.slices, self._slice_grid)],
                                   self._grids)

    def _build_slice(self, name: str, spec: SliceSpec, info: Any, width: int) -> _Slice:
        opts = {k: getattr(spec, k) if getattr(spec, k) is not None else self._common[k]
                for k in _OVERRIDES}
        inc = opts["angle_increment"]
        if inc is None:
            inc = 2.0 * math.pi / max(width, 1)
        amin = -math.pi if opts["angle_min"] is None else opts["angle_min"]
        amax = amin + 2.0 * math.pi if opts["angle_max"] is None else opts["angle_max"]
        grid = AngleGrid.create(amin, amax, inc)
        rmin = opts["range_min"]
        if rmin is None:
            rmin = max(float(info.range_min), 0.0)
        rmax = opts["range_max"]
        if rmax is None:
            rmax = float(info.range_max) if float(info.range_max) > 0 else math.inf
        options = OutputOptions.create(rmin, rmax, bool(opts["use_inf"]), opts["inf_epsilon"],
                                       opts["fill"])
        holes = None
        if opts["holes"]:
            edge_max = opts["hole_range_max"]
            holes = HoleOptions(float(opts["floor_height"]), float(opts["hole_depth"]),
                                options.range_max if edge_max is None else float(edge_max),
                                bool(opts["hole_no_return"]))
        return _Slice(name, float(spec.min_height), float(spec.max_height), grid, options, holes)

    @staticmethod
    def _sweep_sign(info: Any) -> float:
        alpha = as_array(info.horizontal_angles, np.float64).astype(np.float64)
        if alpha.size < 2:
            return 0.0
        step = (np.diff(alpha) + math.pi) % (2.0 * math.pi) - math.pi
        mean = float(np.mean(step))
        return 0.0 if mean == 0 else math.copysign(1.0, mean)

    def _scan_period_ns(self, info: Any, scan: Any) -> float:
        width = int(info.width)
        if int(info.column_time_increment) > 0:
            return float(width * int(info.column_time_increment))
        if scan is not None and width >= 2:
            times = as_array(scan.column_time_offsets, np.int64)
            if times.size == width:
                return float(times[-1] - times[0]) * width / (width - 1)
        return 0.0

    # ------------------------------------------------------------------------------ tables
    def _geometry_key(self, scan: Any) -> tuple[Any, ...]:
        """What the sensor-frame rays of a scan depend on: ("info", destaggered), or
        ("measured", destaggered, digest) for scans with measured azimuths."""
        measured = as_array(scan.column_azimuth_angles, np.float64)
        destaggered = bool(scan.is_destaggered) and bool(np.any(self.projector.shifts))
        azimuths = azimuth_channel(scan, self.range_channel)     # per-pixel azimuths
        if measured.size or azimuths is not None:
            digest = hashlib.blake2b(np.ascontiguousarray(measured).tobytes(), digest_size=16)
            if azimuths is not None:
                digest.update(np.ascontiguousarray(channel(scan, azimuths)).tobytes())
            return ("measured", destaggered, digest.digest())
        return ("info", destaggered)

    def _tie_keys(self, destaggered: bool) -> np.ndarray[Any, Any] | None:
        """Measurement-order tie key ``u*W + c`` per pixel of a destaggered scan (else None)."""
        if not destaggered:
            return None
        height, width = self.projector.height, self.projector.width
        src = self.projector.destagger_index
        return (np.arange(height)[:, None] * width + src).reshape(-1).astype(np.int64)

    def _tables_for(self, scan: Any) -> _Tables:
        key = self._geometry_key(scan)
        tables = self._tables.get(key)
        if tables is None:
            if key[0] == "measured":     # per-scan geometry: keep only the latest such table
                for k in [k for k in self._tables if k[0] == "measured"]:
                    del self._tables[k]
            d32, o32 = self.projector.tables_for(scan, self.range_channel)
            d, o = transform_rays(d32.reshape(-1, 3), o32.reshape(-1, 3), self.extrinsics)
            tables = _Tables(d, o, self._tie_keys(key[1]), self.slices, self._grids,
                             self._slice_grid, self._near, self.projector.width)
            self._tables[key] = tables
        return tables

    def _pose_times(self, scan: Any) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
        """The distinct pixel times of a scan relative to its stamp and each pixel's one.

        Returns:
            (times, index): (P,) int64 ns sorted, and (H*W,) int64 the time of each pixel
            (scan column order, row-major). Kept for the next scan when it has no ``t`` channel
            (then they depend only on the column times and the column order).
        """
        delays = pixel_delays(scan)
        key = None
        if delays is None:
            key = (self.projector.column_times(scan).tobytes(), bool(scan.is_destaggered))
            if self._time_cache is not None and self._time_cache[0] == key:
                return self._time_cache[1]
        unique, index = np.unique(self.projector.pixel_times(scan).reshape(-1),
                                  return_inverse=True)
        found = (unique, index.reshape(-1).astype(np.int64))
        self._time_cache = None if key is None else (key, found)
        return found

    def mount_poses(self, scan: Any) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
        """The moving mount's poses for a scan's pixels.

        Returns:
            (poses, index): (P, 4, 4) float64 target <- sensor at the P distinct pixel times,
            and (H*W,) int64 the pose of each pixel (scan column order, row-major).

        Raises:
            OutOfSpanError: a pixel time outside the track's span.
            TransformLookupError: raised by the callable.
            ValidationError: the callable returned something other than a finite rigid 4x4.
        """
        stamp = to_ns(scan.header.stamp, field="LidarScan.header.stamp")
        relative, index = self._pose_times(scan)
        unique = np.int64(stamp) + relative
        if isinstance(self.moving, TransformTrack):
            poses = self.moving.lookup_many(unique)
        else:
            poses = check_poses([self.moving(int(t)) for t in unique], "extrinsics(stamp_ns)")
        return poses, index

    def _moving_tables(self, scan: Any, r: np.ndarray[Any, Any]) -> _Tables | _MovingRays:
        """Tables of one scan seen by a moving mount: every pixel's ray moved by the mount's
        pose at its time (:meth:`mount_poses`). A mount that holds one pose over the whole
        scan gets fixed-mount tables at that pose (every kernel; kept for the next scan at the
        same pose); else, with the compiled kernels, :class:`_MovingRays` (the rays only, for
        the general kernel), without them the full :class:`_Tables` of the scan (numpy: the
        reference)."""
        poses, index = self.mount_poses(scan)
        geometry = self._geometry_key(scan)
        still = bool(np.all(poses == poses[0]))
        key = (geometry, poses[0].tobytes()) if still else None
        if key is not None and self._moving_cache is not None and self._moving_cache[0] == key:
            return self._moving_cache[1]
        d32, o32 = self._sensor_rays(scan, geometry)
        if key is None and self._kernel is not None and not self._reference_tables:
            return _MovingRays(self._kernel.transform_rays(d32, o32, poses, index),
                               self._tie_keys(geometry[1]), r, self)
        d, o = transform_rays(d32, o32, poses, index)
        tables = _Tables(d, o, self._tie_keys(geometry[1]), self.slices, self._grids,
                         self._slice_grid, self._near, self.projector.width)
        self._moving_cache = None if key is None else (key, tables)
        return tables

    def _no_thresholds(self, n: int) -> np.ndarray[Any, Any]:
        """(G, n) float32 +inf far-field thresholds (atan2 for every point; read only by the
        kernels, kept)."""
        if self._inf_thr is None or self._inf_thr.shape != (len(self._grids), n):
            self._inf_thr = np.full((len(self._grids), n), np.inf, np.float32)
        return self._inf_thr

    def _sensor_rays(self, scan: Any, geometry: tuple[Any, ...]
                     ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
        """(n, 3) float32 C-contiguous sensor-frame directions and origins of a scan (kept
        for the next scan of the same geometry)."""
        if self._rays_cache is not None and self._rays_cache[0] == geometry:
            return self._rays_cache[1]
        d32, o32 = self.projector.tables_for(scan, self.range_channel)
        rays = (np.ascontiguousarray(d32.reshape(-1, 3), np.float32),
                np.ascontiguousarray(o32.reshape(-1, 3), np.float32))
        self._rays_cache = (geometry, rays)
        return rays

    # ----------------------------------------------------------------------------- convert
    def convert(self, scan: Any, info: Any = None) -> dict[str, Any]:
        """All slices of one scan.

        Args:
            scan: a LidarScan (rclpy or dataclass) of this converter's LidarInfo.
            info: a new LidarInfo version to switch to (tables are rebuilt), or None.

        Returns:
            slice name -> ``sensor_msgs.msg.LaserScan`` (rclpy), in configuration order.

        Raises:
            LinkageError: ``scan.lidar_info_time`` does not name the converter's info.
            InfoMismatchError: grid size differs from the info.
            UnknownChannelError: the range or intensity channel is missing.
            TransformLookupError: a moving mount's pose is unknown at a pixel's time
                (:class:`converters.transforms.OutOfSpanError` outside a track's span).
        """
        if info is not None and info_key(info) != self._info_key:
            self._set_info(info)
        self._check(scan)
        r = np.ascontiguousarray(range_m(scan, self.info, self.range_channel)).reshape(-1)
        tables = self._tables_for(scan) if self.moving is None else self._moving_tables(scan, r)
        intensity = None
        wanted = resolve_channel(self.intensity_channel, channel_names(scan))
        if wanted is not None:
            values = channel(scan, wanted, native=True)
            intensity = (values[..., 0] if values.ndim == 3 else values).reshape(-1)
        decoded = self._row_convert(r, tables, intensity)
        if decoded is None:
            best = self._fuse(r, tables)
            if self._holes:
                self._add_holes(best, r, tables)
            decoded = self._decode_all(best, tables, intensity)
        stamp = to_ns(scan.header.stamp)
        period = self._scan_period_ns(self.info, scan)
        out: dict[str, Any] = {}
        for s, off in zip(self.slices, self._offsets):
            if decoded is not None:
                ranges = decoded[0][off:off + s.grid.size]
                ints = None if intensity is None else decoded[1][off:off + s.grid.size]
            else:
                ranges, winners = _grid.decode(best[off:off + s.grid.size], s.options)
                ints = None
                if intensity is not None:
                    ints = np.zeros(s.grid.size, np.float32)
                    hit = winners >= 0
                    ints[hit] = intensity[tables.position(winners[hit])]
            time_inc = self._sweep * period * 1e-9 * s.grid.increment / (2.0 * math.pi)
            out[s.name] = _grid.make_laserscan(
                stamp_ns=stamp, frame_id=self.frame_id, grid=s.grid, ranges=ranges,
                intensities=ints, options=s.options, scan_time=period * 1e-9,
                time_increment=time_inc)
        return out

    def _row_convert(self, r: np.ndarray[Any, Any], tables: _Tables,
                     intensity: np.ndarray[Any, Any] | None
                     ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]] | None:
        """Fusion and decoding in one compiled call (the row-ordered kernels)
        when the row-ordered kernel applies, else None."""
        t = tables.sorted
        if t is None or t.rows is None:
            return None
        if self._c_kernel and not tables.holes:
            plan = t.rows.c_plan(tables, self.slices)
            if plan is not None:
                ranges, ints, _ = plan.run(r, intensity)
                return ranges, ints
        if self._kernel is None:
            return None
        return self._kernel.convert_rows(  # type: ignore[no-any-return]
            np.ascontiguousarray(r, np.float32), t, t.rows, self._bands,
            *self._decode_inputs(tables, intensity), tables.hole_plan)

    @staticmethod
    def _decode_inputs(tables: _Tables, intensity: np.ndarray[Any, Any] | None
                       ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
        """(intensity image, key -> pixel map) as the compiled decoding takes them."""
        inten = _NO_VALUES if intensity is None else np.ascontiguousarray(intensity)
        key_to_pos = _NO_KEYS if tables.key_to_pos is None else tables.key_to_pos
        return inten, key_to_pos

    def _decode_all(self, best: np.ndarray[Any, Any], tables: _Tables,
                    intensity: np.ndarray[Any, Any] | None
                    ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]] | None:
        """Ranges and intensities (float32, slices back to back) of all slices in one compiled
        call; None without the compiled kernels."""
        if self._kernel is None:
            return None
        ranges = np.empty(self._size, np.float32)
        ints = np.empty(self._size if intensity is not None else 0, np.float32)
        b = self._bands
        self._kernel.decode_slices(best, b.offset, b.size, b.inf_value, b.fill_value,
                                   *self._decode_inputs(tables, intensity), ranges, ints)
        return ranges, ints

    def _check(self, scan: Any) -> None:
        if (int(scan.height), int(scan.width)) != (self.projector.height, self.projector.width):
            raise InfoMismatchError("LidarScan.height x width",
                                    f"{int(scan.height)}x{int(scan.width)}",
                                    f"{self.projector.height}x{self.projector.width} "
                                    "from the LidarInfo")
        stamp = to_ns(scan.lidar_info_time, field="LidarScan.lidar_info_time")
        if stamp != self._info_stamp:
            raise LinkageError("LidarScan.lidar_info_time", stamp,
                               f"{self._info_stamp} (the converter's LidarInfo; pass the new "
                               "info to convert(scan, info))")

    def _add_holes(self, best: np.ndarray[Any, Any], r: np.ndarray[Any, Any],
                   tables: _Tables) -> None:
        """Fuse the hole edges of this scan into the reduction array ``best`` (in place; the
        same numpy code after every backend's band fusion)."""
        for i, edges in tables.holes:
            hit = _holes.hole_hits(r[edges.index], edges)
            pixels = edges.index[hit]
            _grid.merge_min(best, edges.bins[hit] + self._offsets[i], edges.codes[hit],
                            tables.key(pixels))

    def _fuse(self, r: np.ndarray[Any, Any], tables: _Tables) -> np.ndarray[Any, Any]:
        """One reduction array (all slices back to back) from the flat range image."""
        best = np.full(self._size, _grid.EMPTY, np.int64)
        kernel = self._kernel
        if kernel is not None:
            r32 = np.ascontiguousarray(r, np.float32)
            if tables.sorted is not None:
                kernel.fuse_sorted(r32, tables.sorted, self._bands, best)
            else:
                kernel.fuse(r32, tables.kernel_rays, self._bands, best)
            return best
        with np.errstate(invalid="ignore", over="ignore"):
            good = (r > 0) & (r < np.inf)
            r64 = r.astype(np.float64)
            z = r64 * tables.dz + tables.oz              # float64: f4 tables are upcast
        d64 = tables.rays[:, :3].astype(np.float64)
        o64 = tables.rays[:, 3:].astype(np.float64)
        special = np.flatnonzero(~good)
        r_special = r64[special]
        all_bins, all_codes, all_keys = [], [], []
        for i, (s, off, g) in enumerate(zip(self.slices, self._offsets, self._slice_grid)):
            idx = np.flatnonzero((z >= s.min_z) & (z <= s.max_z) & good)
            if idx.size:
                sel, bins, codes = _grid.point_codes(
                    r64[idx], d64[idx], o64[idx], s.min_z, s.max_z, s.options.range_min,
                    s.options.range_max, s.grid, tables.bin_far[g][idx], tables.r_thr[g][idx])
                all_bins.append(bins + off)
                all_codes.append(codes)
                all_keys.append(tables.key(idx[sel]))
            if special.size:
                codes = _grid.special_codes(r_special, tables.q_far[i][special],
                                            tables.q_near[i][special])
                qualified = special[codes >= 0]
                all_bins.append(tables.bin_far[g][qualified] + off)
                all_codes.append(codes[codes >= 0])
                all_keys.append(tables.key(qualified))
        if all_bins:
            best = _grid.reduce_min(self._size, np.concatenate(all_bins),
                                    np.concatenate(all_codes), np.concatenate(all_keys))
        return best


def _checkable(extrinsics: Any) -> Any:
    """What the fixed-mount checks see: identity for a moving mount (a track or callable is
    checked per pose), else the extrinsics themselves."""
    return np.eye(4) if callable(extrinsics) else extrinsics


def _as_spec(name: str, spec: SliceSpec | Mapping[str, Any]) -> SliceSpec:
    if isinstance(spec, SliceSpec):
        out = spec
    elif isinstance(spec, Mapping):
        known = {f.name for f in dataclasses.fields(SliceSpec)}
        unknown = set(spec) - known
        if unknown:
            raise ConfigError(f"slices[{name!r}]", sorted(unknown), f"keys among {sorted(known)}")
        if "min_height" not in spec or "max_height" not in spec:
            raise ConfigError(f"slices[{name!r}]", dict(spec),
                              "min_height and max_height (metres, target frame)")
        out = SliceSpec(**spec)
    else:
        raise ConfigError(f"slices[{name!r}]", spec, "a SliceSpec or a dict of its fields")
    return out


_CONVERTERS: OrderedDict[Any, SliceConverter] = OrderedDict()


def to_laserscan(scan: Any, info: Any, *, min_height: float, max_height: float,
                 extrinsics: Any = None, frame_id: str | None = None,
                 angle_min: float | None = None, angle_max: float | None = None,
                 angle_increment: float | None = None, range_min: float | None = None,
                 range_max: float | None = None,
                 intensity_channel: str | None = IfPresent("intensity"),
                 use_inf: bool = True, inf_epsilon: float = 1.0, fill: float | None = None,
                 holes: bool = False, floor_height: float = 0.0, hole_depth: float = 0.05,
                 hole_range_max: float | None = None, hole_no_return: bool = True,
                 range_channel: str = "range", backend: str = "auto") -> Any:
    """One height slice of a LidarScan as a ``sensor_msgs.msg.LaserScan``.

    Arguments are those of :class:`SliceConverter` with a single :class:`SliceSpec`
    ``(min_height, max_height)``. The converter (and its per-pixel tables) is cached per
    LidarInfo version and options, so calling this per scan is cheap; for several slices of the
    same scan use :class:`SliceConverter` (one pass).

    Returns:
        rclpy ``sensor_msgs.msg.LaserScan`` stamped with the scan's stamp, ``ranges`` and
        ``intensities`` as ``array.array('f')``.
    """
    kwargs = {"extrinsics": extrinsics, "frame_id": frame_id, "angle_min": angle_min,
              "angle_max": angle_max, "angle_increment": angle_increment,
              "range_min": range_min, "range_max": range_max,
              "intensity_channel": intensity_channel, "use_inf": use_inf,
              "inf_epsilon": inf_epsilon, "fill": fill, "holes": holes,
              "floor_height": floor_height, "hole_depth": hole_depth,
              "hole_range_max": hole_range_max, "hole_no_return": hole_no_return,
              "range_channel": range_channel, "backend": backend}
    spec = SliceSpec(min_height, max_height)
    options.slice_options({"slice": spec}, {**kwargs, "extrinsics": _checkable(extrinsics)})
    # a moving mount is cached by identity (the cached converter keeps it alive)
    ext = None if extrinsics is None else ("moving", id(extrinsics)) if callable(extrinsics) \
        else check_extrinsics(extrinsics).tobytes()
    # the type tells IfPresent("intensity") (the default) from a required "intensity"
    key = (info_key(info), float(min_height), float(max_height), ext,
           tuple((k, type(v), v) for k, v in kwargs.items() if k != "extrinsics"))
    converter = _CONVERTERS.get(key)
    if converter is None:
        converter = SliceConverter(info, {"slice": spec}, **kwargs)
        _CONVERTERS[key] = converter
        while len(_CONVERTERS) > 8:
            _CONVERTERS.popitem(last=False)
    else:
        _CONVERTERS.move_to_end(key)
    return converter.convert(scan)["slice"]
