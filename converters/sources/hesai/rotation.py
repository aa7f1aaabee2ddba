"""Hesai decoder internals: the per-rotation assembly behind :mod:`converters.sources.hesai.decoder`.

What one rotation of buffered payload rows becomes, apart from the decoder's packet intake:
the stream's geometry and time model (``_Stream``: firing period and block start times, the
scan's channels), the tail's date-time in POSIX seconds, zero-copy structured views of payload
rows (``_records``), the copy of the units into the scan's grids (``_units``: the compiled
kernel of :mod:`converters._kernels.hesai`, with :func:`_units_numpy` as its reference), the
QT128 and (with a firetime file) 128-series per-pixel firing times and the process-wide
LidarInfo templates. Conventions (axes, rows, columns, time): the module docstring of
:mod:`converters.sources.hesai.decoder`; formats: :mod:`converters.sources.hesai.formats`. Nothing here is public API.
"""

from __future__ import annotations

import calendar
import dataclasses
import functools
import math
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from lidarscan.errors import DecodeError
from converters.sources.hesai.formats import HesaiFormat, _block_kinds, _channel_names, _channel_rank


@dataclass
class _Stream:
    """What identifies the geometry of the packets being decoded (a change -> new version)."""

    fmt: HesaiFormat
    mode: int
    returns: int
    dis_unit_m: float
    rpm: int
    packet_size: int
    last_firing_at: int       # byte offset of the last firing's first block from block 0
    state: int = -1           # 128 series: the tail's operational state; -1: none
    #: 128 series with a firetime file: ((rows, 8) int32 ns after the block's start of each
    #: row's channel, column 2 * azimuth state + near; the smallest raw distance that is far
    #: field), else None
    pixel_firetimes: tuple[np.ndarray[Any, Any], int] | None = dataclasses.field(
        default=None, compare=False, repr=False)

    @functools.cached_property
    def first_channel_ns(self) -> int:
        """Firing time of the earliest channel relative to its firing's start (ns)."""
        return int(round(min(self.fmt.channel_ns)))

    @functools.cached_property
    def firings(self) -> int:
        """Firings per packet."""
        return self.fmt.blocks // self.returns

    @functools.cached_property
    def block_start_ns(self) -> np.ndarray[Any, Any]:
        """(firings,) int64 start of each firing of a packet relative to its t0 (ns)."""
        return self.fmt.block_start_ns(np.arange(self.firings), self.firings)

    @functools.cached_property
    def channels(self) -> tuple[list[tuple[str, str]], dict[str, Any]]:
        """(range, intensity) names of each block of a firing; the scan's channel dtypes in
        channel order."""
        names = _channel_names(_block_kinds(self.fmt, self.mode))
        specs = {name: np.uint16 if k == 0 else np.uint8 for pair in names
                 for k, name in enumerate(pair)}
        if self.fmt.pixel_tables or self.pixel_firetimes is not None:
            specs["t"] = np.int32
        return names, {k: specs[k] for k in sorted(specs, key=_channel_rank)}


#: validated LidarInfo dataclasses by geometry (calibration, format, mode, dis unit, rpm,
#: width, frame, options), reused under a new header stamp (they are frozen and read-only)
_INFO_TEMPLATES: dict[tuple[Any, ...], Any] = {}


def _restamped(info: Any, stamp: int) -> Any:
    """The LidarInfo dataclass ``info`` with header.stamp ``stamp`` (int ns)."""
    from lidarscan import types
    from lidarscan.stamps import split_ns
    sec, nanosec = split_ns(stamp)
    return dataclasses.replace(info, header=types.Header(types.Time(sec, nanosec),
                                                         info.header.frame_id))


_U16 = struct.Struct("<H")


class _OneFiring:
    """unpack_from() -> (azimuth, azimuth) for packets of one firing (e.g. 2 blocks, dual)."""

    @staticmethod
    def unpack_from(data: bytes, at: int) -> tuple[int, int]:
        az = _U16.unpack_from(data, at)[0]
        return az, az


def _first_last(last_firing_at: int) -> Any:
    """A struct reading the azimuths of a packet's first and last firing (``unpack_from``)."""
    if last_firing_at == 0:
        return _OneFiring
    return struct.Struct(f"<H{last_firing_at - 2}xH")


@functools.lru_cache(maxsize=64)
def _date_seconds(date: bytes) -> int:
    """POSIX seconds of a tail date-time (year - 1900, month, day, hour, minute, second; UTC).

    A year byte below 70 (before 1970 if counted from 1900) is counted from 2000, as the
    Pandar64 manual's tail table states it ("current year minus 2000"; its recording, like
    every other model's manual, counts from 1900)."""
    y, mo, d, h, mi, s = date
    if not (1 <= mo <= 12 and 1 <= d <= 31 and h < 24 and mi < 60 and s < 61):
        raise DecodeError("hesai tail date-time", list(date),
                          "year-1900, month 1..12, day 1..31, hour < 24, minute < 60, second")
    return calendar.timegm(((2000 if y < 70 else 1900) + y, mo, d, h, mi, s, 0, 0, 0))


@functools.lru_cache(maxsize=None)
def _packet_dtype(fmt: HesaiFormat, size: int) -> np.dtype[Any]:
    """Structured dtype of one payload row of ``size`` bytes: blocks (azimuth, units), tail."""
    unit = np.dtype({"names": ["d", "r"], "formats": ["<u2", "u1"], "offsets": [0, 2],
                     "itemsize": fmt.unit_size})
    block = np.dtype({"names": ["az", "u"], "formats": ["<u2", (unit, (fmt.lasers,))],
                      "offsets": [fmt.azimuth_at, fmt.azimuth_at + 2],
                      "itemsize": fmt.block_size})
    names, formats = ["b", "us", "date"], [(block, (fmt.blocks,)), "<u4", ("u1", (6,))]
    offsets = [fmt.body, fmt.timestamp_at, fmt.datetime_at]
    if fmt.mode_flag_at is not None:
        names, formats, offsets = names + ["flag"], formats + ["u1"], offsets + [fmt.mode_flag_at]
    if fmt.state_at is not None:            # 128 series: the tail's azimuth state (u16)
        names, formats, offsets = (names + ["azimuth_state"], formats + ["<u2"],
                                   offsets + [fmt.state_at - 2])
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": size})


def _firing_states(fmt: HesaiFormat, returns: int, recs: list[np.ndarray[Any, Any]]
                   ) -> np.ndarray[Any, Any]:
    """(F,) index into ``fmt.pixel_tables`` of every buffered firing (PandarQT128: loop 1 = 0,
    loop 2 = 1; single return: block 1 loop 1, block 2 loop 2; dual: the tail's mode flag,
    bit 0 set = loop 1)."""
    flags = np.concatenate([rec["flag"] for rec in recs]).astype(np.int64)
    if returns == 1:
        return np.tile(np.arange(fmt.blocks) % 2, flags.size)
    return np.where(flags & 1, 0, 1)


def _pixel_times(fmt: HesaiFormat, states: np.ndarray[Any, Any], order: np.ndarray[Any, Any],
                 out: np.ndarray[Any, Any]) -> None:
    """Write the per-pixel delays (ns after the column's time) of firings ``states`` (C,) into
    the first C columns of ``out`` (H, W) int32, rows in ``order`` (laser index of each row);
    channels that do not fire in a firing get 0."""
    table = np.asarray(fmt.pixel_tables, np.int32)[:, order]        # (states, H)
    out[:, :states.size] = np.maximum(table[states].T, 0)


def _azimuth_states(stream: _Stream, recs: list[np.ndarray[Any, Any]]
                    ) -> np.ndarray[Any, Any]:
    """(F,) azimuth state (0..3) of every buffered firing of a 128-series stream: the tail's
    azimuth state bits of the block holding the firing's ``range`` return (bits 15:14 block
    1, 13:12 block 2)."""
    names, _ = stream.channels
    primary = names.index(("range", "intensity"))
    blocks = np.arange(stream.firings) * stream.returns + primary
    states = np.concatenate([rec["azimuth_state"] for rec in recs]).astype(np.int64)
    return ((states[:, None] >> (14 - 2 * blocks)[None, :]) & 3).reshape(-1)


def _firetime_pixels(stream: _Stream, flags: np.ndarray[Any, Any], ranges: np.ndarray[Any, Any],
                     out: np.ndarray[Any, Any]) -> None:
    """Write the per-pixel firing times of a 128-series rotation with a firetime file into the
    first C columns of ``out`` (H, W) int32: the delay after its block's start of each row's
    channel in each column's azimuth state ``flags`` (C,), the near-field one where the
    ``ranges`` (H, W) uint16 raw distance is nearer than the file's near/far distance (a
    no-return pixel, raw 0, counts as near)."""
    assert stream.pixel_firetimes is not None
    table, first_far = stream.pixel_firetimes
    c = flags.size
    column = (ranges[:, :c] < first_far).view(np.uint8) + (2 * flags).astype(np.uint8)
    out[:, :c] = np.take_along_axis(table, column, axis=1)


def first_far_raw(near_m: float, dis_unit_m: float) -> int:
    """The smallest raw distance ``r`` with ``r * dis_unit_m >= near_m`` (float64, as the
    module docstring's rule "near: distance < near_m" computes it), at most 65536."""
    r = max(0, math.ceil(near_m / dis_unit_m) - 2)
    while r * dis_unit_m < near_m and r < 65536:
        r += 1
    return r


def _records(rows: np.ndarray[Any, Any], fmt: HesaiFormat) -> np.ndarray[Any, Any]:
    """(P,) structured zero-copy view of payload rows (P, size) uint8 (contiguous rows)."""
    return rows.view(_packet_dtype(fmt, rows.shape[1]))[:, 0]


def _units(pieces: list[tuple[np.ndarray[Any, Any], int, int, int]], stream: _Stream,
           rows: np.ndarray[Any, Any],
           grids: list[tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]]) -> None:
    """Distances and reflectivities of one rotation, read from blocks of payload rows.

    ``pieces``: (payload rows (P, size) uint8, first firing in them, firing count, first
    column). ``grids[r]``: the (L, W) uint16 distance and uint8 reflectivity grids of block r of
    a firing, zero-filled; laser index l goes to row ``rows[l]``, the columns of the pieces are
    written. The compiled kernel of :mod:`converters._kernels.hesai` when available, else
    :func:`_units_numpy` (the reference).
    """
    fill = _kernel()
    if fill is None:
        _units_numpy(pieces, stream, rows, grids)
        return
    fmt = stream.fmt
    returns, firings = stream.returns, stream.firings
    width = grids[0][0].shape[1]
    rowbase = rows.astype(np.uint64) * np.uint64(width)
    flat = [(dist.reshape(-1), refl.reshape(-1)) for dist, refl in grids]
    base = fmt.body + fmt.azimuth_at + 2
    for payloads, first, count, col in pieces:
        src, stride = _flat_rows(payloads)
        for r, (dist, refl) in enumerate(flat):
            fill(src, stride, first, count, col, base, fmt.block_size, fmt.unit_size, returns,
                 r, firings, rowbase, dist, refl)


def _flat_rows(rows: np.ndarray[Any, Any]) -> tuple[np.ndarray[Any, Any], int]:
    """(1-D uint8 view from the first byte of row 0 to the last byte of the last row, row
    stride) of payload rows (P, size) whose rows are contiguous (no copy)."""
    n, size = rows.shape
    stride = rows.strides[0]
    if n > 1 and stride < size:
        rows = np.ascontiguousarray(rows)
        stride = size
    span = (n - 1) * stride + size if n else 0
    return np.lib.stride_tricks.as_strided(rows, shape=(span,), strides=(1,),
                                           writeable=False), int(stride)


def _units_numpy(pieces: list[tuple[np.ndarray[Any, Any], int, int, int]], stream: _Stream,
                 rows: np.ndarray[Any, Any],
                 grids: list[tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]]) -> None:
    """The numpy reference of :func:`_units`: strided structured views of the rows, copied
    firing-major, transposed and put in row order."""
    fmt = stream.fmt
    returns, firings = stream.returns, stream.firings
    order = np.argsort(rows)                  # laser index of each row
    for payloads, first, count, col in pieces:
        k0, k1 = first // firings, -(-(first + count) // firings)
        skip = first - k0 * firings
        units = _records(payloads[k0:k1], fmt)["b"]["u"]            # (k, blocks, L)
        for k, name in enumerate(("d", "r")):
            values = units[name].reshape(k1 - k0, firings, returns, fmt.lasers)
            for r in range(returns):
                part = np.ascontiguousarray(values[:, :, r].transpose(2, 0, 1))
                part = part.reshape(fmt.lasers, -1)[order, skip:skip + count]
                grids[r][k][:, col:col + count] = part


_KERNEL: Any = False


def _kernel() -> Any:
    """The compiled units kernel, or None (no numba, or LIDARSCAN_NUMBA=0)."""
    global _KERNEL
    if _KERNEL is False:
        from converters._kernels import select
        _KERNEL = select("hesai").numba
    return _KERNEL
