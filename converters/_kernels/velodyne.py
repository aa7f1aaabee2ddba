"""Python side of the optional C kernel of the Velodyne packet decoder (``_velokernel.c``).

:func:`fill` writes, in one pass over the packets, what the numpy reference of
``converters.sources.velodyne.packets`` computes in several: the ``range``/``intensity`` grids of
``_fill_numpy`` (integer copies) and the ``azimuth`` channel of ``_nebula_azimuths`` (the same
float32 and float64 operations in the same order, so the same integers), straight into the
channel views of a :class:`lidarscan.scan.ScanBuffer`; :func:`good` is the per-packet header
check of ``PacketDecoder`` (flags, azimuths, factory bytes) in one pass, :func:`words` reads
header words. The kernel reads packets through a table of their addresses: an (n, 1206) array's
rows (:func:`addresses`) or separate ``bytes`` payloads (:func:`table`, one C pass over a list
of (stamp, payload) pairs: ``decode_packets`` needs no copy of its payloads into one buffer).
The tests compare the kernel and the numpy paths byte for byte
(``tests/test_velodyne_golden.py``). Chosen by :func:`converters._kernels.select`
(``"velodyne"``), which reads ``LIDARSCAN_NO_KERNEL``. Inside the kernel, layouts with one
firing sequence per packet (dual-return VLS-128) take an AVX2 path on CPUs that have it, the
others a portable one; :data:`SIMD` 0 (``LIDARSCAN_VELODYNE_SIMD=0`` when this module is
loaded; tests set the attribute) forces the portable path. Both write the same bytes
(``tests/test_velokernel.py``).
"""

from __future__ import annotations

import ctypes
import importlib
import os
from collections.abc import Mapping
from typing import Any

import numpy as np

from converters._kernels import _loader

#: ABI of converters/_kernels/_velokernel.c (its VDK_ABI).
ABI = 3
#: The kernel rounds Nebula's angle in float32, exact while rotations stay below this (0.01 deg,
#: i.e. 10 000 degrees; a larger rot_correction takes the numpy path).
MAX_ROTATION = 1e6
#: 1: the AVX2 path where it applies (default), 0: the portable path (same bytes).
SIMD = int(os.environ.get("LIDARSCAN_VELODYNE_SIMD", "") != "0")

_i64, _i32, _ptr = ctypes.c_int64, ctypes.c_int32, ctypes.c_void_p
#: argument types of the kernel's functions (also used by bench/velokernel_harness.py)
ARGTYPES = {
    "vdk_good": (_i64, [_ptr, _i64, _i32, _ptr, _i64, _ptr]),
    "vdk_words": (None, [_ptr, _i64, _ptr, _i64, _ptr]),
    "vdk_fill": (_i64, [_ptr, _i64, _i64, _i64, _i64, _i64, _i64, _i64,   # .. width
                        _ptr, _ptr, _ptr, _ptr, _i64, _i64, _i64,          # .. n_blocks
                        _ptr, _ptr, _ptr, _ptr, _ptr, _ptr, _i64]),        # views, simd
}


def bind(lib: Any) -> Any:
    """``lib`` (a ctypes library of this kernel's functions) with their argument types set."""
    for name, (restype, argtypes) in ARGTYPES.items():
        fn = getattr(lib, name)
        fn.restype, fn.argtypes = restype, argtypes
    return lib


def _load() -> Any:
    lib = _loader.load_library("converters._kernels._velokernel", "vdk_abi", ABI)
    return None if lib is None else bind(lib)


_library = _loader.LoadOnce(_load)


def library() -> Any:
    """The loaded kernel (ctypes library), or None: not built, stale or disabled
    (``LIDARSCAN_NO_KERNEL``, read at each call). Callers go through
    :func:`converters._kernels.select`."""
    from lidarscan._backends import c_enabled
    return _library.get() if c_enabled() else None


def _address(array: np.ndarray[Any, Any] | None) -> int | None:
    return None if array is None else array.__array_interface__["data"][0]


def addresses(rows: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """(n,) uintp address of each row of an (n, 1206) uint8 array whose rows' bytes are
    contiguous (``rows.strides[1] == 1``); the caller keeps ``rows`` alive while they are used."""
    base = np.uintp(_address(rows))
    return base + np.arange(rows.shape[0], dtype=np.uintp) * np.uintp(rows.strides[0])


def table(pairs: list[Any]) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]] | None:
    """((n,) uintp addresses of the payloads, (n,) int64 stamps) of a list of n (stamp_ns,
    payload) pairs, in one C pass, when every pair is a tuple of an int and a 1206-byte
    ``bytes``; else None (the caller takes the general path). The addresses are valid while
    ``pairs`` is alive and unchanged."""
    n = len(pairs)
    out, stamps = np.empty(n, np.uintp), np.empty(n, np.int64)
    if _module().table(pairs, out, stamps) != n:
        return None
    return out, stamps


def _module() -> Any:
    return importlib.import_module("converters._kernels._velokernel")


def _packets(packets: np.ndarray[Any, Any]) -> tuple[np.ndarray[Any, Any], Any]:
    """(addresses, the array to keep alive) of (n, 1206) uint8 rows or (n,) uintp addresses."""
    if packets.ndim == 1:
        return packets, packets
    rows = packets if packets.strides[1] == 1 else np.ascontiguousarray(packets)
    return addresses(rows), rows


def good(lib: Any, packets: np.ndarray[Any, Any], key: int, flags: bytes,
         out: np.ndarray[Any, Any]) -> int:
    """Set ``out[p]`` (an (n,) bool array) for each of the packets (see :func:`fill`) whose
    factory bytes (product << 8 | return mode) equal ``key`` and that pass the block checks of
    ``PacketDecoder`` (flag 0xFF, ``flags[b]`` and an azimuth below 36000 in each of the first
    ``len(flags)`` blocks); the others' are left as they are. Returns the number set."""
    table, _rows = _packets(packets)              # (_rows: alive during the call)
    return int(lib.vdk_good(_address(table), table.shape[0], key, flags, len(flags),
                            _address(out)))


def words(lib: Any, packets: np.ndarray[Any, Any], at: np.ndarray[Any, Any]
          ) -> np.ndarray[Any, Any]:
    """(n, k) uint16: the little-endian words ``at`` (k word indices, bytes 2w and 2w + 1) of
    the packets (see :func:`fill`)."""
    table, _rows = _packets(packets)              # (_rows: alive during the call)
    at = np.ascontiguousarray(at, np.int64)
    out = np.empty((table.shape[0], at.size), np.uint16)
    lib.vdk_words(_address(table), table.shape[0], _address(at), at.size, _address(out))
    return out


class Plan:
    """The kernel's per-layout arguments (built once per info version).

    Args:
        offsets: (R, S, H) byte offset in a packet of the distance of return slot r, sequence
            s, row h (``converters.sources.velodyne.packets._offsets``).
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


def fill(lib: Any, plan: Plan, packets: np.ndarray[Any, Any], begin: int, count: int,
         column: int, views: Mapping[str, np.ndarray[Any, Any]]) -> None:
    """Sequences begin..begin+count-1 of the packets (an (n, 1206) uint8 array, or (n,) uintp
    addresses of packets, e.g. from :func:`table`) into columns column..column+count-1 of a
    ScanBuffer's (H, W) views ``range``, ``intensity`` [, ``range2``, ``intensity2``]
    [, ``azimuth`` [, ``azimuth2``]] (C-contiguous, native order); the kernel's AVX2 path unless
    :data:`SIMD` is 0 (same bytes either way).
    """
    table, _rows = _packets(packets)              # (_rows: alive during the call)
    r0, i0 = views["range"], views["intensity"]
    width = r0.shape[1]
    a0 = views.get("azimuth")
    status = lib.vdk_fill(_address(table), begin, count, column, *plan._args, width,
                          *plan._tables, _address(r0), _address(i0),
                          _address(views.get("range2")), _address(views.get("intensity2")),
                          _address(a0), _address(views.get("azimuth2")), SIMD)
    if status == -2:
        raise MemoryError("converters._kernels._velokernel: no memory for a column tile")
    if status != 0:
        raise ValueError(f"vdk_fill: unsupported plan (returns {plan.returns}, rows "
                         f"{plan.rows}): status {status}")
