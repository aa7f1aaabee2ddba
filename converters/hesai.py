"""Hesai point-cloud packets -> one LidarScan + LidarInfo per rotation (exact, vectorised).

Implements the packet decoder contract (``PacketDecoder``, ``decode_packets``) for the mechanical
Hesai lidars whose packet layout and firing-time tables are public (vendor user manuals, "Point
Cloud Data Packet" chapters and "Absolute Time and Laser Firing Time" appendices):

=============  ======================================  ======  ======  ====================
format         detected from                           lasers  blocks  UDP payload (bytes)
=============  ======================================  ======  ======  ====================
Pandar40P      no pre-header; every block starts with  40      10      1262 (+4 UDP seq)
               the flag 0xFFEE
Pandar64       header 0xEE 0xFF, laser num 64,         64      6       1194 (+4 UDP seq)
               block num 6 (8-byte header)
PandarXT32     0xEE 0xFF, protocol 6.1, laser num 32   32      8       1076 (+4 UDP seq)
PandarXT16     protocol 6.1, laser num 16, 8 blocks    16      8       564 (+4 UDP seq)
PandarXT32M    protocol 6.1, laser num 32, 6 blocks    32      6       816 (+4 UDP seq)
PandarQT64     0xEE 0xFF, protocol 3.1, laser num 64   64      4       1068 (+4 UDP seq)
PandarQT128    protocol 3.2, laser num 128, 2 blocks   128     2       from the Flags byte
                                                                       (1095 with UDP seq,
                                                                       FS, confidence; +32
                                                                       with signature)
Pandar128E3X,  protocol 1.4, laser num 128, 2 blocks   128     2       from the Flags byte
Pandar128E4X                                                           (861 with UDP seq,
(OT128)                                                                FS, IMU; +32 signed)
=============  ======================================  ======  ======  ====================

The model is detected from the packet's own bytes (pre-header, protocol version major.minor,
laser and block num, the header's Flags byte, payload size), never from file names; the return
mode, motor speed and date-time come from the tail, the distance unit from the header's Dis Unit
byte (the XT32M recording has 5 mm). A packet no format fits raises a
:class:`~lidarscan.errors.DecodeError` naming the field and value (unknown protocol version,
laser/block num, reserved flag bits, size, return mode byte).

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
``column_time_offsets`` are the firings' trigger times (QT128: t0 + 9 us - 111.11 us per later
firing; 128 series: t0 - 55.56 us per later firing, the manual's "absolute time is the trigger
time of the firing in the last block"). The QT128 has two firing loops with different channel
sets and delays (``_QT128_LOOPS``; single return: block 1 loop 1, block 2 loop 2; dual: the
tail's mode flag): its scans carry an extra channel ``t`` (INT32 ns, the delay of each pixel's
channel after its column's time, 0 where the channel does not fire), so a pixel's time is
``stamp + column_time_offsets[c] + beam_time_offsets[u] + t[u, c]`` (the msgs README's "a
sensor with irregular pixel timing can add a ``t`` channel"; ``Projector.pixel_times`` and
the PointCloud2 time fields add it). The 128E3X/E4X delays depend on the tail's azimuth and operational states
(and, on the 128E3X, on near/far-field firing by distance), and the packet does not say
whether it is a 128E3X or a 128E4X, whose tables differ: their channel delays (up to 55 us)
are not applied. ``vendor_metadata``'s ``channel_timing`` says which case a scan is.

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

Conventions
-----------
* Axes: the points are those of the Hesai manuals' frame as the Nebula driver publishes it,
  which was checked against its ground truth: x = rho cos(phi) sin(a), y = rho cos(phi) cos(a),
  z = rho sin(phi), with ``a`` the clockwise azimuth (block azimuth + the calibration's azimuth
  correction) and ``phi`` the calibration's elevation. So azimuth 0 points along +y and the
  sensor turns clockwise seen from above; in the counter-clockwise REP 103 angle theta (from +x)
  this is ``theta = pi/2 - a``. Hence ``LidarScan.column_azimuth_angles[c] = pi/2 -
  radians(block azimuth)`` and ``LidarInfo.beam_azimuth_offsets[u] = -radians(azimuth
  correction)``; ``vertical_angles`` = radians(elevation). No beam origins or range offsets
  (the manuals' formula has none).
* Rows: sorted by elevation, row 0 the highest beam (ties by laser id); ``beam_ids`` = the
  vendor's 1-based laser id (channel number) of each row.
* Columns: one per firing (one block, or the two blocks of a dual-return firing), in firing
  order. A rotation ends where the block azimuth wraps (decreases by more than 180 deg), so
  column 0 is the first firing at or after azimuth 0 (the first scan of a stream starts where
  the stream starts). The width W is derived from the sensor's own timing and rotation rate:
  ``ceil(1.02 * 60 s / (rpm * firing period))``, rpm = the tail's motor speed of the stream's
  first packet rounded to a multiple of 60 (2 % headroom for speed drift). Shorter rotations
  are padded with no-return columns (raw range 0; their azimuths and times continue at the
  nominal step). A rotation with more than W firings is never cut: it is emitted under a new
  LidarInfo version of width ``ceil(1.02 * firings)`` (nothing is dropped); the next normal
  rotation returns to W under yet another version.
* Returns: channels ``range`` (UINT16 in the packet's distance unit, ``range_multiplier`` =
  dis unit in metres, raw 0 = no return) and ``intensity`` (UINT8 reflectivity). Dual return
  adds ``range2``/``intensity2``: ``range`` holds the strongest return where the mode reports
  one (0x39 last+strongest, 0x3C first+strongest), otherwise the last (0x3B first+last);
  ``range2`` the other one. Triple return (0x3D) adds ``range3``/``intensity3``: ``range`` =
  strongest, ``range2`` = first, ``range3`` = last (the other returns in block order). All
  exactly as sent (no de-duplication). The confidence byte of QT128/128-series units is not
  carried.
* Time: int64 ns. The packet's absolute time ``t0`` is the tail's UTC date-time (year - 1900,
  month, day, hour, minute, second) plus its microsecond timestamp. Per the firing-time
  appendices, firing ``k`` of a packet starts at ``t0 + block_offset(k)`` and channel ``l``
  fires ``channel_offset(l)`` later. ``LidarInfo.beam_time_offsets`` = ``channel_offset`` minus
  its minimum (so they are >= 0) and ``column_time_offsets`` the firing times (plus that
  minimum) relative to the scan stamp, the time of column 0. The sensor's clock is the
  default (it is absolute when the sensor is synchronised by GPS/PTP; Hesai packets carry no
  flag saying so). With ``time_source="receive"`` each rotation's times are shifted so that
  its first packet has its recorded (host) stamp; relative timing stays the sensor's.
* Azimuth and firing time: the manuals compute a point's azimuth as the block azimuth plus the
  calibration's azimuth correction, with no term for the rotation between the block azimuth and
  the channel's own firing (the calibration is measured at the nominal speed). That is the
  default, and it reproduces the reference decoder exactly. ``firing_rotation=True`` also
  rotates each beam by ``-omega * beam_time_offsets[u]`` (omega from the nominal rpm), folded
  into ``beam_azimuth_offsets``: at 600 rpm up to 0.184 deg (Pandar64, 51 us), 0.169 deg
  (XT32, 46.9 us), 0.483 deg (QT64, 134 us), i.e. 32 / 29 / 84 mm at 10 m; on the recordings it
  drops the 2 mm agreement with the reference from 100 % to 76 % (XT32), 16 % (Pandar64) and
  7 % (QT64), so it is off by default.
* The beam model of LidarInfo expresses these sensors' geometry exactly (no beam origins, range
  offsets or per-pixel angles needed): measured agreement with the reference decoder is 4 um at
  most, float32 rounding (tests/test_hesai.py); for the XT16, XT32M and QT128 (Nebula's test
  recordings, checked outside the test suite, which does not ship them) 11 um at most, every
  ground-truth point matched. Not expressible in LidarInfo: the QT128/128-series per-firing
  channel delays (QT128: the ``t`` channel; 128 series: not applied, stated in
  vendor_metadata).

* Batches: ``PacketDecoder.push_many`` takes the (N, size) rows of N payloads of one size
  (e.g. a PandarScan message's packet array) and gives exactly the scans and infos of push()
  one by one; a bad packet inside a batch raises a DecodeError naming its index, after the
  packets before it (see push_many). The per-rotation copy of the units into the grids has a
  compiled path (:mod:`converters._kernels.hesai`, numba) with this module's numpy code as the
  reference; both copy integers, so their scans are bit-identical.

What each LidarInfo field carries: vertical_angles, beam_azimuth_offsets (calibration CSV),
beam_time_offsets (firing table), column_time_increment (firing period), beam_ids (laser ids),
range_multiplier (dis unit), range_min/range_max (the model's limits or the options),
horizontal_angles (nominal pi/2 - 2 pi c / W'; scans carry the measured ones), vendor "Hesai",
model, vendor_metadata (a JSON line with the detected format, return mode and rpm).
"""

from __future__ import annotations

import calendar
import functools
import io
import itertools
import json
import math
import os
import struct
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lidarscan.errors import ConfigError, DecodeError, LidarScanError
from lidarscan.scan import ScanBuffer, make_info
from converters._packets import payload_bytes

__all__ = [
    "FORMATS",
    "RETURN_MODES",
    "HesaiFormat",
    "PacketDecoder",
    "decode_packets",
    "detect_format",
    "load_calibration",
]

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
    else:                # 128E3X/E4X: 2 firings of 55.56 us, the last one triggered at t0
        period, base = 55556.0, 0.0
        why = ("azimuth state and operational state of the tail, near/far-field firing on "
               "the 128E3X; the packet does not tell 128E3X and 128E4X apart")
        limits = (0.1, 230.0)
        extra = dict(channel_timing=_NOT_PER_BEAM.format(why))
    return HesaiFormat(
        model=model, lasers=lasers, blocks=blocks, body=12, block_size=block_size,
        azimuth_at=0, unit_size=unit, size=size, return_mode_at=tail + 12,
        motor_speed_at=tail + 13, timestamp_at=tail + 21, datetime_at=tail + 15,
        firing_period_ns=period, block_base_ns=base, block_ref_last=True,
        channel_ns=(0.0,) * lasers, dis_unit_at=9, range_limits=limits,
        dual_orders=_ORDERS_12B, sizes=(size,), **extra)


FORMATS["PandarXT16"] = _xt_format(
    "PandarXT16", 16, 8, tuple(368.0 + 3024.0 * k for k in range(16)), (0.05, 120.0),
    _ORDERS_12B)
# XT32M2X: channels 1-16 and 17-32 fire in pairs, 2.888 us apart; 6 blocks (triple: 2 firings)
FORMATS["PandarXT32M"] = _xt_format(
    "PandarXT32M", 32, 6, tuple(368.0 + 2888.0 * (k % 16) for k in range(32)), (0.5, 300.0),
    _ORDERS_12B + ((0x3D, ("first", "last", "strongest")),))

_SUPPORTED = ("supported: Pandar40P, Pandar64, PandarXT16/XT32/XT32M (protocol 6.1), PandarQT64 "
              "(3.1), PandarQT128 (3.2), Pandar128E3X/E4X/OT128 (1.4)")


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
                     (1, 4): "Pandar128E3X/E4X/OT128 (1.4): 128 lasers, 2 blocks"}
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
                              f" with header flags {packet[11]:#04x}" if fmt.sizes else ""))
    return fmt


#: (protocol major, minor, laser num, block num) of the 12-byte header -> model
_MODELS_12B = {(6, 1, 32, 8): "PandarXT32", (6, 1, 16, 8): "PandarXT16",
               (6, 1, 32, 6): "PandarXT32M", (3, 1, 64, 4): "PandarQT64",
               (3, 2, 128, 2): "PandarQT128", (1, 4, 128, 2): "Pandar128E3X/E4X"}


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
        calib: a path, the CSV text (str containing a newline), a mapping ``{laser_id:
            (elevation_deg, azimuth_deg)}`` or an already parsed calibration.

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
        if isinstance(calib, str) and "\n" in calib:
            text = calib
        else:
            path = Path(os.fspath(calib))
            try:
                text = path.read_text(encoding="utf-8-sig")
            except (OSError, UnicodeDecodeError) as err:
                raise DecodeError("calibration", str(path), "a readable Hesai angle-correction "
                                  "CSV (Laser id,Elevation,Azimuth)") from err
        for i, line in enumerate(io.StringIO(text)):
            cells = [c.strip() for c in line.strip().split(",")]
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


# ----------------------------------------------------------------------------------- decoder

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

    @property
    def first_channel_ns(self) -> int:
        """Firing time of the earliest channel relative to its firing's start (ns)."""
        return int(round(min(self.fmt.channel_ns)))


class PacketDecoder:
    """Raw Hesai packets -> (LidarScan, LidarInfo) per rotation (see the module docstring).

    Args:
        calibration: the sensor's angle-correction CSV (path, text, mapping or parsed). Required:
            Hesai publishes no nominal table this module could default to.
        frame_id: header.frame_id of scans and infos.
        time_source: "sensor" (default): stamps from the packets' UTC date-time + timestamp;
            "receive": the sensor's times shifted so that the first packet of each rotation
            has its recorded stamp (relative timing stays the sensor's).
        firing_rotation: fold the rotation between block azimuth and each channel's firing into
            beam_azimuth_offsets (default False: the manuals' formula).
        range_min, range_max: LidarInfo valid interval (m); default the model's limits.
        as_dataclass: build :mod:`lidarscan.types` dataclasses instead of rclpy messages.
    """

    def __init__(self, calibration: Any = None, *, frame_id: str = "lidar",
                 time_source: str = "sensor", firing_rotation: bool = False,
                 range_min: float | None = None, range_max: float | None = None,
                 as_dataclass: bool = False) -> None:
        if calibration is None:
            raise ConfigError("calibration", None, "the sensor's angle-correction CSV "
                              "(Laser id,Elevation,Azimuth; e.g. PandarXT32.csv): Hesai "
                              "publishes no nominal calibration")
        if time_source not in ("sensor", "receive"):
            raise ConfigError("time_source", time_source, '"sensor" or "receive"')
        self.calibration = load_calibration(calibration)
        self._order = self.calibration.order          # laser index of each row
        self._rows = np.argsort(self._order)          # row of each laser index
        self.frame_id = frame_id
        self.time_source = time_source
        self.firing_rotation = bool(firing_rotation)
        self.range_limits = (range_min, range_max)
        self.as_dataclass = as_dataclass
        self._stream: _Stream | None = None
        self._key = b""
        # packets of the rotation being collected, in arrival order: first the 2-D blocks of
        # rows (stamps (n,) int64, payload rows (n, size) uint8, owned) that push_many() and
        # earlier emissions left, then the single payloads push() appended since
        self._segs: list[tuple[np.ndarray[Any, Any], np.ndarray[Any, Any], bool]] = []
        self._packets: list[bytes] = []
        self._stamps: list[int] = []
        self._skip = 0                      # leading firings of _packets[0] already emitted
        self._last_az = -1
        self._date = b""                    # last tail date-time bytes seen valid
        self._fast: tuple[Any, ...] | None = None   # what push() compares on its fast path
        self._info: Any = None
        self._info_key: tuple[Any, ...] | None = None
        self._last_info_stamp: int | None = None

    # -------------------------------------------------------------------------- packet intake
    def push(self, stamp_ns: int, packet: Any) -> list[tuple[Any, Any]]:
        """Add one UDP payload; returns the rotations it completed (usually 0 or 1).

        Only the packet's header, first/last firing azimuth and date are read here; the body is
        decoded in bulk when a rotation completes.

        Raises:
            DecodeError: malformed or unsupported packet (the decoder stays usable).
        """
        data = packet if type(packet) is bytes else payload_bytes(packet)
        fast = self._fast
        if (fast is not None and len(data) == fast[0] and data.startswith(fast[1])
                and data[fast[2]] == fast[3]):
            first, last = fast[4].unpack_from(data, fast[5])
            if first < 36000 and last < 36000 and data.startswith(self._date, fast[6]):
                wrapped = first < self._last_az - 18000 or last < first - 18000
                self._packets.append(data)
                self._stamps.append(stamp_ns)
                self._last_az = last
                return self._emit(final=False) if wrapped else []
        return self._push_checked(stamp_ns, data)

    def _push_checked(self, stamp_ns: int, data: bytes) -> list[tuple[Any, Any]]:
        """push() for a packet that is not plainly the next one of the current stream."""
        stream = self._stream
        new = None
        if (stream is None or len(data) != stream.packet_size
                or data[:len(self._key)] != self._key
                or data[stream.fmt.return_mode_at] != stream.mode):
            new = self._stream_of(data)           # raises before any state changes
            stream = new
        fmt = stream.fmt
        at = fmt.body + fmt.azimuth_at
        first = _U16.unpack_from(data, at)[0]
        last = _U16.unpack_from(data, at + stream.last_firing_at)[0]
        if first >= 36000 or last >= 36000:
            raise DecodeError("hesai block azimuth", max(first, last), "0..35999 (0.01 deg)")
        date = data[fmt.datetime_at:fmt.datetime_at + 6]
        if date != self._date:
            _date_seconds(date)                   # validates it before any state changes
            self._date = date
        out: list[tuple[Any, Any]] = []
        if new is not None:
            if self._stream is not None and new != self._stream:
                out = self.flush()
            self._stream, self._key = new, data[:max(2, fmt.body)]
            self._fast = (new.packet_size, self._key, fmt.return_mode_at, new.mode,
                          _first_last(new.last_firing_at), at, fmt.datetime_at)
        wrapped = first < self._last_az - 18000 or last < first - 18000
        self._packets.append(data)
        self._stamps.append(stamp_ns)
        self._last_az = last
        if wrapped:
            out.extend(self._emit(final=False))
        return out

    def flush(self) -> list[tuple[Any, Any]]:
        """The last, partial rotation (if it has any firing); the decoder is then empty."""
        out = self._emit(final=True) if self._packets or self._segs else []
        self._segs, self._packets, self._stamps, self._skip, self._last_az = [], [], [], 0, -1
        return out

    def _stream_of(self, data: bytes) -> _Stream:
        fmt = detect_format(data)
        mode = data[fmt.return_mode_at]
        kinds = _block_kinds(fmt, mode)
        returns = len(kinds)
        dis = 4 if fmt.dis_unit_at is None else data[fmt.dis_unit_at]
        if dis == 0:
            raise DecodeError("hesai dis unit", 0, "a distance unit > 0 mm")
        rpm_raw = _U16.unpack_from(data, fmt.motor_speed_at)[0]
        rpm = max(60, int(round(rpm_raw / 60.0)) * 60)
        if self.calibration.laser_ids.size != fmt.lasers:
            raise DecodeError("calibration lasers", self.calibration.laser_ids.size,
                              f"{fmt.lasers} (the {fmt.model} packets' laser count)")
        return _Stream(fmt, mode, returns, dis * 1e-3, rpm, len(data),
                       (fmt.blocks - returns) * fmt.block_size)

    # ------------------------------------------------------------------------------ batches
    def push_many(self, stamps_ns: Any, payloads: Any,
                  errors: list[tuple[int, LidarScanError]] | None = None
                  ) -> list[tuple[Any, Any]]:
        """Add N UDP payloads of one size at once; returns the rotations they completed.

        The same as ``push(stamps_ns[i], payloads[i])`` for i = 0..N-1 with the results
        concatenated (bit-identical scans and infos), but the header checks and rotation
        boundaries are found vectorised over the whole batch and each rotation is decoded
        straight from the rows of ``payloads``.

        Args:
            stamps_ns: (N,) int64 recorded stamps (ns).
            payloads: (N, size) uint8, one payload per row (e.g. ``data[:, :size]`` of a
                PandarScan message's packets); rows may have any stride, each row must be
                contiguous (else it is copied once). Never modified; the decoder keeps no
                reference to it after the call (the rows of an unfinished rotation are copied).

        Raises:
            DecodeError: packet ``i`` of the batch is malformed or unsupported. The message
                starts with ``packets[i]`` and the error carries ``index`` (= i) and
                ``results``: the rotations completed by packets 0..i-1, which are consumed
                exactly as push() would have consumed them (their unfinished rotation stays
                in the decoder). Packet i is dropped and packets i+1.. are not consumed:
                call ``push_many(stamps_ns[i + 1:], payloads[i + 1:])`` to go on. A batch
                whose arrays are themselves wrong (shape, dtype) raises with ``index`` -1
                before consuming anything.

        With a list as ``errors`` (the same contract as :meth:`converters.velodyne.
        PacketDecoder.push_many`), malformed packets are skipped instead: each is recorded as
        ``(row index, DecodeError)`` and decoding goes on with the next row; only a batch
        whose arrays are wrong still raises.
        """
        if errors is None:
            return self._push_rows(stamps_ns, payloads, owned=False)
        out: list[tuple[Any, Any]] = []
        start = 0
        while True:
            try:
                return out + self._push_rows(stamps_ns[start:], payloads[start:], owned=False)
            except DecodeError as err:
                index = getattr(err, "index", -1)
                if index < 0:
                    raise
                out += getattr(err, "results", [])
                errors.append((start + index, err))
                start += index + 1

    def _push_rows(self, stamps_ns: Any, payloads: Any, owned: bool) -> list[tuple[Any, Any]]:
        """push_many(); ``owned``: the caller hands ``payloads`` over (never used again)."""
        rows = payloads
        if not isinstance(rows, np.ndarray) or rows.dtype != np.uint8 or rows.ndim != 2:
            raise _batch_error(DecodeError(
                "payloads", f"{getattr(rows, 'dtype', type(rows).__name__)} "
                f"{getattr(rows, 'shape', '')}", "an (N, size) uint8 ndarray"), -1, [])
        stamps = np.asarray(stamps_ns)
        if stamps.shape != (rows.shape[0],) or stamps.dtype.kind not in "iu":
            raise _batch_error(DecodeError("stamps_ns", f"{stamps.dtype} {stamps.shape}",
                                           f"({rows.shape[0]},) integer ns"), -1, [])
        stamps = stamps.astype(np.int64, copy=False)
        if rows.shape[0] and rows.strides[1] != 1:
            rows = np.ascontiguousarray(rows)
        out: list[tuple[Any, Any]] = []
        n = rows.shape[0]
        i = 0
        try:
            while i < n:
                plain, first, last = self._plain_rows(rows[i:])
                if plain:
                    out += self._append_rows(stamps[i:i + plain], rows[i:i + plain],
                                             first[:plain], last[:plain], owned)
                    i += plain
                if i < n:                     # a first, new-stream, new-date or bad packet
                    try:
                        out += self._push_checked(int(stamps[i]), rows[i].tobytes())
                    except DecodeError as err:
                        raise _batch_error(err, i, out) from err
                    i += 1
        finally:
            self._own_rows()
        return out

    def _plain_rows(self, rows: np.ndarray[Any, Any]
                    ) -> tuple[int, np.ndarray[Any, Any], np.ndarray[Any, Any]]:
        """How many leading rows push()'s fast path would take; their first/last azimuths."""
        fast, stream = self._fast, self._stream
        if fast is None or stream is None or rows.shape[1] != fast[0]:
            return 0, np.empty(0, np.int32), np.empty(0, np.int32)
        size, key, mode_at, mode, _, at, date_at = fast
        az = rows[:, at:at + 2].view("<u2")[:, 0].astype(np.int32)
        at2 = at + stream.last_firing_at
        az2 = rows[:, at2:at2 + 2].view("<u2")[:, 0].astype(np.int32)
        ok = ((rows[:, :len(key)] == np.frombuffer(key, np.uint8)).all(1)
              & (rows[:, mode_at] == mode) & (az < 36000) & (az2 < 36000)
              & (rows[:, date_at:date_at + 6] == np.frombuffer(self._date, np.uint8)).all(1))
        bad = np.flatnonzero(~ok)
        return (int(bad[0]) if bad.size else rows.shape[0]), az, az2

    def _append_rows(self, stamps: np.ndarray[Any, Any], rows: np.ndarray[Any, Any],
                     first: np.ndarray[Any, Any], last: np.ndarray[Any, Any], owned: bool
                     ) -> list[tuple[Any, Any]]:
        """Buffer plain rows (views; ``owned``: no copy needed); emit what their wraps
        complete."""
        self._join_packets()
        prev = np.empty_like(last)
        prev[0] = self._last_az
        prev[1:] = last[:-1]
        wraps = np.flatnonzero((first < prev - 18000) | (last < first - 18000))
        self._segs.append((stamps, rows, owned))
        self._last_az = int(last[-1])
        if not wraps.size:
            return []
        # push() would emit at each wrapping packet: everything complete up to the last one
        buffered = sum(seg[1].shape[0] for seg in self._segs)
        return self._emit(final=False, limit=buffered - (rows.shape[0] - 1 - int(wraps[-1])))

    def _join_packets(self) -> None:
        """Move the payloads push() appended into one owned block of rows."""
        if self._packets:
            rows = np.frombuffer(b"".join(self._packets), np.uint8).reshape(
                len(self._packets), -1)
            self._segs.append((np.array(self._stamps, np.int64), rows, True))
            self._packets, self._stamps = [], []

    def _own_rows(self) -> None:
        """Copy the buffered rows that are still views of a caller's arrays."""
        self._segs = [seg if seg[2] else (seg[0].copy(), seg[1].copy(), True)
                      for seg in self._segs]

    # ------------------------------------------------------------------------------ decoding
    def _columns(self) -> dict[str, np.ndarray[Any, Any]]:
        """Firings of the buffered packets: azimuth (0.01 deg), time (ns), per-packet t0.

        Returns ``azimuth`` (F,) int32 and ``time`` (F,) int64 ns of each firing's start over
        all firings of all buffered packets, ``t0`` (P,) int64 each packet's absolute time and
        ``stamp`` (P,) int64 its recorded stamp.
        """
        stream = self._stream
        assert stream is not None
        fmt = stream.fmt
        self._join_packets()
        segs = [seg[1] for seg in self._segs]
        firings = fmt.blocks // stream.returns
        at = fmt.body + fmt.azimuth_at + stream.returns * fmt.block_size * np.arange(firings)
        azimuth = np.concatenate([_le_fields(rows, at, 2) for rows in segs])       # (P, F)
        us = np.concatenate([_le_fields(rows, (fmt.timestamp_at,), 4)[:, 0]
                             for rows in segs]).astype(np.int64)
        d = fmt.datetime_at
        dates = np.concatenate([rows[:, d:d + 6] for rows in segs])              # (P, 6) uint8
        starts = np.flatnonzero(np.r_[True, (dates[1:] != dates[:-1]).any(1)])
        secs = np.array([_date_seconds(bytes(dates[i])) for i in starts], np.int64)
        secs = np.repeat(secs, np.diff(np.r_[starts, len(dates)]))
        t0 = secs * 1_000_000_000 + us * 1000
        times = t0[:, None] + fmt.block_start_ns(np.arange(firings), firings)[None, :]
        cols = {"azimuth": azimuth.reshape(-1).astype(np.int32), "time": times.reshape(-1),
                "t0": t0, "stamp": np.concatenate([seg[0] for seg in self._segs])}
        if fmt.pixel_tables:
            assert fmt.mode_flag_at is not None
            flags = np.concatenate([rows[:, fmt.mode_flag_at] for rows in segs])
            cols["state"] = _firing_states(fmt, stream.returns, flags)
        return cols

    def _emit(self, final: bool, limit: int | None = None) -> list[tuple[Any, Any]]:
        """Scans of every rotation completed in the buffer (all that is left when ``final``).

        ``limit``: look for rotation ends in the first ``limit`` buffered packets only (what
        push() would have seen when the last wrapping packet of a batch arrived).
        """
        stream = self._stream
        assert stream is not None
        cols = self._columns()
        firings = stream.fmt.blocks // stream.returns
        total = cols["azimuth"].size
        end = total if limit is None else limit * firings
        start = self._skip
        wraps = np.flatnonzero(np.diff(cols["azimuth"][start:end]) < -18000) + 1 + start
        bounds = [start, *wraps.tolist()] + ([total] if final else [])
        out = [self._scan(cols, lo, hi) for lo, hi in zip(bounds[:-1], bounds[1:]) if hi > lo]
        if not final:
            keep = bounds[-1] // firings
            self._skip = bounds[-1] - keep * firings
            segs = []
            for seg in self._segs:
                if keep < seg[1].shape[0]:
                    segs.append((seg[0][keep:], seg[1][keep:], seg[2]))
                keep = max(0, keep - seg[1].shape[0])
            self._segs = segs
        return out

    def _scan(self, cols: dict[str, np.ndarray[Any, Any]], lo: int, hi: int
              ) -> tuple[Any, Any]:
        """(scan, info) of firings lo..hi-1 of the buffer (columns ``cols``)."""
        stream = self._stream
        assert stream is not None
        fmt = stream.fmt
        firings = fmt.blocks // stream.returns
        count = hi - lo
        nominal = 60e9 / (stream.rpm * fmt.firing_period_ns)
        width = int(math.ceil(1.02 * nominal))
        if count > width:
            width = int(math.ceil(1.02 * count))          # a long rotation: new version
        times = cols["time"][lo:hi] + stream.first_channel_ns
        if self.time_source == "receive":     # the host's clock at the rotation's first packet
            p = lo // firings
            times = times + (cols["stamp"][p] - cols["t0"][p])
        stamp = int(times[0])
        info = self._info_for(stream, width, stamp)
        az = cols["azimuth"][lo:hi].astype(np.float64)
        pad = width - count
        if pad:
            steps = np.arange(1, pad + 1)
            az = np.concatenate([az, az[-1] + (36000.0 / nominal) * steps])
            times = np.concatenate([times, times[-1]
                                    + np.rint(fmt.firing_period_ns * steps).astype(np.int64)])
        pieces = []                          # (rows, first firing, firings, column)
        at = 0
        for seg in self._segs:
            n = seg[1].shape[0] * firings
            a, b = max(lo, at), min(hi, at + n)
            if a < b:
                pieces.append((seg[1], a - at, b - a, a - lo))
            at += n
        names = _channel_names(_block_kinds(fmt, stream.mode))
        specs = {name: np.uint16 if k == 0 else np.uint8 for pair in names
                 for k, name in enumerate(pair)}
        if fmt.pixel_tables:
            specs["t"] = np.int32
        buf = ScanBuffer(info, {k: specs[k] for k in sorted(specs, key=_channel_rank)},
                         as_dataclass=self.as_dataclass)
        grids = [tuple(buf.views[name] for name in pair) for pair in names]
        _units(pieces, stream, self._rows, grids)
        if fmt.pixel_tables:
            _pixel_times(fmt, cols["state"][lo:hi], self._order, buf.views["t"])
        angles = np.pi / 2 - np.deg2rad(az * 0.01)
        return buf.build(stamp, column_time_offsets=times - stamp,
                         column_azimuth_angles=angles), info

    def _info_for(self, stream: _Stream, width: int, stamp: int) -> Any:
        key = (stream.fmt.model, stream.mode, stream.dis_unit_m, stream.rpm, width)
        if self._info is not None and key == self._info_key:
            return self._info
        fmt = stream.fmt
        calib = self.calibration
        order = self._order
        channel_ns = np.asarray(fmt.channel_ns)
        beam_time = np.rint(channel_ns - channel_ns.min()).astype(np.int64)[order]
        beta = -np.deg2rad(calib.azimuth_deg[order])
        if self.firing_rotation:
            beta = beta - 2.0 * np.pi * stream.rpm / 60.0 * beam_time * 1e-9
        if self._last_info_stamp is not None and stamp <= self._last_info_stamp:
            stamp = self._last_info_stamp + 1
        lo, hi = self.range_limits
        nominal_width = 60e9 / (stream.rpm * fmt.firing_period_ns)
        meta = {"format": fmt.model, "return_mode": "+".join(RETURN_MODES[stream.mode]),
                "return_mode_byte": stream.mode, "rpm": stream.rpm,
                "dis_unit_m": stream.dis_unit_m, "firing_rotation": self.firing_rotation,
                "channel_timing": fmt.channel_timing}
        info = make_info(
            stamp_ns=stamp, frame_id=self.frame_id,
            vertical_angles=np.deg2rad(calib.elevation_deg[order]),
            horizontal_angles=np.pi / 2 - 2.0 * np.pi * np.arange(width) / nominal_width,
            beam_azimuth_offsets=beta, beam_time_offsets=beam_time,
            column_time_increment=int(round(fmt.firing_period_ns)),
            beam_ids=calib.laser_ids[order].astype(np.uint16),
            range_multiplier=stream.dis_unit_m, range_offset=0.0,
            range_min=fmt.range_limits[0] if lo is None else float(lo),
            range_max=fmt.range_limits[1] if hi is None else float(hi),
            vendor="Hesai", model=fmt.model, vendor_metadata=json.dumps(meta, sort_keys=True),
            as_dataclass=self.as_dataclass)
        self._info, self._info_key, self._last_info_stamp = info, key, stamp
        return info


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


def _date_seconds(date: bytes) -> int:
    """POSIX seconds of a tail date-time (year - 1900, month, day, hour, minute, second; UTC)."""
    y, mo, d, h, mi, s = date
    if not (1 <= mo <= 12 and 1 <= d <= 31 and h < 24 and mi < 60 and s < 61):
        raise DecodeError("hesai tail date-time", list(date),
                          "year-1900, month 1..12, day 1..31, hour < 24, minute < 60, second")
    return calendar.timegm((1900 + y, mo, d, h, mi, s, 0, 0, 0))


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
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": size})


def _firing_states(fmt: HesaiFormat, returns: int, flags: np.ndarray[Any, Any]
                   ) -> np.ndarray[Any, Any]:
    """(F,) index into ``fmt.pixel_tables`` of every buffered firing, from the (P,) tail mode
    flags of the buffered packets (PandarQT128: loop 1 = 0, loop 2 = 1; single return: block 1
    loop 1, block 2 loop 2; dual: the tail's mode flag, bit 0 set = loop 1)."""
    flags = flags.astype(np.int64)
    if returns == 1:
        return np.tile(np.arange(fmt.blocks) % 2, flags.size)
    return np.where(flags & 1, 0, 1)


def _le_fields(rows: np.ndarray[Any, Any], offsets: Any, nbytes: int) -> np.ndarray[Any, Any]:
    """(P, K) little-endian unsigned integers of ``nbytes`` (2 or 4) bytes at byte ``offsets``
    (K,) of each payload row of ``rows`` (P, size) uint8."""
    idx = (np.asarray(offsets)[:, None] + np.arange(nbytes)).reshape(-1)
    return np.ascontiguousarray(rows.take(idx, axis=1)).view(f"<u{nbytes}")


def _pixel_times(fmt: HesaiFormat, states: np.ndarray[Any, Any], order: np.ndarray[Any, Any],
                 out: np.ndarray[Any, Any]) -> None:
    """Write the per-pixel delays (ns after the column's time) of firings ``states`` (C,) into
    the first C columns of ``out`` (H, W) int32, rows in ``order`` (laser index of each row);
    channels that do not fire in a firing get 0."""
    table = np.asarray(fmt.pixel_tables, np.int32)[:, order]        # (states, H)
    out[:, :states.size] = np.maximum(table[states].T, 0)


def _records(rows: np.ndarray[Any, Any], fmt: HesaiFormat) -> np.ndarray[Any, Any]:
    """(P,) structured zero-copy view of payload rows (P, size) uint8 (contiguous rows)."""
    return rows.view(_packet_dtype(fmt, rows.shape[1]))[:, 0]


@functools.lru_cache(maxsize=None)
def _unit_offsets(fmt: HesaiFormat, returns: int) -> np.ndarray[Any, Any]:
    """(firings, returns, lasers) int64 byte offset of each unit (distance) in a payload."""
    firings = fmt.blocks // returns
    block = np.arange(firings * returns).reshape(firings, returns, 1)
    return (fmt.body + block * fmt.block_size + fmt.azimuth_at + 2
            + np.arange(fmt.lasers) * fmt.unit_size).astype(np.int64)


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
    offsets = _unit_offsets(stream.fmt, stream.returns)
    dists = tuple(dist for dist, _ in grids)
    refls = tuple(refl for _, refl in grids)
    for payloads, first, count, col in pieces:
        fill(payloads, first, count, col, offsets, rows, dists, refls)


def _units_numpy(pieces: list[tuple[np.ndarray[Any, Any], int, int, int]], stream: _Stream,
                 rows: np.ndarray[Any, Any],
                 grids: list[tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]]) -> None:
    """The numpy reference of :func:`_units`: strided structured views of the rows, copied
    firing-major, transposed and put in row order."""
    fmt = stream.fmt
    returns = stream.returns
    firings = fmt.blocks // returns
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


def _batch_error(err: DecodeError, index: int, results: list[tuple[Any, Any]]) -> DecodeError:
    """``err`` re-raised for packet ``index`` of a push_many() batch (-1: the batch's arrays),
    with the results of the packets before it."""
    field = f"packets[{index}]: {err.field}" if index >= 0 else err.field
    new = DecodeError(field, err.value, err.expected, hint=err.hint)
    new.index = index                         # type: ignore[attr-defined]
    new.results = results                     # type: ignore[attr-defined]
    return new


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




#: packets taken from the iterable at once by decode_packets (and pushed as runs of one size)
_RUN = 4096


def decode_packets(packets: Iterable[tuple[int, Any]], calibration: Any = None, **kw: Any
                   ) -> Iterator[tuple[Any, Any]]:
    """Decode an iterable of (stamp_ns, payload), then flush(): the results of push() one by one.

    The iterable is read 4096 pairs at a time; each chunk's runs of consecutive payloads of
    one size are joined and go through :meth:`PacketDecoder.push_many` (no Python step per
    packet). A malformed packet raises the DecodeError of push_many() after the rotations
    completed before it have been yielded; its message starts with ``packets[i]``, i counting
    from the iterable's first packet (``index`` = i).
    """
    decoder = PacketDecoder(calibration, **kw)
    it = iter(packets)
    done = 0                                  # packets of the iterable before the chunk
    while True:
        chunk = list(itertools.islice(it, _RUN))
        if not chunk:
            break
        try:
            stamps, datas = zip(*chunk)
        except (TypeError, ValueError):       # not all (stamp, payload) pairs: as a for loop
            stamps, datas = _pairs(chunk)     # raises the loop's error at the first bad item
        bad: DecodeError | None = None
        if set(map(type, datas)) != {bytes}:
            datas, bad = _payloads(datas)     # up to the first unreadable payload
        yield from _push_runs(decoder, stamps[:len(datas)], datas, done)
        if bad is not None:
            raise _batch_error(bad, done + len(datas), []) from bad
        done += len(chunk)
    yield from decoder.flush()


def _pairs(chunk: list[Any]) -> tuple[tuple[Any, ...], tuple[Any, ...]]:
    """(stamps, payloads) of a chunk item by item: the first item that is not a pair raises
    the error a ``for stamp, payload in packets`` loop raises."""
    stamps, datas = [], []
    for stamp, packet in chunk:
        stamps.append(stamp)
        datas.append(packet)
    return tuple(stamps), tuple(datas)


def _payloads(datas: tuple[Any, ...]) -> tuple[list[bytes], DecodeError | None]:
    """The payloads as bytes, up to the first one that is not a payload (and its error)."""
    out = []
    for packet in datas:
        try:
            out.append(packet if type(packet) is bytes else payload_bytes(packet))
        except DecodeError as err:
            return out, err
    return out, None


def _push_runs(decoder: PacketDecoder, stamps: tuple[Any, ...], datas: Any, done: int
               ) -> Iterator[tuple[Any, Any]]:
    """push_many() each run of equal-size payloads of a chunk, joined into one block of rows;
    ``done``: packets of the iterable before the chunk (for the error's index)."""
    if not datas:
        return
    sizes = np.fromiter(map(len, datas), np.int64, len(datas))
    cuts = [0, *(np.flatnonzero(sizes[1:] != sizes[:-1]) + 1).tolist(), len(datas)]
    for lo, hi in zip(cuts[:-1], cuts[1:]):
        rows = np.frombuffer(b"".join(datas[lo:hi]), np.uint8).reshape(hi - lo, int(sizes[lo]))
        try:
            yield from decoder._push_rows(np.array(stamps[lo:hi], np.int64), rows, owned=True)
        except DecodeError as err:
            yield from err.results            # type: ignore[attr-defined]
            cause: Any = err.__cause__
            raise _batch_error(cause, done + lo + err.index, []) from cause  # type: ignore
