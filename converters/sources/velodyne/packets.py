"""Velodyne packet formats: each model's layout and timing, and its bytes -> a scan's pixels.

The facts of the user manuals (:class:`VelodyneModel`, :data:`MODELS`, :func:`_layout`), Nebula's
per-pixel azimuth (:func:`_nebula_azimuths`, the numpy reference), and the per-pixel tables with
which :func:`_fill_views` writes a rotation's channels into a ScanBuffer, by the compiled kernel
(``converters._kernels.velodyne``) or by the numpy references :func:`_fill_numpy` and
:func:`_azimuths_numpy` (identical bytes). Conventions: see :mod:`converters.sources.velodyne`.
"""

from __future__ import annotations

import functools
import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from converters.sources.velodyne.calibration import VLP16_CALIBRATION, VLP32C_CALIBRATION, _laser_values

PACKET_SIZE = 1206
_BLOCKS = 12
_STRONGEST, _LAST, _DUAL = 0x37, 0x38, 0x39
_RETURN_MODES = {_STRONGEST: "strongest", _LAST: "last", _DUAL: "dual"}
_AZIMUTHS = struct.Struct("<" + "2xH96x" * _BLOCKS)      # the 12 block azimuths


@dataclass(frozen=True)
class VelodyneModel:
    """Packet layout and firing timing of one product line (facts of its user manual).

    Attributes:
        name: model name written to ``LidarInfo.model``.
        lasers: lasers per firing sequence (= calibration length = scan height).
        distance_resolution: metres per raw distance unit.
        sequence_ns: firing-sequence period in ns (one column).
        laser_ns: (lasers,) firing time of each laser after its sequence's first firing, ns.
        first_firing_ns: time of the packet's first firing relative to its timestamp, ns
            (single return); ``last_firing_stamp``: the timestamp marks the packet's last firing.
        nominal: public nominal calibration (the manual's elevations, and its azimuth offsets
            where it lists them), or None when the model needs its calibration file.
        nebula: which of Nebula's decoders handles the model ("vlp16", "vlp32", "vls128"):
            the per-pixel azimuth of the default ``azimuth_model`` (:func:`_nebula_azimuths`).
    """

    name: str
    lasers: int
    distance_resolution: float
    sequence_ns: float
    laser_ns: tuple[int, ...]
    first_firing_ns: float = 0.0
    last_firing_stamp: bool = False
    nominal: Mapping[str, Any] | None = None
    nebula: str = "vlp32"


def _nominal(elevations_deg: Any, resolution: float) -> dict[str, Any]:
    return {"num_lasers": len(elevations_deg), "distance_resolution": resolution,
            "lasers": [{"laser_id": k, "vert_correction": math.radians(e), "rot_correction": 0.0,
                        "dist_correction": 0.0, "vert_offset_correction": 0.0,
                        "horiz_offset_correction": 0.0} for k, e in enumerate(elevations_deg)]}


def _fans(low: float, high: float, count: int) -> list[float]:
    """Elevations (deg) of lasers alternating between two fans 4/3 deg apart (Puck Hi-Res,
    HDL-32E): even laser k at low + 4/3 (k // 2), odd at high + 4/3 (k // 2)."""
    return [(low if k % 2 == 0 else high) + 4.0 / 3.0 * (k // 2) for k in range(count)]


_VLP16_TIMES = tuple(2304 * k for k in range(16))
#: product id (factory byte 0x4DF) -> model. VLP-16 and Puck LITE share 0x22; the VLS-128 (and
#: Alpha Prime) reports 0xA1 (0x63 in some manual tables, accepted too).
MODELS: dict[int, VelodyneModel] = {
    0x22: VelodyneModel("VLP-16", 16, 0.002, 55296.0, _VLP16_TIMES,
                        nominal=VLP16_CALIBRATION, nebula="vlp16"),
    0x24: VelodyneModel("Puck Hi-Res", 16, 0.002, 55296.0, _VLP16_TIMES,
                        nominal=_nominal(_fans(-10.0, 2.0 / 3.0, 16), 0.002), nebula="vlp16"),
    0x28: VelodyneModel("VLP-32C", 32, 0.004, 55296.0, tuple(2304 * (k // 2) for k in range(32)),
                        nominal=VLP32C_CALIBRATION),
    0x21: VelodyneModel("HDL-32E", 32, 0.002, 46080.0, tuple(1152 * k for k in range(32)),
                        last_firing_stamp=True,
                        nominal=_nominal(_fans(-92.0 / 3.0, -28.0 / 3.0, 32), 0.002)),
    0xA1: VelodyneModel("VLS-128", 128, 0.004, 53300.0,
                        tuple(2665 * (k // 8 + k // 64) for k in range(128)),
                        first_firing_ns=-8700.0, nebula="vls128"),
}
MODELS[0x63] = MODELS[0xA1]

@dataclass(frozen=True)
class _Layout:
    """Where a packet's sequences are: blocks -> (sequences, lasers[, returns])."""

    model: VelodyneModel
    dual: bool
    sequences: int            # firing sequences per packet
    seq_ns: np.ndarray[Any, Any]   # (sequences,) first-firing time relative to the timestamp
    measured: np.ndarray[Any, Any]  # (sequences,) block whose azimuth is the sequence's, or -1
    flags: bytes              # expected second flag byte of each used block (first is 0xFF)
    last_offset: int          # byte offset of the packet's last measured azimuth
    # derived (per layout, read-only):
    seq_times: np.ndarray[Any, Any]    # (sequences,) int64 round(seq_ns)
    measured_seqs: tuple[int, ...]     # the M sequences with a measured azimuth
    # indices into a packet as 603 little-endian uint16 words (:func:`_words`):
    azimuth_words: np.ndarray[Any, Any]   # (M,) of those sequences' azimuths
    head_words: np.ndarray[Any, Any]   # (2 + S,) the timestamp's low and high word, then the
    #                                    azimuth of each sequence (block 0's where unmeasured)


@functools.cache
def _layout(product: int, mode: int) -> _Layout:
    model = MODELS[product]
    dual = mode == _DUAL
    lasers = model.lasers
    if lasers == 16:                       # two sequences per block
        seqs = 12 if dual else 24
        index = np.arange(seqs)               # even sequences carry their block's azimuth
        measured = np.where(index % 2 == 0, index if dual else index // 2, -1)
        flags = b"\xee" * _BLOCKS
    elif lasers == 32:
        seqs = 6 if dual else 12
        measured = np.arange(seqs) * (2 if dual else 1)
        flags = b"\xee" * _BLOCKS
    else:                                  # 128: four banks per sequence
        seqs = 1 if dual else 3
        measured = np.arange(seqs) * 4
        flags = b"\xee\xee\xdd\xdd\xcc\xcc\xbb\xbb" if dual else b"\xee\xdd\xcc\xbb" * 3
    seq_ns = np.arange(seqs) * model.sequence_ns + model.first_firing_ns
    if model.last_firing_stamp:           # HDL-32E: the stamp is the last firing of the packet
        seq_ns -= (seqs - 1) * model.sequence_ns + model.laser_ns[-1]
    measured = measured.astype(np.int64)
    arrays = (seq_ns, measured, np.round(seq_ns).astype(np.int64),
              1 + 50 * measured[measured >= 0],
              np.concatenate([[600, 601], 1 + 50 * np.maximum(measured, 0)]))
    for array in arrays:
        array.flags.writeable = False                   # shared by every decoder (cached)
    return _Layout(model, dual, seqs, arrays[0], arrays[1], flags,
                   2 + 100 * int(measured[measured >= 0][-1]), arrays[2],
                   tuple(np.flatnonzero(measured >= 0).tolist()), *arrays[3:])


def _words(rows: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """(n, 1206) uint8 packets as (n, 603) little-endian uint16 words (a view when the bytes of
    a row are contiguous; the block azimuths are the words 1 + 50 b, the timestamp 600-601)."""
    return (rows if rows.strides[1] == 1 else np.ascontiguousarray(rows)).view("<u2")


class _Table:
    """m packets by address: rows of a batch that were never copied into one buffer (the kernel
    path of ``decode_packets``); usable where the decoder takes (m, 1206) rows: ``shape``,
    slices, :func:`_words_at`, :func:`_fill_views`.

    Attributes:
        addresses: (m,) uintp address of each packet's 1206 bytes.
        pairs: the list of (stamp, bytes) pairs the packets are in (kept alive with the table:
            ``bytes`` never change, so the addresses stay valid).
        start: the index in ``pairs`` of packet 0.
        lib: the C kernel that reads them (``converters._kernels.velodyne``).
    """

    __slots__ = ("addresses", "pairs", "start", "lib")

    def __init__(self, addresses: np.ndarray[Any, Any], pairs: list[Any], start: int,
                 lib: Any) -> None:
        self.addresses, self.pairs, self.start, self.lib = addresses, pairs, start, lib

    @property
    def shape(self) -> tuple[int, int]:
        return (self.addresses.shape[0], PACKET_SIZE)

    def __getitem__(self, index: slice) -> _Table:
        start, _, step = index.indices(self.addresses.shape[0])
        if step != 1:
            raise IndexError("a _Table takes slices of step 1")
        return _Table(self.addresses[index], self.pairs, self.start + start, self.lib)

    def row(self, i: int) -> bytes:
        """The payload of packet i."""
        return bytes(self.pairs[self.start + i][1])

    def rows(self) -> np.ndarray[Any, Any]:
        """The packets as one new (m, 1206) uint8 array (a copy)."""
        pairs = self.pairs[self.start:self.start + self.addresses.shape[0]]
        return np.frombuffer(b"".join(p[1] for p in pairs), np.uint8).reshape(-1, PACKET_SIZE)


def _words_at(rows: np.ndarray[Any, Any] | _Table, at: np.ndarray[Any, Any]
              ) -> np.ndarray[Any, Any]:
    """(m, k) uint16: the little-endian words ``at`` (k word indices) of m packets, (m, 1206)
    uint8 rows or a :class:`_Table`."""
    if isinstance(rows, _Table):
        from converters._kernels.velodyne import words
        return words(rows.lib, rows.addresses, at)
    return _words(rows)[:, at]


def _blocks_to_sequences(values: np.ndarray[Any, Any], layout: _Layout
                         ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any] | None]:
    """(n, 12, 32) per-block values -> (n, S, L) first/only return and (n, S, L) last return.

    Dual return: blocks come in pairs (even = last return, odd = strongest, or second strongest
    when the strongest is also the last); the first array is the strongest slot.
    """
    n = values.shape[0]
    lasers = layout.model.lasers
    if lasers == 128:
        if layout.dual:
            pairs = values[:, :8].reshape(n, 4, 2, 32)            # bank, return, laser
            return (pairs[:, :, 1].reshape(n, 1, 128), pairs[:, :, 0].reshape(n, 1, 128))
        return values.reshape(n, 3, 128), None
    if layout.dual:
        pairs = values.reshape(n, 6, 2, 32)
        strong, last = pairs[:, :, 1], pairs[:, :, 0]
        if lasers == 16:
            return strong.reshape(n, 12, 16), last.reshape(n, 12, 16)
        return strong, last
    if lasers == 16:
        return values.reshape(n, 24, 16), None
    return values, None


_F32 = np.float32


def _nebula_rotation(calib: Mapping[str, Any], lasers: int) -> np.ndarray[Any, Any]:
    """(L,) float64 ``rot_correction`` of each laser_id in hundredths of a degree, as Nebula
    forms it: the float32 radians times 180 / pi * 100 in double precision."""
    rot = _laser_values(calib)["rot_correction"][:lasers].astype(_F32).astype(np.float64)
    return rot * 180.0 / math.pi * 100.0


def _nebula_lasers(layout: _Layout) -> np.ndarray[Any, Any]:
    """(12, 32) int64 laser id of each point slot as Nebula reads it: VLP-16 slot k % 16,
    VLP-32C/HDL-32E slot k, VLS-128 the block's bank (from its flag) * 32 + k; 0 in blocks
    a dual-return VLS-128 packet does not use."""
    k = np.arange(32)
    laser = np.zeros((_BLOCKS, 32), np.int64)
    if layout.model.nebula == "vlp16":
        laser[:] = k % 16
    elif layout.model.nebula == "vlp32":
        laser[:] = k
    else:
        bank = {0xEE: 0, 0xDD: 32, 0xCC: 64, 0xBB: 96}
        used = len(layout.flags)
        laser[:used] = np.array([bank[f] for f in layout.flags])[:, None] + k
    return laser


def _nebula_azimuths(rows: np.ndarray[Any, Any], layout: _Layout,
                     rotation: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """Nebula's azimuth of every point slot of m packets: (m, 12 * 32) int64, clockwise
    hundredths of a degree in 0..35999 (slot ``32 * block + k``; blocks Nebula does not read
    are 0).

    Nebula's decoders (one per product line, ``VelodyneModel.nebula``) walk the blocks of a
    packet keeping the azimuth of the block ``step`` ahead (step 2 in dual return), so block i
    gets the base azimuth ``A_i`` (block 0: its own; later blocks: the azimuth read ahead by
    the block before, i.e. block i + 1 in dual return) and the gap ``D_i`` to the block read
    ahead (the last gap again, or 0 for the block before the unused ones and for the last
    block, where nothing is read ahead). Slot k of block i then points at
    ``round(A_i + D_i * f_k - rot_correction)`` in float32 arithmetic, with f_k: VLP-16
    ``(2.304 us * (k % 16) + 55.296 us * (k // 16)) / 110.592 us``, VLP-32C/HDL-32E
    ``2.304 / 55.296 * k``, VLS-128 ``2.665 / 53.3 * (g + g // 8)``, g = laser // 8.

    Args: rows (m, 1206) uint8 packets of ``layout``; rotation (L,) from
    :func:`_nebula_rotation`.
    """
    m = rows.shape[0]
    family, dual = layout.model.nebula, layout.dual
    count = 8 if family == "vls128" and dual else _BLOCKS
    step = 2 if dual else 1
    zero = _BLOCKS - (1 if family == "vlp16" else 4) * int(dual) - 1
    heads = rows[:, :100 * _BLOCKS].reshape(m, _BLOCKS, 100)
    block_az = heads[:, :, 2].astype(np.int64) | (heads[:, :, 3].astype(np.int64) << 8)
    base = np.empty((m, count), np.int64)
    gap = np.empty((m, count), _F32)
    ahead = np.zeros(m, np.int64)
    last = np.zeros(m, _F32)
    for i in range(count):
        base[:, i] = block_az[:, 0] if i == 0 else ahead
        if i < _BLOCKS - step:
            ahead = block_az[:, i + step]
            last = np.fmod(36000 + ahead - base[:, i], 36000).astype(_F32)   # C's %
            gap[:, i] = last
        else:
            gap[:, i] = 0 if i == zero else last
    k = np.arange(32)
    laser = _nebula_lasers(layout)[:count]
    if family == "vlp16":
        offset = (k % 16).astype(_F32) * _F32(2.304) + (k // 16).astype(_F32) * _F32(55.296)
        term = gap[:, :, None] * offset / _F32(110.592)
    elif family == "vlp32":
        term = ((gap * _F32(2.304)) / _F32(55.296))[:, :, None] * k.astype(_F32)
    else:
        group = laser // 8
        term = gap[:, :, None] * ((_F32(2.665) / _F32(53.3)) * (group + group // 8).astype(_F32))
    total = (base.astype(_F32)[:, :, None] + term).astype(np.float64) - rotation[laser]
    total = total.astype(_F32).astype(np.float64)
    total = np.where(total < 0, (total + 36000.0).astype(_F32).astype(np.float64), total)
    out = np.zeros((m, _BLOCKS, 32), np.int64)
    out[:, :count] = (np.floor(total + 0.5).astype(np.int64) & 0xFFFF) % 36000
    return out.reshape(m, _BLOCKS * 32)


def _flags(data: bytes, count: int) -> list[str]:
    return [f"0x{data[100 * b + 1]:02X}{data[100 * b]:02X}" for b in range(count)]


def _flag_names(second: bytes) -> str:
    names = [f"0x{b:02X}FF" for b in second]
    return "block flags " + (names[0] + " in every block" if len(set(names)) == 1
                             else " ".join(names))


def _offsets(layout: _Layout, order: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """(R, S, H) int64: byte offset in a packet of the distance of return slot r (0 = the
    strongest/only slot), sequence s, row h (laser ``order[h]``); reflectivity follows at +2."""
    index = np.arange(_BLOCKS * 32).reshape(1, _BLOCKS, 32)      # block * 32 + point
    slots = [s.reshape(layout.sequences, -1)[:, order]
             for s in _blocks_to_sequences(index, layout) if s is not None]
    point = np.stack(slots)
    return np.ascontiguousarray(100 * (point // 32) + 4 + 3 * (point % 32), dtype=np.int64)


@dataclass(frozen=True)
class _Tables:
    """Per-layout tables of one row order (built once per info version).

    Attributes:
        offsets: (R, S, H) int64 byte offset of the distance of return slot r (0 = the
            strongest/only slot), sequence s, row h (:func:`_offsets`).
        rotation: (L,) float64 rot_correction of each laser (:func:`_nebula_rotation`), zeros
            without an azimuth channel.
        plan: the C kernel's arguments (``converters._kernels.velodyne.Plan``), or None (no
            kernel: the numpy references).
        lib: the loaded C kernel the plan is for (None without a plan).
    """

    offsets: np.ndarray[Any, Any]
    rotation: np.ndarray[Any, Any]
    plan: Any = None
    lib: Any = None


def _tables(layout: _Layout, order: np.ndarray[Any, Any], rotation: np.ndarray[Any, Any] | None,
            lib: Any) -> _Tables:
    """The tables of one layout and row order; ``rotation`` from :func:`_nebula_rotation`, or
    None: no azimuth channel; ``lib``: the C kernel the decoder chose
    (``converters._kernels.select("velodyne").c``) or None. The kernel's plan is made when
    there is one (and it can take the rotations)."""
    offsets = _offsets(layout, order)
    nebula = rotation is not None
    if rotation is None:
        rotation = np.zeros(layout.model.lasers)
    if lib is None:
        return _Tables(offsets, rotation)
    from converters._kernels.velodyne import Plan

    laser = _nebula_lasers(layout)                            # (12, 32) laser of each slot
    k = np.broadcast_to(np.arange(32), laser.shape)
    family = layout.model.nebula
    if family == "vlp16":
        factor = (k % 16).astype(_F32) * _F32(2.304) + (k // 16).astype(_F32) * _F32(55.296)
    elif family == "vlp32":
        factor = k.astype(_F32)
    else:
        group = laser // 8
        factor = (_F32(2.665) / _F32(53.3)) * (group + group // 8).astype(_F32)
    plan = Plan(offsets, factor, rotation[laser], ("vlp16", "vlp32", "vls128").index(family),
                layout.dual, 8 if family == "vls128" and layout.dual else _BLOCKS)
    if plan.angles_ok or not nebula:
        return _Tables(offsets, rotation, plan, lib)
    return _Tables(offsets, rotation)


def _fill_views(runs: list[Any], begin: int, count: int, layout: _Layout,
                tables: _Tables, views: Mapping[str, Any]) -> None:
    """Sequences begin..begin+count-1 of the packet runs ((m, 1206) rows, or :class:`_Table`)
    into columns 0..count-1 of a ScanBuffer's views (``range``, ``intensity``, [``range2``,
    ``intensity2``], [``azimuth``, [``azimuth2``]]), by the C kernel when ``tables`` has its
    plan, else by the numpy references (:func:`_fill_numpy`, :func:`_azimuths_numpy`);
    identical results."""
    lib = tables.lib
    if lib is not None:
        from converters._kernels.velodyne import fill
    offsets = tables.offsets
    nebula = "azimuth" in views
    seqs = layout.sequences
    r0, i0 = views["range"], views["intensity"]
    r1, i1 = views.get("range2", r0), views.get("intensity2", i0)
    a0 = views.get("azimuth", r0)
    a1 = views.get("azimuth2", a0)
    column, first = 0, begin                     # the sequences, run by run
    for run in runs:
        have = run.shape[0] * seqs - first
        if have > 0 and column < count:
            take = min(have, count - column)
            if lib is not None:
                fill(lib, tables.plan, run.addresses if isinstance(run, _Table) else run,
                     first, take, column, views)
            else:
                if isinstance(run, _Table):       # (a plan the kernel cannot take)
                    run = run.rows()
                _fill_numpy(run, first, take, offsets,
                            [(g[:, column:], h[:, column:]) for g, h in ((r0, i0), (r1, i1))])
                if nebula:
                    _azimuths_numpy(run, first, take, layout, tables,
                                    [a[:, column:] for a in (a0, a1)[:offsets.shape[0]]])
            column += take
        first = max(0, -have)
    if lib is None and nebula and "azimuth2" in views:
        same = r0 == r1                # Nebula emits an identical pair once, at the last's angle
        a0[same] = a1[same]


def _fill_numpy(buf: np.ndarray[Any, Any], begin: int, count: int, offsets: np.ndarray[Any, Any],
                grids: list[tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]]) -> None:
    """Reference: sequences begin..begin+count-1 of buf (sequence q = sequence q % S of packet
    q // S) into columns 0..count-1 of each return slot's (ranges (H, W) uint16, intensities
    (H, W) uint8) in ``grids``."""
    returns, seqs, rows = offsets.shape
    p0, p1 = begin // seqs, (begin + count - 1) // seqs + 1
    sub = buf[p0:p1]
    skip = begin - p0 * seqs
    for r in range(returns):
        ranges, intensities = grids[r]
        lo, hi = sub[:, offsets[r]], sub[:, offsets[r] + 1]               # (m, S, H)
        dist = (lo.astype(np.uint16) | (hi.astype(np.uint16) << 8)).reshape(-1, rows)
        ranges[:, :count] = dist[skip:skip + count].T
        intensities[:, :count] = sub[:, offsets[r] + 2].reshape(-1, rows)[skip:skip + count].T


def _azimuths_numpy(buf: np.ndarray[Any, Any], begin: int, count: int, layout: _Layout,
                    tables: _Tables, out: list[np.ndarray[Any, Any]]) -> None:
    """Reference: the ``azimuth`` channel(s) of sequences begin..begin+count-1 of buf (Nebula's
    angle of each pixel, :func:`_nebula_azimuths`, counter-clockwise 0.01 deg) into columns
    0..count-1 of each return slot's (H, W) uint16 view in ``out`` (identical pairs: see
    :func:`_fill_views`)."""
    offsets, rotation = tables.offsets, tables.rotation
    seqs = layout.sequences
    slots = offsets // 100 * 32 + (offsets % 100 - 4) // 3              # (R, S, H)
    p0, p1 = begin // seqs, (begin + count - 1) // seqs + 1
    ccw = (36000 - _nebula_azimuths(buf[p0:p1], layout, rotation)) % 36000
    picked = np.take(ccw.astype(np.uint16), slots, axis=1)               # (m, R, S, H)
    picked = picked.transpose(1, 3, 0, 2).reshape(slots.shape[0], slots.shape[2], -1)
    skip = begin - p0 * seqs
    for r, view in enumerate(out):
        view[:, :count] = picked[r, :, skip:skip + count]
