"""The environment switches of the compiled kernels (the bottom of :mod:`converters._kernels`:
every kernel module asks these, none imports the package). They are read by
:mod:`lidarscan._backends`, the lowest layer of the project, and nowhere else (the core's codec
honours them too); this module hands them on to the converters' kernels."""

from __future__ import annotations

from lidarscan._backends import c_enabled, numba_enabled

__all__ = ["c_enabled", "numba_enabled"]
