"""Optional numba kernels of the Velodyne packet decoder: packet bytes -> the scan's channel grids.

``_fill`` does exactly what ``converters.velodyne._fill_numpy`` (the numpy reference) does, so
the results are bit-identical (integer copies only); ``_azimuths`` computes the ``azimuth``
channel as ``converters.velodyne._nebula_azimuths`` (the reference) does, with the same float32
and float64 operations in the same order, so its integers are identical too (the tests compare
both paths byte for byte). Chosen by :func:`converters._kernels.select` (``"velodyne"``), which
reads ``LIDARSCAN_NUMBA``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

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


def _azimuths(buf: Any, begin: int, count: int, slots: Any, laser: Any, family: int,
              dual: bool, rotation: Any, out: Any) -> None:  # pragma: no cover - compiled
    """Nebula's azimuth of ``count`` firing sequences' pixels, counter-clockwise 0.01 deg.

    buf: (n, 1206) uint8 packets; slots: (R, S, H) int64 point slot (32 * block + k) of return
    r, sequence s, row h; laser: (12, 32) int64 laser id of each slot; family: 0 VLP-16,
    1 VLP-32C/HDL-32E, 2 VLS-128 (``VelodyneModel.nebula``); rotation: (L,) float64
    rot_correction in 0.01 deg (``_nebula_rotation``); out: (R, H, W) uint16, columns
    0..count-1 written.
    """
    n_ret, seqs, rows = slots.shape
    blocks = 8 if family == 2 and dual else 12
    step = 2 if dual else 1
    zero = 12 - (1 if family == 0 else 4) * (1 if dual else 0) - 1
    base = np.zeros(12, np.int64)
    gap = np.zeros(12, np.float32)
    packet = -1
    for c in range(count):
        q = begin + c
        p = q // seqs
        s = q - p * seqs
        if p != packet:                       # the block walk of this packet
            packet = p
            ahead = np.int64(0)
            last = np.float32(0.0)
            for i in range(blocks):
                base[i] = (np.int64(buf[p, 2]) | (np.int64(buf[p, 3]) << 8)) if i == 0 \
                    else ahead
                if i < 12 - step:
                    o = 100 * (i + step) + 2
                    ahead = np.int64(buf[p, o]) | (np.int64(buf[p, o + 1]) << 8)
                    diff = 36000 + ahead - base[i]
                    mod = abs(diff) % 36000                      # C's %: sign of diff
                    last = np.float32(mod if diff >= 0 else -mod)
                    gap[i] = last
                else:
                    gap[i] = np.float32(0.0) if i == zero else last
        for r in range(n_ret):
            for h in range(rows):
                slot = slots[r, s, h]
                i = slot // 32
                k = slot - 32 * i
                g = gap[i]
                if family == 0:
                    offset = (np.float32(k % 16) * np.float32(2.304)
                              + np.float32(k // 16) * np.float32(55.296))
                    term = g * offset / np.float32(110.592)
                elif family == 1:
                    term = g * np.float32(2.304) / np.float32(55.296) * np.float32(k)
                else:
                    group = laser[i, k] // 8
                    term = g * ((np.float32(2.665) / np.float32(53.3))
                                * np.float32(group + group // 8))
                value = np.float64(np.float32(np.float32(base[i]) + term)) - rotation[laser[i, k]]
                value = np.float64(np.float32(value))
                if value < 0:
                    value = np.float64(np.float32(value + 36000.0))
                cw = (np.int64(math.floor(value + 0.5)) & 0xFFFF) % 36000
                out[r, h, c] = (36000 - cw) % 36000


_COMPILED = LoadOnce(lambda: numba_jit(_fill))
_AZIMUTHS = LoadOnce(lambda: numba_jit(_azimuths))


def fill_kernel() -> Any:
    """The compiled ``fill(buf, begin, count, offsets, ranges, intensities)`` or None (no
    numba). Callers go through :func:`converters._kernels.select`."""
    return _COMPILED.get()


def azimuth_kernel() -> Any:
    """The compiled ``azimuths(buf, begin, count, slots, laser, family, dual, rotation, out)``
    or None (no numba). Used when :func:`converters._kernels.select` enables numba."""
    return _AZIMUTHS.get()
