"""lidarscan.scan: make_scan / channel / range_m round trips and every validate() inconsistency.

Round trips run over every PointField datatype, count 1..3, both byte orders, mixed integer and
float channels and dual returns (Hypothesis), on the rclpy message and on the dataclass, before
and after encode -> decode. Floats are compared bitwise (NaN payloads included). Each validation
test asserts the specific exception class and that the message names the field and the value.
"""

from __future__ import annotations

import array
import dataclasses
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import lidarscan
from lidarscan import types
from lidarscan.datatypes import dtype_of
from lidarscan.errors import (
    ChannelLayoutError,
    InfoMismatchError,
    LidarScanError,
    LinkageError,
    UnknownChannelError,
    UnknownDatatypeError,
    ValidationError,
)
from lidarscan.scan import data_view

NAMES = ["range", "range2", "intensity", "intensity2", "reflectivity", "ambient", "flags",
         "signal"]


def _bits(arr: np.ndarray) -> np.ndarray:
    """Native unsigned integers holding the raw bits of ``arr``'s elements (NaN-safe compare)."""
    order = arr.dtype.byteorder if arr.dtype.byteorder in "<>" else "="
    return np.ascontiguousarray(arr).view(np.dtype(f"u{arr.dtype.itemsize}").newbyteorder(order)
                                          ).astype(f"=u{arr.dtype.itemsize}")


def _info(height: int, width: int, **fields: Any) -> Any:
    return lidarscan.make_info(stamp_ns=1_000_000_007, frame_id="lidar",
                               vertical_angles=np.linspace(0.2, -0.2, height),
                               horizontal_angles=np.linspace(6.0, 0.0, width),
                               as_dataclass=True, **fields)


@st.composite
def scan_inputs(draw: st.DrawFn) -> tuple[int, int, dict[str, np.ndarray], bool]:
    height, width = draw(st.integers(1, 4)), draw(st.integers(1, 5))
    names = draw(st.lists(st.sampled_from(NAMES), min_size=1, max_size=5, unique=True))
    channels: dict[str, np.ndarray] = {}
    for name in names:
        datatype = draw(st.integers(1, 8))
        count = draw(st.integers(1, 3))
        dtype = dtype_of(datatype, draw(st.booleans()))  # input byte order is arbitrary too
        raw = draw(st.binary(min_size=height * width * count * dtype.itemsize,
                             max_size=height * width * count * dtype.itemsize))
        arr = np.frombuffer(raw, dtype).copy()
        shape = (height, width) if count == 1 and draw(st.booleans()) else (height, width, count)
        channels[name] = arr.reshape(shape)
    return height, width, channels, draw(st.booleans())


def _check_channels(scan: Any, channels: dict[str, np.ndarray], big: bool, base: Any) -> None:
    assert lidarscan.channel_names(scan) == list(channels)
    whole = np.frombuffer(base, np.uint8) if not isinstance(base, np.ndarray) else base
    for name, expected in channels.items():
        got = lidarscan.channel(scan, name)
        count = 1 if expected.ndim == 2 else expected.shape[2]
        assert got.shape == (expected.shape[:2] if count == 1 else expected.shape)
        assert got.dtype == expected.dtype.newbyteorder(">" if big else "<")
        assert np.array_equal(_bits(got), _bits(expected.reshape(got.shape)))
        assert np.shares_memory(got, whole)  # zero-copy
        assert not got.flags.writeable
        with pytest.raises(ValueError):
            got.reshape(-1)[0] = 0


@settings(max_examples=120)
@given(scan_inputs(), st.booleans())
def test_round_trip_dataclass(inputs: Any, destaggered: bool) -> None:
    height, width, channels, big = inputs
    before = {n: a.tobytes() for n, a in channels.items()}
    info = _info(height, width, range_multiplier=0.001)
    scan = lidarscan.make_scan(info, channels, 2_000_000_000, is_bigendian=big,
                               is_destaggered=destaggered, as_dataclass=True)
    assert {n: a.tobytes() for n, a in channels.items()} == before  # inputs untouched
    lidarscan.validate(scan, info)
    assert scan.is_bigendian is big and scan.is_destaggered is destaggered
    _check_channels(scan, channels, big, scan.data)
    for desc in scan.channels:
        assert desc.offset % 8 == 0
    payload = lidarscan.encode(scan)
    decoded = lidarscan.decode_scan(payload)
    lidarscan.validate(decoded, info)
    _check_channels(decoded, channels, big, payload)
    assert decoded == dataclasses.replace(decoded)  # frozen dataclass
    assert decoded.channels == scan.channels


@pytest.mark.ros
@given(scan_inputs())
def test_round_trip_rclpy_message(inputs: Any) -> None:
    pytest.importorskip("lidarscan_msgs.msg")
    height, width, channels, big = inputs
    info = _info(height, width, range_multiplier=0.001)
    scan = lidarscan.make_scan(info, channels, 2_000_000_000, is_bigendian=big)
    assert type(scan).__module__.startswith("lidarscan_msgs.msg")
    lidarscan.validate(scan, info)
    _check_channels(scan, channels, big, np.frombuffer(scan.data, np.uint8))
    payload = lidarscan.encode(scan)
    assert payload == lidarscan.encode(lidarscan.make_scan(
        info, channels, 2_000_000_000, is_bigendian=big, as_dataclass=True))
    _check_channels(lidarscan.decode_scan(payload), channels, big, payload)


def test_round_trip_every_datatype_and_order_explicitly(rng: np.random.Generator) -> None:
    """Deterministic complement of the Hypothesis test: all 8 datatypes x counts x orders."""
    info = _info(3, 4)
    for big in (False, True):
        channels = {}
        for datatype in range(1, 9):
            for count in (1, 2, 3):
                dtype = dtype_of(datatype)
                raw = rng.integers(0, 256, 3 * 4 * count * dtype.itemsize, dtype=np.uint8)
                arr = raw.view(dtype).reshape((3, 4) if count == 1 else (3, 4, count))
                channels[f"c{datatype}_{count}"] = arr
        scan = lidarscan.make_scan(info, channels, 5, is_bigendian=big, as_dataclass=True)
        payload = lidarscan.encode(scan)
        _check_channels(lidarscan.decode_scan(payload), channels, big, payload)


def test_nan_payloads_survive_bitwise() -> None:
    info = _info(1, 4)
    f32 = np.array([0x7FC00001, 0xFFC12345, 0x7F800001, 0x00000001], np.uint32).view(np.float32)
    f64 = np.array([0x7FF8000000000001, 0xFFF0000000000002, 0, 2**63], np.uint64).view(np.float64)
    channels = {"range": f32.reshape(1, 4), "x": f64.reshape(1, 4)}
    for big in (False, True):
        payload = lidarscan.encode(lidarscan.make_scan(info, channels, 1, is_bigendian=big,
                                                       as_dataclass=True))
        _check_channels(lidarscan.decode_scan(payload), channels, big, payload)


def test_dual_returns_as_channels_and_as_count(rng: np.random.Generator) -> None:
    info = _info(2, 3)
    first = rng.random((2, 3), np.float32)
    second = rng.random((2, 3), np.float32)
    scan = lidarscan.make_scan(info, {"range": first, "range2": second,
                                      "intensity": np.stack([first, second], -1).astype(np.uint16)},
                               10, as_dataclass=True)
    np.testing.assert_array_equal(lidarscan.range_m(scan), first)
    np.testing.assert_array_equal(lidarscan.range_m(scan, name="range2"), second)
    assert lidarscan.channel(scan, "intensity").shape == (2, 3, 2)


def test_big_endian_cdr_of_big_endian_channels(rng: np.random.Generator) -> None:
    """A big-endian CDR payload (encapsulation 00 00, made by rosbags) of big-endian blocks."""
    typesys = pytest.importorskip("rosbags.typesys")
    from lidarscan.msgdef import find_msg_text
    store = typesys.get_typestore(typesys.Stores.LATEST)
    for name in ("LidarChannel", "LidarScan"):
        store.register(typesys.get_types_from_msg(find_msg_text(f"lidarscan_msgs/msg/{name}"),
                                                  f"lidarscan_msgs/msg/{name}"))
    T = store.types
    channels = {"range": rng.random((2, 3), np.float32), "ambient": rng.integers(
        0, 2**16, (2, 3, 2)).astype(np.uint16), "x": rng.random((2, 3))}
    scan = lidarscan.make_scan(_info(2, 3), channels, 1, is_bigendian=True,
                               column_time_offsets=[0, 10, 20], as_dataclass=True)
    msg = T["lidarscan_msgs/msg/LidarScan"](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=0, nanosec=1),
                                        frame_id="lidar"),
        lidar_info_time=T["builtin_interfaces/msg/Time"](sec=1, nanosec=7), height=2, width=3,
        is_bigendian=True, is_destaggered=False,
        column_time_offsets=np.array([0, 10, 20], np.int64), column_azimuth_angles=np.zeros(0),
        channels=[T["lidarscan_msgs/msg/LidarChannel"](name=c.name, offset=c.offset,
                                                       datatype=c.datatype, count=c.count)
                  for c in scan.channels],
        data=np.array(scan.data))
    payload = bytes(store.serialize_cdr(msg, "lidarscan_msgs/msg/LidarScan",
                                        little_endian=False))
    assert payload[:2] == b"\x00\x00"
    decoded = lidarscan.decode_scan(payload)
    assert decoded.column_time_offsets.tolist() == [0, 10, 20]
    lidarscan.validate(decoded, _info(2, 3))
    _check_channels(decoded, channels, True, payload)  # uint8[] data still viewed, not copied
    assert lidarscan.encode(decoded) == lidarscan.encode(scan)


# ----------------------------------------------------------------------------- range_m

def test_integer_range_round_trips_losslessly_and_decodes() -> None:
    info = _info(2, 4, range_multiplier=0.001, range_offset=0.0)
    raw = np.array([[0, 1, 1234, 2**32 - 1], [500, 0, 65_535, 120_000]], np.uint32)
    for big in (False, True):
        scan = lidarscan.make_scan(info, {"range": raw}, 3, is_bigendian=big, as_dataclass=True)
        lidarscan.validate(scan, info)
        decoded = lidarscan.decode_scan(lidarscan.encode(scan))
        np.testing.assert_array_equal(lidarscan.channel(decoded, "range"), raw)
        metres = lidarscan.range_m(decoded, info)
        assert metres.dtype == np.float32 and metres.shape == (2, 4)
        expected = (raw.astype(np.float64) * 0.001).astype(np.float32)
        expected[raw == 0] = np.inf
        np.testing.assert_array_equal(metres, expected)
        assert metres[0, 0] == np.inf and metres[0, 2] == np.float32(1.234)


def test_integer_range_offset_and_uint16() -> None:
    info = _info(1, 3, range_multiplier=0.002, range_offset=-0.5)
    scan = lidarscan.make_scan(info, {"range": np.array([[0, 1000, 7]], np.uint16)}, 3,
                               as_dataclass=True)
    np.testing.assert_array_equal(lidarscan.range_m(scan, info),
                                  np.array([[np.inf, 1.5, 0.014 - 0.5]], np.float32))


def test_integer_range_without_multiplier_raises() -> None:
    scan = lidarscan.make_scan(_info(1, 2), {"range": np.ones((1, 2), np.uint32)}, 3,
                               as_dataclass=True)
    with pytest.raises(InfoMismatchError) as err:
        lidarscan.range_m(scan)
    assert "range_multiplier=0.0" in str(err.value)
    with pytest.raises(InfoMismatchError, match="range_multiplier=0.0"):
        lidarscan.range_m(scan, _info(1, 2))


def test_float_range_is_a_view_and_float64_converts() -> None:
    info = _info(1, 2)
    r32 = np.array([[1.0, np.inf]], np.float32)
    scan = lidarscan.make_scan(info, {"range": r32, "range2": r32.astype(np.float64)}, 1,
                               as_dataclass=True)
    view = lidarscan.range_m(scan)
    assert np.shares_memory(view, scan.data) and view.dtype == np.float32
    converted = lidarscan.range_m(scan, name="range2")
    assert converted.dtype == np.float32
    np.testing.assert_array_equal(converted, r32)
    big = lidarscan.make_scan(info, {"range": r32}, 1, is_bigendian=True, as_dataclass=True)
    assert lidarscan.range_m(big).dtype == np.dtype("=f4")
    np.testing.assert_array_equal(lidarscan.range_m(big), r32)


# -------------------------------------------------------------------------- make_scan inputs

def test_make_scan_fills_header_and_linkage(small_info: Any) -> None:
    scan = lidarscan.make_scan(small_info, {"range": np.zeros((4, 8), np.float32)},
                               1_700_000_000_999_999_999, column_time_offsets=np.arange(8) * 10,
                               column_azimuth_angles=np.linspace(0, 1, 8), as_dataclass=True)
    assert scan.header.stamp == types.Time(1_700_000_000, 999_999_999)
    assert scan.header.frame_id == "lidar"
    assert scan.lidar_info_time == small_info.header.stamp
    assert scan.column_time_offsets.dtype == np.int64
    assert scan.column_time_offsets.tolist() == list(range(0, 80, 10))
    assert not scan.column_azimuth_angles.flags.writeable
    lidarscan.validate(scan, small_info)
    other = lidarscan.make_scan(small_info, {}, 5, frame_id="other", as_dataclass=True)
    assert other.header.frame_id == "other" and other.data.size == 0
    lidarscan.validate(other, small_info)


def test_make_scan_accepts_non_contiguous_and_foreign_byte_order(small_info: Any) -> None:
    base = np.arange(8 * 4, dtype=">i4").reshape(8, 4)
    scan = lidarscan.make_scan(small_info, {"t": base.T, "s": base.T[:, ::-1].astype(np.int16)},
                               5, as_dataclass=True)
    np.testing.assert_array_equal(lidarscan.channel(scan, "t"), base.T)
    np.testing.assert_array_equal(lidarscan.channel(scan, "s"), base.T[:, ::-1])


@pytest.mark.parametrize(("channels", "error", "needle"), [
    ({"range": np.zeros((4, 7), np.float32)}, ValidationError, "channels['range'].shape=(4, 7)"),
    ({"range": np.zeros(32, np.float32)}, ValidationError, "channels['range'].shape=(32,)"),
    ({"range": np.zeros((4, 8, 0), np.float32)}, ValidationError, "(4, 8, 0)"),
    ({"range": np.zeros((4, 8), np.int64)}, UnknownDatatypeError, "'int64'"),
    ({"flags": np.zeros((4, 8), bool)}, UnknownDatatypeError, "'bool'"),
    ({"range": np.zeros((4, 8), np.float16)}, UnknownDatatypeError, "'float16'"),
    ({"": np.zeros((4, 8), np.float32)}, ValidationError, "channels=''"),
])
def test_make_scan_rejects_bad_channels(small_info: Any, channels: Any, error: type,
                                        needle: str) -> None:
    with pytest.raises(error) as err:
        lidarscan.make_scan(small_info, channels, 1, as_dataclass=True)
    assert needle in str(err.value)


@pytest.mark.parametrize(("kwargs", "needle"), [
    ({"column_time_offsets": np.arange(7)}, "column_time_offsets.shape=(7,)"),
    ({"column_time_offsets": np.linspace(0, 1, 8)}, "column_time_offsets.dtype='float64'"),
    ({"column_azimuth_angles": np.full(8, np.nan)}, "column_azimuth_angles=[nan, nan, nan]"),
    ({"column_azimuth_angles": np.zeros((2, 4))}, "column_azimuth_angles.shape=(2, 4)"),
])
def test_make_scan_rejects_bad_column_arrays(small_info: Any, kwargs: Any, needle: str) -> None:
    with pytest.raises(ValidationError) as err:
        lidarscan.make_scan(small_info, {}, 1, as_dataclass=True, **kwargs)
    assert needle in str(err.value)


def test_make_scan_rejects_stamp_outside_int32_seconds(small_info: Any) -> None:
    with pytest.raises(ValidationError, match="stamp_ns=4294967296000000000"):
        lidarscan.make_scan(small_info, {}, 2**32 * 10**9, as_dataclass=True)


def test_channel_unknown_name(small_info: Any) -> None:
    scan = lidarscan.make_scan(small_info, {"range": np.zeros((4, 8), np.float32)}, 1,
                               as_dataclass=True)
    with pytest.raises(UnknownChannelError) as err:
        lidarscan.channel(scan, "rnage")
    assert "name='rnage'" in str(err.value) and "['range']" in str(err.value)
    assert isinstance(err.value, KeyError)


def test_channel_at_unaligned_offset_reads_correctly() -> None:
    """Blocks need not be aligned (the .msg does not require it); numpy handles it."""
    values = np.array([[1, 65535, 258]], "<u2")
    data = np.frombuffer(b"\x00" + values.tobytes(), np.uint8)
    scan = types.LidarScan(height=1, width=3, channels=(types.LidarChannel("a", 1, 4, 1),),
                           data=data)
    lidarscan.validate(scan)
    np.testing.assert_array_equal(lidarscan.channel(scan, "a"), values)


def test_data_view_of_rclpy_buffer_is_read_only_alias() -> None:
    pytest.importorskip("lidarscan_msgs.msg")
    info = _info(1, 2)
    scan = lidarscan.make_scan(info, {"range": np.ones((1, 2), np.float32)}, 1)
    view = lidarscan.channel(scan, "range")
    with pytest.raises(ValueError):
        view[0, 0] = 5.0
    scan.data[0:4] = array.array("B", np.float32(3.0).tobytes())  # the owner may still write
    assert view[0, 0] == 3.0  # ... and the view sees it: no copy was made
    assert isinstance(data_view(scan), np.ndarray)


# ----------------------------------------------------------------------------- validate()

def _scan(info: Any, **channels: Any) -> Any:
    if not channels:
        channels = {"range": np.ones((info.height, info.width), np.float32),
                    "intensity": np.ones((info.height, info.width), np.uint16)}
    return lidarscan.make_scan(info, channels, 2_000_000_000, as_dataclass=True)


def _replace_channel(scan: Any, index: int, **changes: Any) -> Any:
    chans = list(scan.channels)
    chans[index] = dataclasses.replace(chans[index], **changes)
    return dataclasses.replace(scan, channels=tuple(chans))


def _raises(error: type, call: Any, *needles: str) -> LidarScanError:
    with pytest.raises(error) as err:
        call()
    for needle in needles:
        assert needle in str(err.value), (needle, str(err.value))
    assert isinstance(err.value, LidarScanError) and err.value.expected
    return err.value


def test_valid_scan_passes(small_info: Any) -> None:
    lidarscan.validate(_scan(small_info), small_info)
    lidarscan.validate(_scan(small_info))


def test_data_too_long(small_info: Any) -> None:
    scan = _scan(small_info)  # range 128 bytes + intensity 64 bytes = 192
    ok = dataclasses.replace(scan, data=np.zeros(192 + 7, np.uint8))  # alignment padding
    lidarscan.validate(ok)
    bad = dataclasses.replace(scan, data=np.zeros(200, np.uint8))
    err = _raises(ChannelLayoutError, lambda: lidarscan.validate(bad), "data=", "length 200",
                  "192")
    assert err.field == "data"


def test_data_without_channels(small_info: Any) -> None:
    bad = dataclasses.replace(_scan(small_info), channels=(), data=np.zeros(3, np.uint8))
    _raises(ChannelLayoutError, lambda: lidarscan.validate(bad), "data=", "length 3")


def test_data_too_short_is_out_of_bounds(small_info: Any) -> None:
    bad = dataclasses.replace(_scan(small_info), data=np.zeros(191, np.uint8))
    _raises(ChannelLayoutError, lambda: lidarscan.validate(bad),
            "channels[1].offset ('intensity')=128", "[128, 192)", "191 bytes")


def test_block_out_of_bounds(small_info: Any) -> None:
    bad = _replace_channel(_scan(small_info), 1, offset=4096)
    _raises(ChannelLayoutError, lambda: lidarscan.validate(bad),
            "channels[1].offset ('intensity')=4096", "inside data of 192 bytes")
    with pytest.raises(ChannelLayoutError, match="channels\\['intensity'\\].offset=4096"):
        lidarscan.channel(bad, "intensity")


def test_negative_offset(small_info: Any) -> None:
    """Only a dataclass can hold one (uint32 on the wire), but it must not reach numpy."""
    bad = _replace_channel(_scan(small_info), 0, offset=-8)
    _raises(ChannelLayoutError, lambda: lidarscan.validate(bad), "channels[0].offset ('range')=-8")
    _raises(ChannelLayoutError, lambda: lidarscan.channel(bad, "range"),
            "channels['range'].offset=-8")


def test_grid_too_big_for_numpy_even_when_empty() -> None:
    """4294967295 x 0 x 4294967295 has no element but numpy cannot shape it (reachable from
    a few bytes of CDR): validate rejects it and channel() raises the project's error."""
    scan = types.LidarScan(height=2**32 - 1, width=0, data=np.zeros(0, np.uint8),
                           channels=(types.LidarChannel("range", 0, 7, 2**32 - 1),))
    scan = lidarscan.decode_scan(lidarscan.encode(scan))
    _raises(ChannelLayoutError, lambda: lidarscan.validate(scan),
            "channels[0].count ('range')=4294967295", "63 bits")
    _raises(ChannelLayoutError, lambda: lidarscan.channel(scan, "range"),
            "(4294967295, 0, 4294967295)")
    fine = dataclasses.replace(scan, channels=(types.LidarChannel("range", 0, 7, 1),))
    lidarscan.validate(fine)
    assert lidarscan.channel(fine, "range").shape == (2**32 - 1, 0)


def test_overlapping_blocks(small_info: Any) -> None:
    bad = _replace_channel(_scan(small_info), 1, offset=120)
    _raises(ChannelLayoutError, lambda: lidarscan.validate(bad),
            "channels['intensity'].offset=120", ">= 128", "'range'", "overlap")


@pytest.mark.parametrize("datatype", [0, 9, 255])
def test_unknown_datatype(small_info: Any, datatype: int) -> None:
    bad = _replace_channel(_scan(small_info), 0, datatype=datatype)
    err = _raises(UnknownDatatypeError, lambda: lidarscan.validate(bad),
                  "channels[0].datatype ('range')", f"={datatype}", "1..8")
    assert err.value == datatype
    _raises(UnknownDatatypeError, lambda: lidarscan.channel(bad, "range"), f"={datatype}")


def test_count_zero(small_info: Any) -> None:
    bad = _replace_channel(_scan(small_info), 1, count=0)
    _raises(ChannelLayoutError, lambda: lidarscan.validate(bad),
            "channels[1].count ('intensity')=0", ">= 1")
    _raises(ChannelLayoutError, lambda: lidarscan.channel(bad, "intensity"), "count", "=0")


def test_duplicate_names(small_info: Any) -> None:
    bad = _replace_channel(_scan(small_info), 1, name="range")
    _raises(ChannelLayoutError, lambda: lidarscan.validate(bad), "channels[1].name='range'",
            "unique")


def test_empty_name(small_info: Any) -> None:
    bad = _replace_channel(_scan(small_info), 0, name="")
    _raises(ChannelLayoutError, lambda: lidarscan.validate(bad), "channels[0].name=''",
            "non-empty")


@pytest.mark.parametrize(("field", "length"), [("column_time_offsets", 7),
                                               ("column_azimuth_angles", 9)])
def test_scan_column_array_length(small_info: Any, field: str, length: int) -> None:
    bad = dataclasses.replace(_scan(small_info), **{field: np.zeros(length)})
    _raises(ValidationError, lambda: lidarscan.validate(bad), f"LidarScan.{field}",
            f"length {length}", "length 8")


def test_scan_column_azimuth_not_finite(small_info: Any) -> None:
    angles = np.zeros(8)
    angles[3] = np.inf
    bad = dataclasses.replace(_scan(small_info), column_azimuth_angles=angles)
    _raises(ValidationError, lambda: lidarscan.validate(bad),
            "LidarScan.column_azimuth_angles=[inf]", "finite")


def test_scan_stamp_nanosec_out_of_range(small_info: Any) -> None:
    bad = dataclasses.replace(_scan(small_info),
                              header=types.Header(types.Time(1, 1_000_000_000), "x"))
    _raises(ValidationError, lambda: lidarscan.validate(bad),
            "LidarScan.header.stamp.nanosec=1000000000")


def test_info_scan_size_mismatch(small_info: Any) -> None:
    other = _info(4, 9)
    other = dataclasses.replace(other, header=small_info.header)
    _raises(InfoMismatchError, lambda: lidarscan.validate(_scan(small_info), other),
            "height x width", "'4x8'", "4x9")


def test_linkage_mismatch(small_info: Any) -> None:
    later = dataclasses.replace(small_info, header=types.Header(types.Time(2, 0), "lidar"))
    err = _raises(LinkageError, lambda: lidarscan.validate(_scan(small_info), later),
                  "LidarScan.lidar_info_time=1500000000", "2000000000")
    assert err.value == 1_500_000_000


def test_integer_range_needs_multiplier(small_info: Any) -> None:
    scan = _scan(small_info, range=np.ones((4, 8), np.uint32))
    lidarscan.validate(scan)  # no info: nothing to check against
    _raises(InfoMismatchError, lambda: lidarscan.validate(scan, small_info),
            "LidarInfo.range_multiplier=0.0", "'range'")
    scan2 = _scan(small_info, range=np.ones((4, 8), np.float32), range2=np.ones((4, 8), np.uint16))
    _raises(InfoMismatchError, lambda: lidarscan.validate(scan2, small_info),
            "range_multiplier", "'range2'")
    good = dataclasses.replace(small_info, range_multiplier=0.001)
    lidarscan.validate(scan, good)


# ------------------------------------------------------------------------- validate_info()

INFO_ARRAYS = [("vertical_angles", 3, False), ("horizontal_angles", 7, False),
               ("beam_azimuth_offsets", 3, True), ("pixel_azimuth_angles", 31, True),
               ("beam_origins", 4 * 3 - 1, True), ("beam_range_offsets", 5, True),
               ("lidar_to_sensor_transform", 9, False), ("pixel_shift_by_row", 8, True),
               ("beam_time_offsets", 1, True), ("beam_ids", 3, True)]


@pytest.mark.parametrize(("field", "length", "may_be_empty"), INFO_ARRAYS)
def test_info_array_lengths(small_info: Any, field: str, length: int, may_be_empty: bool) -> None:
    default = getattr(small_info, field)
    bad = dataclasses.replace(small_info, **{field: np.zeros(length, default.dtype)})
    err = _raises(InfoMismatchError, lambda: lidarscan.validate_info(bad),
                  f"LidarInfo.{field}=", f"length {length}")
    assert ("or 0 (empty)" in err.expected) == may_be_empty
    with pytest.raises(InfoMismatchError):  # also through validate(scan, info)
        lidarscan.validate(_scan(small_info), bad)
    if may_be_empty:
        lidarscan.validate_info(dataclasses.replace(small_info,
                                                    **{field: np.zeros(0, default.dtype)}))


def test_info_pixel_angles_must_pair(small_info: Any) -> None:
    bad = dataclasses.replace(small_info, pixel_azimuth_angles=np.zeros(32))
    _raises(InfoMismatchError, lambda: lidarscan.validate_info(bad),
            "LidarInfo.pixel_altitude_angles='length 0'", "32")
    lidarscan.validate_info(dataclasses.replace(bad, pixel_altitude_angles=np.zeros(32)))


@pytest.mark.parametrize(("field", "index", "value"), [
    ("vertical_angles", 2, np.nan), ("horizontal_angles", 5, np.inf),
    ("beam_azimuth_offsets", 0, -np.inf), ("beam_origins", 11, np.nan),
    ("beam_range_offsets", 3, np.nan), ("pixel_altitude_angles", 31, np.nan)])
def test_info_non_finite(small_info: Any, field: str, index: int, value: float) -> None:
    size = {"beam_origins": 12, "pixel_altitude_angles": 32}.get(field, None)
    arr = np.array(getattr(small_info, field), float) if size is None else np.zeros(size)
    if arr.size == 0:
        arr = np.zeros(4)
    arr[index] = value
    changes = {field: arr}
    if field == "pixel_altitude_angles":
        changes["pixel_azimuth_angles"] = np.zeros(32)
    bad = dataclasses.replace(small_info, **changes)
    _raises(InfoMismatchError, lambda: lidarscan.validate_info(bad),
            f"LidarInfo.{field}[{index}]={value!r}", "finite")


@pytest.mark.parametrize(("changes", "needle"), [
    # a non-finite value before a length error: the earlier field's error comes first
    ({"vertical_angles": np.array([0.1, np.nan, 0.0, -0.1]), "beam_ids": np.zeros(3, np.uint16)},
     "LidarInfo.vertical_angles[1]=nan"),
    ({"beam_origins": np.full(12, np.inf), "beam_time_offsets": np.zeros(2, np.int64)},
     "LidarInfo.beam_origins[0]=inf"),
    # ... and a length error before a later non-finite value
    ({"horizontal_angles": np.zeros(7), "beam_origins": np.full(12, np.nan)},
     "LidarInfo.horizontal_angles='length 7'"),
    ({"pixel_azimuth_angles": np.zeros(32), "beam_range_offsets": np.full(4, np.nan)},
     "LidarInfo.pixel_altitude_angles='length 0'"),
    # every array fine, a transform both non-finite and not rigid: the finiteness error
    ({"lidar_to_sensor_transform": np.full(16, np.nan)},
     "LidarInfo.lidar_to_sensor_transform[0]=nan"),
])
def test_info_errors_come_in_field_order(small_info: Any, changes: Any, needle: str) -> None:
    bad = dataclasses.replace(small_info, **changes)
    _raises(InfoMismatchError, lambda: lidarscan.validate_info(bad), needle)


def test_info_arrays_of_other_shapes_are_read_flat(small_info: Any) -> None:
    """A dataclass built by hand may hold a 4x4 transform or a (H, 3) origins array."""
    rot = np.eye(4)
    rot[:2, :2] = [[0.0, -1.0], [1.0, 0.0]]
    good = dataclasses.replace(small_info, lidar_to_sensor_transform=rot,
                               beam_origins=np.zeros((4, 3)))
    lidarscan.validate_info(good)
    origins = np.zeros((4, 3))
    origins[2, 1] = np.nan
    _raises(InfoMismatchError,
            lambda: lidarscan.validate_info(dataclasses.replace(good, beam_origins=origins)),
            "LidarInfo.beam_origins[7]=nan")
    _raises(InfoMismatchError, lambda: lidarscan.validate_info(
        dataclasses.replace(good, lidar_to_sensor_transform=2 * rot)), "rigid")


@pytest.mark.parametrize("matrix", [
    np.diag([1.0, 1.0, -1.0, 1.0]),                      # reflection
    np.diag([2.0, 1.0, 1.0, 1.0]),                       # scale
    np.vstack([np.eye(4)[:3], [0.0, 0.0, 1.0, 1.0]]),   # bad last row
])
def test_info_bad_transform(small_info: Any, matrix: np.ndarray) -> None:
    bad = dataclasses.replace(small_info, lidar_to_sensor_transform=matrix.reshape(16))
    _raises(InfoMismatchError, lambda: lidarscan.validate_info(bad),
            "LidarInfo.lidar_to_sensor_transform=", "rigid")


def test_info_transform_zero_means_identity(small_info: Any) -> None:
    lidarscan.validate_info(dataclasses.replace(small_info, lidar_to_sensor_transform=np.zeros(16)))
    rot = np.eye(4)
    rot[:2, :2] = [[0.0, -1.0], [1.0, 0.0]]
    rot[:3, 3] = [0.1, -0.2, 0.3]
    lidarscan.validate_info(dataclasses.replace(small_info,
                                                lidar_to_sensor_transform=rot.reshape(16)))


@pytest.mark.parametrize(("changes", "needle"), [
    ({"range_multiplier": -0.001}, "LidarInfo.range_multiplier=-0.001"),
    ({"range_multiplier": np.nan}, "LidarInfo.range_multiplier=nan"),
    ({"range_offset": np.inf}, "LidarInfo.range_offset=inf"),
    ({"range_min": 5.0, "range_max": 1.0}, "LidarInfo.range_min=5.0"),
    ({"range_min": -1.0}, "LidarInfo.range_min=-1.0"),
    ({"column_time_increment": -5}, "LidarInfo.column_time_increment=-5"),
    ({"header": types.Header(types.Time(0, 2_000_000_000), "x")},
     "LidarInfo.header.stamp.nanosec=2000000000"),
])
def test_info_bad_scalars(small_info: Any, changes: Any, needle: str) -> None:
    bad = dataclasses.replace(small_info, **changes)
    with pytest.raises(ValidationError) as err:
        lidarscan.validate_info(bad)
    assert needle in str(err.value)


def test_make_info_rejects_unknown_field() -> None:
    with pytest.raises(ValidationError, match="make_info=\\['vertical_angle'\\]"):
        lidarscan.make_info(stamp_ns=1, frame_id="x", vertical_angles=[0.0],
                            horizontal_angles=[0.0], vertical_angle=[1.0], as_dataclass=True)


@pytest.mark.ros
def test_validate_works_on_rclpy_messages() -> None:
    pytest.importorskip("lidarscan_msgs.msg")
    info = lidarscan.make_info(stamp_ns=7, frame_id="x", vertical_angles=[0.1, -0.1],
                               horizontal_angles=[0.0, 1.0, 2.0])
    scan = lidarscan.make_scan(info, {"range": np.ones((2, 3), np.float32)}, 9)
    lidarscan.validate(scan, info)
    scan.channels[0].datatype = 11
    with pytest.raises(UnknownDatatypeError, match="=11"):
        lidarscan.validate(scan, info)
    scan.channels[0].datatype = 7
    info.vertical_angles = [0.1, float("nan")]
    with pytest.raises(InfoMismatchError, match=r"LidarInfo.vertical_angles\[1\]=nan"):
        lidarscan.validate(scan, info)
