"""PointCloud2 layouts: driver presets, generic field layouts, and reading any cloud's points.

Conventions: PointField datatypes are the ``sensor_msgs/PointField`` ids (1..8); a layout is a
tuple of :class:`FieldSpec` plus ``point_step``; clouds we write are little endian; clouds we
read may be either (:func:`read_points` returns a view whose dtype carries the byte order).

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

Preset channel fields missing from a scan are zero-filled (a range-only scan converts with
every preset); a field named explicitly in ``fields=`` must exist.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from lidarscan.datatypes import FLOAT32, FLOAT64, UINT16, UINT32, dtype_of
from lidarscan.errors import ConversionError, UnknownChannelError

__all__ = ["CHANNEL_ALIASES", "COMPUTED_TYPES", "DEFAULT_FIELDS", "PRESETS", "FieldSpec", "Preset",
           "check_extent", "cloud_dtype", "find_channel", "generic_layout", "read_points", "structured"]

#: Channel aliases tried in order when a field names a scan channel.
CHANNEL_ALIASES: dict[str, tuple[str, ...]] = {
    "intensity": ("intensity", "signal"),
    "ambient": ("ambient", "near_ir", "nearir"),
    "reflectivity": ("reflectivity", "reflec"),
}

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

DEFAULT_FIELDS = ("x", "y", "z", "intensity")
COMPUTED_TYPES = {"x": FLOAT32, "y": FLOAT32, "z": FLOAT32, "ring": UINT16, "t": UINT32,
                   "time": FLOAT32, "timestamp": FLOAT64, "range": FLOAT32}


def generic_layout(names: Sequence[str], scan: Any) -> tuple[tuple[FieldSpec, ...], int]:
    """Fields in the given order at natural alignment; channel fields take the scan's dtype."""
    specs: list[FieldSpec] = []
    offset, align = 0, 4
    for name in names:
        chans: tuple[str, ...] = ()
        if name in COMPUTED_TYPES:
            datatype, count, source = COMPUTED_TYPES[name], 1, name
        else:
            chans = CHANNEL_ALIASES.get(name, (name,))
            source = "channel"
            if name == "intensity":
                datatype, count = FLOAT32, 1
            else:
                desc = find_channel(scan, chans)
                if desc is None:
                    raise UnknownChannelError("fields", name,
                                              f"one of the scan's channels "
                                              f"{[c.name for c in scan.channels]} or "
                                              f"{sorted(COMPUTED_TYPES)}")
                datatype, count = int(desc.datatype), int(desc.count)
        size = dtype_of(datatype).itemsize
        offset += -offset % size
        specs.append(FieldSpec(name, datatype, offset, source, chans, count))
        offset += size * count
        align = max(align, size)
    return tuple(specs), offset + (-offset % align)


def find_channel(scan: Any, names: Sequence[str]) -> Any:
    for name in names:
        for desc in scan.channels:
            if desc.name == name:
                return desc
    return None


def structured(specs: Sequence[FieldSpec], point_step: int, bigendian: bool = False
                ) -> np.dtype[Any]:
    formats: list[Any] = []
    for s in specs:
        base = dtype_of(s.datatype, bigendian)
        formats.append(base if s.count == 1 else (base, (s.count,)))
    return np.dtype({"names": [s.name for s in specs], "formats": formats,
                     "offsets": [s.offset for s in specs], "itemsize": point_step})


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


def check_extent(height: int, width: int, step: int, row_step: int, nbytes: int) -> None:
    """Raise :class:`ConversionError` unless ``nbytes`` of cloud data with this ``row_step``
    hold ``height`` x ``width`` points of ``step`` bytes (both > 0)."""
    if row_step < step * width:
        raise ConversionError("row_step", row_step, f">= point_step * width = {step * width}")
    need = (height - 1) * row_step + width * step
    if nbytes < need:
        raise ConversionError("data", f"length {nbytes}",
                              f">= {need} bytes for {height}x{width} points")


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
    check_extent(height, width, step, row_step, buf.size)
    view = np.ndarray((height, width), dtype=dtype, buffer=buf.data if isinstance(
        buf, np.ndarray) else buf, strides=(row_step, step))
    view.flags.writeable = False
    return view
