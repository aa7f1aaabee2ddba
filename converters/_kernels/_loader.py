"""Loading of the optional C kernels (extensions called through ctypes).

Each kernel is built by ``pip install [-e] .`` when a C compiler is available (setup.py) and is
an importable, otherwise empty, extension module whose shared object exports plain C functions.
A kernel is not used when it was not built, when its ABI number differs from the one the
Python side was written for (a stale build), or when the C kernels are switched off
(:func:`lidarscan._backends.c_enabled`). :class:`LoadOnce` and :func:`numba_jit` live in
:mod:`lidarscan._backends` (the core's compiled codec uses them too) and are re-exported here.
"""

from __future__ import annotations

import ctypes
import importlib
from typing import Any

import numpy as np

from lidarscan._backends import LoadOnce, c_enabled, numba_jit

__all__ = ["DTYPE_CODES", "TYPE_CODES", "LoadOnce", "load_library", "load_planned", "numba_jit",
           "type_code"]


def load_library(module: str, abi_symbol: str, abi: int) -> ctypes.CDLL | None:
    """The shared object of extension ``module`` (e.g. ``"converters._kernels._slicekernel"``)
    if it is built, enabled and both its module constant ``ABI`` and its C function
    ``abi_symbol()`` equal ``abi``; else None."""
    if not c_enabled():
        return None
    try:
        ext = importlib.import_module(module)
        lib = ctypes.CDLL(ext.__file__)
        fn = getattr(lib, abi_symbol)
    except (ImportError, OSError, AttributeError, TypeError):
        return None
    fn.restype = ctypes.c_int32
    fn.argtypes = []
    if fn() != abi or getattr(ext, "ABI", None) != abi:
        return None
    return lib


def load_planned(module: str, prefix: str, abi: int, plan: type[ctypes.Structure]
                 ) -> tuple[ctypes.CDLL, bool] | None:
    """:func:`load_library` of a kernel that takes a plan structure: also None when its C
    ``{prefix}_plan_size()`` differs from ``ctypes.sizeof(plan)`` (a stale layout); else the
    library and its ``{prefix}_vectorised()`` (whether a vector build runs on this CPU)."""
    lib = load_library(module, f"{prefix}_abi", abi)
    if lib is None:
        return None
    size, vectorised = getattr(lib, f"{prefix}_plan_size"), getattr(lib, f"{prefix}_vectorised")
    size.restype, size.argtypes = ctypes.c_int64, []
    vectorised.restype, vectorised.argtypes = ctypes.c_int32, []
    if size() != ctypes.sizeof(plan):
        return None
    return lib, bool(vectorised())


#: Element type codes shared by the C kernels (native byte order only: the converters convert
#: at the message boundary).
TYPE_CODES = {"f4": 0, "f8": 1, "u1": 2, "u2": 3, "u4": 4, "i1": 5, "i2": 6, "i4": 7}
#: The same keyed by native numpy dtype (a dtype of the other byte order is not a key).
DTYPE_CODES = {np.dtype("=" + code): value for code, value in TYPE_CODES.items()}


def type_code(image: Any) -> int | None:
    """The kernels' type code of a numpy array, or None (another dtype, or non-native order)."""
    return DTYPE_CODES.get(image.dtype)
