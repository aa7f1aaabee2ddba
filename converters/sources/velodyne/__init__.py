"""Velodyne-style calibration -> LidarInfo (exact per-beam model), and packets -> LidarScan.

Modules: :mod:`~converters.sources.velodyne.calibration` (the calibration YAML -> LidarInfo, firings ->
LidarScan), :mod:`~converters.sources.velodyne.packets` (each model's packet layout and timing, and its
bytes -> a scan's pixels) and :mod:`~converters.sources.velodyne.decoder` (:class:`PacketDecoder`:
rotations, times, widths, info versions). Every public name is importable from here.

The calibration is the ros-drivers/velodyne YAML format: ``lasers`` is a list of per-laser
dicts (``laser_id``, ``rot_correction`` and ``vert_correction`` in radians, ``dist_correction``,
``vert_offset_correction`` and ``horiz_offset_correction`` in metres, ...), plus optional
``num_lasers`` and ``distance_resolution`` (metres per raw distance unit, default 0.002).

Mapping onto the beam model of ``msgs/msg/LidarInfo.msg`` (rows sorted by elevation, row 0 the
highest; a column is one firing sequence of all lasers)::

    alpha_c = -rotation_c            (rotation: the packet's azimuth, clockwise; measured per scan
                                      and stored in LidarScan.column_azimuth_angles)
    beta_u  = rot_correction_u       (- omega * t_u with the ``rpm`` option, see below)
    phi_u   = vert_correction_u
    delta_u = dist_correction_u
    o_u     = (-vert_offset_u * sin(phi_u), horiz_offset_u, vert_offset_u * cos(phi_u))

This reproduces the velodyne_pointcloud point formula (``rawdata.cpp``) exactly, apart from the
range-dependent two-point distance corrections (``dist_correction_x``/``_y``, HDL-64 only) and
the intensity corrections, which are not part of the geometry. The driver also rotates each
laser by the azimuth swept between the column's first firing and its own (``t_u`` below):
pass ``rpm`` to fold that nominal rotation into ``beta_u``.

Timing (VLP-16 firing table): laser ``k`` of a firing sequence fires 2.304 us * k after the
sequence starts, one sequence every 55.296 us; so ``beam_time_offsets[u] = 2304 ns * laser_id``
and ``column_time_increment = 55296 ns`` for 16-laser calibrations (zeros otherwise unless given).

Packet decoding (:class:`PacketDecoder`, :func:`decode_packets`; facts of the VLP-16, VLP-32C,
HDL-32E and VLS-128 user manuals). A data packet payload is 1206 bytes: 12 blocks of 100 bytes
(flag 0xFF + 0xEE/0xDD/0xCC/0xBB, azimuth u16 in 0.01 deg clockwise, 32 points of distance u16
and reflectivity u8, little-endian), the timestamp (u32, microseconds past the hour) and two
factory bytes: return mode (0x37 strongest, 0x38 last, 0x39 dual) and product id (0x22 VLP-16
and Puck LITE, 0x24 Puck Hi-Res, 0x28 VLP-32C, 0x21 HDL-32E, 0xA1 VLS-128 / Alpha Prime). The
model and return mode come from these bytes only.

============  ==========================  ==================  ===========================
model         sequences per packet        laser k fires at    first firing vs timestamp
============  ==========================  ==================  ===========================
VLP-16/Puck   2 per block: 24 (dual 12)   2.304 us * k        0
VLP-32C       1 per block: 12 (dual 6)    2.304 us * (k//2)   0 (lasers fire in pairs)
HDL-32E       1 per block: 12 (dual 6)    1.152 us * k        the stamp is the last firing
VLS-128       4 blocks (banks): 3 (dual   2.665 us *          -8.7 us
              1: blocks 0-7, 4 unused)    (k//8 + k//64)
============  ==========================  ==================  ===========================

Sequence periods: 55.296 us (VLP-16, VLP-32C), 46.08 us (HDL-32E), 53.3 us (VLS-128); distance
units 2 mm (VLP-16, Puck, HDL-32E) and 4 mm (VLP-32C, VLS-128): the model's unit is used, not
the calibration's ``distance_resolution``. Dual return: blocks in pairs, the even block the last
return and the odd block the strongest (the second strongest when the strongest is also the
last, as the manuals specify).

What the decoder produces (conventions):

- Axes: REP 103 as velodyne_pointcloud publishes them (x forward = packet azimuth 0, y left,
  z up). ``column_azimuth_angles[c] = -radians(azimuth_c)`` (the packets' azimuth is clockwise);
  the azimuth of a VLP-16's second sequence in a block is interpolated half-way to the next block.
- Rows: sorted by elevation, row 0 the highest; ``beam_ids`` = the vendor laser id (position in
  the sequence). Columns = firing sequences in firing order, one rotation per scan, cut before
  the first sequence whose azimuth passed ``cut_angle_deg``; short rotations are padded with
  no-return columns, long ones get a wider info version (see :class:`PacketDecoder`).
- Channels: ``range`` UINT16 raw distance (``range_multiplier`` = the model's unit, 0 = no
  return) and ``intensity`` UINT8 reflectivity; dual return adds ``range2``/``intensity2``:
  ``range`` is the strongest-return slot, ``range2`` the last-return slot, both exactly as sent
  (identical pairs are kept). The default ``azimuth_model="nebula"`` adds ``azimuth`` (and
  ``azimuth2`` for ``range2``): UINT16, the pixel's azimuth in counter-clockwise hundredths of
  a degree (``msgs/README.md``), which the projector uses instead of column azimuth + beam
  offset (see "Point geometry" below).
- Time: ``header.stamp`` = first firing of the rotation; ``column_time_offsets`` = each
  sequence's first firing (timestamp + the table above); ``beam_time_offsets`` = the firing
  offset of each laser; ``column_time_increment`` = the measured mean column period. Stamps come
  from the packets' own clock completed with the hour of the recorded stamps when the two agree
  (GPS/PTP), else from the recorded stamps (``time_source``).
- Intra-sequence rotation: ``beam_azimuth_offsets[u] = rot_correction_u - omega * t_u`` with
  omega the rotation rate measured on the first rotation of the info version. The residual is
  (omega_actual - omega) * t_u: on the shared VLP-32C and VLS-128 recordings the local rate
  (10 ms windows) stays within 0.23 % of omega, i.e. <= 0.6 mm at 100 m; between rotations
  0.01 %. A rotation whose rate differs by more than 1 % from the info's (measured over >= 100
  columns) starts a new info version.
- Point geometry, default ``azimuth_model="nebula"``: the points of Nebula (tier4/nebula, the
  production driver whose clouds are the ground truth in ``tests/data/nebula``), exactly.
  Nebula interpolates each laser's azimuth from the gap to the block it reads ahead, which is
  0 at a packet's last block and, on the VLS-128, for the first three banks of a sequence; in
  dual return the second block of a pair takes the next pair's azimuth (no gap) and the
  VLS-128's reads the unused blocks 8-9; and it rounds every point's azimuth, rot_correction
  included, to 0.01 deg (:func:`~converters.sources.velodyne.packets._nebula_azimuths` follows its float32 arithmetic step by
  step). That angle depends on the column *and* the beam and is quantised, so no column
  azimuth + per-beam offset expresses it (the best such fit left 9 % of the VLP-32C and 30 % of
  the VLS-128 points more than 2 mm off, up to 89 mm at 50 m). Other exact uses of existing
  fields fail too: ``LidarInfo.pixel_azimuth_angles`` is latched but the angles change every
  rotation, and per-bank column azimuths still miss the per-laser fraction and the rounding.
  Hence one per-pixel UINT16 channel (2 bytes per pixel and return, the packets' own unit):
  the decoder computes Nebula's angle from packet fields only (model from the product id,
  return mode byte, calibration) and the projector, ``to_pointcloud2`` and the slicer use it
  (``lidarscan.geometry.pixel_azimuths``). An identical dual pair (Nebula emits it once) gets
  the last return's angle in both channels. Nebula's VLP-16 and VLS-128 formulas ignore
  ``vert/horiz_offset_correction``: so does this model (``beam_origins`` zero); its VLP-32C
  (also used for the HDL-32E) applies them, as the beam model does. Measured, compared directly
  (``tests/test_velodyne_packets.py``, every return inside Nebula's range and azimuth limits):
  VLP-32C 99.58 % of Nebula's points have one of ours within 2 mm and 100.00 % of ours one of
  Nebula's; VLS-128 99.95 % and 99.31 % (the rest: Nebula cuts rotations per packet, this
  decoder per firing sequence: the first and last 0.4 deg of a turn differ).
- ``azimuth_model="manual"``: no azimuth channel; the manuals' firing times, folded into
  ``beam_azimuth_offsets`` (above). Physically the better model (measured,
  ``converters.edge.evidence.velodyne_timing``): vertical depth edges seen by elevation-adjacent
  beams of the real VLS-128 recording (45 296 matched edges, 125 row pairs) line up to an RMS
  per-pair shift of 24.5 millidegrees under the manual's times, 42.6 under Nebula's and 67.8
  with no intra-sequence timing (noise floor 10); with a roll and a constant fitted out, 17.2
  vs 40.2; fitting the untimed shifts with both models' predictions at once gives the manual's
  a weight of 0.81 and Nebula's -0.14. The VLP-32C recording (nominal calibration, half a field
  of view, 2 388 edges) cannot tell: a 112 millidegree per-pair pattern that neither model
  explains (the nominal ``rot_correction`` values, presumably) swamps the difference. Its
  points are 15-28 % within 2 mm of Nebula's (the same ranges and elevations, other
  azimuths). ``beam_time_offsets`` are the manual's in both models (Nebula's point times
  agree), and ``beam_azimuth_offsets`` too (a consumer that ignores the azimuth channel gets
  the manual geometry).
- LidarInfo: ``vertical_angles`` = vert_correction, ``beam_origins`` from the vertical and
  horizontal offsets, ``beam_range_offsets`` = dist_correction, ``range_min``/``range_max`` =
  0 and 65535 units unless given; ``model`` = the product name. Not representable, so not
  applied: the HDL-64 two-point distance corrections and the intensity (focal) corrections.
- A sensor with a restricted field of view sends a packet that ends before the gap and continues
  after it: sequences after an azimuth jump (> 5 deg) inside a packet are timed from the next
  packet.
"""

from converters.sources.velodyne.calibration import (
    VLP16_CALIBRATION,
    VLP16_CYCLE_NS,
    VLP16_FIRING_NS,
    VLP32C_CALIBRATION,
    info_from_calibration,
    laser_ids_by_row,
    load_calibration,
    scan_from_firings,
)
from converters.sources.velodyne.decoder import PacketDecoder, decode_packets
from converters.sources.velodyne.packets import MODELS, PACKET_SIZE, VelodyneModel

__all__ = [
    "MODELS",
    "PACKET_SIZE",
    "PacketDecoder",
    "VLP16_CALIBRATION",
    "VLP16_CYCLE_NS",
    "VLP16_FIRING_NS",
    "VLP32C_CALIBRATION",
    "VelodyneModel",
    "decode_packets",
    "info_from_calibration",
    "laser_ids_by_row",
    "load_calibration",
    "scan_from_firings",
]
