"""numba kernels of the slices and the merger, and their loader.

Each kernel does, in compiled loops, exactly what the numpy reference of
:mod:`converters.slices.spec` does (:func:`~converters.slices.spec.point_codes`,
:func:`~converters.slices.spec.special_codes`, :func:`~converters.slices.spec.reduce_min`,
:func:`~converters.slices.spec.decode`) for several slices at once; results equal it except for
points within one ulp of a bin edge (numpy's SIMD atan2 and libm's may differ in the last bit).
Selected by :func:`converters._kernels.select` (``LIDARSCAN_NUMBA=0`` disables them).

Kernels (drivers in :class:`Compiled`):

* general: pass 1 (band bits per ray), then points and specials (:func:`_pass_bands`,
  :func:`_pass_points`, :func:`_pass_others`; one call below ``_SMALL`` rays); any grids, any
  mount, the merger's inputs;
* bin-ordered (:func:`_sorted_fuse`): one grid and shared range limits;
* row-ordered (:func:`_row_convert`): the bin-ordered layout of an upright sensor, with exact
  per-row float32 band intervals, fusion, hole edges and decoding in one call (these two live
  in :mod:`converters._kernels.slices_numba_ordered`, imported here);
* moving mounts: :func:`_transform_rays` (each ray moved by its pixel's pose, the arithmetic of
  :func:`converters.shared.frames.transform_rays`) or, with a pose per pixel, :func:`_track_rays`
  (each ray's pose interpolated from a track's samples where it is used),
  :func:`_special_tables` (far-field bins and qualifiers of the pixels without a finite range:
  :func:`converters.slices.spec.far_field`'s bin and :func:`converters.slices.spec.qualify`), then the
  general kernel.

The kernels call each other through module globals (``_J_*``, of this module and of
:mod:`~converters._kernels.slices_numba_ordered`), compiled by :func:`kernels` before the
kernels that use them (numba resolves a global dispatcher at compile time).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from converters.slices.spec import CODE_NAN, CODE_NEG_INF, CODE_POS_INF, EMPTY
from converters.slices.holes import HolePlan
from converters._kernels import slices_numba_ordered as _ordered
from converters._kernels.slices_numba_ordered import (
    _angle_bin,
    _near_point,
    _row_convert,
    _row_fuse,
    _sorted_fuse,
    _value,
)

__all__ = ["Bands", "Compiled", "Rays", "SORTED_CHUNK", "kernels"]

# ------------------------------------------------------------------------ compiled kernels
#
# Optional numba kernels doing, in one pass over the rays, exactly what point_codes,
# special_codes and reduce_min do for several slices at once. They are used when numba is
# importable (set LIDARSCAN_NUMBA=0 to disable). Results equal the numpy path except for points
# within one ulp of a bin edge (numpy's SIMD atan2 and libm's may differ in the last bit).
# Pass 1 (band bits per ray) is written as loops the compiler vectorises; numpy's flatnonzero
# compacts; passes 2 and 3 visit only the rays that can contribute.

_KERNELS: Any = None
_KERNELS_TRIED = False


def kernels() -> Compiled | None:
    """The compiled kernels (compiled at the first call, cached on disk by numba), or None
    without numba or when switched off (:func:`converters._kernels.numba_enabled`)."""
    global _KERNELS, _KERNELS_TRIED
    if _KERNELS_TRIED:
        return _KERNELS
    _KERNELS_TRIED = True
    from lidarscan._backends import numba_enabled
    if not numba_enabled():
        return None
    try:
        import numba
    except ImportError:
        return None
    global _J_BANDS, _J_POINTS, _J_OTHERS, _J_DECODE_SLICES, _J_CODE_VALUE, _J_RHO, _J_BIN
    jit = numba.njit(cache=True, nogil=True, error_model="numpy")
    inline = numba.njit(nogil=True, error_model="numpy", inline="always")
    # called by the kernels below, so compiled first; inlined into them (a call per point
    # measured ~15 % slower where most points are near, e.g. an offset mount)
    _J_BIN = _ordered._J_BIN = inline(_angle_bin)   # the binning step, inlined everywhere
    _ordered._J_NEAR = inline(_near_point)
    _ordered._J_VALUE = inline(_value)
    _J_CODE_VALUE = inline(_code_value)
    _J_RHO = inline(_rho_at)
    _J_BANDS, _J_POINTS, _J_OTHERS = jit(_pass_bands), jit(_pass_points), jit(_pass_others)
    _J_DECODE_SLICES = _ordered._J_DECODE_SLICES = jit(_decode_slices)
    _ordered._J_ROW = jit(_row_fuse)
    _KERNELS = Compiled(jit)
    return _KERNELS


_J_BANDS: Any = None     # the compiled passes, referenced by _fuse_small
_J_DECODE_SLICES: Any = None
_J_CODE_VALUE: Any = None
_J_POINTS: Any = None
_J_OTHERS: Any = None
_J_RHO: Any = None
_J_BIN: Any = None


def _fuse_small(r: Any, keep: Any, limits: Any, dx: Any, dy: Any, dz: Any, ox: Any, oy: Any,
                oz: Any, keys: Any, key_base: Any, zmin: Any, zmax: Any, rmin: Any, rmax: Any,
                slice_grid: Any, offset: Any, qual: Any, g_min: Any, g_inc: Any, g_size: Any,
                g_full: Any, bin_far: Any, r_thr: Any, best: Any) -> None:  # pragma: no cover
    """The three passes in one compiled call (small inputs: less call overhead)."""
    n = r.shape[0]
    masks = np.zeros(n, np.uint64)
    good = np.empty(n, np.bool_)
    _J_BANDS(r, keep, limits, dz, oz, zmin, zmax, masks, good)
    hits = np.empty(n, np.int64)
    rest = np.empty(n, np.int64)
    n_hits = 0
    n_rest = 0
    for i in range(n):
        hits[n_hits] = i
        n_hits += masks[i] != 0
        rest[n_rest] = i
        n_rest += not good[i]
    _J_POINTS(hits[:n_hits], masks, r, dx, dy, ox, oy, keys, key_base, rmin, rmax, slice_grid,
              offset, g_min, g_inc, g_size, g_full, bin_far, r_thr, best)
    _J_OTHERS(rest[:n_rest], r, keep, limits, keys, key_base, slice_grid, offset, qual,
              bin_far, best)


_NO_KEEP = np.zeros(0, np.uint8)
_NO_HOLES = HolePlan.create([], None)
_NO_LIMITS = np.array([0.0, np.inf, 0.0])

#: Below this many rays the three passes run in one compiled call (less call overhead).
_SMALL = 32768
#: Positions per chunk of whole bins in :func:`_sorted_fuse` (at least one whole bin).
SORTED_CHUNK = 512


@dataclass(frozen=True)
class Bands:
    """Constants of S slices on G grids, as the kernels take them.

    Attributes:
        zmin, zmax: (S,) float64 inclusive height band, metres (output frame).
        rmin, rmax: (S,) float64 inclusive planar range limits, metres.
        grid: (S,) int64 index of each slice's grid; offset: (S,) int64 first element of each
            slice in the reduction array.
        g_min, g_inc: (G,) float64 grid start and increment (radians); g_size: (G,) int64;
            g_full: (G,) bool full circle.
        size: (S,) int64 bins of each slice; inf_value, fill_value: (S,) float32 decoded values.
        zmin4, zmax4: zmin, zmax padded with empty bands to a multiple of four slices.
    """

    zmin: np.ndarray[Any, Any]
    zmax: np.ndarray[Any, Any]
    rmin: np.ndarray[Any, Any]
    rmax: np.ndarray[Any, Any]
    grid: np.ndarray[Any, Any]
    offset: np.ndarray[Any, Any]
    g_min: np.ndarray[Any, Any]
    g_inc: np.ndarray[Any, Any]
    g_size: np.ndarray[Any, Any]
    g_full: np.ndarray[Any, Any]
    size: np.ndarray[Any, Any]
    inf_value: np.ndarray[Any, Any]
    fill_value: np.ndarray[Any, Any]
    zmin4: np.ndarray[Any, Any]
    zmax4: np.ndarray[Any, Any]

    @classmethod
    def create(cls, slices: list[tuple[float, float, Any, int]], grids: list[Any]) -> Bands:
        """From (min_z, max_z, OutputOptions, grid index) per slice and the distinct
        :class:`converters.slices.spec.AngleGrid` objects."""
        sizes = np.array([grids[g].size for _, _, _, g in slices], np.int64)
        pad = -len(slices) % 4
        zmin = np.array([lo for lo, _, _, _ in slices], np.float64)
        zmax = np.array([hi for _, hi, _, _ in slices], np.float64)
        return cls(
            zmin=zmin, zmax=zmax,
            rmin=np.array([o.range_min for _, _, o, _ in slices], np.float64),
            rmax=np.array([o.range_max for _, _, o, _ in slices], np.float64),
            grid=np.array([g for _, _, _, g in slices], np.int64),
            offset=(np.cumsum(sizes) - sizes).astype(np.int64),
            g_min=np.array([g.angle_min for g in grids], np.float64),
            g_inc=np.array([g.increment for g in grids], np.float64),
            g_size=np.array([g.size for g in grids], np.int64),
            g_full=np.array([g.full_circle for g in grids], np.bool_), size=sizes,
            inf_value=np.array([o.inf_value for _, _, o, _ in slices], np.float32),
            fill_value=np.array([o.fill_value for _, _, o, _ in slices], np.float32),
            zmin4=np.r_[zmin, np.full(pad, np.inf)], zmax4=np.r_[zmax, np.full(pad, -np.inf)])

    def grid0(self) -> tuple[float, float, int, bool]:
        """(g_min, g_inc, g_size, g_full) of the first (single) grid."""
        return (float(self.g_min[0]), float(self.g_inc[0]), int(self.g_size[0]),
                bool(self.g_full[0]))


@dataclass(frozen=True)
class Rays:
    """Per-ray tables of the general kernels (n rays, S slices, G grids).

    Attributes:
        dx, dy, dz, ox, oy, oz: (n,) ray ``p = r*D + O`` in the output frame.
        keys: (n,) int32 tie keys, or empty (key = ray index + ``key_base``).
        qual: (S, n) uint8 bit 0: +Inf/NaN qualify, bit 1: -Inf qualifies.
        bin_far: (G, n) int32 far-field bins (-1: none); r_thr: (G, n) float32 thresholds.
    """

    dx: np.ndarray[Any, Any]
    dy: np.ndarray[Any, Any]
    dz: np.ndarray[Any, Any]
    ox: np.ndarray[Any, Any]
    oy: np.ndarray[Any, Any]
    oz: np.ndarray[Any, Any]
    keys: np.ndarray[Any, Any]
    qual: np.ndarray[Any, Any]
    bin_far: np.ndarray[Any, Any]
    r_thr: np.ndarray[Any, Any]


def frozen_f32(a: Any) -> Any:
    """``a`` as a read-only, C-contiguous float32 array (a view when it already is float32 and
    contiguous, else a cast copy).

    numba compiles one machine-code specialisation per argument type, and an array's type
    includes its dtype and whether it is writeable; a scan's ranges and intensities arrive
    read-only (views of a message) or writeable (decoded integer ranges, byte-swapped
    channels), of any of the eight channel dtypes. Every per-scan array goes through here on
    its way into a kernel, so each kernel has exactly one specialisation, compiled (or loaded
    from the cache) by :mod:`converters.warmup` before the first scan. An intensity
    image cast to float32 gives the values the kernels produced from it anyway; the cast's
    cost is in bench/README.md (start-up).
    """
    out = np.ascontiguousarray(a, np.float32)
    if out.flags.writeable:
        out = out.view()
        out.flags.writeable = False
    return out


class Compiled:
    """The compiled kernels behind calls that take named structures (:class:`Bands`,
    :class:`Rays`, the converters' bin-ordered plans). Per-scan arrays enter the kernels
    through :func:`frozen_f32` (one specialisation per kernel)."""

    def __init__(self, jit: Any) -> None:
        self._bands, self._points, self._others = _J_BANDS, _J_POINTS, _J_OTHERS
        self._small = jit(_fuse_small)
        self._sorted = jit(_sorted_fuse)
        self._row_convert = jit(_row_convert)
        self.decode = jit(_decode_kernel)
        self._decode_slices = _J_DECODE_SLICES
        self._transform = jit(_transform_rays)
        self._track = jit(_track_rays)
        self._special = jit(_special_tables)

    def dispatchers(self) -> dict[str, Any]:
        """Every numba dispatcher behind this object, by name (for the warm-up and its
        tests: ``len(d.signatures)`` is how many specialisations each has compiled)."""
        return {"bands": self._bands, "points": self._points, "others": self._others,
                "small": self._small, "sorted": self._sorted, "row_convert": self._row_convert,
                "row_fuse": _ordered._J_ROW, "decode": self.decode,
                "decode_slices": self._decode_slices,
                "transform_rays": self._transform, "track_rays": self._track,
                "special_tables": self._special}

    def special_tables(self, special: Any, rays: Any, bands: Bands, near: float, bin_far: Any,
                       qual: Any) -> None:
        """Far-field bins (``bin_far[g, i]``, left as they are elsewhere) and qualifiers
        (``qual[s, i]`` bit 0 +Inf/NaN, bit 1 -Inf) of the rays ``special`` ((m,) int64) of
        ``rays`` ((dx, dy, dz, ox, oy, oz) float32 (n,) each), as :class:`Rays` holds them."""
        b = bands
        self._special(np.ascontiguousarray(special, np.int64), *rays, b.zmin, b.zmax, b.rmin,
                      b.rmax, b.grid, b.g_min, b.g_inc, b.g_size, b.g_full, float(near),
                      bin_far, qual)

    def transform_rays(self, d: Any, o: Any, poses: Any, index: Any) -> tuple[Any, ...]:
        """:func:`converters.shared.frames.transform_rays` with one pose per ray, compiled (same bits).

        Args:
            d, o: (n, 3) float32 C-contiguous sensor-frame directions and origins.
            poses: (P, 4, 4) float64 poses; index: (n,) int64 the pose of each ray.

        Returns:
            (dx, dy, dz, ox, oy, oz): (n,) float32 each, in the target frame.
        """
        rows = np.ascontiguousarray(np.asarray(poses, np.float64)[:, :3, :].reshape(-1, 12))
        n = d.shape[0]
        out = np.empty((6, n), np.float32)
        self._transform(frozen_f32(d), frozen_f32(o), rows, np.ascontiguousarray(index, np.int64),
                        out)
        return tuple(out)

    def track_rays(self, d: Any, o: Any, relative: Any, stamp: int, times: Any, poses: Any,
                   deltas: Any) -> tuple[Any, ...]:
        """The rays moved by a pose track's pose at each ray's own time (:func:`_track_rays`).

        Args:
            d, o: (3, n) float32 C-contiguous sensor-frame directions and origins (one row
                per component).
            relative: (n,) int64 ns each ray's time after ``stamp`` (int ns).
            times, poses: (K,) int64 ascending and (K, 4, 4) float64 the track's samples around
                every ray time (:meth:`converters.shared.transforms.TransformTrack.samples`).
            deltas: (K - 1, 3) float64 rotation vector of each pair of consecutive samples
                (:func:`converters.shared.transforms.segment_rotvecs`).

        Returns:
            (dx, dy, dz, ox, oy, oz): (n,) float32 each, in the target frame.
        """
        rows = np.ascontiguousarray(np.asarray(poses, np.float64)[:, :3, :].reshape(-1, 12))
        out = np.empty((6, d.shape[1]), np.float32)
        self._track(frozen_f32(d), frozen_f32(o), np.ascontiguousarray(relative, np.int64),
                    np.int64(stamp), np.ascontiguousarray(times, np.int64), rows,
                    np.ascontiguousarray(np.asarray(deltas, np.float64).reshape(-1, 3)), out)
        return tuple(out)

    def decode_slices(self, best: Any, offset: Any, size: Any, inf_value: Any, fill_value: Any,
                      intensity: Any, key_to_pos: Any, ranges: Any, ints: Any) -> None:
        """:func:`_decode_slices` (``intensity`` through :func:`frozen_f32`)."""
        self._decode_slices(best, offset, size, inf_value, fill_value, frozen_f32(intensity),
                            key_to_pos, ranges, ints)

    def fuse(self, r: Any, rays: Rays, bands: Bands, best: Any, *, keep: Any = _NO_KEEP,
             limits: Any = _NO_LIMITS, key_base: int = 0) -> None:
        """Fuse rays into ``best``: the general kernel (pass 1 band bits, then points and
        specials; one compiled call below ``_SMALL`` rays). ``keep``: (n,) uint8 rays to use
        (empty: all); ``limits``: (scan range_min, scan range_max, input range_min)."""
        t, b = rays, bands
        r = frozen_f32(r)
        args = (t.dx, t.dy, t.dz, t.ox, t.oy, t.oz, t.keys, key_base, b.zmin, b.zmax, b.rmin,
                b.rmax, b.grid, b.offset, t.qual, b.g_min, b.g_inc, b.g_size, b.g_full,
                t.bin_far, t.r_thr, best)
        n = r.shape[0]
        if n < _SMALL:
            self._small(r, keep, limits, *args)
            return
        masks = np.zeros(n, np.uint8 if b.zmin.shape[0] <= 8 else np.uint64)
        good = np.empty(n, np.bool_)
        self._bands(r, keep, limits, t.dz, t.oz, b.zmin, b.zmax, masks, good)
        hits = np.flatnonzero(masks)
        if hits.size:
            self._points(hits, masks, r, t.dx, t.dy, t.ox, t.oy, t.keys, key_base, b.rmin,
                         b.rmax, b.grid, b.offset, b.g_min, b.g_inc, b.g_size, b.g_full,
                         t.bin_far, t.r_thr, best)
        others = np.flatnonzero(~good)
        if others.size:
            self._others(others, r, keep, limits, t.keys, key_base, b.grid, b.offset, t.qual,
                         t.bin_far, best)

    def fuse_sorted(self, r: Any, plan: Any, bands: Bands, best: Any) -> None:
        """The bin-ordered kernel (:func:`_sorted_fuse`; one grid, shared range limits).

        ``plan``: the converter's bin-ordered tables (``src``, ``keys``, ``cols`` = dz, oz,
        dx, dy, ox, oy, r_thr in bin order, ``qf``, ``qn``, ``bin_start``, ``bin_thr``,
        ``max_width``)."""
        g_min, g_inc, g_size, g_full = bands.grid0()
        self._sorted(frozen_f32(r), plan.src, plan.keys, *plan.cols, plan.qf, plan.qn, bands.zmin4,
                     bands.zmax4, bands.zmin.shape[0], float(bands.rmin[0]),
                     float(bands.rmax[0]), plan.bin_start, plan.bin_thr,
                     max(plan.max_width, SORTED_CHUNK), bands.offset, g_min, g_inc, g_size,
                     g_full, best)

    def convert_rows(self, r: Any, plan: Any, rows: Any, bands: Bands, intensity: Any,
                     key_to_pos: Any, holes: HolePlan = _NO_HOLES) -> tuple[Any, Any]:
        """The row-ordered kernel (:func:`_row_convert`): fusion and decoding in one call.

        ``plan``: as :meth:`fuse_sorted`; ``rows``: its row layout (``src``, ``keys``, ``qf``,
        ``qn``, ``q_rows``, ``lo``, ``hi``: per-row float32 band intervals). ``intensity``:
        (n,) native image or empty; ``key_to_pos``: (n,) int64 or empty (key = pixel);
        ``holes``: the hole edges of the slices (default none).

        Returns:
            (ranges, ints): float32 of all slices back to back (ints empty without intensity).
        """
        cols, b = plan.cols, bands
        g_min, g_inc, g_size, g_full = b.grid0()
        r = frozen_f32(r)
        return self._row_convert(  # type: ignore[no-any-return]
            r, rows.src, rows.keys, cols[2], cols[3], cols[4], cols[5], cols[6], rows.qf,
            rows.qn, rows.q_rows, rows.lo, rows.hi, b.zmin.shape[0], float(b.rmin[0]),
            float(b.rmax[0]), rows.lo.shape[1], plan.bin_thr, b.offset, g_min, g_inc, g_size,
            g_full, int(b.size.sum()), b.size, b.inf_value, b.fill_value, frozen_f32(intensity),
            key_to_pos, intensity.shape[0] > 0, holes.start, holes.below, holes.no_return,
            holes.slice_start, holes.slice, holes.pixel, holes.bin, holes.value, holes.dz,
            holes.oz)


def _transform_rays(d: Any, o: Any, rows: Any, index: Any,
                    out: Any) -> None:  # pragma: no cover - compiled
    """``out[0:3]`` = directions, ``out[3:6]`` = origins (float32) of the rays moved by
    ``rows[index[i]]`` (the top 3x4 of each pose, row-major), in float64 left to right as
    :func:`converters.shared.frames.transform_rays` writes it (no fused multiply-add)."""
    for i in range(d.shape[0]):
        m = rows[index[i]]
        x = np.float64(d[i, 0])
        y = np.float64(d[i, 1])
        z = np.float64(d[i, 2])
        a = np.float64(o[i, 0])
        b = np.float64(o[i, 1])
        c = np.float64(o[i, 2])
        for k in range(3):
            out[k, i] = np.float32(m[4 * k] * x + m[4 * k + 1] * y + m[4 * k + 2] * z)
            out[3 + k, i] = np.float32(m[4 * k] * a + m[4 * k + 1] * b + m[4 * k + 2] * c
                                       + m[4 * k + 3])


#: (-1)^n / (2n+1)! and (-1)^n / (2n+2)!, n = 0..7: the series of sin(x)/x and (1-cos(x))/x^2
_SIN_C = tuple((-1) ** n / math.factorial(2 * n + 1) for n in range(8))
_COS_C = tuple((-1) ** n / math.factorial(2 * n + 2) for n in range(8))


def _track_rays(d: Any, o: Any, relative: Any, stamp: Any, times: Any, rows: Any, deltas: Any,
                out: Any) -> None:  # pragma: no cover - compiled
    """``out[0:3]`` = directions, ``out[3:6]`` = origins (float32) of the rays ``d``, ``o``
    ((3, n) float32 each, sensor frame) moved by the pose at ``stamp + relative[i]``,
    interpolated between the samples ``rows`` (top 3x4 of each pose, row-major) at ``times``:
    the pose of :meth:`converters.shared.transforms.TransformTrack.lookup_many` at that stamp (the
    sample at its own stamp or held after the newest one; else
    :func:`converters.shared.transforms.interpolate_poses`'s formula ``R0 exp(u log(R0^T R1))``,
    Rodrigues, ``t0 + u (t1 - t0)``), written per element in float64, then the arithmetic of
    :func:`_transform_rays`. The translation and ``u`` are the reference's bits; the rotation's
    ``sin(theta)/theta`` and ``(1-cos(theta))/theta^2`` come from their series when every
    rotation of the segment is at most 0.5 rad (libm's sin and cos above), and its products
    are written out, so the rotation may differ from numpy's in the last bits of float64
    (``|dR| <~ 1e-15``): a float32 ray component may round to the neighbouring float32
    (1 ulp), in the order of one case in 10^7.

    The rays are taken in runs of consecutive rays whose times lie in one segment between two
    samples (a scan's rows run forward in time): per run the segment's constants, then one
    branch-free loop over the run that the compiler vectorises; no per-ray matrices in memory.
    """
    n = relative.shape[0]
    n_samples = times.shape[0]
    chunk = 1024                      # the longest run (scratch that stays in cache)
    us = np.empty(chunk)              # u, sin(theta)/theta, (1-cos(theta))/theta^2 per ray
    sa = np.empty(chunk)
    sb = np.empty(chunk)
    k = 0
    i = 0
    while i < n:
        t = stamp + relative[i]
        while k + 1 < n_samples and times[k + 1] <= t:
            k += 1
        while k > 0 and times[k] > t:
            k -= 1
        lo = times[k]
        # the run: rays from i on inside [lo, hi) (held after the newest sample: [lo, inf))
        hi = times[k + 1] if k + 1 < n_samples else np.iinfo(np.int64).max
        j = i + 1
        while j < n and j - i < chunk and lo <= stamp + relative[j] < hi:
            j += 1
        m00, m01, m02, m03 = rows[k, 0], rows[k, 1], rows[k, 2], rows[k, 3]
        m10, m11, m12, m13 = rows[k, 4], rows[k, 5], rows[k, 6], rows[k, 7]
        m20, m21, m22, m23 = rows[k, 8], rows[k, 9], rows[k, 10], rows[k, 11]
        if k + 1 < n_samples:
            span = np.float64(hi - lo)
            w0, w1, w2 = deltas[k, 0], deltas[k, 1], deltas[k, 2]
            v0, v1, v2 = rows[k + 1, 3] - m03, rows[k + 1, 7] - m13, rows[k + 1, 11] - m23
        else:                                   # held: u times zeros, the sample itself
            span = 1.0
            w0 = w1 = w2 = v0 = v1 = v2 = 0.0
        # views of the run indexed from 0: no negative-index handling in the loops (which
        # keeps the compiler from vectorising them)
        rel, uv, av, bv = relative[i:j], us[:j - i], sa[:j - i], sb[:j - i]
        dx, dy, dz, ex, ey, ez = d[0, i:j], d[1, i:j], d[2, i:j], o[0, i:j], o[1, i:j], o[2, i:j]
        q0, q1, q2, q3, q4, q5 = (out[0, i:j], out[1, i:j], out[2, i:j], out[3, i:j],
                                  out[4, i:j], out[5, i:j])
        base = stamp - lo
        for h in range(j - i):
            u = np.float64(base + rel[h]) / span
            uv[h] = u
            av[h] = (u * w0) * (u * w0) + (u * w1) * (u * w1) + (u * w2) * (u * w2)   # theta^2
        if w0 * w0 + w1 * w1 + w2 * w2 <= 0.25:      # u < 1: every u*w as small
            for h in range(j - i):
                th2 = av[h]
                # the series up to theta^14 (truncation < 1e-19 for theta <= 0.5)
                av[h] = 1.0 + th2 * (_SIN_C[1] + th2 * (_SIN_C[2] + th2 * (_SIN_C[3] + th2 * (
                    _SIN_C[4] + th2 * (_SIN_C[5] + th2 * (_SIN_C[6] + th2 * _SIN_C[7]))))))
                bv[h] = 0.5 + th2 * (_COS_C[1] + th2 * (_COS_C[2] + th2 * (_COS_C[3] + th2 * (
                    _COS_C[4] + th2 * (_COS_C[5] + th2 * (_COS_C[6] + th2 * _COS_C[7]))))))
        else:
            for h in range(j - i):
                th2 = av[h]
                theta = math.sqrt(th2)
                av[h] = math.sin(theta) / theta if theta >= 1e-6 else 1.0 - th2 / 6
                bv[h] = (1.0 - math.cos(theta)) / th2 if theta >= 1e-6 else 0.5 - th2 / 24
        for h in range(j - i):
            u = uv[h]
            a = av[h]
            b = bv[h]
            # rot = I + a K + b K @ K, K = hat(u w) = [[0, -p2, p1], [p2, 0, -p0], [-p1, p0, 0]]
            k01, k02, k10, k12, k20, k21 = -u * w2, u * w1, u * w2, -u * w0, -u * w1, u * w0
            r00 = 1.0 + b * (k01 * k10 + k02 * k20)
            r01 = a * k01 + b * (k02 * k21)
            r02 = a * k02 + b * (k01 * k12)
            r10 = a * k10 + b * (k12 * k20)
            r11 = 1.0 + b * (k10 * k01 + k12 * k21)
            r12 = a * k12 + b * (k10 * k02)
            r20 = a * k20 + b * (k21 * k10)
            r21 = a * k21 + b * (k20 * k01)
            r22 = 1.0 + b * (k20 * k02 + k21 * k12)
            # the pose [R0 @ rot, t0 + u (t1 - t0)], row by row
            c00 = m00 * r00 + m01 * r10 + m02 * r20
            c01 = m00 * r01 + m01 * r11 + m02 * r21
            c02 = m00 * r02 + m01 * r12 + m02 * r22
            c10 = m10 * r00 + m11 * r10 + m12 * r20
            c11 = m10 * r01 + m11 * r11 + m12 * r21
            c12 = m10 * r02 + m11 * r12 + m12 * r22
            c20 = m20 * r00 + m21 * r10 + m22 * r20
            c21 = m20 * r01 + m21 * r11 + m22 * r21
            c22 = m20 * r02 + m21 * r12 + m22 * r22
            x = np.float64(dx[h])
            y = np.float64(dy[h])
            z = np.float64(dz[h])
            e = np.float64(ex[h])
            f = np.float64(ey[h])
            g = np.float64(ez[h])
            q0[h] = np.float32(c00 * x + c01 * y + c02 * z)
            q1[h] = np.float32(c10 * x + c11 * y + c12 * z)
            q2[h] = np.float32(c20 * x + c21 * y + c22 * z)
            q3[h] = np.float32(c00 * e + c01 * f + c02 * g + (m03 + u * v0))
            q4[h] = np.float32(c10 * e + c11 * f + c12 * g + (m13 + u * v1))
            q5[h] = np.float32(c20 * e + c21 * f + c22 * g + (m23 + u * v2))
        i = j


def _rho_at(dx: Any, dy: Any, ox: Any, oy: Any, r: Any) -> Any:  # pragma: no cover - compiled
    """:func:`converters.slices.spec._rho` of one ray (float64)."""
    if math.isinf(r):
        if dx != 0.0 or dy != 0.0:
            return np.inf
        return math.sqrt(ox * ox + oy * oy)
    x = r * dx + ox
    y = r * dy + oy
    return math.sqrt(x * x + y * y)


def _special_tables(special: Any, fdx: Any, fdy: Any, fdz: Any, fox: Any, foy: Any, foz: Any,
                    zmin: Any, zmax: Any, rmin: Any, rmax: Any, slice_grid: Any, g_min: Any,
                    g_inc: Any, g_size: Any, g_full: Any, near: Any, bin_far: Any,
                    qual: Any) -> None:  # pragma: no cover - compiled
    """Per ray of ``special``: the far-field bin of every grid (:func:`converters.slices.spec.
    far_field`'s ``bin_far``; libm's atan2, which may differ from numpy's in the last bit) and
    the qualifiers of every slice (:func:`converters.slices.spec.qualify`, the same float64
    operations; bits only where the slice's far-field bin exists, as :class:`Rays` holds
    them)."""
    n_grids = g_min.shape[0]
    for h in range(special.shape[0]):
        i = special[h]
        dx, dy, dz = np.float64(fdx[i]), np.float64(fdy[i]), np.float64(fdz[i])
        ox, oy, oz = np.float64(fox[i]), np.float64(foy[i]), np.float64(foz[i])
        a2 = dx * dx + dy * dy
        theta = math.atan2(dy, dx)
        for g in range(n_grids):
            b = np.int64(-1)
            if a2 > 0:
                b = _J_BIN(theta, g_min[g], g_inc[g], g_size[g], g_full[g])
            bin_far[g, i] = b
        r_star = -(dx * ox + dy * oy) / a2 if a2 > 0 else 0.0
        for s in range(zmin.shape[0]):
            if bin_far[slice_grid[s], i] < 0:
                continue
            if dz == 0.0:
                inside = oz >= zmin[s] and oz <= zmax[s]
                lo = 0.0 if inside else np.inf
                hi = np.inf if inside else -np.inf
            else:
                a = (zmin[s] - oz) / dz
                c = (zmax[s] - oz) / dz
                lo = a if dz > 0 else c
                hi = c if dz > 0 else a
            lo = max(lo, 0.0)
            if not lo <= hi:
                continue
            rs = min(max(r_star, lo), max(hi, lo))
            rho_min = _J_RHO(dx, dy, ox, oy, rs)
            rho_max = max(_J_RHO(dx, dy, ox, oy, lo), _J_RHO(dx, dy, ox, oy, hi))
            q = np.uint8(0)
            if rho_min <= rmax[s] and rho_max >= rmin[s]:
                q |= np.uint8(1)
            if lo <= near:
                q |= np.uint8(2)
            qual[s, i] = q


def _decode_kernel(best: Any, inf_value: Any, fill_value: Any, ranges: Any,
                   winners: Any) -> None:  # pragma: no cover - compiled
    """Compiled :func:`decode` into preallocated (N,) float32 ranges and int64 winners."""
    values = best.view(np.int64)
    for k in range(values.shape[0]):
        v = values[k]
        if v == EMPTY:
            ranges[k] = fill_value
            winners[k] = -1
            continue
        winners[k] = v & 0xFFFFFFFF
        ranges[k] = _J_CODE_VALUE(v, inf_value)


def _code_value(v: Any, inf_value: Any) -> Any:  # pragma: no cover - compiled
    """The published float32 value of a non-empty reduction element (``code << 32 | key``):
    the finite range, -Inf, ``inf_value`` for the +Inf class, NaN."""
    code = v >> 32
    if code < CODE_NEG_INF:
        return np.int32(code).view(np.float32)
    if code == CODE_NEG_INF:
        return np.float32(-np.inf)
    if code == CODE_POS_INF:
        return np.float32(inf_value)
    return np.float32(np.nan)


def _decode_slices(best: Any, offset: Any, size: Any, inf_value: Any, fill_value: Any,
                   intensity: Any, key_to_pos: Any, ranges: Any,
                   ints: Any) -> None:  # pragma: no cover - compiled
    """:func:`decode` of every slice (``best[offset[s]:offset[s] + size[s]]``) into ``ranges``
    (float32, same layout) plus, when ``intensity`` is not empty, the winner's intensity cast to
    float32 into ``ints`` (0 for empty bins); ``key_to_pos`` maps tie keys to pixels (empty:
    identity)."""
    use_int = intensity.shape[0] > 0
    use_map = key_to_pos.shape[0] > 0
    for s in range(offset.shape[0]):
        inf_v = inf_value[s]
        fill_v = fill_value[s]
        for k in range(size[s]):
            j = offset[s] + k
            v = best[j]
            if v == EMPTY:
                ranges[j] = fill_v
                if use_int:
                    ints[j] = 0.0
                continue
            ranges[j] = _J_CODE_VALUE(v, inf_v)
            if use_int:
                key = v & 0xFFFFFFFF
                ints[j] = np.float32(intensity[key_to_pos[key] if use_map else key])


def _pass_bands(r: Any, keep: Any, limits: Any, dz: Any, oz: Any, zmin: Any, zmax: Any,
                masks: Any, good: Any) -> None:  # pragma: no cover - compiled
    """Pass 1: ``good[i]``: a point candidate (finite, > 0, inside the limits, kept);
    ``masks[i]`` bit s: the point's height is inside slice s's band (0 unless good)."""
    n = r.shape[0]
    lim0 = limits[0]
    lim1 = limits[1]
    lim2 = limits[2]
    for i in range(n):
        rv = r[i]
        good[i] = (rv > 0.0) & (rv >= lim0) & (rv < np.inf) & (rv <= lim1) & (rv >= lim2)
    if keep.shape[0] == n:
        for i in range(n):
            good[i] &= keep[i] != 0
    z = np.empty(n)
    for i in range(n):
        z[i] = np.float64(r[i]) * dz[i] + oz[i]
    one = masks.dtype.type(1)
    for s in range(zmin.shape[0]):
        lo_z = zmin[s]
        hi_z = zmax[s]
        bit = one << s
        for i in range(n):
            masks[i] |= masks.dtype.type((z[i] >= lo_z) & (z[i] <= hi_z) & good[i]) * bit


def _pass_points(hits: Any, masks: Any, r: Any, dx: Any, dy: Any, ox: Any, oy: Any, keys: Any,
                 key_base: Any, rmin: Any, rmax: Any, slice_grid: Any, offset: Any, g_min: Any,
                 g_inc: Any, g_size: Any, g_full: Any, bin_far: Any, r_thr: Any,
                 best: Any) -> None:  # pragma: no cover - compiled
    """Pass 2: points inside at least one band. Bins from the far-field tables, or atan2 for
    rays closer than ``r_thr``; codes from the float32 bit pattern of rho."""
    bits = np.empty(1, np.float32)
    bits_i = bits.view(np.int32)
    n_grids = g_min.shape[0]
    use_keys = keys.shape[0] == r.shape[0]
    grid_bin = np.empty(n_grids, np.int64)
    for h in range(hits.shape[0]):
        i = hits[h]
        m = np.int64(masks[i])
        rv = r[i]
        rd = np.float64(rv)
        x = rd * dx[i] + ox[i]
        y = rd * dy[i] + oy[i]
        rho = math.sqrt(x * x + y * y)
        bits[0] = rho
        code_f = np.int64(bits_i[0])
        key = np.int64(keys[i]) + key_base if use_keys else np.int64(key_base + i)
        for g in range(n_grids):
            if rv < r_thr[g, i]:
                grid_bin[g] = _J_BIN(math.atan2(y, x), g_min[g], g_inc[g], g_size[g],
                                     g_full[g])
            else:
                grid_bin[g] = bin_far[g, i]
        s = 0
        while m:
            if m & 1:
                b = grid_bin[slice_grid[s]]
                if b >= 0:
                    code = code_f
                    if rho < rmin[s]:
                        code = np.int64(CODE_NEG_INF)
                    elif rho > rmax[s]:
                        code = np.int64(CODE_POS_INF)
                    comb = (code << 32) | key
                    j = offset[s] + b
                    best[j] = min(best[j], comb)
            m >>= 1
            s += 1


def _pass_others(others: Any, r: Any, keep: Any, limits: Any, keys: Any, key_base: Any,
                 slice_grid: Any, offset: Any, qual: Any, bin_far: Any,
                 best: Any) -> None:  # pragma: no cover - compiled
    """Pass 3: no return (+Inf), too close (-Inf), invalid (NaN, <= 0, below limits[0]),
    beyond limits[1] (+Inf); below limits[2] or outside ``keep``: dropped."""
    n_slices = slice_grid.shape[0]
    use_keep = keep.shape[0] == r.shape[0]
    use_keys = keys.shape[0] == r.shape[0]
    for h in range(others.shape[0]):
        i = others[h]
        if use_keep and keep[i] == 0:
            continue
        rv = r[i]
        need = 1
        if rv == np.inf:
            special = CODE_POS_INF
        elif rv == -np.inf:
            special, need = CODE_NEG_INF, 2
        elif math.isnan(rv) or rv <= 0.0 or rv < limits[0]:
            special = CODE_NAN
        elif rv > limits[1]:
            special = CODE_POS_INF
        else:                     # below the user's range filter: dropped
            continue
        key = np.int64(keys[i]) + key_base if use_keys else np.int64(key_base + i)
        comb = (np.int64(special) << 32) | key
        for s in range(n_slices):
            b = bin_far[slice_grid[s], i]
            if b >= 0 and (qual[s, i] & need):
                j = offset[s] + b
                best[j] = min(best[j], comb)
