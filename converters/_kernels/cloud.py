"""ctypes binding of ``_cloudkernel.c``: LidarScan -> PointCloud2 points in one pass.

The kernel writes x, y, z (float32), the validity of each range and one channel field straight
into the cloud's point buffer, from either the per-pixel direction/offset tables
(``lsk_project``) or the factored beam model (``lsk_project_rc``,
:func:`lidarscan.geometry.beam_factors`). Its arithmetic is deterministic (no fused
multiply-add): the AVX-512, AVX2 and baseline builds it picks from at load time give the same
bits, and so does the factored form's hand-written AVX-512 path (16 pixels at a time, where
:func:`vectorised`) against its portable code (:data:`SIMD` 0). The converter that drives it is :class:`converters.pointcloud2.converter.PointCloud2Converter`.
"""

from __future__ import annotations

import ctypes
import dataclasses
import os
from typing import Any

import numpy as np

from converters._kernels import _loader
from lidarscan.errors import ConversionError

__all__ = ["ABI", "DTYPE_CODES", "SIMD", "Job", "Kernels", "addr", "available", "kernel", "load",
           "vectorised"]

#: ABI of _cloudkernel.c (its LSK_ABI): a stale build is ignored, not called.
ABI = 4
#: 1: the factored form's AVX-512 path where the CPU has it (:func:`vectorised`); 0 forces the
#: portable code (``LIDARSCAN_CLOUD_SIMD=0`` when this module is loaded; tests set the
#: attribute). Both write the same bytes (tests/test_pointcloud2_kernel.py).
SIMD = int(os.environ.get("LIDARSCAN_CLOUD_SIMD", "") != "0")
#: Flags of the range decoding (integer ranges: multiplier, offset).
MULTIPLY, OFFSET = 1, 2
#: The kernel's element type code of a native numpy dtype (other dtypes: not readable).
DTYPE_CODES = _loader.DTYPE_CODES


@dataclasses.dataclass(frozen=True)
class Kernels:
    """The compiled kernel's entry points (ctypes functions; they release the GIL)."""

    project: Any        # lsk_project: per-pixel direction / offset tables
    project_rc: Any     # lsk_project_rc: the factored beam model (per-beam, per-column factors)
    vectorised: Any = None    # lsk_vectorised: whether project_rc's AVX-512 path can run


def kernel() -> Kernels | None:
    """The compiled kernel's entry points, or None when the extension was not built (no
    compiler: the install still succeeds), is stale, or the C kernels are switched off
    (:func:`converters._kernels.c_enabled`, read at the first use in the process)."""
    kernels: Kernels | None = _once.get()
    return kernels


def load() -> Kernels | None:
    """Load and bind the extension (:func:`kernel` keeps the result)."""
    lib = _loader.load_library("converters._kernels._cloudkernel", "lsk_abi", ABI)
    if lib is None:
        return None
    fn, rc, vec = lib.lsk_project, lib.lsk_project_rc, lib.lsk_vectorised
    vec.restype, vec.argtypes = ctypes.c_int32, []
    i64, i32, f32, ptr = ctypes.c_int64, ctypes.c_int32, ctypes.c_float, ctypes.c_void_p
    fn.restype = i64
    fn.argtypes = [ptr, i64, i64, i64, i64,          # out, point_step, xyz_offset, start, n
                   ptr, i32,                         # range, range_type
                   ptr, ptr, i64,                    # gather, roll, width
                   i32, f32, f32,                    # scale flags, multiplier, offset
                   ptr, ptr,                         # D, O (pixels, 3) float32
                   ptr, i32, i64,                    # extra, extra_type, extra_offset
                   ptr, i32]                         # r_out, dense
    rc.restype = i64
    rc.argtypes = [ptr, i64, i64, i64, i64,          # out, point_step, xyz_offset, start, n
                   ptr, i32,                         # range, range_type
                   ptr, ptr, i64,                    # roll, colshift, width
                   i32, f32, f32,                    # scale flags, multiplier, offset
                   ptr, ptr, ptr,                    # beam, column factors, constant
                   ptr, i32, i64,                    # extra, extra_type, extra_offset
                   ptr, i32, i32]                    # r_out, dense, simd
    return Kernels(fn, rc, vec)


_once = _loader.LoadOnce(load)


@dataclasses.dataclass
class Job:
    """One kernel call over the whole grid, as named fields; built per scan by the converter,
    :meth:`run` over row blocks. The arrays are held here (their addresses are taken by
    :meth:`run`), so they live as long as the job."""

    fn: Any
    out: Any                                  # the point buffer: array.array('B') or ndarray
    step: int
    xyz_offset: int
    range: np.ndarray[Any, Any]               # (H, W) native, C-contiguous, aligned
    range_type: int
    roll: np.ndarray[Any, Any] | None         # (H,) int64 scan -> grid column rotation
    width: int
    scale: int
    mult: float
    offset: float
    geometry: tuple[np.ndarray[Any, Any] | None, ...]   # (D, O) tables or (colshift, rows,
    extra: np.ndarray[Any, Any] | None                  # cols, constant) factors
    extra_type: int
    extra_offset: int
    r_out: np.ndarray[Any, Any] | None        # (H, W) float32 decoded ranges, or None
    done: frozenset[str]                      # field names the kernel writes
    factored: bool = False                    # fn is lsk_project_rc

    def run(self, start: int, count: int, dense: bool = False) -> int:
        """Points ``start .. start+count`` (pixel order); returns how many are valid
        (``dense``: the valid ones are packed at the front)."""
        out, rng, roll = addr(self.out), addr(self.range), addr(self.roll)
        extra, r_out = addr(self.extra), addr(self.r_out)
        geometry = [addr(a) for a in self.geometry]
        if self.factored:
            colshift, rows, cols, const = geometry
            valid = int(self.fn(out, self.step, self.xyz_offset, start, count, rng,
                                self.range_type, roll, colshift, self.width, self.scale,
                                self.mult, self.offset, rows, cols, const,
                                extra, self.extra_type, self.extra_offset, r_out, int(dense),
                                SIMD))
        else:
            d, o = geometry
            valid = int(self.fn(out, self.step, self.xyz_offset, start, count, rng,
                                self.range_type, None, roll, self.width, self.scale,
                                self.mult, self.offset, d, o,
                                extra, self.extra_type, self.extra_offset, r_out, int(dense)))
        if valid < 0:                                          # unreachable: types checked
            raise ConversionError("kernel source type", (self.range_type, self.extra_type),
                                  f"one of {sorted(_loader.TYPE_CODES.values())}")
        return valid


def available() -> bool:
    """Whether LidarScan -> PointCloud2 can use the compiled kernel."""
    return kernel() is not None


def vectorised() -> bool:
    """Whether the factored form's AVX-512 path runs on this CPU (with :data:`SIMD` 1)."""
    kernels = kernel()
    return bool(kernels is not None and kernels.vectorised is not None
                and kernels.vectorised())


def addr(a: Any) -> int | None:
    """Address of the first element of an ndarray (``.ctypes.data``: no dtype description is
    built, unlike ``__array_interface__``, slow for structured dtypes) or of an
    ``array.array``; None for None."""
    if a is None:
        return None
    if isinstance(a, np.ndarray):
        return int(a.ctypes.data)
    return int(a.buffer_info()[0])
