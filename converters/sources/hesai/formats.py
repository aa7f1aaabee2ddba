"""Hesai point-cloud packet formats: byte layouts, firing-time tables, detection, calibration.

The tables and helpers behind :mod:`converters.sources.hesai.decoder` (which re-exports the public names
``FORMATS``, ``RETURN_MODES``, ``HesaiFormat``, ``detect_format`` and ``load_calibration``;
import them from there). Formats, return modes and conventions: the module docstring of
:mod:`converters.sources.hesai.decoder`.

Layouts (manuals, chapter "Data Structure" / "Point Cloud Data Packet"): pre-header 0xEE 0xFF,
protocol major, minor, 2 reserved; header laser num, block num, first block return, dis unit,
return num, flags. PandarXT (6.1): blocks of azimuth u16 (0.01 deg) + 4-byte units (distance
u16, reflectivity, reserved); tail 10 reserved, return mode, motor speed u16, date-time (year -
1900, month, day, hour, minute, second), timestamp u32 us, factory info; UDP sequence u32.
PandarQT128 (3.2) and Pandar128E3X/E4X/OT128 (1.4): the Flags byte says which optional parts
are present (bit 0 UDP sequence, 1 IMU, 2 functional safety, 3 digital signature, 4 a confidence
byte after each unit's reflectivity: 4-byte instead of 3-byte units); body = 2 blocks + CRC u32;
functional safety 17 bytes; tail: QT128 5 reserved, mode flag, 6 reserved; 128 series 9
reserved, azimuth state u16, operational state; then both: return mode, motor speed, date-time,
timestamp, factory info, UDP sequence, (128: IMU 22 bytes), CRC u32; then the 32-byte signature.
No "fine azimuth" byte exists in these formats (that is the AT128's, not decoded here).
Pandar128 (protocol 1.3, older firmware; its user manual, 3.2.2 "UDP Data"): 12-byte header
whose last byte only says whether the UDP sequence is sent; body = 2 blocks of an azimuth and
128 3-byte units, no CRC; 24-byte tail: 6 reserved, high-temperature flag, 3 reserved, motor
speed, timestamp, return mode, factory, date-time; then the UDP sequence. No operational or
azimuth state, so no firetime table applies (its timing: ``_pandar128_v13``).

Sources of the timing tables: Pandar40P, its manual's Table II.4 (time of each laser before its
block's end) and block end times; Pandar64, its manual's block end times (t0 - 42.58 us - 55.56 us
per later firing) and per-laser formula (1.304 / 1.968 us steps before the end, checked for the
lasers the public excerpt lists), the full 64-entry table as tabulated in the Nebula driver;
PandarXT32 (5.632 us - 50 us per later firing, then 0.368 us + 1.512 us per channel) and
PandarQT64 (25.71 us + 166.67 us per firing, then its 64-entry table) as tabulated in Nebula
(one QT64 entry there, 12960 ns for channel 56, is a typo of the 129600 its 2.06 us step gives).
PandarXT16: the XT block times, 0.368 us + 3.024 us per channel; PandarXT32M: the XT block
times, channels 1-16 and 17-32 fired in pairs, 0.368 us + 2.888 us per pair (as tabulated in
Nebula). PandarQT128 and the 128 series fire a channel at a time that changes from firing to
firing, which per-beam ``beam_time_offsets`` cannot express; for these models they are 0 and
``column_time_offsets`` are the firings' start times (QT128: t0 + 9 us - 111.11 us per later
firing; 128 series: see below). The QT128 has two firing loops with different channel
sets and delays (``_QT128_LOOPS``; single return: block 1 loop 1, block 2 loop 2; dual: the
tail's mode flag): its scans carry an extra channel ``t`` (INT32 ns, the delay of each pixel's
channel after its column's time, 0 where the channel does not fire), so a pixel's time is
``stamp + column_time_offsets[c] + beam_time_offsets[u] + t[u, c]`` (the msgs README's "a
sensor with irregular pixel timing can add a ``t`` channel"; ``Projector.pixel_times`` and
the PointCloud2 time fields add it).

128 series (protocol 1.4), from the Pandar128E3X user manual (doc version 128-en-240310),
appendix "Absolute Time and Laser Firing Time": the tail's Operational State byte sets the
horizontal resolution (its values, from the Pandar128 manual's Tail table: 0 high performance =
high resolution, 1 shutdown, 2 standard, 3 energy saving). "Start Time of Each Block": single
return, block 2 starts at t0 + 3.148 us and block 1 at t0 + 3.148 - 27.778 us (high resolution)
or t0 + 3.148 - 2 * 27.778 us (standard); dual return, both blocks at t0 + 3.148 us. So the
firing period, ``column_time_increment`` and the width are 27.778 us and twice the columns in
high resolution mode, 55.556 us otherwise. Where the manual is silent, this module states its
choice: energy saving and shutdown are timed as standard (the manual's block table has only the
two resolutions, and energy saving has standard's azimuth-flag range 0..1); dual-return packets
in high resolution mode are counted at the high-resolution period (a rotation with more firings
than the width is still never cut: it gets a wider info version); another state byte raises a
DecodeError. A state change starts a new LidarInfo version. "Firing Time Offset of Each Channel"
(same appendix, from printed page 100 on; the Pandar128 manual's "Laser Firing Time of Each
Channel", from page 76 on, has the same values where both could be read): a channel fires
``dt(n)`` ns after its block's start, looked up per channel in a table by operational state
(high performance; standard or energy saving), the block's azimuth flag (tail, bits 15:14 block
1, 13:12 block 2; 0-3 in high performance, 0-1 otherwise) and far/near-field firing (distance >
2.85 m or not). So a pixel's delay depends on its firing (flag) and its own distance, which
neither ``beam_time_offsets`` nor a per-firing table can express; only a per-pixel ``t`` channel
could. Only the rows of channels 41-51 of that table could be read in the manual (the stored copies
of its pages are cut after ~12 rows); they show delays of 7.7-27.4 us in high performance mode
and 12.7-55.2 us in standard mode, the flags shifting them by 0.35-0.7 us and near-field firing
by up to 16.7 us, and equal the same rows of the vendor's "Firetime Correction File" for the
Pandar128E3X (Hesai's SDK, HesaiLidar_SDK_2.0, ``correction/firetime_correction``), which holds
the whole table. Since the packet does not say whether it is a 128E3X or a 128E4X/OT128
(whose tables are not the same), the table is not built in: given the sensor's firetime file
(:func:`load_firetimes`), each pixel gets its time in a ``t`` channel (:mod:`converters.sources.hesai.decoder`,
"Firetime files"); without it, ``beam_time_offsets`` are 0 and a pixel's time is its block's
start, early by up to the firing period (55.6 us). The OT128 (128E4X) manual was not available
either: its block times are taken to be the 128E3X's (same protocol 1.4 packet).
``vendor_metadata``'s ``channel_timing`` and ``operational_state`` say which case a scan is.

Firetime files (vendor data; the SDK's files and the manual's tables, read to learn the
format): per-channel files ``Channel,fire time(us)`` (Pandar40P, Pandar64: negative times
before the block's end, equal to the built-in tables; PandarXT/XT-16/XT-32M2X: after the
firing's nominal time, the built-in table + 5.632 us; PandarQT: the built-in table - 10 us);
the Pandar128E3X table (integer ns after the block's start per operational state 0/2/3,
azimuth state and far/near field: ``distance>=A1`` / ``distance<A1``, A1 = the section distance
in metres in the first cell, 2.85; the SDK's parser picks column (state, azimuth state) and
far/near the same way); the OT128 table (``Operational State`` 0/2 and ``Azimuth State``
lines, microseconds after the block's start, ``-`` = not fired, no near/far). In high
performance mode each azimuth state fires 96 of the 128 channels (the file's 0 or ``-``
elsewhere).

Dual-return block order (what blocks 1 and 2 of a firing hold): Pandar40P and Pandar64 0x39: last,
strongest (manuals; confirmed on the Pandar64 recording: block 1 is never nearer than block 2);
PandarXT32 0x39: strongest, last (its recording: block 2 is never nearer, and it is the stronger
one where the two differ in distance, i.e. the "last = strongest, second strongest in the other
block" case; the manual's text says the opposite); PandarQT64 0x3B: first, last (its
recording). PandarXT16, PandarXT32M, PandarQT128, Pandar128E3X/E4X: the header table's "First
Block Return" (block 1 holds the last return in 0x39 and 0x3B, the first in 0x3C): 0x39 last,
strongest; 0x3B last, first; 0x3C first, strongest (0x39 confirmed on the XT16 and QT128
recordings, 0x3C on the XT32M one: block 1 is never farther). Triple return 0x3D (PandarXT32M
only, 6 blocks = 2 firings of 3 blocks): first, last, strongest, as the mode's name orders them
(not confirmed on a recording). Other multi-return modes of a model raise a DecodeError naming
the byte. Single modes (0x33 first, 0x37 strongest, 0x38 last) are accepted for every model.
"""

from __future__ import annotations

import dataclasses
import functools
import io
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lidarscan.errors import DecodeError

#: Return-mode byte of the packet tail -> the returns it reports.
RETURN_MODES: dict[int, tuple[str, ...]] = {
    0x33: ("first",),
    0x37: ("strongest",),
    0x38: ("last",),
    0x39: ("last", "strongest"),
    0x3B: ("first", "last"),
    0x3C: ("first", "strongest"),
    0x3D: ("first", "last", "strongest"),
}

# Firing-time tables (ns; sources in the module docstring). Pandar40P: time of each laser id
# 1..40 before its block's end. Pandar64: the same per laser index (1.304 / 1.968 us steps from
# 3.62 us). PandarQT64: per channel after the block's start (2.04-2.06 us apart, 2.44-3.05 us
# between groups of 8 or 16). PandarXT32: 0.368 us + 1.512 us * channel index (in HesaiFormat).
_P40P_BEFORE_END_US = {
    4: 3.62, 40: 3.62, 36: 4.92, 28: 6.23, 12: 8.19, 16: 8.19, 32: 9.5, 24: 11.47, 29: 12.77,
    17: 14.74, 3: 16.04, 39: 16.04, 35: 17.35, 25: 18.65, 9: 20.62, 13: 20.62, 31: 21.92,
    21: 23.89, 26: 25.19, 14: 27.16, 2: 28.47, 38: 28.47, 34: 29.77, 6: 31.74, 22: 31.74,
    10: 33.71, 30: 35.01, 18: 36.98, 23: 38.95, 11: 40.91, 1: 42.22, 37: 42.22, 33: 43.52,
    5: 45.49, 19: 45.49, 7: 47.46, 27: 48.76, 15: 50.73, 20: 52.7, 8: 54.67,
}
_P64_BEFORE_END_NS = (
    23180, 21876, 20572, 19268, 17964, 16660, 11444, 46796, 7532, 36956, 50732, 54668, 40892,
    44828, 31052, 34988, 48764, 52700, 38924, 42860, 29084, 33020, 46796, 25148, 36956, 50732,
    27116, 40892, 44828, 31052, 34988, 48764, 25148, 38924, 42860, 29084, 33020, 52700, 6228,
    54668, 15356, 27116, 10140, 23180, 4924, 21876, 14052, 17964, 8836, 19268, 3620, 20572,
    12748, 16660, 7532, 11444, 6228, 15356, 10140, 4924, 3620, 14052, 8836, 12748,
)
# QT64: 16 channels per group, 2.05-2.06 us apart, groups 2.45 / 3.05 us apart.
_QT64_AFTER_START_NS = (
    12310, 14370, 16430, 18490, 20540, 22600, 24660, 26710, 29160, 31220, 33280, 35340, 37390,
    39450, 41500, 43560, 46610, 48670, 50730, 52780, 54840, 56900, 58950, 61010, 63450, 65520,
    67580, 69630, 71690, 73740, 75800, 77860, 80900, 82970, 85020, 87080, 89140, 91190, 93250,
    95300, 97750, 99820, 101870, 103930, 105980, 108040, 110100, 112150, 115200, 117260,
    119320, 121380, 123430, 125490, 127540, 129600, 132050, 134110, 136170, 138220, 140280,
    142340, 144390, 146450,
)

# PandarQT128 firing loops (delay of each channel after its firing's trigger, ns; -1: the
# channel does not fire in that loop: channels 1-32 in loop 1, 33-64 in loop 2), as tabulated in
# Nebula. Loop of a firing: single return, block 1 loop 1 and block 2 loop 2; dual return, the
# tail's mode flag (bit 0 set: loop 1). Confirmed on the QT128 recording: in packets of mode
# flag 0 channels 33-64 never return, with flag 1 channels 1-32 never do.
_QT128_LOOPS = (
    (-1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1,
     -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, 27656, 53000, 2312, 78344, 81512, 5480,
     56168, 30824, 33992, 59336, 8648, 84680, 87848, 11816, 62504, 37160, 40328, 65672,
     14984, 91016, 94184, 18152, 68840, 43496, 46664, 72008, 21320, 97352, 100520, 24488,
     75176, 49832, 1456, 77488, 26800, 52144, 55312, 29968, 80656, 4624, 7792, 83824,
     33136, 58480, 61648, 36304, 86992, 10960, 14128, 90160, 39472, 64816, 67984, 42640,
     93328, 17296, 20464, 96496, 45808, 71152, 74320, 48976, 99664, 23632, 25944, 51288,
     600, 76632, 79800, 3768, 54456, 29112, 32280, 57624, 6936, 82968, 86136, 10104,
     60792, 35448, 38616, 63960, 13272, 89304, 92472, 16440, 67128, 41784, 44952, 70296,
     19608, 95640, 98808, 22776, 73464, 48120),
    (2312, 78344, 27656, 53000, 56168, 30824, 81512, 5480, 8648, 84680, 33992, 59336, 62504,
     37160, 87848, 11816, 14984, 91016, 40328, 65672, 68840, 43496, 94184, 18152, 21320,
     97352, 46664, 72008, 75176, 49832, 100520, 24488, -1, -1, -1, -1, -1, -1, -1, -1, -1,
     -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1,
     -1, -1, 600, 76632, 25944, 51288, 54456, 29112, 79800, 3768, 6936, 82968, 32280,
     57624, 60792, 35448, 86136, 10104, 13272, 89304, 38616, 63960, 67128, 41784, 92472,
     16440, 19608, 95640, 44952, 70296, 73464, 48120, 98808, 22776, 26800, 52144, 1456,
     77488, 80656, 4624, 55312, 29968, 33136, 58480, 7792, 83824, 86992, 10960, 61648,
     36304, 39472, 64816, 14128, 90160, 93328, 17296, 67984, 42640, 45808, 71152, 20464,
     96496, 99664, 23632, 74320, 48976),
)


@dataclass(frozen=True)
class HesaiFormat:
    """Byte layout and timing of one packet format (offsets in bytes from the payload start).

    Block ``b`` starts at ``body + b * block_size``; its azimuth (uint16 LE, 0.01 deg) sits at
    ``azimuth_at`` inside the block and channel ``l``'s unit (distance uint16 LE, reflectivity
    uint8, then ``unit_size - 3`` other bytes) at ``azimuth_at + 2 + l * unit_size``. Tail
    fields are at fixed offsets. Timing: firing ``k`` (of ``firings`` per packet) starts at
    ``t0 + block_base_ns + firing_period_ns * (k - block_ref)`` where ``block_ref`` is 0 or the
    last firing, and channel ``l`` fires ``channel_ns[l]`` after that.
    """

    model: str
    lasers: int
    blocks: int
    body: int
    block_size: int
    azimuth_at: int
    unit_size: int
    size: int                 # payload without the optional 4-byte UDP sequence number
    return_mode_at: int
    motor_speed_at: int
    timestamp_at: int
    datetime_at: int
    firing_period_ns: float
    block_base_ns: float
    block_ref_last: bool
    channel_ns: tuple[float, ...]
    dis_unit_at: int | None   # header byte holding the distance unit (mm), None: fixed 4 mm
    range_limits: tuple[float, float]
    dual_orders: tuple[tuple[int, tuple[str, ...]], ...]   # mode -> what blocks 1, 2(, 3) hold
    sizes: tuple[int, ...] = ()       # accepted payload sizes; () = (size, size + 4)
    channel_timing: str = "beam"      # "beam": channel_ns per beam; else how it is carried
    mode_flag_at: int | None = None   # QT128 tail mode flag (which firing loop a packet holds)
    #: per firing state (QT128: loop 1, loop 2): delay (ns) of each channel after the firing's
    #: trigger, -1 = the channel does not fire; () = channel_ns per beam
    pixel_tables: tuple[tuple[int, ...], ...] = ()
    #: tail byte of the operational state (128 series: 0 high performance = high resolution,
    #: 1 shutdown, 2 standard, 3 energy saving), None: the format has none
    state_at: int | None = None

    def block_start_ns(self, firing: np.ndarray[Any, Any], firings: int) -> np.ndarray[Any, Any]:
        """Start of each firing (index ``firing`` of ``firings`` per packet) relative to t0."""
        ref = firings - 1 if self.block_ref_last else 0
        return np.rint(self.block_base_ns
                       + self.firing_period_ns * (np.asarray(firing) - ref)).astype(np.int64)


def _p40p_channels() -> tuple[float, ...]:
    return tuple(-1000.0 * _P40P_BEFORE_END_US[k] for k in range(1, 41))


FORMATS: dict[str, HesaiFormat] = {
    "Pandar40P": HesaiFormat(
        model="Pandar40P", lasers=40, blocks=10, body=0, block_size=124, azimuth_at=2,
        unit_size=3, size=1262, return_mode_at=1240 + 14, motor_speed_at=1240 + 8,
        timestamp_at=1240 + 10, datetime_at=1240 + 16, firing_period_ns=55560.0,
        block_base_ns=-28580.0, block_ref_last=True, channel_ns=_p40p_channels(),
        dis_unit_at=None, range_limits=(0.3, 200.0),
        dual_orders=((0x39, ("last", "strongest")),)),
    "Pandar64": HesaiFormat(
        model="Pandar64", lasers=64, blocks=6, body=8, block_size=194, azimuth_at=0,
        unit_size=3, size=1194, return_mode_at=1172 + 14, motor_speed_at=1172 + 8,
        timestamp_at=1172 + 10, datetime_at=1172 + 16, firing_period_ns=55560.0,
        block_base_ns=-42580.0, block_ref_last=True,
        channel_ns=tuple(-float(v) for v in _P64_BEFORE_END_NS), dis_unit_at=5,
        range_limits=(0.3, 200.0), dual_orders=((0x39, ("last", "strongest")),)),
    "PandarXT32": HesaiFormat(
        model="PandarXT32", lasers=32, blocks=8, body=12, block_size=130, azimuth_at=0,
        unit_size=4, size=1076, return_mode_at=1052 + 10, motor_speed_at=1052 + 11,
        timestamp_at=1052 + 19, datetime_at=1052 + 13, firing_period_ns=50000.0,
        block_base_ns=5632.0, block_ref_last=True,
        channel_ns=tuple(368.0 + 1512.0 * k for k in range(32)), dis_unit_at=9,
        range_limits=(0.05, 120.0), dual_orders=((0x39, ("strongest", "last")),)),
    "PandarQT64": HesaiFormat(
        model="PandarQT64", lasers=64, blocks=4, body=12, block_size=258, azimuth_at=0,
        unit_size=4, size=1068, return_mode_at=1044 + 16, motor_speed_at=1044 + 10,
        timestamp_at=1044 + 12, datetime_at=1044 + 18, firing_period_ns=500000.0 / 3.0,
        block_base_ns=25710.0, block_ref_last=False,
        channel_ns=tuple(float(v) for v in _QT64_AFTER_START_NS), dis_unit_at=9,
        range_limits=(0.1, 60.0), dual_orders=((0x3B, ("first", "last")),)),
}

#: dual/triple block orders of the formats with a 12-byte header ("First Block Return" field
#: of the manuals' header tables: block 1 holds the last return in modes 0x39 and 0x3B, the
#: first in 0x3C; 0x39 and 0x3C confirmed on the XT16, XT32M and QT128 recordings)
_ORDERS_12B = ((0x39, ("last", "strongest")), (0x3B, ("last", "first")),
               (0x3C, ("first", "strongest")))
_PER_PIXEL = ("per pixel: channel 't' (INT32 ns) = the pixel's firing time after its column's "
              "time (the firing's trigger); beam_time_offsets are 0")
_NOT_PER_BEAM = ("not applied: the firing time of a channel changes from firing to firing "
                 "({}), which per-beam LidarInfo.beam_time_offsets cannot express; column "
                 "times are the firings' trigger times and beam_time_offsets are 0")


def _xt_format(model: str, lasers: int, blocks: int, channel_ns: tuple[float, ...],
               limits: tuple[float, float], orders: tuple[tuple[int, tuple[str, ...]], ...]
               ) -> HesaiFormat:
    """A PandarXT-family format (protocol 6.1): 12-byte header, blocks of an azimuth and
    4-byte units, 24-byte tail (+ optional 4-byte UDP sequence); firing k of a packet starts
    at t0 + 5.632 us - 50 us per later firing (PandarXT manuals, Appendix "Absolute Time and
    Laser Firing Time")."""
    tail = 12 + blocks * (2 + 4 * lasers)
    return HesaiFormat(
        model=model, lasers=lasers, blocks=blocks, body=12, block_size=2 + 4 * lasers,
        azimuth_at=0, unit_size=4, size=tail + 24, return_mode_at=tail + 10,
        motor_speed_at=tail + 11, timestamp_at=tail + 19, datetime_at=tail + 13,
        firing_period_ns=50000.0, block_base_ns=5632.0, block_ref_last=True,
        channel_ns=channel_ns, dis_unit_at=9, range_limits=limits, dual_orders=orders)


@functools.lru_cache(maxsize=None)
def _format_v1(model: str, major: int, lasers: int, blocks: int, flags: int) -> HesaiFormat:
    """Pandar128E3X/E4X/OT128 (protocol 1.4) and PandarQT128 (3.2): 12-byte header whose Flags
    byte says which optional parts the packet has (bit 0 UDP sequence, 1 IMU, 2 functional
    safety, 3 digital signature, 4 confidence byte per unit); body = blocks of an azimuth and
    3-byte (4 with confidence) units, then a 4-byte CRC; functional safety 17 bytes; tail:
    reserved, (128: azimuth state u16 at +9, operational state at +11; QT128: mode flag at
    +5), return mode +12, motor speed +13, date-time +15, timestamp +21, factory +25, UDP
    sequence (4), IMU (22), CRC (4); signature (32)."""
    unit = 4 if flags & 0x10 else 3
    block_size = 2 + unit * lasers
    tail = 12 + blocks * block_size + 4 + (17 if flags & 0x04 else 0)
    size = (tail + 26 + (4 if flags & 0x01 else 0) + (22 if flags & 0x02 else 0) + 4
            + (32 if flags & 0x08 else 0))
    extra: dict[str, Any] = {}
    if major == 3:       # QT128: 2 firings of 111.11 us, last one triggered at t0 + 9 us
        period, base = 111110.0, 9000.0
        limits = (0.05, 50.0)
        extra = dict(mode_flag_at=tail + 5, pixel_tables=_QT128_LOOPS,
                     channel_timing=_PER_PIXEL)
    else:                # 128E3X/E4X: block 2 (or both, dual) starts at t0 + 3.148 us; block
        # 1 one firing period earlier: 55.556 us in standard mode (this format), 27.778 us in
        # high resolution mode (hires_format)
        period, base = 55556.0, 3148.0
        why = ("the tail's operational state, the block's azimuth flag and near/far-field "
               "firing (distance <= 2.85 m); the packet does not tell 128E3X and 128E4X apart")
        limits = (0.1, 230.0)
        extra = dict(channel_timing=_NOT_PER_BEAM.format(why), state_at=tail + 11)
    return HesaiFormat(
        model=model, lasers=lasers, blocks=blocks, body=12, block_size=block_size,
        azimuth_at=0, unit_size=unit, size=size, return_mode_at=tail + 12,
        motor_speed_at=tail + 13, timestamp_at=tail + 21, datetime_at=tail + 15,
        firing_period_ns=period, block_base_ns=base, block_ref_last=True,
        channel_ns=(0.0,) * lasers, dis_unit_at=9, range_limits=limits,
        dual_orders=_ORDERS_12B, sizes=(size,), **extra)


#: operational states of the 128 series (tail byte; the Pandar128 manual's Tail table)
OPERATIONAL_STATES = {0: "high resolution", 1: "shutdown", 2: "standard", 3: "energy saving"}
#: firing period (ns) of the 128 series in high resolution mode (Pandar128E3X manual, "Start
#: Time of Each Block": block 1 starts 27.778 us before block 2 in single return mode)
HIRES_PERIOD_NS = 27778.0


@functools.lru_cache(maxsize=None)
def hires_format(fmt: HesaiFormat) -> HesaiFormat:
    """The 128-series format ``fmt`` in high resolution mode (operational state 0): firings
    27.778 us apart instead of 55.556 us (twice the columns per rotation)."""
    return dataclasses.replace(fmt, firing_period_ns=HIRES_PERIOD_NS)


FORMATS["PandarXT16"] = _xt_format(
    "PandarXT16", 16, 8, tuple(368.0 + 3024.0 * k for k in range(16)), (0.05, 120.0),
    _ORDERS_12B)
# XT32M2X: channels 1-16 and 17-32 fire in pairs, 2.888 us apart; 6 blocks (triple: 2 firings)
FORMATS["PandarXT32M"] = _xt_format(
    "PandarXT32M", 32, 6, tuple(368.0 + 2888.0 * (k % 16) for k in range(32)), (0.5, 300.0),
    _ORDERS_12B + ((0x3D, ("first", "last", "strongest")),))



def _pandar128_v13() -> HesaiFormat:
    """The Pandar128's older firmware (protocol 1.3; the Pandar128 user manual, 3.2.2 "UDP
    Data" and Appendix II.1): 12-byte header (its last byte: UDP sequence on/off), body of 2
    blocks of an azimuth and 128 3-byte units (distance, reflectivity) = 772 bytes, no CRC;
    24-byte tail: 6 reserved, high-temperature flag, 3 reserved, motor speed u16 (+10),
    timestamp u32 (+12), return mode (+16), factory (+17), date-time (+18); then the optional
    4-byte UDP sequence. t0 is the trigger of block 2's firing (single return; both blocks'
    firing in dual return, block 1 last, block 2 strongest); block 1 fires one period earlier,
    55.556 us as the 128E3X's standard mode (the 1.3 manual's block-time table could not be
    read); its channel delays are not applied (no table)."""
    tail = 12 + 2 * (2 + 3 * 128)
    why = "the Pandar128 (protocol 1.3) manual's per-channel table could not be read"
    return HesaiFormat(
        model="Pandar128", lasers=128, blocks=2, body=12, block_size=2 + 3 * 128, azimuth_at=0,
        unit_size=3, size=tail + 24, return_mode_at=tail + 16, motor_speed_at=tail + 10,
        timestamp_at=tail + 12, datetime_at=tail + 18, firing_period_ns=55556.0,
        block_base_ns=0.0, block_ref_last=True, channel_ns=(0.0,) * 128, dis_unit_at=9,
        range_limits=(0.3, 200.0), dual_orders=((0x39, ("last", "strongest")),),
        channel_timing=_NOT_PER_BEAM.format(why))


FORMATS["Pandar128"] = _pandar128_v13()

_SUPPORTED = ("supported: Pandar40P, Pandar64, PandarXT16/XT32/XT32M (protocol 6.1), PandarQT64 "
              "(3.1), PandarQT128 (3.2), Pandar128E3X/E4X/OT128 (1.4), Pandar128 (1.3)")


def detect_format(packet: bytes) -> HesaiFormat:
    """The :class:`HesaiFormat` of one UDP payload, from its own header bytes and size.

    Raises:
        DecodeError: not a Hesai point-cloud packet, or a model this module does not decode.
    """
    n = len(packet)
    if n < 12:
        raise DecodeError("hesai packet size", n, "a Hesai point-cloud UDP payload (>= 1068 "
                          "bytes)")
    if packet[0] == 0xFF and packet[1] == 0xEE:
        fmt = FORMATS["Pandar40P"]
        if n not in (fmt.size, fmt.size + 4):
            raise DecodeError("hesai packet size", n, f"{fmt.size} or {fmt.size + 4} bytes for "
                              "a Pandar40P packet (block flag 0xFFEE)")
        flags = {bytes(packet[b * fmt.block_size:b * fmt.block_size + 2])
                 for b in range(fmt.blocks)}
        if flags != {b"\xff\xee"}:
            raise DecodeError("Pandar40P block flags", sorted(f.hex() for f in flags),
                              "0xFFEE at the start of each of the 10 blocks")
        return fmt
    if packet[0] != 0xEE or packet[1] != 0xFF:
        raise DecodeError("hesai pre-header", packet[:2].hex(), "0xEE 0xFF (Hesai point-cloud "
                          "packet) or 0xFF 0xEE (Pandar40P block flag)")
    if packet[2] == 64 and packet[3] == 6:        # Pandar64: 8-byte header, laser num first
        fmt = FORMATS["Pandar64"]
    else:
        major, minor, lasers, blocks, flags = (packet[2], packet[3], packet[6], packet[7],
                                               packet[11])
        key = (major, minor, lasers, blocks)
        model = _MODELS_12B.get(key)
        if model is None:
            names = {(6, 1): "PandarXT (6.1): 16 or 32 lasers, 8 blocks; 32 lasers, 6 blocks",
                     (3, 1): "PandarQT64 (3.1): 64 lasers, 4 blocks",
                     (3, 2): "PandarQT128 (3.2): 128 lasers, 2 blocks",
                     (1, 4): "Pandar128E3X/E4X/OT128 (1.4): 128 lasers, 2 blocks",
                     (1, 3): "Pandar128 (1.3): 128 lasers, 2 blocks"}
            expected = names.get((major, minor))
            raise DecodeError("hesai header (protocol major.minor, laser num, block num)",
                              f"{major}.{minor}, {lasers}, {blocks}",
                              expected or f"a known protocol version ({_SUPPORTED})")
        if model in FORMATS:
            fmt = FORMATS[model]
        else:
            if flags & 0xE0:
                raise DecodeError(f"{model} header flags", hex(flags), "bits 7..5 clear (bits "
                                  "4..0: confidence, signature, functional safety, IMU, UDP "
                                  "sequence)")
            fmt = _format_v1(model, major, lasers, blocks, flags)
    sizes = fmt.sizes or (fmt.size, fmt.size + 4)
    if n not in sizes:
        raise DecodeError("hesai packet size", n, " or ".join(map(str, sizes))
                          + f" bytes for a {fmt.model} packet" + (
                              f" with header flags {packet[11]:#04x}" if fmt.sizes else
                          f" (header {packet[2]}.{packet[3]}, 128, 2)" if fmt.model ==
                          "Pandar128" else ""))
    return fmt


#: (protocol major, minor, laser num, block num) of the 12-byte header -> model
_MODELS_12B = {(6, 1, 32, 8): "PandarXT32", (6, 1, 16, 8): "PandarXT16",
               (6, 1, 32, 6): "PandarXT32M", (3, 1, 64, 4): "PandarQT64",
               (3, 2, 128, 2): "PandarQT128", (1, 4, 128, 2): "Pandar128E3X/E4X",
               (1, 3, 128, 2): "Pandar128"}


# ------------------------------------------------------------------------------- calibration

@dataclass(frozen=True)
class _Calibration:
    laser_ids: np.ndarray[Any, Any]     # (L,) int, 1-based, ascending
    elevation_deg: np.ndarray[Any, Any]
    azimuth_deg: np.ndarray[Any, Any]
    text: str

    @property
    def order(self) -> np.ndarray[Any, Any]:
        """(L,) laser index of each row: highest elevation first, ties by laser id."""
        return np.lexsort((self.laser_ids, -self.elevation_deg))


def load_calibration(calib: Any) -> _Calibration:
    """Parse a Hesai angle-correction CSV (``Laser id,Elevation,Azimuth``, degrees).

    Args:
        calib: a path, the CSV text (str or UTF-8 bytes containing a newline), a mapping
            ``{laser_id: (elevation_deg, azimuth_deg)}`` or an already parsed calibration.
            Lines whose first cell is not a number (headers such as ``Laser id,...`` or
            ``Channel,...``, comments) are skipped; cells may be quoted, lines may end in
            CRLF, a UTF-8 byte-order mark is ignored, columns after the third are ignored.

    Returns:
        the parsed calibration, lasers in ascending id order (ids must be 1..L).

    Raises:
        DecodeError: unreadable file, malformed rows, ids not 1..L, non-finite angles.
    """
    if isinstance(calib, _Calibration):
        return calib
    rows: list[tuple[int, float, float]] = []
    if isinstance(calib, Mapping):
        try:
            rows = [(int(k), float(v[0]), float(v[1])) for k, v in calib.items()]
        except (TypeError, ValueError, IndexError) as err:
            raise DecodeError("calibration", calib, "{laser_id: (elevation_deg, azimuth_deg)}"
                              ) from err
        text = ""
    else:
        text = _read_text(calib, "calibration",
                          "Hesai angle-correction CSV (Laser id,Elevation,Azimuth)",
                          "a path, the CSV text (str or bytes), a mapping or a parsed calibration")
        for i, line in enumerate(io.StringIO(text)):
            cells = _cells(line)
            if not cells or not cells[0] or not (cells[0][0].isdigit() or cells[0][0] == "-"):
                continue                      # header or blank line
            try:
                rows.append((int(cells[0]), float(cells[1]), float(cells[2])))
            except (ValueError, IndexError) as err:
                raise DecodeError(f"calibration line {i + 1}", line.strip(),
                                  "laser_id,elevation_deg,azimuth_deg") from err
    rows.sort()
    ids = np.array([r[0] for r in rows], np.int64)
    if ids.size == 0 or not np.array_equal(ids, np.arange(1, ids.size + 1)):
        raise DecodeError("calibration laser ids", ids.tolist()[:8], "each of 1..L exactly once")
    elev = np.array([r[1] for r in rows], np.float64)
    azim = np.array([r[2] for r in rows], np.float64)
    if not (np.all(np.isfinite(elev)) and np.all(np.isfinite(azim))):
        raise DecodeError("calibration angles", "non-finite", "finite degrees")
    return _Calibration(ids, elev, azim, text)


def _read_text(source: Any, field: str, what: str, accepts: str) -> str:
    """The text of a vendor CSV given as a path, or as text (str, or UTF-8 bytes containing a
    newline); a UTF-8 byte-order mark is dropped. ``accepts``: the caller's accepted forms, for
    the error on any other type."""
    if isinstance(source, (bytes, bytearray, memoryview)):
        source = bytes(source)
        if b"\n" in source:
            try:
                source = source.decode("utf-8-sig")
            except UnicodeDecodeError as err:
                raise DecodeError(field, source[:16], f"UTF-8 text of a {what}") from err
    if isinstance(source, str) and "\n" in source:
        return source.removeprefix("\ufeff")
    try:
        path = Path(os.fsdecode(source))
    except TypeError as err:
        raise DecodeError(field, type(source).__name__, accepts) from err
    try:
        return path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as err:
        raise DecodeError(field, str(path), f"a readable {what}") from err


def _block_kinds(fmt: HesaiFormat, mode: int) -> tuple[str, ...]:
    """What each block of a firing holds under return-mode byte ``mode``, in block order."""
    kinds = RETURN_MODES.get(mode)
    if kinds is None:
        raise DecodeError("hesai return mode byte", hex(mode),
                          "one of " + ", ".join(hex(m) for m in RETURN_MODES))
    if len(kinds) == 1:
        return kinds
    orders = dict(fmt.dual_orders)
    if mode not in orders:
        raise DecodeError(f"{fmt.model} return mode byte", hex(mode),
                          "a single-return mode or dual mode " + ", ".join(
                              hex(m) for m in orders) + " (the block order of this dual mode "
                          "is not confirmed for this model)")
    return orders[mode]


def _channel_names(kinds: tuple[str, ...]) -> list[tuple[str, str]]:
    """(range, intensity) channel names of each block of a firing, in block order.

    The strongest return (else the last) is ``range``/``intensity``; the other returns are
    ``range2``/``intensity2`` and (triple) ``range3``/``intensity3`` in block order.
    """
    if len(kinds) == 1:
        return [("range", "intensity")]
    primary = kinds.index("strongest") if "strongest" in kinds else kinds.index("last")
    others = iter(range(2, len(kinds) + 1))
    return [("range", "intensity") if r == primary else
            (f"range{(n := next(others))}", f"intensity{n}") for r in range(len(kinds))]


def _channel_rank(name: str) -> tuple[int, int]:
    """Channel order in the scan: range, intensity, range2, intensity2, range3, intensity3,
    then t."""
    if name == "t":
        return (9, 0)
    if name.startswith("range"):
        return (int(name[5:] or 1), 0)
    return (int(name[9:] or 1), 1)


# ------------------------------------------------------------------------ firetime files

@dataclass(frozen=True)
class Firetimes:
    """A Hesai "Firetime Correction File" (vendor data; formats: :func:`load_firetimes`).

    ``kind`` "channel": one firing time per channel, ``channel_ns`` (L,) float64 ns (relative to
    a reference the file does not state; only differences between channels are used).
    ``kind`` "state": ``table`` (S, 2, L) int64 ns after the block's start, per column state
    ``states[s]`` = (operational state, azimuth state), [far, near]; 0 also where a channel
    does not fire in that state; near = measured distance < ``near_m`` metres.
    """

    kind: str
    lasers: int
    channel_ns: np.ndarray[Any, Any] | None = None
    states: tuple[tuple[int, int], ...] = ()
    table: np.ndarray[Any, Any] | None = None
    near_m: float = 0.0
    text: str = ""

    def state_table(self, op_state: int) -> np.ndarray[Any, Any] | None:
        """(4, 2, L) int64 ns of operational state ``op_state`` by azimuth state 0..3 (zeros
        for azimuth states the file does not list), or None if the file has no column of it
        (energy saving and shutdown then use standard's columns, 2)."""
        assert self.table is not None
        for state in (op_state, 2) if op_state in (1, 3) else (op_state,):
            cols = [(az, s) for s, (op, az) in enumerate(self.states) if op == state]
            if cols:
                out = np.zeros((4, 2, self.lasers), np.int64)
                for az, s in cols:
                    if 0 <= az < 4:
                        out[az] = self.table[s]
                return out
        return None


def _cells(line: str) -> list[str]:
    return [c.strip().strip('"').strip() for c in line.strip().split(",")]


def _firetime_value(cell: str, where: str, unit_ns: float, allow_dash: bool,
                    allow_negative: bool) -> float:
    """One time cell in ns (``-``: the channel does not fire, 0)."""
    if allow_dash and cell == "-":
        return 0.0
    try:
        value = float(cell)
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or (value < 0 and not allow_negative):
        raise DecodeError(f"firetimes {where}", cell, "a finite firing time" + (
            "" if allow_negative else " >= 0") + (" or '-' (not fired)" if allow_dash else ""))
    return value * unit_ns


def load_firetimes(source: Any) -> Firetimes:
    """Parse a Hesai "Firetime Correction File" CSV (vendor data shipped with the sensor or
    in the vendor's SDK, directory ``correction/firetime_correction``).

    Three forms (the first line tells them apart):

    * one time per channel, header ``Channel,fire time(us)`` (or ``channel,firetime/us``):
      Pandar40P, Pandar64, PandarXT/XT-16/XT-32/XT-32M2X, PandarQT; rows ``channel,us``.
    * the Pandar128E3X table: line 1 the near/far section distance in metres then, per
      column, ``distance>=A1`` (far) or ``distance<A1`` (near); line 2 ``operation mode``
      and line 3 ``angle state`` per column; then one row per channel of integer ns after
      the block's start (0: the channel does not fire in that state).
    * the OT128 (Pandar128E4X) table: ``Operational State`` and ``Azimuth State`` lines, then
      one row per channel of microseconds after the block's start, ``-`` where the channel
      does not fire; no near/far distinction.

    Args:
        source: a path, the CSV text (str or UTF-8 bytes containing a newline) or an
            already parsed :class:`Firetimes`. A UTF-8 byte-order mark, CRLF line ends,
            quoted cells and blank lines are accepted; empty trailing cells are ignored.

    Raises:
        DecodeError: unreadable file, unknown header, a malformed row or cell (the message
            names the line and column, 1-based), channels not 1..L.
    """
    if isinstance(source, Firetimes):
        return source
    text = _read_text(source, "firetimes", "Hesai firetime correction CSV",
                      "a path, the CSV text (str or bytes) or a parsed Firetimes")
    lines = [(i + 1, cells) for i, line in enumerate(io.StringIO(text))
             if any(cells := _cells(line))]
    for _, cells in lines:                    # trailing empty cells (e.g. "1,2.31,")
        while cells and not cells[-1]:
            cells.pop()
    if not lines:
        raise DecodeError("firetimes", "empty", "a Hesai firetime correction CSV")
    n1, head = lines[0]
    first = head[0].lower()
    if first == "operational state":
        return _state_table(lines, text, near=False)
    if _is_number(first) and len(head) > 1 and head[1].lower().startswith("distance"):
        return _state_table(lines, text, near=True)
    if not _is_number(first) and len(head) == 2 and ("fire" in head[1].lower()):
        unit = head[1].lower().replace("μ", "u").replace("µ", "u")
        if "us" not in unit:
            raise DecodeError(f"firetimes line {n1} column 2", head[1], "a time unit of "
                              "microseconds ('fire time(us)' or 'firetime/us')")
        rows = []
        for n, cells in lines[1:]:
            if len(cells) != 2:
                raise DecodeError(f"firetimes line {n}", ",".join(cells), "channel,time_us")
            rows.append((_channel_id(cells[0], n), _firetime_value(
                cells[1], f"line {n} column 2", 1000.0, False, True)))
        ids = _check_ids([r[0] for r in rows])
        times = np.zeros(ids, np.float64)
        for ch, t in rows:
            times[ch - 1] = t
        return Firetimes("channel", ids, channel_ns=times, text=text)
    raise DecodeError(f"firetimes line {n1}", ",".join(head)[:80], "a Hesai firetime header: "
                      "'Channel,fire time(us)', '<distance m>,distance>=A1,...' (Pandar128E3X) "
                      "or 'Operational State,...' (OT128)")


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def _channel_id(cell: str, n: int) -> int:
    try:
        ch = int(cell)
    except ValueError:
        ch = 0
    if ch < 1:
        raise DecodeError(f"firetimes line {n} column 1", cell, "a channel number >= 1")
    return ch


def _check_ids(ids: list[int]) -> int:
    """L, checking that ``ids`` are each of 1..L exactly once."""
    if not ids or sorted(ids) != list(range(1, len(ids) + 1)):
        dup = sorted({i for i in ids if ids.count(i) > 1})[:8]
        raise DecodeError("firetimes channels", f"{len(ids)} rows" + (
            f", repeated {dup}" if dup else ""), "each of 1..L exactly once")
    return len(ids)


def _state_table(lines: list[tuple[int, list[str]]], text: str, near: bool) -> Firetimes:
    """The Pandar128E3X (``near``: a near/far line first) or OT128 state table."""
    names = ("operation mode", "angle state") if near else ("operational state",
                                                            "azimuth state")
    heads = lines[1:3] if near else lines[0:2]
    for (n, cells), name in zip(heads, names):
        if not cells or cells[0].lower() != name:
            raise DecodeError(f"firetimes line {n} column 1", cells[0] if cells else "",
                              f"'{name}'")
    width = len(lines[0][1])
    for n, cells in heads:
        if len(cells) != width:
            raise DecodeError(f"firetimes line {n}", f"{len(cells)} columns",
                              f"{width} (as line {lines[0][0]})")
    keys = []
    for j in range(1, width):
        try:
            op, az = int(heads[0][1][j]), int(heads[1][1][j])
        except ValueError as err:
            raise DecodeError(f"firetimes lines {heads[0][0]}-{heads[1][0]} column {j + 1}",
                              f"{heads[0][1][j]}, {heads[1][1][j]}",
                              "integer operational and azimuth states") from err
        if op not in OPERATIONAL_STATES or not 0 <= az < 4:
            raise DecodeError(f"firetimes lines {heads[0][0]}-{heads[1][0]} column {j + 1}",
                              f"{op}, {az}", "operational state 0..3, azimuth state 0..3")
        side = 0
        if near:
            label = lines[0][1][j].replace(" ", "").lower()
            if label not in ("distance>=a1", "distance<a1"):
                raise DecodeError(f"firetimes line {lines[0][0]} column {j + 1}",
                                  lines[0][1][j], "'distance>=A1' (far) or 'distance<A1' "
                                  "(near)")
            side = 1 if label == "distance<a1" else 0
        keys.append((op, az, side))
    states = sorted({(op, az) for op, az, _ in keys})
    sides = {1, 0} if near else {0}
    for op, az in states:
        got = {s for o, a, s in keys if (o, a) == (op, az)}
        if got != sides or sum(1 for o, a, _ in keys if (o, a) == (op, az)) != len(sides):
            raise DecodeError("firetimes columns", f"operational state {op}, azimuth state "
                              f"{az}", "one far and one near column" if near else
                              "one column")
    body = lines[3:] if near else lines[2:]
    unit = 1.0 if near else 1000.0
    rows = []
    for n, cells in body:
        if len(cells) != width:
            raise DecodeError(f"firetimes line {n}", f"{len(cells)} columns",
                              f"{width} (channel, then one time per state column)")
        rows.append((_channel_id(cells[0], n), [
            _firetime_value(cells[j], f"line {n} column {j + 1}", unit, not near, False)
            for j in range(1, width)]))
    ids = _check_ids([r[0] for r in rows])
    table = np.zeros((len(states), 2, ids), np.int64)
    index = {s: i for i, s in enumerate(states)}
    for ch, values in rows:
        for (op, az, side), v in zip(keys, values):
            table[index[(op, az)], side, ch - 1] = int(round(v))
            if not near:
                table[index[(op, az)], 1, ch - 1] = int(round(v))
    near_m = 0.0
    if near:
        near_m = float(lines[0][1][0])
        if not (math.isfinite(near_m) and near_m >= 0):
            raise DecodeError(f"firetimes line {lines[0][0]} column 1", lines[0][1][0],
                              "the near/far section distance in metres (>= 0)")
    return Firetimes("state", ids, states=tuple(states), table=table, near_m=near_m, text=text)
