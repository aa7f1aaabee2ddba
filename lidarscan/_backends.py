"""The backend switches of the whole project, read here and nowhere else, and the numba loader.

Every compiled path (the C kernels and numba kernels of ``converters``, the compiled residual
coder of :mod:`lidarscan.codec`) is optional: the numpy reference is the spec and the test
oracle. Which compiled paths may run is decided by two environment variables, read at each
call of :func:`c_enabled` / :func:`numba_enabled` (the callers read them at the first use of a
backend in the process, or per object):

* ``LIDARSCAN_NO_KERNEL`` set to anything but "" / "0" disables the C kernels;
* ``LIDARSCAN_NUMBA=0`` disables numba.

This is the lowest layer of the seam: ``converters._kernels.select`` (the converters' kernels)
and :func:`lidarscan.codec.residual_coder` (the codec's) ask it. Nothing here imports numba:
:func:`numba_jit` imports it at its first call (a kernel's first use), and
:class:`LoadOnce` keeps what a loader built.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from typing import Any

__all__ = ["LoadOnce", "c_enabled", "numba_enabled", "numba_jit"]


def c_enabled() -> bool:
    """Whether the C kernels may be loaded (``LIDARSCAN_NO_KERNEL`` unset, "" or "0")."""
    return os.environ.get("LIDARSCAN_NO_KERNEL", "") in ("", "0")


def numba_enabled() -> bool:
    """Whether the numba kernels may be compiled (``LIDARSCAN_NUMBA`` not "0")."""
    return os.environ.get("LIDARSCAN_NUMBA", "1") != "0"


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


def numba_jit(fn: Callable[..., Any], **options: Any) -> Any:
    """``fn`` compiled by ``numba.njit(cache=True, nogil=True, **options)`` (compiled at its
    first call, cached on disk), or None without numba. The switch ``LIDARSCAN_NUMBA`` is
    honoured by the callers (:func:`numba_enabled`), not here."""
    try:
        import numba
    except ImportError:
        return None
    return numba.njit(cache=True, nogil=True, **options)(fn)
