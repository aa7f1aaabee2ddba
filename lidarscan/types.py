"""Plain-Python mirrors of ROS messages, built without rclpy.

Each is a frozen, slotted dataclass with fields in ``.msg`` order and a ``__msgtype__``. The CDR
decoder returns them (numeric arrays become read-only numpy arrays that view the payload), and
:func:`lidarscan.encode` accepts them as well as rclpy messages. The hand-written classes below
cover the project's own messages; any other type gets a dataclass generated from its ``.msg``
(see :func:`message_class`). ``tests/test_types.py`` cross-checks these classes against the
``.msg`` files and rclpy's ``get_fields_and_field_types()``.
"""

from __future__ import annotations

import dataclasses
import keyword
from typing import Any, ClassVar

import numpy as np

from lidarscan.msgdef import get_msgdef, normalize_type, on_definitions_changed

__all__ = ["Time", "Header", "LidarChannel", "LidarScan", "LidarInfo", "message_class",
           "msgtype_of"]


def _readonly_zeros(size: int) -> np.ndarray[Any, Any]:
    arr = np.zeros(size)
    arr.flags.writeable = False
    return arr


def _empty(dtype: Any) -> Any:
    """Factory of an empty read-only array (dataclass default)."""
    def make() -> np.ndarray[Any, Any]:
        arr = np.zeros(0, dtype)
        arr.flags.writeable = False
        return arr
    return dataclasses.field(default_factory=make)


@dataclasses.dataclass(frozen=True, slots=True)
class Time:
    """builtin_interfaces/Time: seconds and nanoseconds (0 <= nanosec < 1e9)."""

    __msgtype__: ClassVar[str] = "builtin_interfaces/msg/Time"
    sec: int = 0
    nanosec: int = 0


@dataclasses.dataclass(frozen=True, slots=True)
class Header:
    """std_msgs/Header."""

    __msgtype__: ClassVar[str] = "std_msgs/msg/Header"
    stamp: Time = Time()
    frame_id: str = ""


@dataclasses.dataclass(frozen=True, slots=True)
class LidarChannel:
    """lidarscan_msgs/LidarChannel: one planar channel block (see the .msg for semantics)."""

    __msgtype__: ClassVar[str] = "lidarscan_msgs/msg/LidarChannel"
    INT8: ClassVar[int] = 1
    UINT8: ClassVar[int] = 2
    INT16: ClassVar[int] = 3
    UINT16: ClassVar[int] = 4
    INT32: ClassVar[int] = 5
    UINT32: ClassVar[int] = 6
    FLOAT32: ClassVar[int] = 7
    FLOAT64: ClassVar[int] = 8
    name: str = ""
    offset: int = 0
    datatype: int = 0
    count: int = 1


@dataclasses.dataclass(frozen=True, slots=True)
class LidarScan:
    """lidarscan_msgs/LidarScan. ``data`` is a read-only uint8 array (a view of the payload
    when decoded); the per-column arrays are read-only numpy arrays."""

    __msgtype__: ClassVar[str] = "lidarscan_msgs/msg/LidarScan"
    header: Header = Header()
    lidar_info_time: Time = Time()
    height: int = 0
    width: int = 0
    is_bigendian: bool = False
    is_destaggered: bool = False
    column_time_offsets: Any = _empty(np.int64)
    column_azimuth_angles: Any = _empty(np.float64)
    channels: tuple[LidarChannel, ...] = ()
    data: Any = _empty(np.uint8)


@dataclasses.dataclass(frozen=True, slots=True)
class LidarInfo:
    """lidarscan_msgs/LidarInfo: sensor intrinsics; ``header.stamp`` is the version key."""

    __msgtype__: ClassVar[str] = "lidarscan_msgs/msg/LidarInfo"
    header: Header = Header()
    vendor: str = ""
    model: str = ""
    serial_number: str = ""
    firmware_version: str = ""
    height: int = 0
    width: int = 0
    vertical_angles: Any = _empty(np.float64)
    horizontal_angles: Any = _empty(np.float64)
    beam_azimuth_offsets: Any = _empty(np.float64)
    pixel_azimuth_angles: Any = _empty(np.float64)
    pixel_altitude_angles: Any = _empty(np.float64)
    beam_origins: Any = _empty(np.float64)
    beam_range_offsets: Any = _empty(np.float64)
    lidar_to_sensor_transform: Any = dataclasses.field(  # all zeros = identity (see .msg)
        default_factory=lambda: _readonly_zeros(16))
    pixel_shift_by_row: Any = _empty(np.int32)
    beam_time_offsets: Any = _empty(np.int64)
    column_time_increment: int = 0
    beam_ids: Any = _empty(np.uint16)
    range_multiplier: float = 0.0
    range_offset: float = 0.0
    range_min: float = 0.0
    range_max: float = 0.0
    vendor_metadata: str = ""


_HANDWRITTEN: dict[str, type] = {cls.__msgtype__: cls for cls in
                                 (Time, Header, LidarChannel, LidarScan, LidarInfo)}
_GENERATED: dict[str, type] = {}
on_definitions_changed(_GENERATED.clear)


def message_class(msgtype: str) -> type:
    """The dataclass for ``msgtype`` (``pkg/msg/Name``): hand-written, or generated from the .msg.

    Generated classes are frozen and slotted, with every field defaulting to ``None``.
    """
    full = normalize_type(msgtype)
    cls = _HANDWRITTEN.get(full) or _GENERATED.get(full)
    if cls is None:
        msgdef = get_msgdef(full)
        names = [f.name + "_" if keyword.iskeyword(f.name) else f.name for f in msgdef.fields]
        cls = dataclasses.make_dataclass(
            full.split("/")[-1], [(n, Any, None) for n in names],
            namespace={"__msgtype__": full}, frozen=True, slots=True)
        _GENERATED[full] = cls
    return cls


def msgtype_of(msg: Any) -> str:
    """``pkg/msg/Name`` of a dataclass (``__msgtype__``) or an rclpy message instance."""
    explicit = getattr(msg, "__msgtype__", None)
    if isinstance(explicit, str):
        return explicit
    cls = type(msg)
    module = cls.__module__.split(".")
    if len(module) >= 2 and module[1] == "msg" and hasattr(cls, "get_fields_and_field_types"):
        return f"{module[0]}/msg/{cls.__name__}"
    from lidarscan.errors import SchemaError
    raise SchemaError("msg", cls.__name__, "an rclpy message or a lidarscan.types dataclass")
