"""Python side of the optional C kernel of the Velodyne packet decoder (``_velokernel.c``).

:func:`fill` writes, in one pass over the packets, what the numpy reference of
``converters.velodyne.packets`` computes in several: the ``range``/``intensity`` grids of
``_fill_numpy`` (integer copies) and the ``azimuth`` channel of ``_nebula_azimuths`` (the same
float32 and float64 operations in the same order, so the same integers), straight into the
channel views of a :class:`lidarscan.scan.ScanBuffer`; :func:`first_bad` is the per-packet
header check of ``PacketDecoder`` (flags, azimuths, factory bytes) in one pass. The tests
compare both paths byte for byte (``tests/test_velodyne_golden.py``). Chosen by
:func:`converters._kernels.select` (``"velodyne"``), which reads ``LIDARSCAN_NO_KERNEL``.
Inside the kernel, layouts with one firing sequence per packet (dual-return VLS-128) take an
AVX2 path on CPUs that have it, the others a portable one; ``LIDARSCAN_VELODYNE_SIMD=0`` (read
by :func:`fill` at each call) forces the portable path. Both write the same bytes
(``tests/test_velokernel.py``).
"""

from __future__ import annotations

import ctypes
import os
from collections.abc import Mapping
from typing import Any

import numpy as np

from converters._kernels import _loader

#: ABI of converters/_kernels/_velokernel.c (its VDK_ABI).
ABI = 2
#: The kernel rounds Nebula's angle in float32, exact while rotations stay below this (0.01 deg,
#: i.e. 10 000 degrees; a larger rot_correction takes the numpy path).
MAX_ROTATION = 1e6

_i64, _i32, _ptr = ctypes.c_int64, ctypes.c_int32, ctypes.c_void_p


def _load() -> Any:
    lib = _loader.load_library("converters._kernels._velokernel", "vdk_abi", ABI)
    if lib is None:
        return None
    lib.vdk_check.restype = _i64
    lib.vdk_check.argtypes = [_ptr, _i64, _i64, _i32, _ptr, _i64]
    lib.vdk_fill.restype = _i64
    lib.vdk_fill.argtypes = [_ptr, _i64, _i64, _i64, _i64, _i64, _i64, _i64,   # .. width
                             _ptr, _ptr, _ptr, _ptr, _i64, _i64, _i64,          # .. n_blocks
                             _ptr, _ptr, _ptr, _ptr, _ptr, _ptr, _i64]          # views, simd
    return lib


_library = _loader.LoadOnce(_load)


def library() -> Any:
    """The loaded kernel (ctypes library), or None: not built, stale or disabled
    (``LIDARSCAN_NO_KERNEL``, read at each call). Callers go through
    :func:`converters._kernels.select`."""
    from converters._kernels import c_enabled
    return _library.get() if c_enabled() else None


def _address(array: np.ndarray[Any, Any] | None) -> int | None:
    return None if array is None else array.__array_interface__["data"][0]


class Plan:
    """The kernel's per-layout arguments (built once per info version).

    Args:
        offsets: (R, S, H) byte offset in a packet of the distance of return slot r, sequence
            s, row h (``converters.velodyne.packets._offsets``).
        factor: (12, 32) float32 firing factor of each point slot's laser (block, k).
        rotation: (12, 32) float64 rot_correction of each slot's laser, 0.01 deg.
        family: 0 VLP-16, 1 VLP-32C/HDL-32E, 2 VLS-128 (``VelodyneModel.nebula``).
        dual: dual-return packets.
        n_blocks: the blocks Nebula's walk reads (8 for a dual-return VLS-128, else 12).
    """

    def __init__(self, offsets: np.ndarray[Any, Any], factor: np.ndarray[Any, Any],
                 rotation: np.ndarray[Any, Any], family: int, dual: bool,
                 n_blocks: int) -> None:
        self.returns, self.seqs, self.rows = offsets.shape
        self.offsets = np.ascontiguousarray(offsets, np.int32)
        self.slots = np.ascontiguousarray(offsets // 100 * 32 + (offsets % 100 - 4) // 3,
                                          np.int16)
        self.factor = np.ascontiguousarray(factor, np.float32).reshape(-1)
        self.rotation = np.ascontiguousarray(rotation, np.float64).reshape(-1)
        self.family, self.dual, self.n_blocks = int(family), bool(dual), int(n_blocks)
        #: whether the kernel can compute this layout's angles (else the numpy path)
        self.angles_ok = bool(np.all(np.abs(self.rotation) < MAX_ROTATION))
        self._args = (self.returns, self.seqs, self.rows)
        self._tables = (_address(self.offsets), _address(self.slots), _address(self.factor),
                        _address(self.rotation), self.family, int(self.dual), self.n_blocks)


def fill(lib: Any, plan: Plan, run: np.ndarray[Any, Any], begin: int, count: int, column: int,
         views: Mapping[str, np.ndarray[Any, Any]]) -> None:
    """Sequences begin..begin+count-1 of ``run`` ((n, 1206) C-contiguous uint8 packets) into
    columns column..column+count-1 of a ScanBuffer's (H, W) views ``range``, ``intensity``
    [, ``range2``, ``intensity2``] [, ``azimuth`` [, ``azimuth2``]] (C-contiguous, native order);
    the kernel's AVX2 path unless ``LIDARSCAN_VELODYNE_SIMD`` is "0" (same bytes either way).
    """
    r0, i0 = views["range"], views["intensity"]
    width = r0.shape[1]
    a0 = views.get("azimuth")
    simd = os.environ.get("LIDARSCAN_VELODYNE_SIMD", "") != "0"
    status = lib.vdk_fill(_address(run), begin, count, column, *plan._args, width,
                          *plan._tables, _address(r0), _address(i0),
                          _address(views.get("range2")), _address(views.get("intensity2")),
                          _address(a0), _address(views.get("azimuth2")), int(simd))
    if status == -2:
        raise MemoryError("converters._kernels._velokernel: no memory for a column tile")
    if status != 0:
        raise ValueError(f"vdk_fill: unsupported plan (returns {plan.returns}, rows "
                         f"{plan.rows}): status {status}")


def first_bad(lib: Any, rows: np.ndarray[Any, Any], key: int, flags: bytes) -> int:
    """The index of the first of the (n, 1206) C-contiguous uint8 ``rows`` whose factory bytes
    (product << 8 | return mode) differ from ``key`` or that fails the block checks of
    ``PacketDecoder`` (flag 0xFF, ``flags[b]`` and an azimuth below 36000 in each of the first
    ``len(flags)`` blocks); n when all pass."""
    return int(lib.vdk_check(_address(rows), rows.shape[0], rows.strides[0], key, flags,
                             len(flags)))
