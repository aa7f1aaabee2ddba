"""CDR codec (lidarscan.cdr): golden bytes, rclpy, rosbags and mcap-ros2-support agreement,
big-endian input, and decoder robustness.

Layers:

* golden hex written by hand from the XCDR1 rules, one row per field (payload offset, value,
  padding); ``encode`` must produce exactly these bytes and ``decode`` must give the values back;
* an independent layout walker (:func:`cdr_layout`, written here from the rules, sharing no code
  with ``lidarscan.cdr``) gives the padding mask used to compare with rclpy, whose
  ``serialize_message`` leaves padding uninitialised; the walker itself is checked against
  rosbags, which writes zero padding;
* Hypothesis messages of every type of interest, generated from their ``.msg`` definitions:
  byte-identical to rosbags, equal to rclpy modulo padding, decoded back by rclpy, rosbags,
  mcap-ros2-support and ourselves;
* bad input (truncation, bit flips, lying length fields, bad UTF-8, bad encapsulation) raises
  only :mod:`lidarscan.errors` exceptions, quickly and without large allocations.
"""

from __future__ import annotations

import array
import importlib
import math
import struct
import tracemalloc
from functools import lru_cache
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import lidarscan
from lidarscan import types
from lidarscan.errors import DecodeError, EncodeError, LidarScanError
from lidarscan.msgdef import get_msgdef, schema_text
from lidarscan.types import message_class

SCAN = "lidarscan_msgs/msg/LidarScan"
INFO = "lidarscan_msgs/msg/LidarInfo"
CHANNEL = "lidarscan_msgs/msg/LidarChannel"
ROS_TYPES = [SCAN, INFO, CHANNEL, "sensor_msgs/msg/PointCloud2", "sensor_msgs/msg/LaserScan",
             "sensor_msgs/msg/PointField", "sensor_msgs/msg/Imu", "nav_msgs/msg/Odometry"]

# ----------------------------------------------------------------------------- helpers

_SIZE = {"bool": 1, "byte": 1, "char": 1, "int8": 1, "uint8": 1, "int16": 2, "uint16": 2,
         "int32": 4, "uint32": 4, "int64": 8, "uint64": 8, "float32": 4, "float64": 8}
_DTYPE = {"bool": "?", "byte": "u1", "char": "u1", "int8": "i1", "uint8": "u1", "int16": "<i2",
          "uint16": "<u2", "int32": "<i4", "uint32": "<u4", "int64": "<i8", "uint64": "<u8",
          "float32": "<f4", "float64": "<f8"}
_STRUCT = {"bool": "?", "byte": "B", "char": "B", "int8": "b", "uint8": "B", "int16": "h",
           "uint16": "H", "int32": "i", "uint32": "I", "int64": "q", "uint64": "Q",
           "float32": "f", "float64": "d"}


def golden(rows: list[tuple[str, str]]) -> bytes:
    """Bytes from ``(hex, comment)`` rows (the comment documents the field; spaces ignored)."""
    return bytes.fromhex("".join(h.replace(" ", "") for h, _ in rows))


def cdr_layout(value: Any, msgtype: str) -> tuple[int, np.ndarray]:
    """Independent XCDR1 layout of ``value``: (payload size, bool mask, True = padding byte).

    Written from the rules, not from lidarscan.cdr: alignment counts from the end of the
    encapsulation header; primitives align to their size; strings and sequences start with a
    4-aligned uint32; an empty sequence adds no element alignment; an empty struct holds one
    uint8 (rosidl's ``structure_needs_at_least_one_member``).
    """
    used: list[tuple[int, int]] = []

    def align(pos: int, size: int) -> int:
        return (pos + size - 1) // size * size

    def one(v: Any, ftype: str, pos: int) -> int:
        if ftype in _SIZE:
            pos = align(pos, _SIZE[ftype])
            used.append((pos, pos + _SIZE[ftype]))
            return pos + _SIZE[ftype]
        if ftype == "string":
            pos = align(pos, 4)
            end = pos + 4 + len(v.encode("utf-8")) + 1
            used.append((pos, end))
            return end
        return struct_(v, ftype, pos)

    def struct_(v: Any, ftype: str, pos: int) -> int:
        fields = get_msgdef(ftype).fields
        if not fields:
            used.append((pos, pos + 1))
            return pos + 1
        for f in fields:
            x = getattr(v, f.name)
            if f.array is None:
                pos = one(x, f.type, pos)
                continue
            n = len(x)
            if f.array < 0:
                pos = align(pos, 4)
                used.append((pos, pos + 4))
                pos += 4
            if f.type in _SIZE:
                if n:
                    pos = align(pos, _SIZE[f.type])
                    used.append((pos, pos + n * _SIZE[f.type]))
                    pos += n * _SIZE[f.type]
            else:
                for item in x:
                    pos = one(item, f.type, pos)
        return pos

    size = struct_(value, msgtype, 0)
    padding = np.ones(size, bool)
    for start, end in used:
        padding[start:end] = False
    return size, padding


def _prim_bytes(x: Any, ftype: str) -> bytes:
    """Canonical little-endian bytes of a primitive array value from any library."""
    if isinstance(x, (bytes, bytearray, memoryview)):
        return bytes(x)
    if isinstance(x, (list, tuple)) and x and isinstance(x[0], bytes):  # rclpy byte[]
        return b"".join(x)
    arr = np.asarray(x)
    if ftype == "bool":
        return arr.astype(bool).tobytes()
    return arr.astype(_DTYPE[ftype]).tobytes()


def plain(value: Any, msgtype: str) -> dict[str, Any]:
    """Library-neutral, bitwise comparable form of a message (rclpy, rosbags, mcap_ros2, ours)."""
    out: dict[str, Any] = {}
    for f in get_msgdef(msgtype).fields:
        x = getattr(value, f.name)
        if f.array is None:
            out[f.name] = _plain_one(x, f.type)
        elif f.type in _SIZE:
            out[f.name] = (len(x), _prim_bytes(x, f.type))
        else:
            out[f.name] = [_plain_one(i, f.type) for i in x]
    return out


def _plain_one(x: Any, ftype: str) -> Any:
    if ftype in ("float32", "float64"):
        return struct.pack("<" + _STRUCT[ftype], x)  # bitwise, NaN-safe
    if ftype == "bool":
        return bool(x)
    if ftype == "byte":  # an octet; rosbags reads it as int8, rclpy as bytes, we as uint8
        return x[0] if isinstance(x, bytes) else int(x) & 0xFF
    if ftype in _SIZE:
        return int(x)
    if ftype == "string":
        return str(x)
    return plain(x, ftype)


def _np_array(x: Any, ftype: str) -> np.ndarray:
    if isinstance(x, (bytes, bytearray)):
        return np.frombuffer(x, np.uint8)
    dtype = bool if ftype == "bool" else np.dtype(_DTYPE[ftype]).newbyteorder("=")
    return np.asarray(x, dtype=dtype)


def to_rclpy(value: Any, msgtype: str) -> Any:
    """rclpy instance with the values of any message object (arrays assigned the fast way)."""
    pkg, _, name = msgtype.split("/")
    msg = getattr(importlib.import_module(f"{pkg}.msg"), name)()
    for f in get_msgdef(msgtype).fields:
        x = getattr(value, f.name)
        if f.array is None:
            if f.type == "byte":
                x = bytes([int(x)])
            elif f.type == "bool":
                x = bool(x)
            elif f.type not in _SIZE and f.type != "string":
                x = to_rclpy(x, f.type)
        elif f.type in _SIZE:
            arr = _np_array(x, f.type)
            if f.type == "byte":
                x = [bytes([b]) for b in arr.tolist()]
            elif f.type == "bool":
                x = [bool(b) for b in arr]
            elif f.array > 0:
                x = arr
            elif f.type in ("uint8", "char"):
                x = arr.tobytes()
            else:
                x = array.array(arr.dtype.char if arr.dtype.char != "l" else "q", arr.tobytes())
        elif f.type == "string":
            x = list(x)
        else:
            x = [to_rclpy(i, f.type) for i in x]
        setattr(msg, f.name, x)
    return msg


@lru_cache(maxsize=1)
def rosbags_store() -> Any:
    """rosbags typestore with lidarscan_msgs registered from msgs/msg/*.msg.

    rosbags 0.11.9 has no ROS2_JAZZY store; LATEST carries the same sensor_msgs/nav_msgs
    definitions (checked field by field in :func:`test_rosbags_store_matches_jazzy_definitions`).
    """
    typesys = pytest.importorskip("rosbags.typesys")
    from lidarscan.msgdef import find_msg_text
    store = typesys.get_typestore(typesys.Stores.LATEST)
    add: dict[str, Any] = {}
    for name in (CHANNEL, INFO, SCAN):
        add.update(typesys.get_types_from_msg(find_msg_text(name), name))
    store.register(add)
    return store


def to_rosbags(value: Any, msgtype: str, store: Any) -> Any:
    kwargs: dict[str, Any] = {}
    for f in get_msgdef(msgtype).fields:
        x = getattr(value, f.name)
        if f.array is None:
            if f.type in _SIZE:
                x = bool(x) if f.type == "bool" else (x[0] if isinstance(x, bytes) else x)
            elif f.type != "string":
                x = to_rosbags(x, f.type, store)
        elif f.type in _SIZE:
            x = _np_array(x, f.type)
        elif f.type == "string":
            x = list(x)
        else:
            x = [to_rosbags(i, f.type, store) for i in x]
        kwargs[f.name] = x
    return store.types[msgtype](**kwargs)


def mcap_decoder(msgtype: str) -> Any:
    decoder_mod = pytest.importorskip("mcap_ros2.decoder")
    from mcap.records import Schema
    schema = Schema(id=1, name=msgtype, encoding="ros2msg",
                    data=schema_text(msgtype).encode())
    return decoder_mod.DecoderFactory().decoder_for("cdr", schema)


# --------------------------------------------------------------- Hypothesis messages from .msg

_INT_RANGE = {"int8": (-2**7, 2**7 - 1), "uint8": (0, 255), "byte": (0, 255), "char": (0, 255),
              "int16": (-2**15, 2**15 - 1), "uint16": (0, 2**16 - 1),
              "int32": (-2**31, 2**31 - 1), "uint32": (0, 2**32 - 1),
              "int64": (-2**63, 2**63 - 1), "uint64": (0, 2**64 - 1)}
_TEXT = st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00"),
                max_size=7)


def _prim_strategy(ftype: str) -> st.SearchStrategy[Any]:
    if ftype == "bool":
        return st.booleans()
    if ftype == "float32":
        return st.floats(width=32)
    if ftype == "float64":
        return st.floats()
    low, high = _INT_RANGE[ftype]
    return st.integers(low, high)


def message_strategy(msgtype: str) -> st.SearchStrategy[Any]:
    """Any valid (for CDR) value of ``msgtype`` as a lidarscan.types dataclass."""
    cls = message_class(msgtype)
    fields: dict[str, st.SearchStrategy[Any]] = {}
    for f in get_msgdef(msgtype).fields:
        if f.array is None:
            if f.type in _SIZE:
                fields[f.name] = _prim_strategy(f.type)
            elif f.type == "string":
                fields[f.name] = _TEXT
            else:
                fields[f.name] = message_strategy(f.type)
            continue
        sizes = {"min_size": f.array, "max_size": f.array} if f.array > 0 else {"max_size": 4}
        if f.type in _SIZE:
            dtype = bool if f.type == "bool" else np.dtype(_DTYPE[f.type]).newbyteorder("=")
            fields[f.name] = st.lists(_prim_strategy(f.type), **sizes).map(
                lambda v, d=dtype: np.array(v, dtype=d))
            if f.type == "uint8" and f.array < 0:
                fields[f.name] = st.one_of(fields[f.name], st.binary(max_size=13))
        elif f.type == "string":
            fields[f.name] = st.lists(_TEXT, **sizes).map(tuple)
        else:
            fields[f.name] = st.lists(message_strategy(f.type), **dict(sizes, max_size=min(
                sizes["max_size"], 3))).map(tuple)
    return st.builds(cls, **fields)


_MESSAGES = st.sampled_from(ROS_TYPES).flatmap(
    lambda t: st.tuples(st.just(t), message_strategy(t)))


# ------------------------------------------------------------------------------- golden bytes

CHANNEL_ROWS = [
    ("00 01 00 00", "encapsulation: CDR little-endian, options 0"),
    ("03 00 00 00", "0   name length 3 (2 chars + NUL)"),
    ("61 62 00", "4   name 'ab' NUL"),
    ("00", "7   padding to 4 (odd-length string)"),
    ("08 00 00 00", "8   offset = 8"),
    ("07", "12  datatype = FLOAT32"),
    ("00 00 00", "13  padding to 4"),
    ("02 00 00 00", "16  count = 2"),
]
CHANNEL_VALUE = types.LidarChannel(name="ab", offset=8, datatype=7, count=2)

SCAN_ROWS = [
    ("00 01 00 00", "encapsulation: CDR little-endian"),
    ("01 00 00 00", "0   header.stamp.sec = 1"),
    ("02 00 00 00", "4   header.stamp.nanosec = 2"),
    ("06 00 00 00", "8   header.frame_id length 6"),
    ("6c 69 64 61 72 00", "12  'lidar' NUL"),
    ("00 00", "18  padding to 4"),
    ("01 00 00 00", "20  lidar_info_time.sec = 1"),
    ("00 00 00 00", "24  lidar_info_time.nanosec = 0"),
    ("01 00 00 00", "28  height = 1"),
    ("02 00 00 00", "32  width = 2"),
    ("00", "36  is_bigendian = false"),
    ("01", "37  is_destaggered = true"),
    ("00 00", "38  padding to 4"),
    ("02 00 00 00", "40  column_time_offsets count = 2"),
    ("00 00 00 00", "44  padding to 8 (int64 after a uint32 count)"),
    ("00 00 00 00 00 00 00 00", "48  column_time_offsets[0] = 0"),
    ("50 c3 00 00 00 00 00 00", "56  column_time_offsets[1] = 50000"),
    ("00 00 00 00", "64  column_azimuth_angles count = 0 (empty: no padding to 8)"),
    ("02 00 00 00", "68  channels count = 2"),
    ("06 00 00 00", "72  channels[0].name length 6"),
    ("72 61 6e 67 65 00", "76  'range' NUL"),
    ("00 00", "82  padding to 4"),
    ("00 00 00 00", "84  channels[0].offset = 0"),
    ("07", "88  channels[0].datatype = FLOAT32"),
    ("00 00 00", "89  padding to 4"),
    ("01 00 00 00", "92  channels[0].count = 1"),
    ("02 00 00 00", "96  channels[1].name length 2"),
    ("69 00", "100 'i' NUL"),
    ("00 00", "102 padding to 4"),
    ("08 00 00 00", "104 channels[1].offset = 8"),
    ("02", "108 channels[1].datatype = UINT8"),
    ("00 00 00", "109 padding to 4"),
    ("01 00 00 00", "112 channels[1].count = 1"),
    ("0a 00 00 00", "116 data count = 10"),
    ("00 00 c0 3f", "120 data[0:4]  range[0,0] = 1.5f"),
    ("00 00 80 7f", "124 data[4:8]  range[0,1] = +inf (no return)"),
    ("07 ff", "128 data[8:10] i[0,0] = 7, i[0,1] = 255; payload ends at 130, no trailing pad"),
]


def _scan_value() -> Any:
    data = np.frombuffer(struct.pack("<ff", 1.5, math.inf) + bytes([7, 255]), np.uint8)
    return types.LidarScan(
        header=types.Header(types.Time(1, 2), "lidar"), lidar_info_time=types.Time(1, 0),
        height=1, width=2, is_bigendian=False, is_destaggered=True,
        column_time_offsets=np.array([0, 50000], np.int64),
        column_azimuth_angles=np.zeros(0),
        channels=(types.LidarChannel("range", 0, 7, 1), types.LidarChannel("i", 8, 2, 1)),
        data=data)


_IDENTITY_ROWS = [
    ("00 00 00 00 00 00 f0 3f" if i % 5 == 0 else "00" * 8,
     f"{152 + 8 * i} lidar_to_sensor_transform[{i}] = {1.0 if i % 5 == 0 else 0.0}")
    for i in range(16)]

INFO_ROWS = [
    ("00 01 00 00", "encapsulation: CDR little-endian"),
    ("01 00 00 00", "0   header.stamp.sec = 1"),
    ("00 00 00 00", "4   header.stamp.nanosec = 0"),
    ("03 00 00 00", "8   header.frame_id length 3"),
    ("6f 73 00", "12  'os' NUL"),
    ("00", "15  padding to 4"),
    ("01 00 00 00", "16  vendor length 1 (empty string = just the NUL)"),
    ("00", "20  NUL"),
    ("00 00 00", "21  padding to 4"),
    ("02 00 00 00", "24  model length 2"),
    ("58 00", "28  'X' NUL"),
    ("00 00", "30  padding to 4"),
    ("01 00 00 00 00 00 00 00", "32  serial_number = '' (length 1, NUL, 3 padding)"),
    ("01 00 00 00 00 00 00 00", "40  firmware_version = '' (length 1, NUL, 3 padding)"),
    ("01 00 00 00", "48  height = 1"),
    ("02 00 00 00", "52  width = 2"),
    ("01 00 00 00", "56  vertical_angles count = 1"),
    ("00 00 00 00", "60  padding to 8"),
    ("00 00 00 00 00 00 e0 3f", "64  vertical_angles[0] = 0.5"),
    ("02 00 00 00", "72  horizontal_angles count = 2"),
    ("00 00 00 00", "76  padding to 8"),
    ("00 00 00 00 00 00 00 00", "80  horizontal_angles[0] = 0.0"),
    ("00 00 00 00 00 00 f0 bf", "88  horizontal_angles[1] = -1.0"),
    ("00 00 00 00", "96  beam_azimuth_offsets count = 0"),
    ("00 00 00 00", "100 pixel_azimuth_angles count = 0"),
    ("00 00 00 00", "104 pixel_altitude_angles count = 0"),
    ("03 00 00 00", "108 beam_origins count = 3 (112 is 8-aligned: no padding)"),
    ("00 00 00 00 00 00 d0 3f", "112 beam_origins[0] = 0.25"),
    ("00 00 00 00 00 00 00 00", "120 beam_origins[1] = 0.0"),
    ("00 00 00 00 00 00 c0 bf", "128 beam_origins[2] = -0.125"),
    ("01 00 00 00", "136 beam_range_offsets count = 1"),
    ("00 00 00 00", "140 padding to 8"),
    ("00 00 00 00 00 00 00 40", "144 beam_range_offsets[0] = 2.0"),
    *_IDENTITY_ROWS,  # 152..280 fixed float64[16]: no count, 152 already 8-aligned
    ("01 00 00 00", "280 pixel_shift_by_row count = 1"),
    ("10 00 00 00", "284 pixel_shift_by_row[0] = 16"),
    ("01 00 00 00", "288 beam_time_offsets count = 1"),
    ("00 00 00 00", "292 padding to 8"),
    ("e8 03 00 00 00 00 00 00", "296 beam_time_offsets[0] = 1000"),
    ("50 c3 00 00 00 00 00 00", "304 column_time_increment = 50000"),
    ("01 00 00 00", "312 beam_ids count = 1"),
    ("07 00", "316 beam_ids[0] = 7"),
    ("00 00", "318 padding to 8"),
    ("fc a9 f1 d2 4d 62 50 3f", "320 range_multiplier = 0.001"),
    ("00 00 00 00 00 00 00 00", "328 range_offset = 0.0"),
    ("00 00 00 3f", "336 range_min = 0.5f"),
    ("00 00 f0 42", "340 range_max = 120.0f"),
    ("03 00 00 00", "344 vendor_metadata length 3"),
    ("7b 7d 00", "348 '{}' NUL; payload ends at 351"),
]


def _info_value() -> Any:
    return types.LidarInfo(
        header=types.Header(types.Time(1, 0), "os"), vendor="", model="X", serial_number="",
        firmware_version="", height=1, width=2, vertical_angles=np.array([0.5]),
        horizontal_angles=np.array([0.0, -1.0]), beam_origins=np.array([0.25, 0.0, -0.125]),
        beam_range_offsets=np.array([2.0]), lidar_to_sensor_transform=np.eye(4).reshape(16),
        pixel_shift_by_row=np.array([16], np.int32), beam_time_offsets=np.array([1000]),
        column_time_increment=50000, beam_ids=np.array([7], np.uint16), range_multiplier=0.001,
        range_offset=0.0, range_min=0.5, range_max=120.0, vendor_metadata="{}")


GOLDEN = [(CHANNEL, CHANNEL_ROWS, lambda: CHANNEL_VALUE), (SCAN, SCAN_ROWS, _scan_value),
          (INFO, INFO_ROWS, _info_value)]


@pytest.mark.parametrize(("msgtype", "rows", "make"), GOLDEN, ids=["channel", "scan", "info"])
def test_golden_encode(msgtype: str, rows: list[tuple[str, str]], make: Any) -> None:
    expected = golden(rows)
    assert lidarscan.encode(make()) == expected
    size, padding = cdr_layout(make(), msgtype)
    assert size == len(expected) - 4
    assert not np.frombuffer(expected, np.uint8)[4:][padding].any()  # every padding byte is zero


@pytest.mark.parametrize(("msgtype", "rows", "make"), GOLDEN, ids=["channel", "scan", "info"])
def test_golden_decode(msgtype: str, rows: list[tuple[str, str]], make: Any) -> None:
    decoded = lidarscan.decode(golden(rows), msgtype)
    assert type(decoded) is type(make())
    assert plain(decoded, msgtype) == plain(make(), msgtype)


def test_golden_scan_decode_details() -> None:
    payload = golden(SCAN_ROWS)
    scan = lidarscan.decode_scan(payload)
    assert scan.header.frame_id == "lidar" and scan.is_destaggered is True
    assert scan.is_bigendian is False
    assert scan.column_time_offsets.dtype == np.int64
    assert scan.column_time_offsets.tolist() == [0, 50000]
    assert scan.column_azimuth_angles.size == 0
    assert [c.name for c in scan.channels] == ["range", "i"]
    np.testing.assert_array_equal(lidarscan.channel(scan, "range"), [[1.5, np.inf]])
    np.testing.assert_array_equal(lidarscan.channel(scan, "i"), [[7, 255]])
    lidarscan.validate(scan)
    # data and the int64 array view the payload (zero copy, read-only)
    whole = np.frombuffer(payload, np.uint8)
    assert np.shares_memory(scan.data, whole)
    assert np.shares_memory(scan.column_time_offsets, whole)
    assert not scan.data.flags.writeable


def test_golden_info_decode_details() -> None:
    info = lidarscan.decode_info(golden(INFO_ROWS))
    assert info.range_multiplier == 0.001 and info.range_min == 0.5
    assert info.beam_ids.dtype == np.uint16 and info.beam_ids.tolist() == [7]
    assert info.pixel_shift_by_row.dtype == np.int32
    np.testing.assert_array_equal(info.lidar_to_sensor_transform, np.eye(4).reshape(16))
    lidarscan.validate_info(info)


def test_golden_big_endian_channel() -> None:
    """Encapsulation 00 00: every multi-byte number big-endian, same alignment."""
    payload = golden([
        ("00 00 00 00", "encapsulation: CDR big-endian"),
        ("00 00 00 03", "0  name length 3"),
        ("61 62 00", "4  'ab' NUL"),
        ("00", "7  padding to 4"),
        ("00 00 00 08", "8  offset = 8"),
        ("07", "12 datatype = FLOAT32"),
        ("00 00 00", "13 padding to 4"),
        ("00 00 00 02", "16 count = 2"),
    ])
    assert lidarscan.decode(payload, CHANNEL) == CHANNEL_VALUE


def test_golden_big_endian_arrays_are_native_copies() -> None:
    store = rosbags_store()
    value = _info_value()
    payload = bytes(store.serialize_cdr(to_rosbags(value, INFO, store), INFO,
                                        little_endian=False))
    assert payload[:2] == b"\x00\x00"
    info = lidarscan.decode_info(payload)
    assert plain(info, INFO) == plain(value, INFO)
    assert info.vertical_angles.dtype.byteorder in "=<"  # usable as native numbers
    assert not info.vertical_angles.flags.writeable


# ---------------------------------------------------------------------------- rosbags (zero pad)

def test_rosbags_store_matches_jazzy_definitions() -> None:
    store = rosbags_store()
    for msgtype in ROS_TYPES + ["geometry_msgs/msg/PoseWithCovariance", "std_msgs/msg/Header"]:
        ours = [f.name for f in get_msgdef(msgtype).fields]
        theirs = [n for n in store.types[msgtype].__dataclass_fields__
                  if n != "__msgtype__" and not n.isupper()]
        assert theirs == ours, msgtype


@pytest.mark.parametrize(("msgtype", "rows", "make"), GOLDEN, ids=["channel", "scan", "info"])
def test_golden_equals_rosbags(msgtype: str, rows: list[tuple[str, str]], make: Any) -> None:
    store = rosbags_store()
    assert bytes(store.serialize_cdr(to_rosbags(make(), msgtype, store), msgtype)) == golden(rows)


@settings(max_examples=150)
@given(_MESSAGES)
def test_rosbags_byte_identical(case: tuple[str, Any]) -> None:
    msgtype, value = case
    store = rosbags_store()
    ours = lidarscan.encode(value)
    theirs = bytes(store.serialize_cdr(to_rosbags(value, msgtype, store), msgtype))
    assert ours == theirs
    # our layout walker agrees with rosbags (so the rclpy mask below is right)
    size, padding = cdr_layout(value, msgtype)
    assert size == len(theirs) - 4
    assert not np.frombuffer(theirs, np.uint8)[4:][padding].any()
    # both directions of decoding
    assert plain(store.deserialize_cdr(ours, msgtype), msgtype) == plain(value, msgtype)
    assert plain(lidarscan.decode(theirs, msgtype), msgtype) == plain(value, msgtype)
    assert lidarscan.encode(lidarscan.decode(ours, msgtype)) == ours


@given(_MESSAGES)
def test_rosbags_big_endian_decodes(case: tuple[str, Any]) -> None:
    msgtype, value = case
    store = rosbags_store()
    payload = bytes(store.serialize_cdr(to_rosbags(value, msgtype, store), msgtype,
                                        little_endian=False))
    decoded = lidarscan.decode(payload, msgtype)
    assert plain(decoded, msgtype) == plain(value, msgtype)
    assert lidarscan.encode(decoded) == lidarscan.encode(value)


@given(_MESSAGES)
def test_mcap_ros2_decodes_ours(case: tuple[str, Any]) -> None:
    msgtype, value = case
    decoded = mcap_decoder(msgtype)(lidarscan.encode(value))
    assert plain(decoded, msgtype) == plain(value, msgtype)


# -------------------------------------------------------------------------- rclpy (modulo pad)

def _compare_with_rclpy(value: Any, msgtype: str) -> None:
    serialization = pytest.importorskip("rclpy.serialization")
    msg = to_rclpy(value, msgtype)
    ours = lidarscan.encode(msg)
    assert ours == lidarscan.encode(value)  # rclpy instance and dataclass encode the same
    theirs = serialization.serialize_message(msg)
    size, padding = cdr_layout(msg, msgtype)
    assert len(ours) == size + 4
    # rclpy sizes its buffer from an estimate that aligns even empty sequences and rounds to
    # 4: it may append a few uninitialised bytes, never fewer bytes than ours
    assert 0 <= len(theirs) - len(ours) < 64
    assert ours[:4] == theirs[:4] == b"\x00\x01\x00\x00"
    mask = ~padding
    a = np.frombuffer(ours, np.uint8)[4:]
    b = np.frombuffer(theirs, np.uint8)[4:4 + size]
    assert np.array_equal(a[mask], b[mask]), np.flatnonzero(a[mask] != b[mask])[:10]
    assert not a[padding].any()
    # rclpy reads our bytes back to the same values; we read theirs (garbage padding included)
    back = serialization.deserialize_message(ours, type(msg))
    assert plain(back, msgtype) == plain(value, msgtype)
    assert lidarscan.encode(back) == ours
    assert plain(lidarscan.decode(theirs, msgtype), msgtype) == plain(value, msgtype)
    assert plain(lidarscan.decode(theirs, msgtype, strict=True), msgtype) == plain(value, msgtype)


@pytest.mark.ros
@settings(max_examples=150)
@given(_MESSAGES)
def test_rclpy_equal_modulo_padding(case: tuple[str, Any]) -> None:
    msgtype, value = case
    _compare_with_rclpy(value, msgtype)


def _realistic_scan(as_dataclass: bool, **kwargs: Any) -> Any:
    info = lidarscan.make_info(stamp_ns=1_700_000_000_123_456_789, frame_id="os_sensor",
                               vertical_angles=np.linspace(0.3, -0.3, 3),
                               horizontal_angles=np.linspace(6.2, 0, 5), as_dataclass=True)
    rng = np.random.default_rng(7)
    chans = {"range": rng.random((3, 5), np.float32) * 50,
             "intensity": rng.integers(0, 2**16, (3, 5), dtype=np.uint16),
             "reflectivity": rng.integers(0, 256, (3, 5), dtype=np.uint8),
             "range2": np.full((3, 5), np.inf, np.float32),
             "xyz": rng.random((3, 5, 3)),
             "flags": rng.integers(-128, 128, (3, 5), dtype=np.int8)}
    return lidarscan.make_scan(info, chans, 1_700_000_000_223_456_789, as_dataclass=as_dataclass,
                               column_time_offsets=np.arange(5) * 97_000, **kwargs)


def _ouster_like_info(as_dataclass: bool) -> Any:
    h, w = 4, 6
    return lidarscan.make_info(
        stamp_ns=1_700_000_000_000_000_001, frame_id="os_sensor", vendor="Ouster",
        model="OS-1-128", serial_number="992313000123", firmware_version="v2.5.2",
        vertical_angles=np.radians([21.0, 7.3, -7.1, -21.5]),
        horizontal_angles=2 * np.pi * (1 - np.arange(w) / w),
        beam_azimuth_offsets=-np.radians([4.2, 1.4, -1.4, -4.2]),
        beam_origins=np.tile([0.015806, 0.0, 0.0], h), beam_range_offsets=np.full(h, -0.015806),
        lidar_to_sensor_transform=[-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 0.038195, 0, 0, 0, 1],
        pixel_shift_by_row=[12, 4, -4, -12], beam_time_offsets=np.zeros(h, np.int64),
        column_time_increment=48_828, beam_ids=np.arange(h, dtype=np.uint16),
        range_multiplier=0.001, range_min=0.5, range_max=120.0,
        vendor_metadata='{"prod_line": "OS-1-128", "ünïcode": "ok"}', as_dataclass=as_dataclass)


@pytest.mark.ros
@pytest.mark.parametrize("kind", ["scan", "scan_bigendian_channels", "info"])
def test_rclpy_realistic_messages(kind: str) -> None:
    if kind == "info":
        value, msgtype = _ouster_like_info(True), INFO
    else:
        value = _realistic_scan(True, is_bigendian=kind != "scan")
        msgtype = SCAN
    _compare_with_rclpy(value, msgtype)
    # make_* building rclpy messages directly gives the same bytes as the dataclasses
    if kind == "info":
        assert lidarscan.encode(_ouster_like_info(False)) == lidarscan.encode(value)
    else:
        rclpy_msg = _realistic_scan(False, is_bigendian=kind != "scan")
        assert lidarscan.encode(rclpy_msg) == lidarscan.encode(value)


@pytest.mark.ros
def test_rclpy_sensor_msgs_examples() -> None:
    """Hand-built sensor_msgs / nav_msgs instances (fixed arrays, nested types, NaN/Inf)."""
    pytest.importorskip("rclpy.serialization")
    from builtin_interfaces.msg import Time
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import Imu, LaserScan, PointCloud2, PointField
    from std_msgs.msg import Header

    header = Header(stamp=Time(sec=12, nanosec=345), frame_id="base_laser")
    fields = [PointField(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")]
    fields.append(PointField(name="intensity", offset=12, datatype=4, count=1))
    cloud = PointCloud2(header=header, height=1, width=3, fields=fields, is_bigendian=False,
                        point_step=16, row_step=48, data=bytes(range(48)), is_dense=True)
    scan = LaserScan(header=header, angle_min=-1.5, angle_max=1.5, angle_increment=0.75,
                     time_increment=1e-5, scan_time=0.1, range_min=0.1, range_max=30.0,
                     ranges=array.array("f", [1.0, math.inf, -math.inf, math.nan, 2.5]),
                     intensities=array.array("f"))
    imu = Imu(header=header)
    imu.orientation.w = 1.0
    imu.orientation_covariance = np.arange(9, dtype=np.float64)
    imu.angular_velocity_covariance[0] = -1.0
    imu.linear_acceleration.z = 9.81
    odom = Odometry(header=header, child_frame_id="base_link")
    odom.pose.pose.position.x = 1.25
    odom.pose.covariance = np.linspace(0, 1, 36)
    odom.twist.covariance[35] = 0.5
    odom.twist.twist.angular.z = -0.1
    for msg, msgtype in [(cloud, "sensor_msgs/msg/PointCloud2"),
                         (scan, "sensor_msgs/msg/LaserScan"),
                         (fields[3], "sensor_msgs/msg/PointField"),
                         (imu, "sensor_msgs/msg/Imu"), (odom, "nav_msgs/msg/Odometry")]:
        _compare_with_rclpy(msg, msgtype)
    decoded = lidarscan.decode(lidarscan.encode(scan), "sensor_msgs/msg/LaserScan")
    assert np.isnan(decoded.ranges[3]) and decoded.ranges[2] == -math.inf


@pytest.mark.ros
@pytest.mark.parametrize("msgtype", ["std_msgs/msg/Empty", "std_msgs/msg/Byte",
                                     "std_msgs/msg/Char", "std_msgs/msg/ByteMultiArray",
                                     "std_msgs/msg/String", "std_msgs/msg/Bool"])
def test_rclpy_std_msgs_corner_types(msgtype: str) -> None:
    """Empty structs (one hidden uint8), ``byte`` (rclpy uses bytes objects), ``char``."""
    serialization = pytest.importorskip("rclpy.serialization")
    pkg, _, name = msgtype.split("/")
    cls = getattr(importlib.import_module(f"{pkg}.msg"), name)
    msg = cls()
    if name == "Byte":
        msg.data = b"\xfe"
    elif name == "Char":
        msg.data = 200
    elif name == "ByteMultiArray":
        msg.data = [b"\x01", b"\x00", b"\xff"]
    elif name == "String":
        msg.data = "grüß"
    elif name == "Bool":
        msg.data = True
    ours = lidarscan.encode(msg)
    theirs = serialization.serialize_message(msg)
    size, padding = cdr_layout(msg, msgtype)
    assert len(ours) == size + 4
    keep = np.flatnonzero(~padding) + 4
    a, b = np.frombuffer(ours, np.uint8), np.frombuffer(theirs, np.uint8)
    assert np.array_equal(a[keep], b[keep])
    back = serialization.deserialize_message(ours, cls)
    assert back == msg
    assert plain(lidarscan.decode(theirs, msgtype), msgtype) == plain(msg, msgtype)
    store = rosbags_store()
    assert plain(store.deserialize_cdr(ours, msgtype), msgtype) == plain(msg, msgtype)


# --------------------------------------------------------------------------- encoder errors

@pytest.mark.parametrize(("field", "value", "needle"), [
    ("height", -1, "LidarScan.height"),
    ("width", 2**32, "LidarScan.width"),
    ("column_time_offsets", np.array([0.5, 1.5]), "column_time_offsets"),
    ("data", np.array([1, 256, 3]), "LidarScan.data"),
    ("data", ["a"], "LidarScan.data"),
])
def test_encode_rejects_out_of_range_values(field: str, value: Any, needle: str) -> None:
    import dataclasses
    scan = dataclasses.replace(_scan_value(), **{field: value})
    with pytest.raises(EncodeError) as err:
        lidarscan.encode(scan)
    assert needle in str(err.value)


def test_encode_rejects_wrong_fixed_array_length() -> None:
    import dataclasses
    info = dataclasses.replace(_info_value(), lidar_to_sensor_transform=np.eye(3).reshape(9))
    with pytest.raises(EncodeError, match=r"lidar_to_sensor_transform=9: expected exactly 16"):
        lidarscan.encode(info)


def test_encode_rejects_non_string_and_missing_field() -> None:
    import dataclasses
    with pytest.raises(EncodeError, match="frame_id"):
        lidarscan.encode(dataclasses.replace(_scan_value(), header=types.Header(frame_id=3)))
    with pytest.raises(EncodeError, match="LidarChannel.name"):
        lidarscan.encode(object(), CHANNEL)


def test_encode_rejects_float32_overflow_and_bad_text() -> None:
    import dataclasses
    info = _info_value()
    with pytest.raises(EncodeError, match=r"LidarInfo.range_min=1e\+300"):
        lidarscan.encode(dataclasses.replace(info, range_min=1e300))
    with pytest.raises(EncodeError, match="LidarInfo.vendor=.*UTF-8"):
        lidarscan.encode(dataclasses.replace(info, vendor="\ud800"))
    laser = message_class("sensor_msgs/msg/LaserScan")(
        header=types.Header(), angle_min=0.0, angle_max=0.0, angle_increment=0.0,
        time_increment=0.0, scan_time=0.0, range_min=0.0, range_max=0.0,
        ranges=np.array([1.0, np.inf, 1e300]), intensities=[])
    with pytest.raises(EncodeError, match=r"LaserScan.ranges=1e\+300"):
        lidarscan.encode(laser)
    ok = dataclasses.replace(laser, ranges=np.array([1.0, np.inf, -np.inf, np.nan, 3e38]))
    decoded = lidarscan.decode(lidarscan.encode(ok), "sensor_msgs/msg/LaserScan")
    assert decoded.ranges.dtype == np.float32 and decoded.ranges[4] == np.float32(3e38)


def test_encode_does_not_mutate_inputs() -> None:
    value = _realistic_scan(True)
    before = (value.data.tobytes(), value.column_time_offsets.tobytes())
    lidarscan.encode(value)
    assert (value.data.tobytes(), value.column_time_offsets.tobytes()) == before


# ------------------------------------------------------------------------- decoder robustness

def test_every_truncation_raises_decode_error() -> None:
    payload = lidarscan.encode(_realistic_scan(True))
    for cut in range(len(payload)):
        with pytest.raises(DecodeError):
            lidarscan.decode_scan(payload[:cut])
    lidarscan.decode_scan(payload)  # the whole message is fine


def test_every_truncation_of_info_raises_decode_error() -> None:
    payload = lidarscan.encode(_ouster_like_info(True))
    for cut in range(len(payload)):
        with pytest.raises(DecodeError):
            lidarscan.decode_info(payload[:cut])


def _only_project_errors(payload: bytes, msgtype: str) -> None:
    try:
        msg = lidarscan.decode(payload, msgtype)
        if msgtype == SCAN:
            for desc in msg.channels:
                lidarscan.channel(msg, desc.name)
            lidarscan.validate(msg)
        elif msgtype == INFO:
            lidarscan.validate_info(msg)
        lidarscan.encode(msg)
    except LidarScanError:
        pass


@given(st.data())
def test_bit_flips_raise_only_project_errors(data: st.DataObject) -> None:
    msgtype = data.draw(st.sampled_from([SCAN, INFO]))
    payload = bytearray(lidarscan.encode(
        _realistic_scan(True) if msgtype == SCAN else _ouster_like_info(True)))
    for _ in range(data.draw(st.integers(1, 4))):
        bit = data.draw(st.integers(0, 8 * len(payload) - 1))
        payload[bit // 8] ^= 1 << (bit % 8)
    _only_project_errors(bytes(payload), msgtype)


@given(st.binary(max_size=200), st.sampled_from(ROS_TYPES))
def test_random_bytes_raise_only_project_errors(tail: bytes, msgtype: str) -> None:
    _only_project_errors(b"\x00\x01\x00\x00" + tail, msgtype)


@pytest.mark.parametrize("msgtype", [SCAN, INFO])
def test_lying_lengths_fail_fast_without_allocating(msgtype: str) -> None:
    value = _realistic_scan(True) if msgtype == SCAN else _ouster_like_info(True)
    payload = lidarscan.encode(value)
    tracemalloc.start()
    try:
        for offset in range(4, len(payload) - 3, 4):  # every aligned word: lengths and counts
            for word in (b"\xff\xff\xff\xff", b"\x00\x00\x00\x80", b"\x01\x00\x00\x01"):
                bad = payload[:offset] + word + payload[offset + 4:]
                _only_project_errors(bad, msgtype)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 8 * 2**20  # never allocates what a lying length claims


def test_data_claiming_4_gib_raises() -> None:
    payload = bytearray(golden(SCAN_ROWS))
    payload[4 + 116:4 + 120] = struct.pack("<I", 0xFFFFFFFF)  # data count
    tracemalloc.start()
    try:
        with pytest.raises(DecodeError) as err:
            lidarscan.decode_scan(bytes(payload))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 2**20
    assert "LidarScan.data" in str(err.value) and "truncated" in str(err.value)


def test_channel_count_claiming_billions_raises() -> None:
    payload = bytearray(golden(SCAN_ROWS))
    payload[4 + 68:4 + 72] = struct.pack("<I", 1_000_000_000)  # channels count
    with pytest.raises(DecodeError, match=r"LidarScan.channels=1000000000"):
        lidarscan.decode_scan(bytes(payload))


def test_string_claiming_4_gib_raises() -> None:
    payload = bytearray(golden(SCAN_ROWS))
    payload[4 + 8:4 + 12] = b"\xff\xff\xff\xff"  # frame_id length
    with pytest.raises(DecodeError, match="Header.frame_id"):
        lidarscan.decode_scan(bytes(payload))


def test_bad_utf8_raises() -> None:
    payload = bytearray(golden(SCAN_ROWS))
    payload[4 + 12] = 0xC3  # 'l' -> first byte of a 2-byte sequence followed by 'i'
    with pytest.raises(DecodeError) as err:
        lidarscan.decode_scan(bytes(payload))
    assert "frame_id" in str(err.value) and "UTF-8" in str(err.value)


@pytest.mark.parametrize("header", [b"\x00\x02\x00\x00", b"\x00\x03\x00\x00", b"\x01\x01\x00\x00",
                                    b"\xff\xff\xff\xff"])
def test_bad_encapsulation_raises(header: bytes) -> None:
    payload = header + golden(SCAN_ROWS)[4:]
    with pytest.raises(DecodeError) as err:
        lidarscan.decode_scan(payload)
    assert "encapsulation" in str(err.value) and header.hex() in str(err.value)


@pytest.mark.parametrize("payload", [b"", b"\x00", b"\x00\x01\x00"])
def test_shorter_than_header_raises(payload: bytes) -> None:
    with pytest.raises(DecodeError, match="payload"):
        lidarscan.decode_scan(payload)


def test_strict_rejects_trailing_garbage() -> None:
    payload = golden(SCAN_ROWS)
    lidarscan.decode(payload + b"\x00" * 3, SCAN, strict=True)  # rounding to 4 is normal
    lidarscan.decode(payload + b"\xaa" * 64, SCAN)  # lenient by default
    with pytest.raises(DecodeError, match="payload length"):
        lidarscan.decode(payload + b"\xaa" * 64, SCAN, strict=True)


def test_decode_accepts_bytearray_memoryview_and_numpy() -> None:
    payload = golden(SCAN_ROWS)
    expected = plain(_scan_value(), SCAN)
    for buf in (bytearray(payload), memoryview(payload), np.frombuffer(payload, np.uint8),
                memoryview(payload)[0:]):
        assert plain(lidarscan.decode_scan(buf), SCAN) == expected


def test_decode_views_a_slice_without_copy() -> None:
    """Decoding from a memoryview slice of a larger buffer (e.g. an MCAP chunk) aliases it."""
    payload = golden(SCAN_ROWS)
    big = bytearray(b"\xee" * 13 + payload + b"\xee" * 5)
    scan = lidarscan.decode_scan(memoryview(big)[13:13 + len(payload)])
    assert np.shares_memory(scan.data, np.frombuffer(big, np.uint8))
    assert lidarscan.channel(scan, "i").tolist() == [[7, 255]]
    with pytest.raises(ValueError):
        lidarscan.channel(scan, "i")[0, 0] = 1
