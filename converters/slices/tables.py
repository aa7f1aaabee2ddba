"""The per-pixel tables behind :class:`converters.slices.converter.SliceConverter` (its conventions
are stated there).

:class:`_Tables` (static, per LidarInfo version and fixed extrinsics) with its bin-ordered
permutation :class:`_Sorted` and row layout :class:`_RowLayout` for the compiled kernels, and
:class:`_MovingRays` (one scan's rays seen by a moving mount). Private to the slicer.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from converters.slices import spec as _grid

from converters.slices import holes as _holes
from converters.slices.spec import AngleGrid, OutputOptions
from converters.slices.holes import HoleOptions
from converters._kernels import slices as _cslices
from converters._kernels.slices_numba import Rays


@dataclass(frozen=True)
class MovingPlan:
    """What :class:`_MovingRays` needs of its slicer (fixed per converter): the angle grids,
    the slices, the compiled kernels, the bands and near flags per slice, whether any slice
    has holes, and ``no_thresholds(n)``: (G, n) float32 +inf far-field thresholds."""

    grids: Any
    slices: Any
    kernel: Any
    bands: Any
    near: Any
    holes: bool
    no_thresholds: Any


@dataclass(frozen=True)
class _Slice:
    name: str
    min_z: float
    max_z: float
    grid: AngleGrid
    options: OutputOptions
    holes: HoleOptions | None = None


class _PixelKeys:
    """Tie keys of a scan's pixels (measurement order ``u*W + c``; None = the pixel index) and
    the tables both :class:`_Tables` and :class:`_MovingRays` derive from them."""

    def __init__(self, keys: np.ndarray[Any, Any] | None, n: int) -> None:
        self.n = n
        self.keys = keys                     # measurement-order tie key per pixel, None = index
        self.key_to_pos: np.ndarray[Any, Any] | None = None
        if keys is not None:
            self.key_to_pos = np.empty(n, np.int64)
            self.key_to_pos[keys] = np.arange(n)

    def key(self, index: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        """Tie keys of pixel indices."""
        return index.astype(np.int64) if self.keys is None else self.keys[index]

    def position(self, key: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        """Pixel indices of tie keys."""
        return key if self.key_to_pos is None else self.key_to_pos[key]

    def kernel_keys(self) -> np.ndarray[Any, Any]:
        """The keys as :class:`converters._kernels.slices_numba.Rays` holds them (int32; empty:
        key = pixel index)."""
        return np.zeros(0, np.int32) if self.keys is None else self.keys.astype(np.int32)


def _hole_edges(d64: np.ndarray[Any, Any], o64: np.ndarray[Any, Any], slices: list[_Slice]
                ) -> list[tuple[int, Any]]:
    """(slice index, :class:`converters.slices.holes.HoleEdges`) of the slices with holes, for rays
    ``p = r*D + O`` ((n, 3) float64 each, target frame)."""
    return [(i, _holes.hole_edges(d64, o64, s.holes, s.grid, s.options.range_min,
                                  s.options.range_max))
            for i, s in enumerate(slices) if s.holes is not None]


class _Tables(_PixelKeys):
    """Static per-pixel tables of one column order (per LidarInfo version and extrinsics).

    Rays ``p = r*D + O`` in the target frame (float32 components, arithmetic in float64); per
    distinct grid the far-field bin and ``r_thr``; per slice the +Inf/NaN/-Inf qualifiers and,
    for slices with holes, their :class:`converters.slices.holes.HoleEdges`.
    """

    def __init__(self, d: np.ndarray[Any, Any], o: np.ndarray[Any, Any],
                 keys: np.ndarray[Any, Any] | None, slices: list[_Slice],
                 grids: list[AngleGrid], slice_grid: list[int], near: float,
                 width: int) -> None:
        super().__init__(keys, d.shape[0])
        self.rays = np.ascontiguousarray(np.concatenate([d, o], axis=1))     # (n, 6) f4
        self.dx, self.dy, self.dz = (np.ascontiguousarray(d[:, k]) for k in range(3))
        self.ox, self.oy, self.oz = (np.ascontiguousarray(o[:, k]) for k in range(3))
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
        self.holes = _hole_edges(d64, o64, slices)
        self.hole_plan = _holes.HolePlan.create(self.holes, self.key)
        self.k_r_thr = np.ascontiguousarray(np.stack([_grid.round_up_f32(t) for t in self.r_thr]))
        #: the tables as the general compiled kernels take them
        self.kernel_rays = Rays(
            self.dx, self.dy, self.dz, self.ox, self.oy, self.oz, keys=self.kernel_keys(),
            qual=np.ascontiguousarray(np.stack(
                [qf.astype(np.uint8) | (qn.astype(np.uint8) << 1)
                 for qf, qn in zip(self.q_far, self.q_near)])),
            bin_far=np.ascontiguousarray(np.stack(self.bin_far).astype(np.int32)),
            r_thr=self.k_r_thr)
        self.sorted: _Sorted | None = None
        if len(grids) == 1 and len(slices) <= 60 and len(
                {(s.options.range_min, s.options.range_max) for s in slices}) == 1:
            self.sorted = _Sorted(self, grids[0].size, slices, width)

    def near_fraction(self, r: np.ndarray[Any, Any], index: int = 0) -> float:
        """Fraction of finite pixels that need atan2 on grid ``index`` (diagnostics)."""
        ok = np.isfinite(r) & (r > 0)
        return float(np.mean(r[ok] < self.r_thr[index][ok])) if ok.any() else 0.0


class _MovingRays(_PixelKeys):
    """One scan's rays seen by a moving mount, as the general compiled kernel takes them
    (:meth:`converters._kernels.slices_numba.Compiled.fuse`), built per scan from the cached
    sensor-frame rays and the per-pixel poses
    (:meth:`converters.slices.converter.SliceConverter._moving_tables`).

    Unlike :class:`_Tables` nothing is precomputed for reuse: the far-field thresholds are
    +inf (every in-band point takes atan2, which gives the bin the far-field tables would:
    they are exact), and the far-field bins and +Inf/NaN/-Inf qualifiers are computed only
    for this scan's pixels without a finite positive range (the only ones that read them,
    :func:`converters._kernels.slices_numba._pass_others`), compiled
    (:func:`converters._kernels.slices_numba._special_tables`: the float64 operations of
    :func:`converters.slices.spec.far_field` and :func:`converters.slices.spec.qualify`; libm's atan2 may
    differ from numpy's in the last bit, which moves a far-field bin only for a ray within an
    ulp of a bin edge). Hole edges (slices with holes) are computed per scan by numpy.
    Same slices, bit for bit, as the full tables on the tests' scenes
    (tests/test_moving_slices.py).
    """

    sorted = None                      # no bin-ordered / row-ordered layout

    def __init__(self, rays: tuple[np.ndarray[Any, Any], ...], keys: np.ndarray[Any, Any] | None,
                 r: np.ndarray[Any, Any], conv: MovingPlan) -> None:
        dx, dy, dz, ox, oy, oz = rays
        super().__init__(keys, dx.shape[0])
        n = self.n
        with np.errstate(invalid="ignore"):
            special = np.flatnonzero(~((r > 0) & (r < np.inf)))
        n_grids, n_slices = len(conv.grids), len(conv.slices)
        bin_far = np.full((n_grids, n), -1, np.int32)
        qual = np.zeros((n_slices, n), np.uint8)
        if special.size:
            conv.kernel.special_tables(special, rays, conv.bands, conv.near, bin_far, qual)
        #: (slice index, edges) of the slices with holes (as :attr:`_Tables.holes`)
        self.holes: list[tuple[int, Any]] = []
        if conv.holes:
            d64 = np.array([dx, dy, dz], np.float64).T
            o64 = np.array([ox, oy, oz], np.float64).T
            self.holes = _hole_edges(d64, o64, conv.slices)
        self.kernel_rays = Rays(dx, dy, dz, ox, oy, oz, keys=self.kernel_keys(), qual=qual,
                                bin_far=bin_far, r_thr=conv.no_thresholds(n))


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
