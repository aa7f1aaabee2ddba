"""The environment switches of the compiled kernels, read here and nowhere else (the bottom of
:mod:`converters._kernels`: every kernel module asks these, none imports the package)."""

from __future__ import annotations

import os


def c_enabled() -> bool:
    """Whether the C kernels may be loaded (``LIDARSCAN_NO_KERNEL`` unset, "" or "0")."""
    return os.environ.get("LIDARSCAN_NO_KERNEL", "") in ("", "0")


def numba_enabled() -> bool:
    """Whether the numba kernels may be compiled (``LIDARSCAN_NUMBA`` not "0")."""
    return os.environ.get("LIDARSCAN_NUMBA", "1") != "0"
