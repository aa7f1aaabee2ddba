"""Optional numba kernel of the Velodyne packet decoder: packet bytes -> the scan's channel grids.

It does exactly what ``converters.velodyne._fill_numpy`` (the numpy reference) does, so the
results are bit-identical (integer copies only). Chosen by :func:`converters._kernels.select`
(``"velodyne"``), which reads ``LIDARSCAN_NUMBA``.
"""

from __future__ import annotations

from typing import Any

from converters._kernels._loader import LoadOnce, numba_jit


def _fill(buf: Any, begin: int, count: int, offsets: Any, ranges: Any,
          intensities: Any) -> None:  # pragma: no cover - compiled
    """Decode ``count`` firing sequences, from sequence ``begin`` of ``buf``, into the grids.

    buf: (n, 1206) uint8 packets (sequence q is sequence q % S of packet q // S);
    offsets: (R, S, H) int64 byte offset, in a packet, of the distance (u16 little-endian,
    followed by the reflectivity byte) of return slot r, sequence s, row h;
    ranges: (R, H, W) uint16 and intensities: (R, H, W) uint8, columns 0..count-1 written.
    """
    n_ret, seqs, rows = offsets.shape
    for c in range(count):
        q = begin + c
        p = q // seqs
        s = q - p * seqs
        for r in range(n_ret):
            for h in range(rows):
                o = offsets[r, s, h]
                ranges[r, h, c] = buf[p, o] | (buf[p, o + 1] << 8)
                intensities[r, h, c] = buf[p, o + 2]


_COMPILED = LoadOnce(lambda: numba_jit(_fill))


def fill_kernel() -> Any:
    """The compiled ``fill(buf, begin, count, offsets, ranges, intensities)`` or None (no
    numba). Callers go through :func:`converters._kernels.select`."""
    return _COMPILED.get()
