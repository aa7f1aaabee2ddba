"""Python side of the optional compiled kernel of :mod:`converters.slices.cloud`
(``converters/_kernels/_cloudslicekernel.c``): unstructured cloud -> several LaserScan slices in
one pass over the points, fusion and decoding in one call.

The kernel does exactly what ``converters.slices.cloud._fuse_numpy`` (the reference) and
:func:`converters.slices.spec.decode` do, reading the cloud's x, y, z fields (float32 or float64,
native byte order, any offsets and steps) and its intensity field (any element type) in place.
Per point, its target-frame height first (from z alone for an upright target), dropped unless
it lies in the hull of the bands; only a kept point has its x, y read and transformed and its
finiteness tested (a non-finite height is never inside a finite hull, and every kept point is
tested). Kept points are buffered in chunks; per chunk the bin of every point once per distinct
grid, its planar range and float32 code once, then band by band the points inside the band and
the minimum of ``code << 32 | point index`` in the reduction array. The C file's header says
how each step is vectorised (AVX2, chosen at run time; the scalar build gives the same bits).

Binning without libm's ``atan2`` for almost every point: an odd polynomial of ``atan`` on
``[0, 1]`` (:data:`ATAN_COEFFS`, error below 4e-8 rad, checked by a test) after the octant
reduction gives the azimuth within :data:`EPS` = 1e-7 rad. The bin is a monotone function of the
azimuth, so when the approximate azimuth is more than ``2 * EPS`` from every bin edge (and, for
sectors, from the wrap point) the bin is the one of the exact ``atan2``; the other points (about
``4e-7 / increment`` of them: 7e-5 at 2*pi/1024) and points at the origin take libm's ``atan2``
with the reference's formula. Results therefore equal the reference bit for bit wherever numpy's
``arctan2`` is libm's (numpy's own SIMD ``arctan2``, used on AVX-512 CPUs, may differ from libm
in the last bit for a point within an ulp of a bin edge).

Chosen by :func:`converters._kernels.select` (``"cloud_slices"``), which reads the switches.
"""

from __future__ import annotations

import ctypes
import math
from typing import Any

import numpy as np

from converters._kernels import _loader

__all__ = ["ABI", "ATAN_COEFFS", "EPS", "CloudSlicePlan", "atan2_approx", "available",
           "library", "vectorised"]

#: ABI of _cloudslicekernel.c (its LCS_ABI).
ABI = 1
#: 0 forces the kernel's scalar build even where AVX2 is available (tests cover both).
SIMD = 1
#: atan(u) ~= u * sum(c_j * u**(2j)) on 0 <= u <= 1 (least squares on Chebyshev nodes,
#: reweighted towards minimax); the C file holds the same constants
ATAN_COEFFS = (0.9999993356986212, -0.33329861034289326, 0.19946567288244435,
               -0.13908634232863948, 0.09642203544865086, -0.05591235776154396,
               0.021862952643013092, -0.00405456031490202)
#: bound on |atan2_approx - atan2| in radians (polynomial error 3.7e-8 plus rounding; a test
#: checks the polynomial against it)
EPS = 1e-7

_i32, _i64, _f64, _ptr = ctypes.c_int32, ctypes.c_int64, ctypes.c_double, ctypes.c_void_p


def atan2_approx(y: float, x: float) -> float:
    """The kernel's ``lcs_atan2_approx`` in Python (for tests): atan2(y, x) within :data:`EPS`
    for finite (x, y) not both 0; range [-pi, pi]."""
    ax, ay = abs(x), abs(y)
    z = min(ax, ay) / max(ax, ay)
    u2 = z * z
    p = ATAN_COEFFS[7]
    for c in ATAN_COEFFS[6::-1]:
        p = p * u2 + c
    a = z * p
    a = a + float(ay > ax) * (0.5 * math.pi - 2.0 * a)
    a = a + float(x < 0.0) * (math.pi - 2.0 * a)
    return math.copysign(a, y)


class _Plan(ctypes.Structure):
    """``lcs_plan`` of _cloudslicekernel.c: the same fields, in the same order."""

    _fields_ = [("n_slices", _i64), ("n_grids", _i64), ("m", _ptr),
                ("zlo", _ptr), ("zhi", _ptr), ("rlo", _ptr), ("rhi", _ptr),
                ("sgrid", _ptr), ("soff", _ptr), ("inf_value", _ptr), ("fill_value", _ptr),
                ("gmin", _ptr), ("ginc", _ptr), ("ginv", _ptr), ("gsize", _ptr),
                ("gfull", _ptr), ("zall_lo", _f64), ("zall_hi", _f64), ("size", _i64)]


def library() -> Any:
    """The kernel's ``lcs_slices`` (a ctypes function; it releases the GIL), or None when the
    kernel is not built, stale or disabled (``LIDARSCAN_NO_KERNEL``, read at the first use)."""
    return _library.get()


def _load() -> Any:
    loaded = _loader.load_planned("converters._kernels._cloudslicekernel", "lcs", ABI, _Plan)
    if loaded is None:
        return None
    fn = loaded[0].lcs_slices
    fn.vectorised = loaded[1]
    fn.restype = _i64
    fn.argtypes = [ctypes.POINTER(_Plan), _i64, _i64,          # plan, height, width
                   _ptr, _ptr, _ptr, _i64, _i64, _i32,          # x, y, z, steps, type
                   _ptr, _i64, _i64, _i32,                      # intensity, steps, type
                   _ptr, _ptr, _ptr, _i32]                      # best, ranges, ints, simd
    return fn


_library = _loader.LoadOnce(_load)


def available() -> bool:
    """Whether the compiled cloud slices kernel is built and enabled."""
    return library() is not None


def vectorised() -> bool:
    """Whether the kernel runs its AVX2 build on this CPU (else its scalar build)."""
    fn = library()
    return fn is not None and bool(fn.vectorised)


class CloudSlicePlan:
    """Everything the kernel needs but the cloud, for one converter (arrays kept alive here).

    Args:
        m: (12,) float64 rotation row-major, then translation (target <- cloud).
        zlo, zhi, rlo, rhi: (S,) float64 bands and planar range limits (inclusive).
        sgrid, soff: (S,) int64 grid of each slice, first bin in the reduction array.
        inf_value, fill_value: (S,) float32 decoded +Inf and empty-bin values.
        gmin, ginc, gsize, gfull: (G,) the distinct grids.
        size: bins of all slices.

    Raises:
        RuntimeError: the compiled kernel is not available (:func:`available`).
    """

    def __init__(self, *, m: Any, zlo: Any, zhi: Any, rlo: Any, rhi: Any, sgrid: Any,
                 soff: Any, inf_value: Any, fill_value: Any, gmin: Any, ginc: Any,
                 gsize: Any, gfull: Any, size: int) -> None:
        fn = library()
        if fn is None:
            raise RuntimeError("the compiled cloud slices kernel is not available")
        self._fn = fn                          # fetched once per plan, not per cloud
        f8, i8, f4 = np.float64, np.int64, np.float32
        keep = {"m": np.ascontiguousarray(m, f8), "zlo": np.ascontiguousarray(zlo, f8),
                "zhi": np.ascontiguousarray(zhi, f8), "rlo": np.ascontiguousarray(rlo, f8),
                "rhi": np.ascontiguousarray(rhi, f8), "sgrid": np.ascontiguousarray(sgrid, i8),
                "soff": np.ascontiguousarray(soff, i8),
                "inf_value": np.ascontiguousarray(inf_value, f4),
                "fill_value": np.ascontiguousarray(fill_value, f4),
                "gmin": np.ascontiguousarray(gmin, f8), "ginc": np.ascontiguousarray(ginc, f8),
                "ginv": 1.0 / np.ascontiguousarray(ginc, f8),
                "gsize": np.ascontiguousarray(gsize, i8),
                "gfull": np.ascontiguousarray(gfull, i8)}
        if keep["m"].size != 12:
            raise ValueError(f"m of {keep['m'].size} elements, expected 12")
        self._keep = keep
        self.size = int(size)
        self.plan = _Plan(n_slices=keep["zlo"].size, n_grids=keep["gmin"].size,
                          zall_lo=float(keep["zlo"].min()), zall_hi=float(keep["zhi"].max()),
                          size=self.size, **{k: v.ctypes.data for k, v in keep.items()})
        self._plan_ref = ctypes.byref(self.plan)

    def run(self, height: int, width: int, xyz: tuple[int, int, int], step: int,
            row_step: int, xyz_type: int, intensity: tuple[int, int, int, int] | None,
            best: np.ndarray[Any, Any], ranges: np.ndarray[Any, Any] | None,
            ints: np.ndarray[Any, Any] | None) -> None:
        """All slices of one cloud of ``height`` rows of ``width`` points.

        Args:
            xyz: addresses of the first point's x, y, z (point (v, u) at ``+ v * row_step +
                u * step`` bytes), all of the type code ``xyz_type`` (0 float32, 1 float64).
            intensity: (address, step, row_step, type code of :data:`_loader.TYPE_CODES`) of
                the first point's intensity, or None.
            best: (size,) int64, written: the reduction array.
            ranges, ints: (size,) float32, written: the published ranges and the winners'
                intensities (0 in empty bins; ``ints`` needs ``intensity``), or None (fusion
                only).

        The caller keeps the buffers alive and checks their sizes (the kernel reads
        ``(height - 1) * row_step + width * step`` bytes from each field's address).
        """
        i_addr, i_step, i_row, i_type = (None, 0, 0, 0) if intensity is None else intensity
        status = self._fn(self._plan_ref, height, width, xyz[0], xyz[1], xyz[2], step, row_step,
                    xyz_type, i_addr, i_step, i_row, i_type, best.ctypes.data,
                    None if ranges is None else ranges.ctypes.data,
                    None if ints is None else ints.ctypes.data, SIMD)
        if status == -1:
            raise MemoryError("the cloud slices kernel could not allocate its buffers")
        if status != 0:
            raise RuntimeError(f"the cloud slices kernel failed with status {status}")
