"""ctypes binding of ``_cloudkernel.c``: LidarScan -> PointCloud2 points in one pass.

The kernel writes x, y, z (float32), the validity of each range and one channel field straight
into the cloud's point buffer, from either the per-pixel direction/offset tables
(``lsk_project``) or the factored beam model (``lsk_project_rc``,
:func:`lidarscan.geometry.beam_factors`). Its arithmetic is deterministic (no fused
multiply-add): the AVX-512, AVX2 and baseline builds it picks from at load time give the same
bits. The converter that drives it is :class:`converters.pointcloud2.converter.PointCloud2Converter`.
"""

from __future__ import annotations

import ctypes
import dataclasses
from typing import Any

import numpy as np

from converters._kernels import _loader
from lidarscan.errors import ConversionError

__all__ = ["ABI", "Job", "Kernels", "available", "kernel", "load"]

#: ABI of _cloudkernel.c (its LSK_ABI): a stale build is ignored, not called.
ABI = 3
#: Flags of the range decoding (integer ranges: multiplier, offset).
MULTIPLY, OFFSET = 1, 2


@dataclasses.dataclass(frozen=True)
class Kernels:
    """The compiled kernel's entry points (ctypes functions; they release the GIL)."""

    project: Any        # lsk_project: per-pixel direction / offset tables
    project_rc: Any     # lsk_project_rc: the factored beam model (per-beam, per-column factors)


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
    fn, rc = lib.lsk_project, lib.lsk_project_rc
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
                   ptr, i32]                         # r_out, dense
    return Kernels(fn, rc)


_once = _loader.LoadOnce(load)


@dataclasses.dataclass
class Job:
    """One kernel call over the whole grid, as named fields (addresses as ints); built per
    layout by the converter, :meth:`run` over row blocks."""

    fn: Any
    out: int
    step: int
    xyz_offset: int
    range: int
    range_type: int
    roll: int | None
    width: int
    scale: int
    mult: float
    offset: float
    geometry: tuple[int | None, ...]          # (D, O) tables or (colshift, rows, cols, g)
    extra: int | None
    extra_type: int
    extra_offset: int
    r_out: int | None
    done: frozenset[str]                      # field names the kernel writes
    keep: tuple[Any, ...]                     # arrays the addresses point into
    factored: bool = False                    # fn is lsk_project_rc

    def run(self, start: int, count: int, dense: bool = False) -> int:
        """Points ``start .. start+count`` (pixel order); returns how many are valid
        (``dense``: the valid ones are packed at the front)."""
        if self.factored:
            colshift, rows, cols, const = self.geometry
            valid = int(self.fn(self.out, self.step, self.xyz_offset, start, count, self.range,
                                self.range_type, self.roll, colshift, self.width, self.scale,
                                self.mult, self.offset, rows, cols, const,
                                self.extra, self.extra_type, self.extra_offset,
                                self.r_out, int(dense)))
        else:
            d, o = self.geometry
            valid = int(self.fn(self.out, self.step, self.xyz_offset, start, count, self.range,
                                self.range_type, None, self.roll, self.width, self.scale,
                                self.mult, self.offset, d, o,
                                self.extra, self.extra_type, self.extra_offset,
                                self.r_out, int(dense)))
        if valid < 0:                                          # unreachable: types checked
            raise ConversionError("kernel source type", (self.range_type, self.extra_type),
                                  f"one of {sorted(_loader.TYPE_CODES.values())}")
        return valid


def available() -> bool:
    """Whether LidarScan -> PointCloud2 can use the compiled kernel."""
    return kernel() is not None


def addr(a: np.ndarray[Any, Any]) -> int:
    """Address of an array's first element (``.ctypes.data``: no dtype description is built,
    unlike ``__array_interface__``, slow for structured dtypes)."""
    return int(a.ctypes.data)
