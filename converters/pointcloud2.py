"""LidarScan <-> sensor_msgs/PointCloud2, with driver presets, deskew and geometry estimation.

LidarScan -> PointCloud2
========================
:func:`to_pointcloud2` (or a reusable :class:`PointCloud2Converter`) projects a scan with the
cached :func:`lidarscan.make_projector` tables (``P = rho * D + O``) and writes every field
straight into one structured numpy buffer (names / offsets / itemsize = ``point_step``), little
endian, ``row_step = point_step * width``. Points of pixels without a return (range +Inf, NaN,
<= 0, raw 0) are NaN in organized clouds (``is_dense`` false) and dropped in unorganized ones.

Fields (``fields=``, when no preset is given; x, y, z are required):

==============  =========  ==================================================================
name            datatype   value
==============  =========  ==================================================================
x, y, z         FLOAT32    metres in the info's frame (REP 103)
ring            UINT16     beam index (row, 0 = top beam)
t               UINT32     ns since the cloud's header stamp
time            FLOAT32    s since the cloud's header stamp
timestamp       FLOAT64    absolute s (sensor clock of the scan stamp)
range           FLOAT32    metres along the beam (NaN without return)
intensity       FLOAT32    the ``intensity`` channel (alias ``signal``) as float32
any other       native     the scan channel of that name (aliases: ambient = near_ir/nearir,
                           reflectivity = reflec), its own datatype and count
==============  =========  ==================================================================

Generic layouts place fields in the order given at their natural alignment (x, y, z, intensity
-> the 16-byte XYZI layout). Per-point time = ``column_time_offsets[c] + beam_time_offsets[u]``
(:meth:`lidarscan.Projector.pixel_times`), so it follows destaggering.

Presets (``preset=``) reproduce what the drivers publish, so consumers work unchanged
(LIO-SAM needs ring + time, FAST-LIO / kiss-icp / rtabmap probe t / time / timestamp):

============  =================================================================  ====  ==========
preset        fields: name type @offset                                          step  source
============  =================================================================  ====  ==========
ouster        x,y,z f32 @0,4,8; intensity f32 @16; t u32 @20; reflectivity u16   48    [1]
              @24; ring u16 @26; ambient u16 @28; range u32 @32 (mm); padding
ouster_xyzi   x,y,z,intensity f32 @0,4,8,12                                      16    [2]
ouster_xyzir  x,y,z f32 @0,4,8; intensity f32 @16; ring u16 @20                  32    [1]
velodyne      x,y,z,intensity f32 @0..12; ring u16 @16; time f32 @18 (packed)    22    [3]
hesai         x,y,z,intensity f32 @0..12; ring u16 @16; timestamp f64 @18        26    [4]
robosense     x,y,z,intensity f32 @0..12; ring u16 @16; timestamp f64 @18        26    [5]
xyzi          x,y,z,intensity f32 @0,4,8,12                                      16    --
============  =================================================================  ====  ==========

[1] ouster-ros ``include/ouster_ros/os_point.h`` (``ouster_ros::Point``: PCL_ADD_POINT4D then the
fields, EIGEN_ALIGN16 -> 48 bytes; ``PointXYZIR``: 32 bytes), organized H x W destaggered,
``t`` = ns since the header stamp = time of measurement column 0, ``ring`` = row (0 = top beam),
``range`` = raw millimetres (0 = no return), NaN points for no return.
[2] ouster-ros ``include/ouster_ros/common_point_types.h`` (``_Ouster_PointXYZI``, 16 bytes).
[3] ros-drivers/velodyne ``velodyne_pointcloud/src/lib/pointcloudXYZIRT.cpp``: packed 22-byte
points, header stamp = the scan's LAST packet, ``time`` = s relative to it (<= 0), ``ring``
0 = lowest beam (``H-1-row``: rows run top to bottom, rings bottom to top); unorganized, points
in firing order; organized (``organize_cloud``): height = firings, width = lasers by ring.
[4] HesaiLidar_ROS_2.0 ``src/manager/source_driver_ros2.hpp``: unorganized, header stamp = frame
start (earliest point), ``timestamp`` = absolute s, ``ring`` = the correction-file channel order
(``beam_ids`` when given, else the row: Hesai channels run top to bottom).
[5] rslidar_sdk ``src/source/source_pointcloud_ros.hpp``: as Hesai; header stamp = first point,
``ring`` 0 = lowest beam (``H-1-row``); organized (``send_by_rows`` false, the default) =
height firings x width lasers.

Presets choose their defaults for ``organized`` / ``destagger`` / ``time_reference`` (ouster:
organized, destaggered, "stamp"; velodyne: unorganized, firing order, "last"; hesai/robosense:
unorganized, firing order, "first"); explicit arguments override them. ``time_reference``:
"stamp" (cloud stamp = scan stamp, time of measurement column 0), "first" (earliest pixel time),
"last" (latest pixel time). Preset channel fields missing from a scan are zero-filled.

Deskew: ``motion=`` (:mod:`converters.deskew`) moves every point to the pose at the cloud's header
stamp (or ``motion.reference_ns``) using each pixel's own time.

PointCloud2 -> LidarScan + LidarInfo
====================================
:func:`from_pointcloud2` estimates the geometry of the beam model from the points themselves:
organized clouds (rows = beams, e.g. ouster-ros H x W destaggered) and ring-tagged clouds
(velodyne with ring + time, Hesai / RoboSense with ring + timestamp; organized velodyne clouds
too). The model fitted, in the cloud's frame (spin axis = z, identity lidar_to_sensor)::

    theta(u, c) = alpha_c + beta_u       P = Rz(theta) (0, o_y[u], o_z[u]) + rho * d(theta, phi_u)

The along-beam offset is gauge-free (``o_x = 0``: rho is measured from where the beam line
crosses the spin axis) unless the cloud has a range field (ouster-ros ``range`` mm), whose values
are kept and the full offset fitted. Column order / stagger come from per-point times (the time of
each destaggered pixel reveals its measurement column); without times the cloud's own column order
is used (exact for organized clouds, whose destaggered columns still fit ``alpha_v + beta'_u``).
:func:`estimation_error` re-projects the estimate and compares it with the cloud's points.

What is achievable (tests/test_pointcloud2.py): ouster-ros clouds of the REAL Ouster frames in
tests/data re-project to <= 0.03 mm (float32 rounding; OS-2-128 0.015 mm max with the range
field, 0.03 mm from xyz alone; OS-0-32 0.005 mm), times exactly; a noise-free VLP-16-like ring
cloud to 0.006 mm, times to 4 ns (f32 relative) or ~0.27 us (f64 absolute seconds: that is the
float64 resolution of an epoch time). Real Velodyne output is bounded by the driver itself:
velodyne_pointcloud rounds every laser's interpolated azimuth to 0.01 deg, a per-point pattern a
per-column + per-beam model cannot hold, so expect up to ~1.3e-4 rad x range (simulated VLP-16:
7.6 mm max at 60 m, 1.5 mm RMS). Very sparse clouds (most columns with < 2 points, e.g. second
returns) are fitted with evenly spaced column azimuths.

Speed: the hot loop (validity of each range, x, y, z, one float32 channel field such as
intensity, destaggering, dropping invalid points for unorganized row-order clouds) runs in an
optional compiled kernel, ``converters/_cloudkernel.c``, that ``pip install [-e] .`` builds when a
C compiler is available (:func:`kernel_available`; ``LIDARSCAN_NO_KERNEL=1`` or ``kernel=False``
turn it off); every other field, and everything without the kernel, is numpy (~8 passes over the
image). The kernel projects from the factored beam model
(:func:`lidarscan.geometry.beam_factors`: per-beam and per-column factors that stay in the
caches, instead of 24 bytes of per-pixel tables per point), the numpy path from the projector's
float32 tables ``r * D + O``: both are float32 evaluations of the same model, a few ulps apart
(< 0.05 mm on a real OS-2 frame against the float64 model). Every other byte is identical,
including the canonical quiet NaN (0x7fc00000) of every point without a return. Infos with
per-pixel angles do not factor; the kernel then reads the tables, byte-identical to numpy
(float32 products and sums in the same order, no fused multiply-add, -0 table offsets
normalised to +0). The kernel's arithmetic is deterministic: the AVX-512, AVX2 and baseline
builds it picks from at load time give the same bits. Layouts without padding reuse the
buffer of the converter's previous message once that message was dropped (no allocation and
zero-fill). bench/bench_pointcloud2.py compares both paths with ouster-sdk's XYZLut. Rows can be
split over threads (``threads=``).
"""

from __future__ import annotations

import array
import ctypes
import dataclasses
import itertools
import math
import sys
import threading
from collections import OrderedDict
from collections.abc import Sequence
from typing import Any

import numpy as np

from lidarscan.datatypes import FLOAT32, FLOAT64, UINT16, UINT32, datatype_of, dtype_of
from lidarscan.errors import (
    ConfigError,
    ConversionError,
    InfoMismatchError,
    LinkageError,
    UnknownChannelError,
    ValidationError,
)
from converters import _ckernel
from converters._rosmsg import bare_message
from lidarscan.geometry import info_key, make_projector
from lidarscan.scan import _as_array, channel, make_info, make_scan
from lidarscan.stamps import split_ns, to_ns

__all__ = [
    "PRESETS",
    "FieldSpec",
    "PointCloud2Converter",
    "Preset",
    "ReprojectionError",
    "cloud_dtype",
    "estimation_error",
    "from_pointcloud2",
    "kernel_available",
    "read_points",
    "to_pointcloud2",
]

_NS = 1_000_000_000

#: Channel aliases tried in order when a field names a scan channel.
CHANNEL_ALIASES: dict[str, tuple[str, ...]] = {
    "intensity": ("intensity", "signal"),
    "ambient": ("ambient", "near_ir", "nearir"),
    "reflectivity": ("reflectivity", "reflec"),
}

_COMPUTED = {"x", "y", "z", "ring", "t", "time", "timestamp", "range"}
_TIME_REFERENCES = ("stamp", "first", "last")


# ============================================================================ compiled kernel

#: ABI of converters/_cloudkernel.c (its LSK_ABI): a stale build is ignored, not called.
_KERNEL_ABI = 3
#: Source type codes of the kernel (native byte order only).
_KERNEL_TYPES = {"f4": 0, "f8": 1, "u1": 2, "u2": 3, "u4": 4, "i1": 5, "i2": 6, "i4": 7}
_KERNEL_MULTIPLY, _KERNEL_OFFSET = 1, 2


#: Output buffers a converter keeps for reuse (the caller may hold the previous messages).
_POOL = 3


@dataclasses.dataclass(frozen=True)
class _Kernels:
    """The compiled kernel's entry points (ctypes functions; they release the GIL)."""

    project: Any        # lsk_project: per-pixel direction / offset tables
    project_rc: Any     # lsk_project_rc: the factored beam model (per-beam, per-column factors)


def _kernel() -> _Kernels | None:
    """The compiled kernel's entry points (:class:`_Kernels`), or None.

    None when the extension was not built (no compiler: the install still succeeds), is stale,
    or the environment variable ``LIDARSCAN_NO_KERNEL`` is set to anything but "" / "0" (read at
    the first conversion of the process).
    """
    kernels: _Kernels | None = _kernel_once.get()
    return kernels


def _load_kernel() -> Any:
    lib = _ckernel.load_library("converters._cloudkernel", "lsk_abi", _KERNEL_ABI)
    if lib is None:
        return None
    fn, rc = lib.lsk_project, lib.lsk_project_rc
    i64, i32, f32, ptr = ctypes.c_int64, ctypes.c_int32, ctypes.c_float, ctypes.c_void_p
    fn.restype = i64
    fn.argtypes = [ptr, i64, i64, i64, i64,          # out, point_step, xyz_offset, start, n
                   ptr, i32,                         # range, range_type
                   ptr, ptr, i64,                    # gather, roll, width
                   i32, f32, f32,                    # scale flags, multiplier, offset
                   ptr, ptr,                         # D, O (pixels, 3) float32
                   ptr, i32, i64,                    # extra, extra_type, extra_offset
                   ptr, i32]                         # r_out, dense
    rc.restype = i64
    rc.argtypes = [ptr, i64, i64, i64, i64,          # out, point_step, xyz_offset, start, n
                   ptr, i32,                         # range, range_type
                   ptr, ptr, i64,                    # roll, colshift, width
                   i32, f32, f32,                    # scale flags, multiplier, offset
                   ptr, ptr, ptr,                    # beam, column factors, constant
                   ptr, i32, i64,                    # extra, extra_type, extra_offset
                   ptr, i32]                         # r_out, dense
    return _Kernels(fn, rc)


_kernel_once = _ckernel.LoadOnce(_load_kernel)


def kernel_available() -> bool:
    """Whether LidarScan -> PointCloud2 uses the compiled kernel (converters/_cloudkernel.c).

    The kernel is optional; it is built by ``pip install [-e] .`` when a C compiler is
    available. ``LIDARSCAN_NO_KERNEL=1`` disables it. It projects from the factored beam model
    (:func:`lidarscan.geometry.beam_factors`) where the info has no per-pixel angles, and from
    the same per-pixel tables as the numpy path otherwise (then bit-identical to it); the two
    forms are float32 evaluations of one model, a few ulps apart (both well within 0.1 mm).
    """
    return _kernel() is not None


def _kernel_type(image: np.ndarray[Any, Any]) -> int | None:
    """Kernel type code of a native-order image, or None."""
    if not image.dtype.isnative:
        return None
    return _KERNEL_TYPES.get(image.dtype.str[1:])


def _addr(a: np.ndarray[Any, Any]) -> int:
    """Address of an array's first element (``.ctypes.data``: no dtype description is built,
    unlike ``__array_interface__``, slow for structured dtypes)."""
    return int(a.ctypes.data)


# ==================================================================================== presets

@dataclasses.dataclass(frozen=True)
class FieldSpec:
    """One PointField of an output layout.

    Attributes:
        name: PointField name.
        datatype: PointField datatype id (1..8).
        offset: byte offset inside the point.
        source: "x", "y", "z", "ring", "t", "time", "timestamp", "range" or "channel".
        channels: channel names tried in order for source "channel".
        count: PointField count.
    """

    name: str
    datatype: int
    offset: int
    source: str
    channels: tuple[str, ...] = ()
    count: int = 1


@dataclasses.dataclass(frozen=True)
class Preset:
    """A driver's PointCloud2 layout and conventions (see the module docstring).

    Attributes:
        name: preset name.
        fields: the PointFields.
        point_step: bytes per point (padding included).
        time_reference: default header-stamp convention ("stamp", "first", "last").
        ring: "row" (row index, 0 = top beam), "low" (H-1-row: 0 = lowest beam, the rank by
            elevation that Velodyne / RoboSense rings are), "ids" (``LidarInfo.beam_ids``, the
            vendor's numbering, or the row index when empty).
        organized: default for ``organized``.
        destagger: default for ``destagger``.
        order: "rows" (H x W image) or "firings" (firing by firing, beams by ring; organized
            clouds are firings x beams).
        source: the driver source the layout comes from.
    """

    name: str
    fields: tuple[FieldSpec, ...]
    point_step: int
    time_reference: str = "stamp"
    ring: str = "row"
    organized: bool = True
    destagger: bool = True
    order: str = "rows"
    source: str = ""


def _xyz(offsets: tuple[int, int, int] = (0, 4, 8)) -> tuple[FieldSpec, ...]:
    return tuple(FieldSpec(n, FLOAT32, o, n) for n, o in zip("xyz", offsets))


def _chan(name: str, datatype: int, offset: int) -> FieldSpec:
    return FieldSpec(name, datatype, offset, "channel", CHANNEL_ALIASES.get(name, (name,)))


PRESETS: dict[str, Preset] = {
    "ouster": Preset(
        "ouster",
        _xyz() + (_chan("intensity", FLOAT32, 16), FieldSpec("t", UINT32, 20, "t"),
                  _chan("reflectivity", UINT16, 24), FieldSpec("ring", UINT16, 26, "ring"),
                  _chan("ambient", UINT16, 28), FieldSpec("range", UINT32, 32, "range")),
        48, source="ouster-ros include/ouster_ros/os_point.h (ouster_ros::Point)"),
    "ouster_xyzi": Preset(
        "ouster_xyzi", _xyz() + (_chan("intensity", FLOAT32, 12),), 16,
        source="ouster-ros include/ouster_ros/common_point_types.h (PointXYZI)"),
    "ouster_xyzir": Preset(
        "ouster_xyzir",
        _xyz() + (_chan("intensity", FLOAT32, 16), FieldSpec("ring", UINT16, 20, "ring")), 32,
        source="ouster-ros include/ouster_ros/os_point.h (PointXYZIR)"),
    "velodyne": Preset(
        "velodyne",
        _xyz() + (_chan("intensity", FLOAT32, 12), FieldSpec("ring", UINT16, 16, "ring"),
                  FieldSpec("time", FLOAT32, 18, "time")),
        22, time_reference="last", ring="low", organized=False, destagger=False,
        order="firings",
        source="ros-drivers/velodyne velodyne_pointcloud/src/lib/pointcloudXYZIRT.cpp"),
    "hesai": Preset(
        "hesai",
        _xyz() + (_chan("intensity", FLOAT32, 12), FieldSpec("ring", UINT16, 16, "ring"),
                  FieldSpec("timestamp", FLOAT64, 18, "timestamp")),
        26, time_reference="first", ring="ids", organized=False, destagger=False,
        order="firings", source="HesaiLidar_ROS_2.0 src/manager/source_driver_ros2.hpp"),
    "robosense": Preset(
        "robosense",
        _xyz() + (_chan("intensity", FLOAT32, 12), FieldSpec("ring", UINT16, 16, "ring"),
                  FieldSpec("timestamp", FLOAT64, 18, "timestamp")),
        26, time_reference="first", ring="low", organized=False, destagger=False,
        order="firings", source="rslidar_sdk src/source/source_pointcloud_ros.hpp"),
    "xyzi": Preset("xyzi", _xyz() + (_chan("intensity", FLOAT32, 12),), 16,
                   source="minimal x, y, z, intensity"),
}

_DEFAULT_FIELDS = ("x", "y", "z", "intensity")
_COMPUTED_TYPES = {"x": FLOAT32, "y": FLOAT32, "z": FLOAT32, "ring": UINT16, "t": UINT32,
                   "time": FLOAT32, "timestamp": FLOAT64, "range": FLOAT32}


def _generic_layout(names: Sequence[str], scan: Any) -> tuple[tuple[FieldSpec, ...], int]:
    """Fields in the given order at natural alignment; channel fields take the scan's dtype."""
    specs: list[FieldSpec] = []
    offset, align = 0, 4
    for name in names:
        chans: tuple[str, ...] = ()
        if name in _COMPUTED_TYPES:
            datatype, count, source = _COMPUTED_TYPES[name], 1, name
        else:
            chans = CHANNEL_ALIASES.get(name, (name,))
            source = "channel"
            if name == "intensity":
                datatype, count = FLOAT32, 1
            else:
                desc = _find_channel(scan, chans)
                if desc is None:
                    raise UnknownChannelError("fields", name,
                                              f"one of the scan's channels "
                                              f"{[c.name for c in scan.channels]} or "
                                              f"{sorted(_COMPUTED_TYPES)}")
                datatype, count = int(desc.datatype), int(desc.count)
        size = dtype_of(datatype).itemsize
        offset += -offset % size
        specs.append(FieldSpec(name, datatype, offset, source, chans, count))
        offset += size * count
        align = max(align, size)
    return tuple(specs), offset + (-offset % align)


def _find_channel(scan: Any, names: Sequence[str]) -> Any:
    for name in names:
        for desc in scan.channels:
            if desc.name == name:
                return desc
    return None


def _structured(specs: Sequence[FieldSpec], point_step: int, bigendian: bool = False
                ) -> np.dtype[Any]:
    formats: list[Any] = []
    for s in specs:
        base = dtype_of(s.datatype, bigendian)
        formats.append(base if s.count == 1 else (base, (s.count,)))
    return np.dtype({"names": [s.name for s in specs], "formats": formats,
                     "offsets": [s.offset for s in specs], "itemsize": point_step})


# ================================================================================ row rolling

def _shift_groups(shifts: np.ndarray[Any, Any], width: int) -> list[tuple[Any, int]]:
    """Rows grouped by shift (mod W): (slice or index array, shift) pairs."""
    values = np.asarray(shifts, dtype=np.int64) % max(width, 1)
    groups: list[tuple[Any, int]] = []
    for value in np.unique(values):
        rows = np.flatnonzero(values == value)
        step = int(rows[1] - rows[0]) if rows.size > 1 else 1
        if rows.size == 1 or np.all(np.diff(rows) == step):
            sel: Any = slice(int(rows[0]), int(rows[-1]) + 1, step)
        else:
            sel = rows
        groups.append((sel, int(value)))
    return groups


def _roll_into(dst: np.ndarray[Any, Any], src: np.ndarray[Any, Any],
               groups: list[tuple[Any, int]] | None, sign: int) -> None:
    """``dst[u, (c + sign * s_u) mod W] = src[u, c]`` (destagger: sign +1, restagger: -1).

    ``dst`` may be a strided field view of another dtype (values are cast).
    """
    if groups is None:
        dst[...] = src
        return
    width = src.shape[1]
    for rows, shift in groups:
        k = (sign * shift) % width
        if k == 0:
            dst[rows] = src[rows]
        else:
            dst[rows, k:] = src[rows, :width - k]
            dst[rows, :k] = src[rows, width - k:]


# ================================================================================= converter

def _xy_pair(grid: np.ndarray[Any, Any], specs: Sequence[FieldSpec]
             ) -> np.ndarray[Any, Any] | None:
    """complex64 (H, W) view of adjacent float32 x, y fields of a C-contiguous grid, or None."""
    by_name = {s.name: s for s in specs}
    sx, sy = by_name.get("x"), by_name.get("y")
    if (sx is None or sy is None or sx.source != "x" or sy.source != "y"
            or not sx.datatype == FLOAT32 == sy.datatype or sy.offset != sx.offset + 4
            or not grid.flags.c_contiguous):
        return None
    # a plain ndarray over the buffer (a structured-field view of the same bytes makes numpy's
    # ufuncs take a much slower path)
    return np.ndarray(grid.shape, np.complex64, buffer=grid, offset=sx.offset,
                      strides=grid.strides)


@dataclasses.dataclass
class _Block:
    rows: slice
    groups: list[tuple[Any, int]] | None      # destagger row groups, relative to rows.start


@dataclasses.dataclass
class _Job:
    scan: Any
    raw: np.ndarray[Any, Any]
    grid: np.ndarray[Any, Any]
    pair: np.ndarray[Any, Any] | None
    specs: Sequence[FieldSpec]
    tables: _Planes | None                    # None: the kernel's factored form does x, y, z
    images: dict[str, Any]
    times: np.ndarray[Any, Any] | None
    ref: int
    stamp_ns: int
    scan_dest: bool
    kernel: _KernelJob | None = None


@dataclasses.dataclass(frozen=True)
class _Plan:
    """What the kernel writes for one layout and scan (see PointCloud2Converter._kernel_plan)."""

    xyz_offset: int
    raw: np.ndarray[Any, Any]                 # the range image, C-contiguous and aligned
    raw_type: int                             # its kernel type code
    extra: FieldSpec | None                   # a float32 channel field, or None
    image: np.ndarray[Any, Any] | None        # its channel image
    extra_type: int
    covers_all: bool                          # x, y, z (+ extra) are all the fields


@dataclasses.dataclass
class _KernelJob:
    """Arguments of one ``lsk_project`` call over the whole grid (addresses as ints)."""

    fn: Any
    out: int
    step: int
    xyz_offset: int
    range: int
    range_type: int
    roll: int | None
    width: int
    scale: int
    mult: float
    offset: float
    geometry: tuple[int | None, ...]          # (D, O) tables or (colshift, rows, cols, g)
    extra: int | None
    extra_type: int
    extra_offset: int
    r_out: int | None
    done: frozenset[str]                      # field names the kernel writes
    keep: tuple[Any, ...]                     # arrays the addresses point into
    factored: bool = False                    # fn is lsk_project_rc

    def run(self, start: int, count: int, dense: bool = False) -> int:
        if self.factored:
            colshift, rows, cols, const = self.geometry
            valid = int(self.fn(self.out, self.step, self.xyz_offset, start, count, self.range,
                                self.range_type, self.roll, colshift, self.width, self.scale,
                                self.mult, self.offset, rows, cols, const,
                                self.extra, self.extra_type, self.extra_offset,
                                self.r_out, int(dense)))
        else:
            d, o = self.geometry
            valid = int(self.fn(self.out, self.step, self.xyz_offset, start, count, self.range,
                                self.range_type, None, self.roll, self.width, self.scale,
                                self.mult, self.offset, d, o,
                                self.extra, self.extra_type, self.extra_offset,
                                self.r_out, int(dense)))
        if valid < 0:                                          # unreachable: types checked
            raise ConversionError("kernel source type", (self.range_type, self.extra_type),
                                  f"one of {sorted(_KERNEL_TYPES.values())}")
        return valid


class _Planes:
    """Direction / offset tables as contiguous float32 (H, W) planes (x, y, z each), plus the
    (x, y) pairs as complex64 planes: ``r * (Dx + iDy) + (Ox + iOy)`` computes x and y in one
    pass and writes both with one strided store when the layout has y right after x."""

    def __init__(self, d: list[np.ndarray[Any, Any]], o: list[np.ndarray[Any, Any]]) -> None:
        self.d, self.o = d, o
        self._pair: tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]] | None = None
        self._interleaved: (tuple[np.ndarray[Any, Any], np.ndarray[Any, Any], int, int]
                            | None) = None

    def interleaved(self) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any], int, int]:
        """(D, O) as C-contiguous float32 (H, W, 3), the compiled kernel's tables, and their
        addresses."""
        if self._interleaved is None:
            d = np.ascontiguousarray(np.stack(self.d, -1))
            o = np.ascontiguousarray(np.stack(self.o, -1))
            self._interleaved = (d, o, _addr(d), _addr(o))
        return self._interleaved

    def pair(self) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
        if self._pair is None:
            dc = np.empty(self.d[0].shape, np.complex64)
            oc = np.empty(self.d[0].shape, np.complex64)
            dc.real, dc.imag = self.d[0], self.d[1]
            oc.real, oc.imag = self.o[0], self.o[1]
            self._pair = (dc, oc)
        return self._pair


class PointCloud2Converter:
    """Reusable LidarScan -> PointCloud2 converter for one LidarInfo.

    Holds the projector tables split into contiguous float32 planes in the output column order,
    the output layouts and preallocated scratch images, so a conversion allocates only the
    message's own byte buffer, which the fields are written into directly and which the message
    then takes over without a copy. Not thread-safe: use one converter per thread.

    Args:
        info: the LidarInfo (rclpy message or dataclass) of the scans to convert.
        preset: a name in :data:`PRESETS`, or None for a generic layout from ``fields``.
        fields: field names (see the module docstring); default x, y, z, intensity (x, y, z
            when the scan has no intensity channel). Not allowed together with a preset.
        organized: keep the H x W grid with NaN points (True) or drop points without a return
            (False); default: the preset's (True without preset).
        destagger: columns in azimuth order (True) or measurement order; default: the preset's.
        time_reference: "stamp", "first" or "last" (see the module docstring); default: the
            preset's ("stamp" without preset).
        motion: default motion for deskew (:func:`converters.deskew.as_motion` forms), or None.
        range_channel: the channel holding the ranges ("range", "range2", ...).
        frame_id: header.frame_id of the clouds; default the scan's.
        threads: split the rows over this many threads (numpy and the kernel release the
            GIL); 1 = no thread pool.
        kernel: use the optional compiled kernel for x, y, z (+ one float32 channel field and
            the validity test): None = when available (:func:`kernel_available`), False = numpy
            only, True = required. Both paths give the same clouds up to float32 rounding of
            x, y, z (see :func:`kernel_available`); every other byte is identical.

    Raises:
        ConfigError: unknown preset / time reference, fields with a preset, no x/y/z, kernel
            required but not available.
    """

    def __init__(self, info: Any, *, preset: str | None = None,
                 fields: Sequence[str] | None = None, organized: bool | None = None,
                 destagger: bool | None = None, time_reference: str | None = None,
                 motion: Any = None, range_channel: str = "range",
                 frame_id: str | None = None, threads: int = 1,
                 kernel: bool | None = None) -> None:
        if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
            raise ConfigError("threads", threads, "an int >= 1")
        if kernel not in (None, True, False):
            raise ConfigError("kernel", kernel, "None, True or False")
        self._kfn = _kernel() if kernel is not False else None
        if kernel and self._kfn is None:
            raise ConfigError("kernel", kernel, "None or False: the compiled kernel is not "
                              "available (not built, or LIDARSCAN_NO_KERNEL is set)")
        if preset is not None:
            if preset not in PRESETS:
                raise ConfigError("preset", preset, f"one of {sorted(PRESETS)} or None")
            if fields is not None:
                raise ConfigError("fields", list(fields), "None when a preset is given "
                                  "(a preset fixes the fields)")
        self.preset: Preset | None = PRESETS[preset] if preset is not None else None
        if fields is not None:
            names = tuple(fields)
            if isinstance(fields, str) or not all(isinstance(n, str) and n for n in names):
                raise ConfigError("fields", fields, "a sequence of non-empty field names")
            if len(set(names)) != len(names):
                raise ConfigError("fields", names, "unique field names")
        else:
            names = _DEFAULT_FIELDS
        self._default_fields = fields is None
        if self.preset is None and not {"x", "y", "z"} <= set(names):
            raise ConfigError("fields", names, "x, y and z among the fields")
        self.field_names = names
        p = self.preset
        self.organized = bool(p.organized if p and organized is None else
                              (True if organized is None else organized))
        self.time_reference = time_reference if time_reference is not None else (
            p.time_reference if p else "stamp")
        if self.time_reference not in _TIME_REFERENCES:
            raise ConfigError("time_reference", self.time_reference, f"one of {_TIME_REFERENCES}")
        if motion is not None:
            from converters.deskew import as_motion
            motion = as_motion(motion)
        self.motion = motion
        self.range_channel = range_channel
        self.frame_id = frame_id
        self.order = p.order if p else "rows"
        self.ring_mode = p.ring if p else "row"

        self.info = info
        self.projector = make_projector(info)
        proj = self.projector
        self.height, self.width = proj.height, proj.width
        self._info_stamp = proj.info_stamp_ns
        self._has_shift = bool(np.any(proj.shifts % max(self.width, 1)))
        want = p.destagger if p and destagger is None else (True if destagger is None
                                                            else destagger)
        self.destagger = bool(want)
        self._grid_destaggered = self.destagger and self._has_shift
        self._groups = _shift_groups(proj.shifts, self.width) if self._has_shift else None
        bounds = np.linspace(0, self.height, min(threads, max(self.height, 1)) + 1).astype(int)
        self._blocks = [
            _Block(slice(int(a), int(b)),
                   _shift_groups(proj.shifts[a:b], self.width) if self._has_shift else None)
            for a, b in itertools.pairwise(bounds) if b > a]
        self._pool = None
        if len(self._blocks) > 1:
            from concurrent.futures import ThreadPoolExecutor
            self._pool = ThreadPoolExecutor(len(self._blocks), "pointcloud2")
        self._mult = float(info.range_multiplier)
        self._offset = float(info.range_offset)
        self._ring_values = self._rings(info)
        self._planes: _Planes | None = None
        self._scan_planes: tuple[np.ndarray[Any, Any], _Planes] | None = None
        self._scan_factors: tuple[np.ndarray[Any, Any], Any] | None = None
        self._static_args: tuple[Any, ...] | None = None      # see _kernel_job
        self._times_cache: tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]] | None = None
        self._layouts: dict[Any, tuple[tuple[FieldSpec, ...], int, np.dtype[Any]]] = {}
        shape = (self.height, self.width)
        self._r = np.empty(shape, np.float32)
        self._tmp = np.empty(shape, np.float32)
        self._cplx = np.empty(shape, np.complex64)
        self._mask = np.empty(shape, bool)
        self._mask2 = np.empty(shape, bool)
        self._rolls: dict[bool | str, np.ndarray[Any, Any]] = {}
        self._grid: np.ndarray[Any, Any] | None = None
        self._spares: list[array.array[int]] = []            # see _output
        self._coverage: dict[tuple[int, int], bool] = {}
        self._order_index: np.ndarray[Any, Any] | None = None

    # ---------------------------------------------------------------------------- helpers
    def _rings(self, info: Any) -> np.ndarray[Any, Any]:
        height = self.height
        ids = _as_array(info.beam_ids, np.uint16)
        rows = np.arange(height)
        if self.ring_mode == "low":            # elevation rank from the bottom beam
            values = height - 1 - rows
        elif self.ring_mode == "ids" and ids.size:
            values = ids.astype(np.int64)
        else:
            values = rows
        return np.asarray(values, dtype=np.uint16)

    def _layout(self, scan: Any) -> tuple[tuple[FieldSpec, ...], int, np.dtype[Any]]:
        if self.preset is not None:
            key: Any = None
        else:
            key = tuple((d.name, int(d.datatype), int(d.count)) for d in scan.channels
                        if d.name not in _COMPUTED_TYPES)
        layout = self._layouts.get(key)
        if layout is None:
            if self.preset is not None:
                specs, step = self.preset.fields, self.preset.point_step
            else:
                names = self.field_names
                if self._default_fields and _find_channel(
                        scan, CHANNEL_ALIASES["intensity"]) is None:
                    names = ("x", "y", "z")                  # default fields, no intensity
                specs, step = _generic_layout(names, scan)
            layout = (specs, step, _structured(specs, step))
            self._layouts[key] = layout
        return layout

    def _tables(self, scan: Any) -> _Planes:
        """Projection tables as contiguous float32 planes in grid order (cached)."""
        measured = _as_array(scan.column_azimuth_angles, np.float64)
        if measured.size:
            cached = self._scan_planes
            if cached is not None and np.array_equal(cached[0], measured):
                return cached[1]
            d, o = self.projector.tables_for(scan)
            planes = self._split(d, o, bool(scan.is_destaggered) and self._has_shift)
            self._scan_planes = (np.array(measured, copy=True), planes)
            return planes
        if self._planes is None:
            d, o = self.projector.tables(self._grid_destaggered)
            self._planes = self._split(d, o, self._grid_destaggered)
        return self._planes

    def _factors(self, scan: Any) -> tuple[np.ndarray[Any, Any], ...] | None:
        """Factored beam model (float32 rows, columns, constant) for the scan's column
        azimuths, or None (per-pixel angles in the info)."""
        measured = _as_array(scan.column_azimuth_angles, np.float64)
        if not measured.size:
            return self.projector.factors()
        cached = self._scan_factors
        if cached is None or not np.array_equal(cached[0], measured):
            if measured.size != self.width:
                raise ValidationError("LidarScan.column_azimuth_angles",
                                      f"length {measured.size}", f"length {self.width} or 0")
            cached = (np.array(measured, copy=True), self.projector.factors(measured))
            self._scan_factors = cached
        return cached[1]  # type: ignore[no-any-return]

    def _split(self, d: np.ndarray[Any, Any], o: np.ndarray[Any, Any], tables_destaggered: bool
               ) -> _Planes:
        planes = []
        for table in (d, o):
            for k in range(3):
                plane = np.empty((self.height, self.width), np.float32)
                src = table[..., k]
                if tables_destaggered == self._grid_destaggered or not self._has_shift:
                    plane[...] = src
                else:
                    _roll_into(plane, src, self._groups,
                               1 if self._grid_destaggered else -1)
                planes.append(plane)
        for plane in planes[3:]:
            # -0 offsets -> +0: x = r * D + O then has the same sign of zero whether computed
            # per axis (compiled kernel) or as the complex x + iy product below
            np.add(plane, np.float32(0), out=plane)
        return _Planes(planes[:3], planes[3:])

    def _pixel_times(self, scan: Any) -> np.ndarray[Any, Any]:
        """(H, W) int64 ns since the scan stamp, grid order (cached per column times)."""
        cols = self.projector.column_times(scan)
        cached = self._times_cache
        if cached is not None and np.array_equal(cached[0], cols):
            return cached[1]
        times = cols[None, :] + self.projector.beam_time_offsets[:, None]
        if self._grid_destaggered:
            grid = np.empty_like(times)
            _roll_into(grid, times, self._groups, 1)
            times = grid
        self._times_cache = (cols.copy(), times)
        return np.asarray(times, dtype=np.int64)

    def _output(self, dtype: np.dtype[Any], points: int, recycle: bool = False
                ) -> tuple[array.array[int], np.ndarray[Any, Any]]:
        """A byte buffer for ``points`` points and its structured view.

        The message takes the buffer over without a copy, so every message gets its own: a new
        zero-filled one, or with ``recycle`` (layouts whose every byte is written each time)
        the buffer of one of this converter's last ``_POOL`` messages that nothing else
        references any more (the message was dropped, e.g. after publishing: CPython reference
        count), which saves the allocation, page faults and zero-fill of a fresh buffer."""
        size = points * dtype.itemsize
        if not recycle:
            self._spares.clear()
            buf = self._output_buffer(size)
        else:
            for spare in self._spares:  # a plain list iteration holds no extra reference
                if len(spare) == size and sys.getrefcount(spare) == 3:  # list, `spare`, argument
                    buf = spare
                    break
            else:
                # every recent buffer is still in use (the caller keeps the last message, a
                # publisher queues it): a fresh one, keeping at most _POOL candidates
                buf = self._output_buffer(size)
                self._spares.append(buf)
                del self._spares[:-_POOL]
        return buf, np.frombuffer(buf, dtype=dtype)

    def _full_coverage(self, specs: Sequence[FieldSpec], step: int) -> bool:
        """Whether the fields cover every byte of a point (no padding); cached per layout (the
        layouts live as long as the converter, so their ids are stable)."""
        key = (id(specs), step)
        if key not in self._coverage:
            covered = np.zeros(step, bool)
            for s in specs:
                covered[s.offset:s.offset + dtype_of(s.datatype).itemsize * s.count] = True
            self._coverage[key] = bool(covered.all())
        return self._coverage[key]

    @staticmethod
    def _output_buffer(size: int) -> array.array[int]:
        return array.array("B", b"\0") * size

    def _scratch(self, dtype: np.dtype[Any]) -> np.ndarray[Any, Any]:
        """Reused (H, W) structured grid for clouds that are reordered or filtered after."""
        if self._grid is None or self._grid.dtype != dtype:
            self._grid = np.zeros((self.height, self.width), dtype)
            self._order_index = None
        return self._grid

    def _firing_order(self) -> np.ndarray[Any, Any]:
        """Flat grid indices in firing order: column by column, beams by ring ascending."""
        if self._order_index is None:
            rows = np.argsort(self._ring_values, kind="stable")
            cols = np.arange(self.width)
            self._order_index = (rows[None, :] * self.width + cols[:, None]).reshape(-1)
        return self._order_index

    # ----------------------------------------------------------------------------- convert
    def convert(self, scan: Any, *, motion: Any = None) -> Any:
        """Convert one scan.

        Args:
            scan: a LidarScan of this converter's info (rclpy message or dataclass).
            motion: deskew motion for this scan (overrides the converter's), or None.

        Returns:
            ``sensor_msgs.msg.PointCloud2`` (see the module docstring for the layout).

        Raises:
            InfoMismatchError / LinkageError: the scan does not belong to the info.
            UnknownChannelError: a requested channel is missing (preset channels zero-fill).
            ConversionError: a time that does not fit the requested time field.
        """
        height, width = int(scan.height), int(scan.width)
        if (height, width) != (self.height, self.width):
            raise InfoMismatchError("LidarScan.height x width", f"{height}x{width}",
                                    f"{self.height}x{self.width} from the LidarInfo")
        link = to_ns(scan.lidar_info_time, field="LidarScan.lidar_info_time")
        if link != self._info_stamp:
            raise LinkageError("LidarScan.lidar_info_time", link,
                               f"{self._info_stamp} (the LidarInfo's header.stamp, in ns)")
        specs, step, dtype = self._layout(scan)
        raw = channel(scan, self.range_channel, native=True)
        if raw.ndim == 3:
            raw = raw[..., 0]
        if raw.dtype.kind != "f" and (not self._mult > 0 or not math.isfinite(self._mult)):
            raise InfoMismatchError("LidarInfo.range_multiplier", self._mult,
                                    f"> 0 to decode the integer channel {self.range_channel!r}")
        stamp_ns = to_ns(scan.header.stamp, field="LidarScan.header.stamp")
        motion = motion if motion is not None else self.motion
        ref = 0
        if self.time_reference != "stamp":
            cols = self.projector.column_times(scan)
            beams = self.projector.beam_time_offsets
            pick = np.min if self.time_reference == "first" else np.max
            ref = (int(pick(cols)) if cols.size else 0) + (int(pick(beams)) if beams.size else 0)
        header_ns = stamp_ns + ref
        scan_dest = bool(scan.is_destaggered)
        images = self._images(scan, specs)
        plan = (self._kernel_plan(specs, raw, images) if self._kfn is not None and motion is None
                else None)
        factors = self._factors(scan) if plan is not None else None
        # the per-pixel tables: only for the numpy path and the kernel's table form
        tables = self._tables(scan) if factors is None else None
        pixels = self.height * self.width

        if plan is not None and plan.covers_all and not self.organized and self.order == "rows":
            # the kernel writes every field: valid points straight into the message, compacted
            buf = self._output_buffer(pixels * step)
            djob = self._kernel_job(plan, buf.buffer_info()[0], step, tables, factors,
                                    scan_dest, False)
            count = djob.run(0, pixels, dense=True)
            del buf[count * step:]
            return self._message(scan, specs, step, (1, count), buf, True, header_ns)

        direct = self.organized and self.order == "rows"
        if direct:                                    # fields go straight into the message
            buf, flat = self._output(dtype, pixels, recycle=self._full_coverage(specs, step))
            grid = flat.reshape(self.height, self.width)
        else:
            grid = self._scratch(dtype)
        kjob = None
        if plan is not None:
            needs_r = not direct or any(s.source == "range" for s in specs)
            kjob = self._kernel_job(plan, _addr(grid), step, tables, factors, scan_dest,
                                    needs_r)
        needs_times = motion is not None or any(
            s.source in ("t", "time", "timestamp") for s in specs)
        job = _Job(scan=scan, raw=raw, grid=grid,
                   pair=_xy_pair(grid, specs) if kjob is None else None, specs=specs,
                   tables=tables, images=images,
                   times=self._pixel_times(scan) if needs_times else None,
                   ref=ref, stamp_ns=stamp_ns, scan_dest=scan_dest, kernel=kjob)
        if job.pair is not None and job.tables is not None:
            job.tables.pair()                        # built once, before any worker thread
        if motion is not None:
            self._fill(job, _Block(slice(0, self.height), self._groups), xyz=False)
            self._deskew(job, motion, header_ns)
            counts: list[int | None] = [None]
        elif self._pool is not None:
            counts = list(self._pool.map(lambda block: self._fill(job, block), self._blocks))
        else:
            counts = [self._fill(job, block) for block in self._blocks]

        r = self._r
        if direct:
            if kjob is not None:
                dense = sum(c or 0 for c in counts) == pixels
            else:
                dense = not bool(np.isnan(r).any())
            return self._message(scan, specs, step, (self.height, self.width), buf,
                                 dense, header_ns)
        valid = ~np.isnan(r).reshape(-1)
        if self.order == "rows":
            index = np.flatnonzero(valid)
        else:
            index = self._firing_order()
            if not self.organized:
                index = index[valid[index]]
        buf, flat = self._output(dtype, index.size)
        np.take(grid.reshape(-1), index, out=flat)
        if self.organized:
            shape = (self.width, self.height)                       # firings x beams
            dense = bool(valid.all())
        else:
            shape, dense = (1, int(index.size)), True
        return self._message(scan, specs, step, shape, buf, dense, header_ns)

    # --------------------------------------------------------------------- compiled kernel
    def _kernel_plan(self, specs: Sequence[FieldSpec], raw: np.ndarray[Any, Any],
                     images: dict[str, Any]) -> _Plan | None:
        """What the kernel can write for this layout and scan: x, y, z (float32, consecutive)
        and the first float32 channel field with a kernel-readable image; None: numpy only."""
        by_source = {s.source: s for s in specs if s.source in ("x", "y", "z")}
        if len(by_source) != 3:
            return None
        xoff = by_source["x"].offset
        for k, axis in enumerate("xyz"):
            s = by_source[axis]
            if s.datatype != FLOAT32 or s.count != 1 or s.offset != xoff + 4 * k:
                return None
        raw_type = _kernel_type(raw)
        if raw_type is None:
            return None
        if not (raw.flags.c_contiguous and raw.flags.aligned):
            raw = np.require(raw, requirements=["C", "A"])
        extra, extra_image, extra_type = None, None, 0
        for s in specs:
            if s.source != "channel" or s.datatype != FLOAT32 or s.count != 1:
                continue
            image = images.get(s.name)
            if image is None or image.ndim != 2:
                continue
            code = _kernel_type(image)
            if code is not None:
                if not (image.flags.c_contiguous and image.flags.aligned):
                    image = np.require(image, requirements=["C", "A"])
                extra, extra_image, extra_type = s, image, code
                break
        covered = {"x", "y", "z"} | ({extra.name} if extra is not None else set())
        return _Plan(xoff, raw, raw_type, extra, extra_image, extra_type,
                     all(s.name in covered for s in specs))

    def _roll(self, scan_dest: bool) -> np.ndarray[Any, Any] | None:
        """Per-row right rotation (0..W-1, int64) taking scan columns to grid columns, or None
        when both are in the same order (the kernel's ``roll``)."""
        if not self._has_shift or scan_dest == self._grid_destaggered:
            return None
        if scan_dest not in self._rolls:
            sign = 1 if self._grid_destaggered else -1
            shifts = np.asarray(self.projector.shifts, np.int64)
            self._rolls[scan_dest] = np.ascontiguousarray((sign * shifts) % self.width)
        return self._rolls[scan_dest]

    def _colshift(self) -> np.ndarray[Any, Any] | None:
        """Per-row right rotation (0..W-1, int64) from measurement columns to grid columns, or
        None when the grid is in measurement order (the factored kernel's ``colshift``)."""
        if not self._grid_destaggered:
            return None
        if "colshift" not in self._rolls:
            shifts = np.asarray(self.projector.shifts, np.int64)
            self._rolls["colshift"] = np.ascontiguousarray(shifts % self.width)
        return self._rolls["colshift"]

    def _kernel_job(self, plan: _Plan, out: int, step: int, tables: _Planes | None,
                    factors: tuple[np.ndarray[Any, Any], ...] | None, scan_dest: bool,
                    r_out: bool) -> _KernelJob:
        """One kernel call's arguments: the factored form when ``factors`` is given, else the
        per-pixel ``tables``."""
        raw, spec, image = plan.raw, plan.extra, plan.image
        scale = 0
        if raw.dtype.kind != "f":
            scale = ((_KERNEL_MULTIPLY if self._mult != 1.0 else 0)
                     | (_KERNEL_OFFSET if self._offset != 0.0 else 0))
        source = factors if factors is not None else tables
        static = self._static_args                 # of the latest geometry and column order
        if static is None or static[0] is not source or static[1] != scan_dest:
            static = (source, scan_dest,
                      *self._static_kernel_args(source, factors is not None, scan_dest))
            self._static_args = static
        fn, geometry, roll_addr, keep = static[2:]
        return _KernelJob(
            fn=fn, out=out, step=int(step), xyz_offset=int(plan.xyz_offset),
            range=_addr(raw), range_type=plan.raw_type,
            roll=roll_addr, width=self.width,
            scale=scale, mult=self._mult, offset=self._offset, geometry=geometry,
            extra=None if image is None else _addr(image),
            extra_type=plan.extra_type,
            extra_offset=0 if spec is None else int(spec.offset),
            r_out=_addr(self._r) if r_out else None,
            done=frozenset({"x", "y", "z"} | ({spec.name} if spec is not None else set())),
            keep=(raw, image, keep), factored=factors is not None)

    def _static_kernel_args(self, source: Any, factored: bool, scan_dest: bool
                            ) -> tuple[Any, tuple[int | None, ...], int | None, Any]:
        """(kernel function, geometry addresses, roll address, arrays to keep alive) of one
        geometry (factors or tables) and scan column order: the same for every scan."""
        kernels: Any = self._kfn
        roll = self._roll(scan_dest)
        geometry: tuple[int | None, ...]
        if factored:
            colshift = self._colshift()
            geometry = (None if colshift is None else _addr(colshift),
                        *(_addr(a) for a in source))
            return (kernels.project_rc, geometry, None if roll is None else _addr(roll),
                    (roll, colshift, source))
        if source is None:                                     # unreachable: see convert()
            raise ConversionError("kernel geometry", None, "tables or factors")
        d, o, d_addr, o_addr = source.interleaved()
        return (kernels.project, (d_addr, o_addr), None if roll is None else _addr(roll),
                (roll, d, o))

    def _images(self, scan: Any, specs: Sequence[FieldSpec]) -> dict[str, Any]:
        """The scan channel (view) feeding each channel field; None: zero-fill (presets)."""
        images: dict[str, Any] = {}
        for spec in specs:
            if spec.source != "channel":
                continue
            desc = _find_channel(scan, spec.channels)
            if desc is None:
                if self.preset is None:
                    raise UnknownChannelError("fields", spec.name,
                                              f"a channel named one of {spec.channels}")
                images[spec.name] = None
                continue
            image = channel(scan, desc.name, native=True)
            if image.ndim == 3 and spec.count == 1:
                image = image[..., 0]
            images[spec.name] = image
        return images

    def _place_rows(self, dst: np.ndarray[Any, Any], src: np.ndarray[Any, Any],
                    block: _Block, scan_dest: bool) -> None:
        """Rows ``block.rows`` of a scan image (scan column order) into ``dst`` (those rows of
        the grid, grid column order)."""
        src = src[block.rows]
        if not self._has_shift or scan_dest == self._grid_destaggered:
            dst[...] = src
        else:
            _roll_into(dst, src, block.groups, 1 if self._grid_destaggered else -1)

    def _fill(self, job: _Job, block: _Block, xyz: bool = True) -> int | None:
        """Write every field of the rows ``block.rows`` (independent of the other rows, so
        blocks can run on several threads: numpy and the kernel release the GIL).

        Returns the number of valid pixels when the compiled kernel ran, else None."""
        rows = block.rows
        r, mask, tmp = self._r[rows], self._mask[rows], self._tmp[rows]
        kjob = job.kernel
        if kjob is not None and xyz:
            # x, y, z, the extra channel field and (if asked) r in one pass
            valid: int | None = kjob.run(rows.start * self.width,
                                         (rows.stop - rows.start) * self.width)
            done = kjob.done
        else:
            self._ranges(job, block, r, mask, tmp)
            if xyz:
                self._write_xyz(job.grid[rows], job.specs, r, job.tables, rows, job.pair)
            valid, done = None, frozenset()
        grid = job.grid[rows]
        for spec in job.specs:
            src = spec.source
            if src in ("x", "y", "z") or spec.name in done:
                continue
            field = grid[spec.name]
            if src == "channel":
                image = job.images[spec.name]
                if image is None:
                    field[...] = 0
                elif field.dtype == np.float32 and image.dtype != np.float32:
                    # a contiguous cast plus a strided float copy beats a strided cast
                    self._place_rows(tmp, image, block, job.scan_dest)
                    field[...] = tmp
                else:
                    self._place_rows(field, image, block, job.scan_dest)
            elif src == "ring":
                field[...] = self._ring_values[rows, None]
            elif src == "range":
                self._range_field(field, spec, r, job.raw, block, job.scan_dest)
            else:
                times = job.times if job.times is not None else self._pixel_times(job.scan)
                self._time_field(field, spec, times[rows], job.ref, job.stamp_ns)
        return valid

    def _ranges(self, job: _Job, block: _Block, r: np.ndarray[Any, Any],
                mask: np.ndarray[Any, Any], tmp: np.ndarray[Any, Any]) -> None:
        """Metres of the rows ``block.rows`` into ``r`` (grid order), NaN (the canonical quiet
        NaN, as the kernel writes) where there is no return: float ranges not in (0, +Inf),
        integer ranges 0 (others: ``raw * multiplier + offset`` in float32)."""
        raw = job.raw
        self._place_rows(r, raw, block, job.scan_dest)
        with np.errstate(invalid="ignore"):
            if raw.dtype.kind == "f":
                ok, bad = mask, self._mask2[block.rows]
                np.greater(r, 0, out=ok)                      # False: NaN, -Inf, 0, negative
                np.less(r, np.float32(np.inf), out=bad)       # False: +Inf, NaN
                np.logical_and(ok, bad, out=ok)
                if not ok.all():
                    np.logical_not(ok, out=bad)
                    np.copyto(r, np.float32(np.nan), where=bad)
            else:
                np.equal(r, 0, out=mask)                      # raw 0 = no return
                if self._mult != 1.0:
                    np.multiply(r, np.float32(self._mult), out=r)
                if self._offset != 0.0:
                    np.add(r, np.float32(self._offset), out=r)
                if mask.any():
                    np.copyto(r, np.float32(np.nan), where=mask)

    def _deskew(self, job: _Job, motion: Any, header_ns: int) -> None:
        from converters.deskew import deskew_points
        r, tables, grid = self._r, job.tables, job.grid
        xyz = np.stack([r * d + o for d, o in zip(tables.d, tables.o)], axis=-1)
        times = job.times if job.times is not None else self._pixel_times(job.scan)
        moved = deskew_points(xyz, times + np.int64(job.stamp_ns), motion, header_ns)
        for k, name in enumerate("xyz"):
            if name in grid.dtype.names:
                grid[name] = moved[..., k]

    def _write_xyz(self, grid: np.ndarray[Any, Any], specs: Sequence[FieldSpec],
                   r: np.ndarray[Any, Any], tables: _Planes, rows: slice,
                   pair_full: np.ndarray[Any, Any] | None) -> None:
        """x, y, z = r * D + O for the grid rows ``rows`` (float32 throughout)."""
        tmp = self._tmp[rows]
        todo = [s.name for s in specs if s.source in ("x", "y", "z")]
        if pair_full is not None:
            # x and y together: one complex64 product and one strided 8-byte store
            pair = pair_full[rows]
            dc, oc = tables.pair()
            cplx = self._cplx[rows]
            np.multiply(r, dc[rows], out=cplx)
            np.add(cplx, oc[rows], out=pair)
            todo = [n for n in todo if n not in ("x", "y")]
        for name in todo:
            k = "xyz".index(name)
            np.multiply(r, tables.d[k][rows], out=tmp)
            np.add(tmp, tables.o[k][rows], out=tmp)
            grid[name] = tmp

    def _range_field(self, field: np.ndarray[Any, Any], spec: FieldSpec,
                     r: np.ndarray[Any, Any], raw: np.ndarray[Any, Any], block: _Block,
                     scan_dest: bool) -> None:
        if dtype_of(spec.datatype).kind == "f":
            field[...] = r
            return
        # integer millimetres (ouster-ros), 0 = no return
        if raw.dtype.kind in "iu" and math.isclose(self._mult, 0.001) and self._offset == 0:
            self._place_rows(field, raw, block, scan_dest)
            return
        mm = np.rint(r.astype(np.float64) * 1000.0)
        mm[np.isnan(mm)] = 0
        info = np.iinfo(dtype_of(spec.datatype))
        np.clip(mm, 0, info.max, out=mm)
        field[...] = mm

    def _time_field(self, field: np.ndarray[Any, Any], spec: FieldSpec,
                    times: np.ndarray[Any, Any], ref: int, stamp_ns: int) -> None:
        if spec.source == "timestamp":
            sec, nsec = divmod(stamp_ns, _NS)
            field[...] = (times + np.int64(nsec)) * 1e-9 + float(sec)
            return
        rel = times - np.int64(ref)
        if spec.source == "time":
            field[...] = rel * 1e-9
            return
        lo, hi = int(rel.min(initial=0)), int(rel.max(initial=0))
        kind = dtype_of(spec.datatype)
        if kind.kind in "iu":
            limits = np.iinfo(kind)
            if lo < limits.min or hi > limits.max:
                raise ConversionError(f"field {spec.name!r}", (lo, hi),
                                      f"pixel times since the header stamp within "
                                      f"[{limits.min}, {limits.max}] ns",
                                      hint='use time_reference="first" or a float "time" field')
        field[...] = rel

    def _message(self, scan: Any, specs: Sequence[FieldSpec], step: int,
                 shape: tuple[int, int], buf: array.array[int], dense: bool,
                 header_ns: int) -> Any:
        from builtin_interfaces.msg import Time
        from sensor_msgs.msg import PointCloud2, PointField
        from std_msgs.msg import Header

        sec, nanosec = split_ns(header_ns)
        frame = self.frame_id if self.frame_id is not None else scan.header.frame_id
        header = Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame)
        fields = [PointField(name=s.name, offset=s.offset, datatype=s.datatype, count=s.count)
                  for s in specs]
        return bare_message(PointCloud2, header=header, height=int(shape[0]),
                            width=int(shape[1]), fields=fields, is_bigendian=False,
                            point_step=int(step), row_step=int(step) * int(shape[1]),
                            data=buf, is_dense=bool(dense))


_CONVERTERS: OrderedDict[Any, PointCloud2Converter] = OrderedDict()
_CONVERTERS_LOCK = threading.Lock()


def to_pointcloud2(scan: Any, info: Any, *, preset: str | None = None,
                   fields: Sequence[str] | None = None, organized: bool | None = None,
                   destagger: bool | None = None, time_reference: str | None = None,
                   motion: Any = None, range_channel: str = "range",
                   frame_id: str | None = None) -> Any:
    """LidarScan -> ``sensor_msgs.msg.PointCloud2``.

    One-call form of :class:`PointCloud2Converter` (same arguments; converters are cached per
    info version and options, so repeated calls reuse tables and buffers). Fields default to
    x, y, z, intensity (float32, 16 bytes per point), organized H x W in destaggered column order.

    Args:
        scan: the LidarScan (rclpy message or dataclass).
        info: its LidarInfo (``scan.lidar_info_time`` must equal ``info.header.stamp``).
        preset, fields, organized, destagger, time_reference, range_channel, frame_id: see
            :class:`PointCloud2Converter`.
        motion: deskew motion (see :mod:`converters.deskew`), or None.

    Returns:
        A new ``sensor_msgs.msg.PointCloud2``; points in ``info.header.frame_id`` metres.
    """
    key = (info_key(info), preset, None if fields is None else tuple(fields), organized,
           destagger, time_reference, range_channel, frame_id)
    with _CONVERTERS_LOCK:
        conv = _CONVERTERS.pop(key, None)
    if conv is None:
        conv = PointCloud2Converter(info, preset=preset, fields=fields, organized=organized,
                                    destagger=destagger, time_reference=time_reference,
                                    range_channel=range_channel, frame_id=frame_id)
    try:
        return conv.convert(scan, motion=motion)
    finally:
        # checked out while converting: a concurrent call builds its own converter
        with _CONVERTERS_LOCK:
            _CONVERTERS[key] = conv
            while len(_CONVERTERS) > 8:
                _CONVERTERS.popitem(last=False)


# ============================================================================ reading clouds

def cloud_dtype(fields: Sequence[Any], point_step: int, is_bigendian: bool = False
                ) -> np.dtype[Any]:
    """Structured dtype of a PointCloud2 point (names, offsets, itemsize = point_step).

    Raises:
        ConversionError: duplicate names, unknown datatypes or a field beyond ``point_step``.
    """
    names, formats, offsets = [], [], []
    for i, f in enumerate(fields):
        name, offset, count = str(f.name), int(f.offset), max(int(f.count), 1)
        base = dtype_of(int(f.datatype), bool(is_bigendian), field=f"fields[{i}].datatype")
        if name in names:
            raise ConversionError(f"fields[{i}].name", name, "unique field names")
        if offset < 0 or offset + base.itemsize * count > int(point_step):
            raise ConversionError(f"fields[{i}].offset ({name!r})", offset,
                                  f"a field inside point_step={int(point_step)}")
        names.append(name)
        formats.append(base if count == 1 else (base, (count,)))
        offsets.append(offset)
    if not 0 < int(point_step) < 2**31:
        raise ConversionError("point_step", int(point_step), "1 <= point_step < 2**31")
    try:
        return np.dtype({"names": names, "formats": formats, "offsets": offsets,
                         "itemsize": int(point_step)})
    except (ValueError, OverflowError, TypeError) as err:     # numpy's own size limits
        raise ConversionError("fields", [(n, o) for n, o in zip(names, offsets)],
                              f"a point layout numpy can represent ({err})") from err


def read_points(cloud: Any) -> np.ndarray[Any, Any]:
    """Zero-copy, read-only structured (height, width) view of a cloud's points.

    Handles any field order, padding, ``row_step > point_step * width`` and big-endian data
    (the dtype carries the byte order; the caller's buffer is never modified or byteswapped).

    Raises:
        ConversionError: inconsistent sizes.
    """
    height, width = int(cloud.height), int(cloud.width)
    step, row_step = int(cloud.point_step), int(cloud.row_step)
    dtype = cloud_dtype(cloud.fields, step, bool(cloud.is_bigendian))
    data = cloud.data
    buf = data if isinstance(data, np.ndarray) else np.frombuffer(data, np.uint8)
    if height == 0 or width == 0:
        return np.zeros((height, width), dtype)
    if row_step < step * width:
        raise ConversionError("row_step", row_step, f">= point_step * width = {step * width}")
    need = (height - 1) * row_step + width * step
    if buf.size < need:
        raise ConversionError("data", f"length {buf.size}",
                              f">= {need} bytes for {height}x{width} points")
    view = np.ndarray((height, width), dtype=dtype, buffer=buf.data if isinstance(
        buf, np.ndarray) else buf, strides=(row_step, step))
    view.flags.writeable = False
    return view


def _field_f64(points: np.ndarray[Any, Any], name: str) -> np.ndarray[Any, Any]:
    arr = points[name]
    if arr.ndim == 3:
        arr = arr[..., 0]
    return arr.astype(np.float64)


def _time_ns(points: np.ndarray[Any, Any], name: str, stamp_ns: int
             ) -> np.ndarray[Any, np.dtype[np.int64]]:
    """Absolute int64 ns of every point from a time field (see :func:`from_pointcloud2`)."""
    arr = points[name]
    if arr.ndim == 3:
        arr = arr[..., 0]
    if arr.dtype.kind in "iu":
        values = arr.astype(np.int64)
        big = np.abs(values).max(initial=0) > 10**15
        return values if big else values + np.int64(stamp_ns)
    seconds = arr.astype(np.float64)
    finite = seconds[np.isfinite(seconds)]
    peak = float(np.abs(finite).max(initial=0.0))
    if peak > 1e14:                         # absolute ns stored as float (Livox)
        return np.asarray(np.rint(np.nan_to_num(seconds)), dtype=np.int64)
    if peak > 1e6:                          # absolute seconds
        sec = np.floor(np.nan_to_num(seconds))
        frac = np.rint((np.nan_to_num(seconds) - sec) * 1e9)
        return np.asarray(sec, dtype=np.int64) * _NS + np.asarray(frac, dtype=np.int64)
    rel = np.asarray(np.rint(np.nan_to_num(seconds) * 1e9), dtype=np.int64)
    return rel + np.int64(stamp_ns)


# ========================================================================= geometry estimate

def _wrap(a: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    return (a + np.pi) % (2 * np.pi) - np.pi


def _group_mean(index: np.ndarray[Any, Any], values: np.ndarray[Any, Any], size: int,
                counts: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    sums = np.bincount(index, weights=values, minlength=size)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, sums / np.maximum(counts, 1), 0.0)


@dataclasses.dataclass
class _Fit:
    phi: np.ndarray[Any, Any]        # (H,)
    beta: np.ndarray[Any, Any]       # (H,)
    alpha: np.ndarray[Any, Any]      # (W,)
    origins: np.ndarray[Any, Any]    # (H, 3)
    rho: np.ndarray[Any, Any]        # (H, W) metres, NaN where not valid


def _fill_periodic(values: np.ndarray[Any, Any], known: np.ndarray[Any, Any],
                   field: str) -> np.ndarray[Any, Any]:
    """Fill unknown column azimuths by linear interpolation of the unwrapped known ones."""
    width = values.size
    idx = np.flatnonzero(known)
    if idx.size == width:
        return values
    if idx.size < 2:
        raise ConversionError(field, f"{idx.size} columns with points",
                              "at least two columns with valid points")
    unwrapped = np.unwrap(values[idx])
    slope = (unwrapped[-1] - unwrapped[0]) / max(idx[-1] - idx[0], 1)
    ext_idx = np.concatenate([[idx[-1] - width], idx, [idx[0] + width]])
    ext_val = np.concatenate([[unwrapped[-1] - slope * width], unwrapped,
                              [unwrapped[0] + slope * width]])
    out = np.interp(np.arange(width), ext_idx, ext_val)
    out[idx] = unwrapped
    return _wrap(out)


def _linear_fit(alpha: np.ndarray[Any, Any], counts: np.ndarray[Any, Any]
                ) -> np.ndarray[Any, Any]:
    """Column azimuths as a straight line in the column index (count-weighted fit of the
    unwrapped azimuths of the columns that have points)."""
    idx = np.flatnonzero(counts > 0)
    if idx.size < 2:
        return alpha
    unwrapped = np.unwrap(alpha[idx])
    slope, icpt = np.polyfit(idx.astype(np.float64), unwrapped, 1, w=np.sqrt(counts[idx]))
    return np.asarray(icpt + slope * np.arange(alpha.size, dtype=np.float64), dtype=np.float64)


def _fit_geometry(points: np.ndarray[Any, Any], valid: np.ndarray[Any, Any],
                  cidx: np.ndarray[Any, Any], width: int,
                  known_range: np.ndarray[Any, Any] | None, min_spread: float = 0.02) -> _Fit:
    """Fit the per-row / per-column beam model to a grid of points.

    Args:
        points: (H, G, 3) float64 points in the grid.
        valid: (H, G) bool.
        cidx: (H, G) measurement column of every grid pixel (0..width-1).
        width: number of measurement columns.
        known_range: (H, G) ranges along the beam (m) from the cloud, or None.
        min_spread: rows whose points spread less than this (m, standard deviation along the
            beam) take their elevation from the common point of the other rows' beam lines
            (one range fixes no direction).
    """
    height = points.shape[0]
    u_idx, g_idx = np.nonzero(valid)
    if u_idx.size < 3:
        raise ConversionError("cloud", f"{u_idx.size} valid points",
                              "at least 3 finite points to estimate a geometry")
    pts = points[u_idx, g_idx]
    X, Y, Z = pts[:, 0], pts[:, 1], pts[:, 2]
    c = cidx[u_idx, g_idx]
    rxy = np.hypot(X, Y)
    psi = np.arctan2(Y, X)
    cnt_u = np.bincount(u_idx, minlength=height).astype(np.float64)
    cnt_c = np.bincount(c, minlength=width).astype(np.float64)
    # initial column azimuths: circular mean over the rows
    alpha = np.arctan2(np.bincount(c, np.sin(psi), width), np.bincount(c, np.cos(psi), width))
    beta = np.zeros(height)
    oy = np.zeros(height)
    g = 1.0 / np.maximum(rxy, 1e-9)
    # angle model psi = alpha_c + beta_u + asin(o_y[u] / rxy): alternate between the columns
    # (alpha) and, per row, the joint linear regression of psi - alpha on (1, 1/rxy) -> (beta,
    # o_y); the asin curvature (< 1e-7 rad) is carried as a fixed correction.
    sum_g = np.bincount(u_idx, g, height)
    sum_gg = np.bincount(u_idx, g * g, height)
    denom = cnt_u * sum_gg - sum_g**2
    solvable = (cnt_u >= 3) & (denom > 1e-9 * np.maximum(cnt_u * sum_gg, 1e-300))
    # too few points per column to fix every column's azimuth: assume evenly spaced columns
    sparse = float(np.mean(cnt_c >= 2)) < 0.5
    if sparse:
        alpha = _linear_fit(alpha, cnt_c)
    psi = alpha[c] + _wrap(psi - alpha[c])        # one branch: the loop needs no wrapping
    for _ in range(500):
        x_ratio = np.clip(oy[u_idx] * g, -1, 1)
        e = psi - alpha[c] - (np.arcsin(x_ratio) - x_ratio)
        sum_e = np.bincount(u_idx, e, height)
        sum_eg = np.bincount(u_idx, e * g, height)
        with np.errstate(invalid="ignore", divide="ignore"):
            new_oy = np.where(solvable, (cnt_u * sum_eg - sum_g * sum_e) / np.where(
                solvable, denom, 1.0), 0.0)
            new_beta = np.where(cnt_u > 0, (sum_e - new_oy * sum_g) / np.maximum(cnt_u, 1), 0.0)
        x_ratio = np.clip(new_oy[u_idx] * g, -1, 1)
        res = psi - np.arcsin(x_ratio) - new_beta[u_idx] - alpha[c]
        step = _group_mean(c, res, width, cnt_c)
        if sparse:
            step = _linear_fit(alpha + step, cnt_c) - alpha
        alpha = alpha + step
        change = max(np.abs(step).max(initial=0), np.abs(new_beta - beta).max(initial=0),
                     np.abs(new_oy - oy).max(initial=0) * 1e-1)
        beta, oy = new_beta, new_oy
        if change < 1e-14:
            break
    # gauge: mean beam offset 0 over rows with points
    has_row = cnt_u > 0
    shift = float(beta[has_row].mean()) if has_row.any() else 0.0
    beta[has_row] -= shift
    beta[~has_row] = 0.0
    alpha = _wrap(alpha + shift)
    alpha = _fill_periodic(alpha, cnt_c > 0, "cloud columns")
    theta = alpha[c] + beta[u_idx]
    cos_t, sin_t = np.cos(theta), np.sin(theta)
    xr = cos_t * X + sin_t * Y

    # elevation and axis-crossing height per row (total least squares in the (xr, z) plane)
    mx = _group_mean(u_idx, xr, height, cnt_u)
    mz = _group_mean(u_idx, Z, height, cnt_u)
    dx, dz = xr - mx[u_idx], Z - mz[u_idx]
    sxx = _group_mean(u_idx, dx * dx, height, cnt_u)
    szz = _group_mean(u_idx, dz * dz, height, cnt_u)
    sxz = _group_mean(u_idx, dx * dz, height, cnt_u)
    phi = 0.5 * np.arctan2(2 * sxz, sxx - szz)
    spread = np.sqrt(np.maximum(0.5 * (sxx + szz) + np.hypot(0.5 * (sxx - szz), sxz), 0))
    good = (cnt_u >= 3) & (spread >= min_spread)
    oz = mz - mx * np.tan(phi)
    weak = has_row & ~good
    if weak.any():
        # a row whose points all lie at about one range fixes no direction: take the line
        # through its centroid and the point closest to the other rows' lines (the common beam
        # origin of Ouster-like sensors; the spin axis at the median crossing height otherwise)
        x0, z0 = 0.0, float(np.median(oz[good])) if good.any() else 0.0
        if good.sum() >= 2:
            nrm = np.stack([-np.sin(phi[good]), np.cos(phi[good])], -1)          # line normals
            a = nrm.T @ nrm
            b = nrm.T @ np.sum(nrm * np.stack([mx[good], mz[good]], -1), -1)
            reg = 1e-6 * np.trace(a)
            sol = np.linalg.solve(a + reg * np.eye(2), b + reg * np.array([x0, z0]))
            x0, z0 = float(sol[0]), float(sol[1])
        phi[weak] = np.arctan2(mz[weak] - z0, mx[weak] - x0)
        oz[weak] = z0 - x0 * np.tan(phi[weak])
    origins = np.zeros((height, 3))
    origins[:, 1], origins[:, 2] = oy, oz

    rho = np.full(valid.shape, np.nan)
    if known_range is not None:
        k = known_range[u_idx, g_idx]
        cos_p, sin_p = np.cos(phi)[u_idx], np.sin(phi)[u_idx]
        ax = _group_mean(u_idx, xr - k * cos_p, height, cnt_u)
        az = _group_mean(u_idx, Z - k * sin_p, height, cnt_u)
        resid = np.hypot(xr - ax[u_idx] - k * cos_p, Z - az[u_idx] - k * sin_p)
        if np.all(np.isfinite(resid)) and float(np.percentile(resid, 99)) < 1e-3:
            origins[:, 0], origins[:, 2] = ax, az
            rho[u_idx, g_idx] = k
        else:
            known_range = None
    if known_range is None:
        rho[u_idx, g_idx] = xr * np.cos(phi)[u_idx] + (Z - oz[u_idx]) * np.sin(phi)[u_idx]
    # rows without any point: interpolate the elevation by row index
    if not has_row.all():
        rows = np.arange(height)
        phi[~has_row] = np.interp(rows[~has_row], rows[has_row], phi[has_row])
    return _Fit(phi=phi, beta=beta, alpha=alpha, origins=origins, rho=rho)


# --------------------------------------------------------------------------- cloud layouts

_TIME_FIELDS = ("t", "time", "timestamp", "time_stamp", "offset_time")
_RANGE_FIELDS = ("range",)
_SKIP = {"x", "y", "z", "ring"}


def _pick_time_field(names: Sequence[str], time_field: str | None) -> str | None:
    if time_field is not None:
        if time_field not in names:
            raise ConfigError("time_field", time_field, f"one of the cloud's fields {names}")
        return time_field
    for name in _TIME_FIELDS:
        if name in names:
            return name
    return None


def _median_by(index: np.ndarray[Any, Any], values: np.ndarray[Any, Any], size: int
               ) -> np.ndarray[Any, Any]:
    """Median of ``values`` per group (NaN for empty groups)."""
    out = np.full(size, np.nan)
    if index.size == 0:
        return out
    order = np.lexsort((values, index))
    idx, vals = index[order], values[order]
    starts = np.searchsorted(idx, np.arange(size), "left")
    ends = np.searchsorted(idx, np.arange(size), "right")
    has = ends > starts
    lo = (starts + ends - 1) // 2
    hi = (starts + ends) // 2
    out[has] = 0.5 * (vals[lo[has]] + vals[hi[has]])
    return out


def _interp_missing(values: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    known = np.isfinite(values)
    if known.all() or not known.any():
        return np.asarray(np.nan_to_num(values), dtype=np.float64)
    idx = np.arange(values.size)
    return np.asarray(np.interp(idx, idx[known], values[known]), dtype=np.float64)


@dataclasses.dataclass
class _Grid:
    """Points arranged on (rows = beams, grid columns) plus their bookkeeping."""

    points: np.ndarray[Any, Any]              # (H, G, 3) float64, NaN where no point
    valid: np.ndarray[Any, Any]               # (H, G)
    cidx: np.ndarray[Any, Any]                # (H, G) measurement column
    width: int
    shifts: np.ndarray[Any, Any]              # (H,) pixel shift (grid = destaggered if any)
    beam_ids: np.ndarray[Any, Any]            # (H,) ring / source row
    beam_times: np.ndarray[Any, Any]          # (H,) int64 ns
    column_times: np.ndarray[Any, Any] | None  # (W,) absolute int64 ns, or None
    channels: dict[str, np.ndarray[Any, Any]]  # grid images
    known_range: np.ndarray[Any, Any] | None
    per_scan_azimuths: bool
    dropped: int = 0


def _organized_grid(pts: np.ndarray[Any, Any], names: Sequence[str], time_name: str | None,
                    stamp_ns: int, range_name: str | None, range_scale: float) -> _Grid:
    height, width = pts.shape
    xyz = np.stack([_field_f64(pts, n) for n in "xyz"], -1)
    valid = np.all(np.isfinite(xyz), -1) & np.any(xyz != 0, -1)
    shifts = np.zeros(height, np.int64)
    beam_times = np.zeros(height, np.int64)
    column_times = None
    if time_name is not None:
        t_abs = _time_ns(pts, time_name, stamp_ns)
        if np.ptp(t_abs) > 0:
            # the measurement column 0 of each row is where its times wrap (largest drop)
            drop = t_abs - np.roll(t_abs, 1, axis=1)
            shifts = np.argmin(drop, axis=1).astype(np.int64)
            if not np.any(drop < 0):
                shifts[:] = 0
            cols = np.arange(width)
            src = (cols[None, :] + shifts[:, None]) % width          # grid column of c
            meas = np.take_along_axis(t_abs, src, axis=1).astype(np.float64)
            col = np.median(meas, axis=0)
            beam = np.median(meas - col[None, :], axis=1)
            beam -= beam.min()
            col = np.median(meas - beam[:, None], axis=0)
            beam_times = np.rint(beam).astype(np.int64)
            column_times = np.rint(col).astype(np.int64)
            shifts = shifts % width
            shifts[shifts > width // 2] -= width   # smallest magnitude representation
    cidx = (np.arange(width)[None, :] - shifts[:, None]) % width
    if "ring" in names:
        ring = pts["ring"]
        ring = (ring[..., 0] if ring.ndim == 3 else ring).astype(np.int64)
        beam_ids = np.array([np.bincount(r - r.min()).argmax() + r.min() for r in ring])
    else:
        beam_ids = np.arange(height)
    known = None
    if range_name is not None:
        known = _field_f64(pts, range_name) * range_scale
        known = np.where(valid & (known > 0), known, np.nan)
        if not np.isfinite(known[valid]).all():
            known = None
    channels = {n: np.array(pts[n]) for n in names
                if n not in _SKIP and n != time_name and n != range_name}
    return _Grid(points=np.where(valid[..., None], xyz, np.nan), valid=valid, cidx=cidx,
                 width=width, shifts=shifts, beam_ids=beam_ids, beam_times=beam_times,
                 column_times=column_times, channels=channels, known_range=known,
                 per_scan_azimuths=False)


#: Largest grid estimated from an unorganized cloud: no spinning lidar has more beams or more
#: columns per turn; the checks keep garbage fields from allocating gigabytes.
MAX_ROWS, MAX_COLUMNS = 1024, 1 << 16


def _check_grid_size(height: int, width: int, points: int, source: str) -> None:
    """Refuse a ring x column grid that no lidar produces, before allocating it."""
    if height > MAX_ROWS or width > MAX_COLUMNS or height * width > 16 * points + 65536:
        raise ConversionError("cloud", f"{height} rings x {width} columns from {points} points",
                              f"at most {MAX_ROWS} rings, {MAX_COLUMNS} columns and a grid not "
                              f"much larger than the cloud (check the cloud's {source})")


def _ring_grid(pts: np.ndarray[Any, Any], names: Sequence[str], time_name: str | None,
               stamp_ns: int, range_name: str | None, range_scale: float) -> _Grid:
    flat = pts.reshape(-1)
    xyz = np.stack([_field_f64(flat[None, :], n)[0] for n in "xyz"], -1)
    ok = np.all(np.isfinite(xyz), -1) & np.any(xyz != 0, -1)
    flat, xyz = flat[ok], xyz[ok]
    ring = flat["ring"]
    ring = (ring[:, 0] if ring.ndim == 2 else ring).astype(np.int64)
    rings, row_of = np.unique(ring, return_inverse=True)
    height = rings.size
    _check_grid_size(height, 1, flat.size, "ring values")
    if flat.size < 3:
        raise ConversionError("cloud", f"{flat.size} valid points", "at least 3 finite points")
    # rows top -> bottom: order rings by their median elevation
    elev = np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1]))
    med = _median_by(row_of, elev, height)
    order = np.argsort(-med, kind="stable")
    rank = np.empty(height, np.int64)
    rank[order] = np.arange(height)
    rows = rank[row_of]
    beam_ids = rings[order]
    psi = np.arctan2(xyz[:, 1], xyz[:, 0])

    beam_times = np.zeros(height, np.int64)
    column_times = None
    t_abs = _time_ns(flat[None, :], time_name, stamp_ns)[0] if time_name else None
    cols = None
    if t_abs is not None and np.ptp(t_abs) > 0:
        cols, beam_times = _columns_from_times(t_abs, rows, height)
    time_cols = cols is not None
    if cols is None:
        cols = _columns_from_azimuth(psi, rows, height)
    width = int(cols.max()) + 1
    _check_grid_size(height, width, flat.size, "time or azimuth spacing")
    pix = rows * width + cols
    first = np.unique(pix, return_index=True)[1]
    dropped = int(pix.size - first.size)
    grid_pts = np.full((height * width, 3), np.nan)
    grid_pts[pix[first]] = xyz[first]
    valid = np.zeros(height * width, bool)
    valid[pix[first]] = True
    if t_abs is not None and np.ptp(t_abs) > 0 and cols is not None and time_cols:
        tf, rf, cf = t_abs[first], rows[first], cols[first]
        beam = beam_times.astype(np.float64)
        for _ in range(2):
            col = _interp_missing(_median_by(cf, tf - beam[rf], width))
            beam = np.nan_to_num(_median_by(rf, tf - col[cf], height))
            beam -= beam.min()
        beam_times = np.rint(beam).astype(np.int64)
        column_times = _column_times(tf - beam_times[rf], cf, width)
    known = None
    if range_name is not None:
        k = _field_f64(flat[None, :], range_name)[0] * range_scale
        flat_known = np.full(height * width, np.nan)
        flat_known[pix[first]] = k[first]
        known = flat_known.reshape(height, width)
        if not np.isfinite(flat_known[valid]).all() or np.any(flat_known[valid] <= 0):
            known = None
    channels = {}
    for n in names:
        if n in _SKIP or n == time_name or n == range_name:
            continue
        src = flat[n][first]
        img = np.zeros((height * width,) + src.shape[1:], src.dtype)
        img[pix[first]] = src
        channels[n] = img.reshape((height, width) + src.shape[1:])
    cidx = np.broadcast_to(np.arange(width)[None, :], (height, width))
    return _Grid(points=grid_pts.reshape(height, width, 3), valid=valid.reshape(height, width),
                 cidx=cidx, width=width, shifts=np.zeros(height, np.int64), beam_ids=beam_ids,
                 beam_times=beam_times, column_times=column_times, channels=channels,
                 known_range=known, per_scan_azimuths=True, dropped=dropped)


def _columns_from_times(t_abs: np.ndarray[Any, Any], rows: np.ndarray[Any, Any], height: int
                        ) -> tuple[Any, np.ndarray[Any, Any]]:
    """Column index of every point from its time, and each beam's firing offset (ns).

    Firings repeat with a period (median spacing of a beam's consecutive times, refined by the
    mean of the spacings near it); each beam's phase inside the period is its circular mean, and
    a firing starts after the largest gap between the beams' phases. Points are then sorted by
    ``t - beam offset`` and a new column starts at every gap longer than half a period (a gap of
    k periods skips k - 1 empty columns), so slow drifts of the rotation never accumulate.
    """
    order = np.lexsort((t_abs, rows))
    tt, rr = t_abs[order], rows[order]
    d = np.diff(tt)
    d = d[(rr[1:] == rr[:-1]) & (d > 0)].astype(np.float64)
    if d.size == 0:
        return None, np.zeros(height, np.int64)
    period = float(np.median(d))
    near = (d > 0.5 * period) & (d < 1.5 * period)
    if near.any():
        period = float(d[near].mean())
    t0 = int(t_abs.min())
    rel = (t_abs - t0).astype(np.float64)
    ang = 2 * np.pi * np.mod(rel, period) / period
    cnt = np.bincount(rows, minlength=height)
    phase = np.arctan2(np.bincount(rows, np.sin(ang), height),
                       np.bincount(rows, np.cos(ang), height))
    phase = np.mod(phase, 2 * np.pi) * period / (2 * np.pi)           # ns in [0, period)
    used = np.sort(phase[cnt > 0])
    gaps = np.diff(np.concatenate([used, [used[0] + period]]))
    start = used[(int(np.argmax(gaps)) + 1) % used.size]
    beam = np.mod(phase - start, period)
    beam[cnt == 0] = 0.0
    tc = rel - beam[rows]
    o = np.argsort(tc, kind="stable")
    steps = np.diff(tc[o])
    inc = np.where(steps > 0.5 * period, np.maximum(np.rint(steps / period), 1), 0)
    k = np.empty(tc.size, np.int64)
    k[o] = np.concatenate([[0], np.cumsum(inc)]).astype(np.int64)
    return k, np.rint(beam).astype(np.int64)


def _column_times(t_col: np.ndarray[Any, Any], cols: np.ndarray[Any, Any], width: int
                  ) -> np.ndarray[Any, Any]:
    """Absolute ns of each column: median over its points, interpolated where empty."""
    med = _median_by(cols, t_col.astype(np.float64), width)
    return np.asarray(np.rint(_interp_missing(med)), dtype=np.int64)


def _columns_from_azimuth(psi: np.ndarray[Any, Any], rows: np.ndarray[Any, Any], height: int
                          ) -> np.ndarray[Any, Any]:
    """Column index from azimuth bins (clockwise sweep, as spinning lidars turn)."""
    order = np.lexsort((psi, rows))
    pp, rr = psi[order], rows[order]
    d = np.diff(pp)
    d = d[(rr[1:] == rr[:-1]) & (d > 1e-9)]
    if d.size == 0:
        raise ConversionError("cloud", "points without azimuth spread",
                              "points spread over azimuth (or a time field)")
    step = float(np.median(d))
    width = max(round(2 * np.pi / step), 1)
    step = 2 * np.pi / width
    ang = 2 * np.pi * np.mod(psi, step) / step
    phase = np.arctan2(np.bincount(rows, np.sin(ang), height),
                       np.bincount(rows, np.cos(ang), height)) * step / (2 * np.pi)
    k = np.rint((np.pi - (psi - phase[rows])) / step).astype(np.int64) % width
    return np.asarray(k, dtype=np.int64)


# ----------------------------------------------------------------------------- public API

def from_pointcloud2(cloud: Any, *, layout: str = "auto", time_field: str | None = None,
                     range_field: str | None = "auto", range_scale: float | None = None,
                     stamp_ns: int | None = None, frame_id: str | None = None,
                     as_dataclass: bool = False) -> tuple[Any, Any]:
    """PointCloud2 from a lidar driver -> (LidarScan, estimated LidarInfo).

    Args:
        cloud: ``sensor_msgs/PointCloud2`` (rclpy message or dataclass); any byte order, float32
            or float64 x/y/z, padding, row padding. Never modified.
        layout: "organized" (rows = beams, e.g. ouster-ros H x W), "ring" (group points by their
            ``ring`` field; velodyne / Hesai / RoboSense, organized or not) or "auto" (organized
            when height > 1 and each row holds one ring, else ring).
        time_field: per-point time field; default the first of t, time, timestamp,
            time_stamp, offset_time. Integer fields are ns, float fields s; values > 1e6 s
            (or > 1e15 ns) are absolute, smaller ones relative to the header stamp.
        range_field: field with ranges along the beam ("auto": ``range`` if present; None:
            ignore). Its values become the scan's ranges when they fit the geometry.
        range_scale: metres per unit of the range field; default 0.001 for integer fields
            (ouster-ros millimetres), 1 for float fields.
        stamp_ns: the info's stamp (version key); default the scan's stamp.
        frame_id: frame of scan and info; default the cloud's.
        as_dataclass: return :mod:`lidarscan.types` dataclasses instead of rclpy messages.

    Returns:
        (scan, info): ``range`` float32 metres (+Inf where the cloud has no point) first, then
        every other scalar field of the cloud as a channel of its own datatype (time, ring, range
        and x/y/z excluded). Organized clouds keep their column order (``is_destaggered`` true
        with the estimated ``pixel_shift_by_row`` when times reveal a stagger); ring clouds are
        in firing order with per-scan ``column_azimuth_angles``. ``beam_ids`` = ring values.

    Raises:
        ConversionError: no x/y/z, too few points, a layout that cannot be inferred.
        ConfigError: bad option values.
    """
    if layout not in ("auto", "organized", "ring"):
        raise ConfigError("layout", layout, '"auto", "organized" or "ring"')
    pts = read_points(cloud)
    names = list(pts.dtype.names or ())
    for axis in "xyz":
        if axis not in names:
            raise ConversionError("fields", names, "x, y and z fields")
    if pts.size == 0:
        raise ConversionError("cloud", f"{pts.shape[0]}x{pts.shape[1]} points",
                              "a cloud with points to estimate a geometry from")
    header_ns = to_ns(cloud.header.stamp, field="cloud.header.stamp")
    time_name = _pick_time_field(names, time_field)
    range_name: str | None = None
    if range_field == "auto":
        range_name = next((n for n in _RANGE_FIELDS if n in names), None)
    elif range_field is not None:
        if range_field not in names:
            raise ConfigError("range_field", range_field, f"one of the cloud's fields {names}")
        range_name = range_field
    scale = 1.0
    if range_name is not None:
        kind = pts.dtype[range_name].base.kind
        scale = float(range_scale) if range_scale is not None else (0.001 if kind in "iu"
                                                                     else 1.0)
    chosen = layout
    if layout == "auto":
        chosen = "ring" if "ring" in names else "organized"
        if chosen == "ring" and pts.shape[0] > 1:
            ring = pts["ring"]
            ring = ring[..., 0] if ring.ndim == 3 else ring
            if np.all(ring == ring[:, :1]) and np.unique(ring[:, 0]).size == pts.shape[0]:
                chosen = "organized"
        if chosen == "organized" and pts.shape[0] < 2:
            raise ConversionError("cloud.height", pts.shape[0],
                                  "an organized cloud (height > 1, rows = beams) or a ring field")
    if chosen == "ring" and "ring" not in names:
        raise ConversionError("fields", names, 'a "ring" field for layout="ring"')
    build = _organized_grid if chosen == "organized" else _ring_grid
    grid = build(pts, names, time_name, header_ns, range_name, scale)
    fit = _fit_geometry(grid.points, grid.valid, grid.cidx, grid.width, grid.known_range)
    return _assemble(cloud, grid, fit, header_ns, stamp_ns, frame_id, as_dataclass)


def _assemble(cloud: Any, grid: _Grid, fit: _Fit, header_ns: int, info_stamp: int | None,
              frame_id: str | None, as_dataclass: bool) -> tuple[Any, Any]:
    width = grid.width
    order = np.argsort(-fit.phi, kind="stable")           # rows top -> bottom

    def rows(a: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
        return a[order]
    col_offsets = None
    increment = 0
    scan_stamp = header_ns
    if grid.column_times is not None:
        scan_stamp = int(grid.column_times[0])
        col_offsets = grid.column_times - np.int64(scan_stamp)
        if width > 1:
            increment = round(float(np.median(np.diff(col_offsets))))
            increment = max(increment, 0)
    frame = frame_id if frame_id is not None else cloud.header.frame_id
    shifts = rows(grid.shifts)
    info = make_info(
        stamp_ns=scan_stamp if info_stamp is None else int(info_stamp), frame_id=frame,
        vertical_angles=rows(fit.phi), horizontal_angles=fit.alpha,
        beam_azimuth_offsets=rows(fit.beta), beam_origins=rows(fit.origins).reshape(-1),
        pixel_shift_by_row=shifts if np.any(shifts) else [],
        beam_time_offsets=rows(grid.beam_times) if np.any(grid.beam_times) else [],
        column_time_increment=increment,
        beam_ids=rows(np.asarray(grid.beam_ids)).astype(np.uint16),
        model="estimated from sensor_msgs/PointCloud2",
        as_dataclass=as_dataclass)
    rng = np.where(grid.valid, fit.rho, np.inf).astype(np.float32)
    channels: dict[str, Any] = {"range": rows(rng)}
    for name, img in grid.channels.items():
        if name == "range":
            continue
        try:
            datatype_of(img.dtype)
        except ValidationError:
            continue
        channels[name] = rows(np.ascontiguousarray(img).astype(img.dtype.newbyteorder("=")))
    scan = make_scan(info, channels, scan_stamp, frame_id=frame,
                     is_destaggered=bool(np.any(shifts)),
                     column_time_offsets=col_offsets,
                     column_azimuth_angles=fit.alpha if grid.per_scan_azimuths else None,
                     as_dataclass=as_dataclass)
    return scan, info


@dataclasses.dataclass(frozen=True)
class ReprojectionError:
    """How well a (scan, info) pair reproduces a cloud's points.

    Attributes:
        points: finite points in the cloud.
        matched: of those, points whose pixel re-projects to a point.
        max_m, rms_m: largest and RMS distance (metres) between the cloud's xyz and the
            re-projected pixel (over matched points).
        max_time_ns: largest |cloud time - pixel time| (None without a time field).
    """

    points: int
    matched: int
    max_m: float
    rms_m: float
    max_time_ns: int | None


def estimation_error(cloud: Any, scan: Any, info: Any, *, time_field: str | None = None
                     ) -> ReprojectionError:
    """Re-project ``scan`` with ``info`` and compare with the cloud's points.

    Points are matched to pixels like :func:`from_pointcloud2` arranges them: organized clouds of
    the scan's size pixel by pixel (rows through ``info.beam_ids`` = ring / source row), other
    clouds by ring and time (or azimuth when there is no time field).
    """
    from lidarscan.geometry import make_projector as _mk

    proj = _mk(info)
    xyz_scan = proj.project(scan, info).astype(np.float64)
    stamp = to_ns(scan.header.stamp)
    times = proj.pixel_times(scan) + np.int64(stamp)
    pts = read_points(cloud)
    names = list(pts.dtype.names or ())
    time_name = _pick_time_field(names, time_field)
    header_ns = to_ns(cloud.header.stamp)
    ids = _as_array(info.beam_ids, np.uint16).astype(np.int64)
    height, width = int(info.height), int(info.width)
    if ids.size == 0:
        ids = np.arange(height)
    row_of_id = {int(v): i for i, v in enumerate(ids)}
    xyz = np.stack([_field_f64(pts, n) for n in "xyz"], -1)
    ok = np.all(np.isfinite(xyz), -1) & np.any(xyz != 0, -1)
    t_abs = _time_ns(pts, time_name, header_ns) if time_name else None
    if pts.shape == (height, width) and not (
            "ring" in names and not np.all(_ring_rows(pts) == _ring_rows(pts)[:, :1])):
        ring = _ring_rows(pts)[:, 0] if "ring" in names else np.arange(height)
        rows = np.array([row_of_id.get(int(r), -1) for r in ring])
        if np.any(rows < 0):
            raise InfoMismatchError("LidarInfo.beam_ids", ids.tolist(), "the cloud's rings")
        u = np.broadcast_to(rows[:, None], pts.shape)[ok]
        c = np.broadcast_to(np.arange(width)[None, :], pts.shape)[ok]
    else:
        ring = _ring_rows(pts)[ok]
        u = np.array([row_of_id.get(int(r), -1) for r in ring], dtype=np.int64)
        if np.any(u < 0):
            raise InfoMismatchError("LidarInfo.beam_ids", ids.tolist(), "the cloud's rings")
        if t_abs is not None:
            c = _nearest_time_column(times, u, t_abs[ok])
        else:
            c = _nearest_azimuth_column(xyz_scan, u, xyz[ok])
    target = xyz_scan[u, c]
    matched = np.all(np.isfinite(target), -1)
    diff = np.linalg.norm(xyz[ok][matched] - target[matched], axis=-1)
    max_t = None
    if t_abs is not None:
        max_t = int(np.abs(t_abs[ok] - times[u, c]).max(initial=0))
    return ReprojectionError(points=int(ok.sum()), matched=int(matched.sum()),
                             max_m=float(diff.max(initial=0.0)),
                             rms_m=float(np.sqrt(np.mean(diff**2))) if diff.size else 0.0,
                             max_time_ns=max_t)


def _ring_rows(pts: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    ring = pts["ring"]
    return (ring[..., 0] if ring.ndim == 3 else ring).astype(np.int64)


def _nearest_time_column(times: np.ndarray[Any, Any], u: np.ndarray[Any, Any],
                         t: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """Column whose pixel time in row u is nearest to t (pixel times increase along a row)."""
    out = np.empty(u.size, np.int64)
    for row in np.unique(u):
        sel = u == row
        line = times[row]
        k = np.clip(np.searchsorted(line, t[sel]), 1, line.size - 1)
        left = np.abs(t[sel] - line[k - 1]) <= np.abs(line[k] - t[sel])
        out[sel] = np.where(left, k - 1, k)
    return out


def _nearest_azimuth_column(xyz_scan: np.ndarray[Any, Any], u: np.ndarray[Any, Any],
                            p: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """Column whose re-projected direction in row u is nearest in azimuth to the point."""
    out = np.empty(u.size, np.int64)
    psi = np.arctan2(p[:, 1], p[:, 0])
    for row in np.unique(u):
        sel = np.flatnonzero(u == row)
        line = np.arctan2(xyz_scan[row, :, 1], xyz_scan[row, :, 0])
        known = np.isfinite(line)
        cols = np.flatnonzero(known)
        diff = np.abs(_wrap(psi[sel, None] - line[None, cols]))
        out[sel] = cols[np.argmin(diff, axis=1)]
    return out

