"""Loading of the optional compiled kernels (C extensions called through ctypes).

Each kernel is built by ``pip install [-e] .`` when a C compiler is available (setup.py) and is
an importable, otherwise empty, extension module whose shared object exports plain C functions.
A kernel is not used when it was not built, when its ABI number differs from the one the
Python side was written for (a stale build), or when the environment variable
``LIDARSCAN_NO_KERNEL`` is set to anything but "" / "0".
"""

from __future__ import annotations

import ctypes
import importlib
import os
import threading
from collections.abc import Callable
from typing import Any


def disabled() -> bool:
    """Whether ``LIDARSCAN_NO_KERNEL`` switches the compiled kernels off."""
    return os.environ.get("LIDARSCAN_NO_KERNEL", "") not in ("", "0")


def load_library(module: str, abi_symbol: str, abi: int) -> ctypes.CDLL | None:
    """The shared object of extension ``module`` (e.g. ``"converters._slicekernel"``) if it is
    built, enabled and both its module constant ``ABI`` and its C function ``abi_symbol()``
    equal ``abi``; else None."""
    if disabled():
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


class LoadOnce:
    """The result of ``loader()``, computed at the first :meth:`get` (thread-safe) and kept."""

    def __init__(self, loader: Callable[[], Any]) -> None:
        self._loader = loader
        self._lock = threading.Lock()
        self._value: list[Any] = []

    def get(self) -> Any:
        with self._lock:
            if not self._value:
                self._value.append(self._loader())
            return self._value[0]
