"""Optional compiled (numba) path of converters.sources.hesai.decoder: packet units -> grid rows.

One kernel, ``fill_units``, doing exactly what ``converters.sources.hesai.rotation._units_numpy`` does (the
reference): copy the raw distance (uint16 little-endian) and reflectivity (uint8) of each laser
in block ``r`` of firings ``first .. first + count - 1`` of a run of packets into columns
``col ..`` of the (lasers, width) grids of that return, laser ``l`` to row ``row_of[l]``.
Integer copies only, so the results are bit-identical. Chosen by
:func:`converters._kernels.select` (``"hesai"``), which reads the switches.

The arrays are flat and C-contiguous and every index is unsigned (numba then emits neither
stride multiplications nor negative-index wraparound per unit): this copy is the bulk of the
decoder's time.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from converters._kernels._loader import LoadOnce, numba_jit


def _fill_units(src: Any, stride: int, first: int, count: int, col: int, base: int,
                block_size: int, unit_size: int, returns: int, r: int, firings: int,
                rowbase: Any, dist: Any, refl: Any) -> None:  # pragma: no cover - compiled
    """src: 1-D uint8, packet ``p`` starting at ``p * stride``; the unit of laser ``l`` in block
    ``b`` of a packet at ``base + b * block_size + l * unit_size`` (block ``f * returns + r``
    holds return ``r`` of firing ``f``; ``firings`` per packet); return ``r`` is copied.
    rowbase (L,) uint64: ``row * width`` of each laser. dist (L * width,) uint16 and refl
    (L * width,) uint8: the flattened grids of return ``r`` (written)."""
    lasers = rowbase.size
    one = np.uint64(1)
    two = np.uint64(2)
    step = np.uint64(unit_size)
    for i in range(count):
        g = first + i
        p = g // firings
        f = g - p * firings
        c = np.uint64(col + i)
        o = np.uint64(p * stride + base + (f * returns + r) * block_size)
        for laser in range(lasers):
            k = rowbase[laser] + c
            dist[k] = np.uint16(src[o]) | (np.uint16(src[o + one]) << np.uint16(8))
            refl[k] = src[o + two]
            o += step


_COMPILED = LoadOnce(lambda: numba_jit(_fill_units, boundscheck=False))


def kernel() -> Any:
    """The compiled ``fill_units`` (same arguments as ``_fill_units``), or None without numba.
    Callers go through :func:`converters._kernels.select`, which honours ``LIDARSCAN_NUMBA``."""
    return _COMPILED.get()
