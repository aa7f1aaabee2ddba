"""Optional numba kernel of the Velodyne packet decoder: packet bytes -> a scan's channel views.

``_fill`` writes, in one pass over the packets, what the numpy reference of
``converters.velodyne.packets`` computes in several: the ``range``/``intensity`` grids of
``_fill_numpy`` (integer copies) and the ``azimuth`` channel of ``_nebula_azimuths`` (the same
float32 and float64 operations in the same order, so the same integers), straight into the
channel views of a :class:`lidarscan.scan.ScanBuffer`. The tests compare both paths byte for
byte (``tests/test_velodyne_golden.py``). Chosen by :func:`converters._kernels.select`
(``"velodyne"``), which reads ``LIDARSCAN_NUMBA``.

The loop is tiled: a tile of packets is read while it sits in cache, one (sequence, row) at a
time, so each channel row is written in runs and the per-pixel work has no per-pixel lookups.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from converters._kernels._loader import LoadOnce, numba_jit

_TILE = 128     # packets per tile (measured: 16-64 slower, 256 the same)


def _fill(buf: Any, begin: int, count: int, column: int, offsets: Any, blocks: Any,
          factors: Any, rotation: Any, family: int, dual: bool, nebula: bool,
          range0: Any, intensity0: Any, range1: Any, intensity1: Any, azimuth0: Any,
          azimuth1: Any) -> None:  # pragma: no cover - compiled
    """Decode ``count`` firing sequences, from sequence ``begin`` of ``buf``, into columns
    ``column..column+count-1`` of the channel views.

    buf: (n, 1206) uint8 packets (sequence q is sequence q % S of packet q // S);
    offsets: (R, S, H) int64 byte offset, in a packet, of the distance (u16 little-endian,
    followed by the reflectivity byte) of return slot r (0 = strongest/only), sequence s, row h;
    blocks: (R, S, H) int64 block of that point; factors: (R, S, H) float32 its firing factor
    (VLP-16: 2.304 (k % 16) + 55.296 (k // 16); VLP-32C/HDL-32E: k; VLS-128:
    2.665 / 53.3 * (g + g // 8), g = laser // 8); rotation: (R, S, H) float64 rot_correction
    of its laser in 0.01 deg; family: 0 VLP-16, 1 VLP-32C/HDL-32E, 2 VLS-128
    (``VelodyneModel.nebula``); nebula: write the azimuth views.
    range0/intensity0 (H, W) uint16/uint8 (range1/intensity1 too when R == 2; else unused),
    azimuth0/azimuth1 (H, W) uint16: counter-clockwise 0.01 deg, Nebula's angle (an identical
    dual pair gets the last return's angle in both).
    """
    n_ret, seqs, rows = offsets.shape
    n_blocks = 8 if family == 2 and dual else 12
    step = 2 if dual else 1
    zero = 12 - (1 if family == 0 else 4) * (1 if dual else 0) - 1
    base = np.zeros((_TILE, 12), np.float32)     # float32 of each block's base azimuth
    gap = np.zeros((_TILE, 12), np.float32)      # its gap (VLP-32C: gap * 2.304 / 55.296)
    raw = np.zeros(12, np.int64)
    p_first = begin // seqs
    p_end = (begin + count - 1) // seqs + 1
    for pa in range(p_first, p_end, _TILE):       # a tile of packets
        pb = min(pa + _TILE, p_end)
        if nebula:
            for p in range(pa, pb):               # Nebula's block walk of each packet
                ahead = np.int64(0)
                last = np.float32(0.0)
                for i in range(n_blocks):
                    raw[i] = (np.int64(buf[p, 2]) | (np.int64(buf[p, 3]) << 8)) if i == 0 \
                        else ahead
                    if i < 12 - step:
                        o = 100 * (i + step) + 2
                        ahead = np.int64(buf[p, o]) | (np.int64(buf[p, o + 1]) << 8)
                        diff = 36000 + ahead - raw[i]
                        mod = abs(diff) % 36000                      # C's %: sign of diff
                        last = np.float32(mod if diff >= 0 else -mod)
                        g = last
                    else:
                        g = np.float32(0.0) if i == zero else last
                    base[p - pa, i] = np.float32(raw[i])
                    gap[p - pa, i] = g * np.float32(2.304) / np.float32(55.296) \
                        if family == 1 else g
        for s in range(seqs):                     # the tile's packets whose sequence s is used
            lo = max(pa, (begin - s + seqs - 1) // seqs)
            hi = min(pb, (begin + count - 1 - s) // seqs + 1)
            if hi <= lo:
                continue
            m = hi - lo
            c0 = column + lo * seqs + s - begin
            c1 = c0 + (m - 1) * seqs + 1
            for h in range(rows):
                for r in range(n_ret):
                    o = offsets[r, s, h]
                    low, high, refl = buf[lo:hi, o], buf[lo:hi, o + 1], buf[lo:hi, o + 2]
                    out_r = (range0 if r == 0 else range1)[h, c0:c1:seqs]
                    out_i = (intensity0 if r == 0 else intensity1)[h, c0:c1:seqs]
                    for j in range(m):
                        out_r[j] = np.uint16(low[j]) | (np.uint16(high[j]) << np.uint16(8))
                        out_i[j] = refl[j]
                if not nebula:
                    continue
                for r in range(n_ret - 1, -1, -1):    # the last return's slot first
                    i = blocks[r, s, h]
                    f = factors[r, s, h]
                    turn = rotation[r, s, h]
                    b = base[lo - pa:hi - pa, i]
                    g = gap[lo - pa:hi - pa, i]
                    out = (azimuth0 if r == 0 else azimuth1)[h, c0:c1:seqs]
                    pair = r == 0 and n_ret == 2
                    first = range0[h, c0:c1:seqs]
                    second = range1[h, c0:c1:seqs]
                    other = azimuth1[h, c0:c1:seqs]
                    for j in range(m):
                        if pair and first[j] == second[j]:
                            out[j] = other[j]     # an identical pair: the last return's angle
                            continue
                        if family == 0:
                            term = g[j] * f / np.float32(110.592)
                        else:
                            term = g[j] * f
                        value = np.float64(np.float32(b[j] + term)) - turn
                        value = np.float64(np.float32(value))
                        if value < 0:
                            value = np.float64(np.float32(value + 36000.0))
                        cw = np.int64(math.floor(value + 0.5)) & 0xFFFF
                        if cw >= 36000:
                            cw -= 36000
                        out[j] = 36000 - cw if cw else 0


_COMPILED = LoadOnce(lambda: numba_jit(_fill))


def fill_kernel() -> Any:
    """The compiled :func:`_fill` or None (no numba). Callers go through
    :func:`converters._kernels.select`."""
    return _COMPILED.get()
