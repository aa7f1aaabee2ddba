"""The clouds ROS 2's ``velodyne_pointcloud`` publishes for a VLP-16, made from packets by its
rules; and VLP-16 dual-return packets made from the real VLP-32C recording in tests/data.

The rules (facts read from the driver's public sources, ros-drivers/velodyne branch ``ros2``
(04a7ca7): ``velodyne_pointcloud/src/lib/rawdata.cpp`` (``buildTimings``, ``unpack_vlp16``),
``calibration.cpp``, ``pointcloudXYZIRT.cpp``, ``organized_cloudXYZIRT.cpp``,
``datacontainerbase.hpp``, ``conversions/transform.cpp``,
``velodyne_driver/src/driver/driver.cpp``; this code is our own):

1. ``ring`` = rank of the laser's ``vert_correction``, rising (0 = the lowest beam).
2. The VelodyneScan, hence the cloud, is stamped with its LAST packet's stamp
   (``timestamp_first_packet`` false by default); a point's ``time`` (float32 s) is its firing
   offset plus ``packet stamp - cloud stamp``: negative but for the last packet, and jittery
   because packet stamps are receive times.
3. Firing offsets come from the single-return VLP-16 table for every packet (its ``dual_mode``
   is hard-wired false): block x, firing sequence f, laser d at
   ``110.592 x + 55.296 f + 2.304 d`` us. In a dual-return packet blocks 2k and 2k+1 hold the
   last and the strongest return of the same two firing sequences, so the second return of a
   firing is stamped 110.592 us after the first and a packet's offsets reach 1.306 ms (twice
   the 663.5 us the packet covers).
4. Azimuth of a point: ``block azimuth + diff * (2.304 d + 55.296 f) / 110.592``, rounded to
   0.01 deg, ``diff`` = the NEXT BLOCK's azimuth - this block's, in every return mode
   (``raw->blocks[block + 1].rotation - raw->blocks[block].rotation`` in ``unpack_vlp16`` on
   ``ros2`` d2304ce and ``humble-devel`` d8cf623, as on ROS 1 ``master``; only the VLS-128
   path looks ``1 + dual_return`` blocks ahead); the last block takes the previous diff; a
   negative diff takes the previous one, or skips the block when that was 0. In a dual packet
   both blocks of a pair carry one azimuth, so an even block's diff is 0: all its points (both
   firing sequences, every laser) sit at the pair's azimuth, the odd block's points at their
   firings' azimuths, and the last pair of a packet (block 11 takes block 10's zero diff) has
   all four echoes at its pair's azimuth; an odd block whose next pair wraps past 0 deg is
   skipped. No grid of one direction per pixel and a per-beam azimuth offset holds the
   first echoes (up to 1.6 firing steps off); from_pointcloud2 gives each pixel its own
   azimuth (channels ``azimuth``, ``azimuth2``).
5. x, y, z from the calibration (distance = raw * 0.002 m + dist_correction, vertical and
   horizontal offsets, ROS axes x = y', y = -x'), float32, sin/cos from a 0.01 deg table;
   points outside [0.9, 130] m (the default min_range / max_range) and no-returns are out of
   range; every other point is published, both points of an identical pair (a single echo is
   reported in both blocks of a pair) included. ``organize_cloud`` (default true,
   ``transform.cpp``): ``OrganizedCloudXYZIRT``, one row of 16 points per firing sequence of
   a block, the point of ring r in column r, out-of-range points NaN x/y/z/intensity with
   their ring and time (so the silent laser's ring is in the cloud, with NaN points only);
   false: ``PointcloudXYZIRT``, the in-range points in packet / block / firing / laser order,
   height 1.
6. Fields (both containers, packed as ``setPointCloud2Fields`` lays them out): x, y, z,
   intensity float32, ring uint16, time float32: 22 bytes a point. ``with_time=False`` leaves
   ``time`` out (clouds whose time field was dropped).

The packets (:func:`vlp16_dual_packets`): there is no VLP-16 recording in tests/data, so the
real VLP-32C recording (tests/data/nebula/velodyne_vlp32, single return, packets 663.5 us apart
like a VLP-16 dual-return stream, real receive stamps) is re-packed: VLP-32C blocks 2k and 2k+1
(two firing sequences) become the VLP-16 block pair k (same azimuth, same stamp), 16 of its 32
lasers (those nearest to the VLP-16's -15..15 deg fan) become VLP-16 lasers with their own
calibration lines, each echo is reported in both blocks (the VLP-16's single-echo rule: every
pair identical), and one laser is silent.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

VLP16_BLOCK_US, VLP16_FIRING_US, VLP16_LASER_US = 110.592, 55.296, 2.304
MIN_RANGE, MAX_RANGE = 0.9, 130.0
SILENT_LASER = 9

#: PointcloudXYZIRT's fields as setPointCloud2Fields packs them (offset, PointField datatype)
FIELDS = (("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7), ("ring", 16, 4),
          ("time", 18, 7))


def timing_offsets() -> np.ndarray[Any, Any]:
    """(12, 32) float64 seconds: the driver's VLP-16 table (single-return, for every packet)."""
    x = np.arange(12)[:, None]
    y = np.arange(32)[None, :]
    return (VLP16_FIRING_US * (2 * x + y // 16) + VLP16_LASER_US * (y % 16)) * 1e-6


def laser_rings(vert_correction: Sequence[float]) -> np.ndarray[Any, Any]:
    """Ring of each laser: rank of its elevation, rising (ties by laser id)."""
    v = np.asarray(vert_correction, np.float64)
    rings = np.empty(v.size, np.int64)
    rings[np.lexsort((np.arange(v.size), v))] = np.arange(v.size)
    return rings


def _laser_table(calibration: Mapping[str, Any]) -> dict[str, np.ndarray[Any, Any]]:
    by_id = {int(laser["laser_id"]): laser for laser in calibration["lasers"]}
    keys = ("vert_correction", "rot_correction", "dist_correction", "vert_offset_correction",
            "horiz_offset_correction")
    return {k: np.array([float(by_id[i].get(k, 0.0)) for i in range(len(by_id))])
            for k in keys}


def _azimuth_units(blocks: np.ndarray[Any, Any]
                   ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """(12, 32) int azimuth (0.01 deg) of each point of one packet, (12,) block kept: the
    driver's gap to the NEXT block, whatever the return mode."""
    out = np.zeros((12, 32), np.int64)
    kept = np.ones(12, bool)
    last_diff = 0.0
    k = np.arange(32)
    frac = (VLP16_LASER_US * (k % 16) + VLP16_FIRING_US * (k // 16)) / VLP16_BLOCK_US
    for b in range(12):
        az = float(blocks[b])
        if b < 11:
            raw = int(blocks[b + 1]) - int(blocks[b])
            diff = float((36000 + raw) % 36000)
            if raw < 0:
                if last_diff > 0:
                    diff = last_diff
                else:
                    kept[b] = False
                    continue
            last_diff = diff
        else:
            diff = last_diff
        out[b] = np.asarray([math.floor(az + diff * f + 0.5) % 36000 for f in frac])  # C round
    return out, kept


def velodyne_cloud(packets: Sequence[tuple[int, bytes]], calibration: Mapping[str, Any], *,
                   with_time: bool = True, organize_cloud: bool = True,
                   frame_id: str = "velodyne") -> tuple[Any, dict[str, np.ndarray[Any, Any]]]:
    """The ``sensor_msgs/PointCloud2`` velodyne_pointcloud makes of one VelodyneScan of VLP-16
    packets (the rules in the module docstring), and the source of each of its finite points.

    Args:
        packets: [(packet stamp ns, 1206-byte payload)] of one scan message, in order.
        calibration: ros-drivers calibration (``lasers`` with ``laser_id``, corrections).
        with_time: publish the ``time`` field (False: a cloud whose time field was dropped).
        organize_cloud: the driver's ``organize_cloud`` (default true): one row a firing
            sequence of a block (16 points by ring, NaN x/y/z/intensity out of range); false:
            the in-range points only, height 1.

    Returns:
        (cloud dataclass, {"packet", "block", "firing", "laser", "xyz" (N, 3) float64} of the
        finite points in cloud order).
    """
    from cloud_oracles import make_cloud

    table = _laser_table(calibration)
    rings = laser_rings(table["vert_correction"])
    cos_t = np.cos(np.radians(np.arange(36000) * 0.01).astype(np.float32)).astype(np.float32)
    sin_t = np.sin(np.radians(np.arange(36000) * 0.01).astype(np.float32)).astype(np.float32)
    offsets = timing_offsets()
    stamp = int(packets[-1][0])
    f32 = np.float32
    nan = f32("nan")
    names = ("x", "y", "z", "intensity", "ring", "time", "packet", "block", "firing", "laser")
    cols: dict[str, list[Any]] = {n: [] for n in names}
    rows = 0
    for p, (pkt_stamp, data) in enumerate(packets):
        blocks = np.array([struct.unpack_from("<H", data, 100 * b + 2)[0] for b in range(12)])
        az_units, kept = _azimuth_units(blocks)
        rel = f32((pkt_stamp - stamp) * 1e-9)
        for b in range(12):
            if struct.unpack_from("<H", data, 100 * b)[0] != 0xEEFF:
                break                                    # bad packet: the rest is skipped
            if not kept[b]:
                continue
            for f in range(2):
                line = [None] * 16
                for d in range(16):
                    k = 16 * f + d
                    raw, refl = struct.unpack_from("<HB", data, 100 * b + 4 + 3 * k)
                    distance = f32(f32(raw * 0.002) + f32(table["dist_correction"][d]))
                    point = (nan, nan, nan, nan)
                    if MIN_RANGE <= distance <= MAX_RANGE:
                        cv, sv = f32(math.cos(table["vert_correction"][d])), f32(
                            math.sin(table["vert_correction"][d]))
                        cr, sr = f32(math.cos(table["rot_correction"][d])), f32(
                            math.sin(table["rot_correction"][d]))
                        a = int(az_units[b, k])
                        cos_rot = cos_t[a] * cr + sin_t[a] * sr
                        sin_rot = sin_t[a] * cr - cos_t[a] * sr
                        h, v = f32(table["horiz_offset_correction"][d]), f32(
                            table["vert_offset_correction"][d])
                        xy = distance * cv - v * sv
                        x = xy * sin_rot - h * cos_rot
                        y = xy * cos_rot + h * sin_rot
                        z = distance * sv + v * cv
                        point = (y, -x, z, f32(refl))
                    elif not organize_cloud:
                        continue
                    line[rings[d]] = (*point, rings[d], f32(f32(offsets[b, k]) + rel),
                                      p, b, f, d)
                rows += 1                # organized: one row a firing sequence, by ring
                seq = line if organize_cloud else [v for d in range(16)
                                                   for v in [line[rings[d]]] if v is not None]
                for v in seq:
                    for n, value in zip(names, v):
                        cols[n].append(value)
    names_out = [n for n, _, _ in FIELDS if with_time or n != "time"]
    dtype = np.dtype({"names": names_out,
                      "formats": ["<u2" if n == "ring" else "<f4" for n in names_out],
                      "offsets": [o for n, o, _ in FIELDS if n in names_out],
                      "itemsize": 22 if with_time else 18})
    pts = np.zeros(len(cols["x"]), dtype)
    for n in names_out:
        pts[n] = cols[n]
    height, width = (rows, 16) if organize_cloud else (1, pts.size)
    cloud = make_cloud(pts, height=height, width=width, stamp_ns=stamp, frame_id=frame_id)
    finite = np.isfinite(np.asarray(cols["x"], np.float64))
    source = {n: np.asarray(cols[n], np.int64)[finite]
              for n in ("packet", "block", "firing", "laser")}
    source["xyz"] = np.stack([np.asarray(cols[a], np.float64)[finite] for a in "xyz"], -1)
    return cloud, source


# ----------------------------------------------------------- VLP-16 packets from the VLP-32C

def vlp16_lasers(calibration32: Mapping[str, Any]) -> list[int]:
    """The 16 VLP-32C laser ids nearest to the VLP-16 fan (-15, 1, -13, 3, ..., -1, 15 deg, in
    VLP-16 laser order), each used once."""
    vert = _laser_table(calibration32)["vert_correction"]
    free = set(range(vert.size))
    out = []
    for d in range(16):
        want = math.radians(d - 15 if d % 2 == 0 else d)
        best = min(free, key=lambda i: (abs(vert[i] - want), i))
        free.remove(best)
        out.append(best)
    return out


def vlp16_calibration(calibration32: Mapping[str, Any]) -> dict[str, Any]:
    """The VLP-16 calibration of the re-packed lasers: laser d = the VLP-32C laser
    ``vlp16_lasers()[d]``'s calibration line, 2 mm distance units."""
    by_id = {int(laser["laser_id"]): laser for laser in calibration32["lasers"]}
    return {"num_lasers": 16, "distance_resolution": 0.002,
            "lasers": [{**by_id[src], "laser_id": d}
                       for d, src in enumerate(vlp16_lasers(calibration32))]}


def vlp16_dual_packets(packets32: Sequence[tuple[int, bytes]], calibration32: Mapping[str, Any],
                       *, silent: int | None = SILENT_LASER) -> list[tuple[int, bytes]]:
    """VLP-16 dual-return packets (product 0x22, mode 0x39) carrying the VLP-32C packets'
    echoes: block pair k = VLP-32C blocks 2k, 2k+1 (firing sequences 0, 1), azimuth of block
    2k, both blocks the same echo (4 mm units -> 2 mm; beyond 131 m none), laser ``silent``
    without returns; same stamps and sensor timestamps."""
    lasers = vlp16_lasers(calibration32)
    out = []
    for stamp, data in packets32:
        body = bytearray()
        for k in range(6):
            az = struct.unpack_from("<H", data, 100 * 2 * k + 2)[0]
            points = bytearray()
            for f in range(2):
                for d in range(16):
                    raw, refl = struct.unpack_from("<HB", data, 100 * (2 * k + f) + 4
                                                   + 3 * lasers[d])
                    raw = 2 * raw if 2 * raw <= 0xFFFF else 0
                    if d == silent:
                        raw, refl = 0, 0
                    points += struct.pack("<HB", raw, refl)
            for _ in range(2):                         # last, strongest: the same echo
                body += struct.pack("<HH", 0xEEFF, az) + points
        body += data[1200:1204] + bytes([0x39, 0x22])
        out.append((int(stamp), bytes(body)))
    return out
