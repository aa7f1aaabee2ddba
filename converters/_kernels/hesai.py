"""Optional compiled (numba) path of converters.hesai: packet units -> grid rows.

One kernel, ``fill_units``, doing exactly what ``converters.hesai._units_numpy`` does (the
reference): copy the raw distance (uint16 little-endian) and reflectivity (uint8) of each laser
in block ``r`` of firings ``first .. first + count - 1`` of a block of packet rows into columns
``col ..`` of the (lasers, width) grids, laser ``l`` to row ``row_of[l]``. Integer copies only, so
the results are bit-identical. Chosen by :func:`converters._kernels.select` (``"hesai"``), which reads the switches.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from converters._kernels._loader import LoadOnce, numba_jit


def _fill_units(rows: Any, first: int, count: int, col: int, offsets: Any, r: int,
                row_of: Any, dist: Any, refl: Any) -> None:  # pragma: no cover - compiled
    """rows (P, size) uint8 (any row stride); offsets (F, R, L) int64 byte offset of each unit
    in a packet; block ``r`` of each firing; row_of (L,) int64; dist (L, W) uint16, refl
    (L, W) uint8 (written, any strides)."""
    firings = offsets.shape[0]
    lasers = offsets.shape[2]
    for i in range(count):
        g = first + i
        p = g // firings
        f = g - p * firings
        c = col + i
        for laser in range(lasers):
            o = offsets[f, r, laser]
            u = row_of[laser]
            dist[u, c] = np.uint16(rows[p, o]) | (np.uint16(rows[p, o + 1]) << np.uint16(8))
            refl[u, c] = rows[p, o + 2]


_COMPILED = LoadOnce(lambda: numba_jit(_fill_units, boundscheck=False))


def kernel() -> Any:
    """The compiled ``fill_units`` (same arguments as ``_fill_units``), or None without numba.
    Callers go through :func:`converters._kernels.select`, which honours ``LIDARSCAN_NUMBA``."""
    return _COMPILED.get()
