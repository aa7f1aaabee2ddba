"""converters.images: one sensor_msgs/Image per channel and back, bit for bit.

Round trips on hypothesis scans (shapes, every datatype, counts, both byte orders, NaN/+-Inf/-0,
staggered and destaggered, images in either column order), the encodings against REP 118 /
image_encodings by hand, the destaggered image against a loop over ``pixel_shift_by_row``, the
real Ouster frames, and the errors.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import lidarscan as ls
from converters import images
from lidarscan.errors import ConversionError, UnknownChannelError

_DTYPES = ["i1", "u1", "i2", "u2", "i4", "u4", "f4", "f8"]


def _info(height: int, width: int, shifts: list[int]) -> Any:
    return ls.make_info(stamp_ns=2_000_000_000, frame_id="lidar",
                        vertical_angles=np.linspace(0.3, -0.3, height),
                        horizontal_angles=2 * np.pi * (1 - np.arange(width) / width),
                        pixel_shift_by_row=shifts, as_dataclass=True)


@st.composite
def _case(draw: Any) -> tuple[Any, Any]:
    height, width = draw(st.integers(1, 5)), draw(st.integers(1, 8))
    shifts = draw(st.lists(st.integers(-9, 9), min_size=height, max_size=height))
    info = _info(height, width, shifts)
    big = draw(st.booleans())
    chans = {}
    for i in range(draw(st.integers(1, 4))):
        dtype = np.dtype(draw(st.sampled_from(_DTYPES)))
        count = draw(st.integers(1, 3))
        shape = (height, width) if count == 1 else (height, width, count)
        raw = draw(st.binary(min_size=int(np.prod(shape)) * dtype.itemsize,
                             max_size=int(np.prod(shape)) * dtype.itemsize))
        arr = np.frombuffer(raw, dtype).reshape(shape).copy()
        if dtype.kind == "f" and arr.size >= 4:
            arr.reshape(-1)[:4] = [np.nan, np.inf, -np.inf, -0.0]
        chans[f"c{i}"] = arr
    scan = ls.make_scan(info, chans, 3_000_000_007, is_bigendian=big,
                        is_destaggered=draw(st.booleans()),
                        column_time_offsets=np.arange(width) * 11, as_dataclass=True)
    return scan, info


@given(_case(), st.booleans())
def test_roundtrip_is_bit_exact(case: tuple[Any, Any], destagger: bool) -> None:
    scan, info = case
    imgs = images.to_images(scan, info, destagger=destagger, as_dataclass=True)
    image_order = destagger or bool(scan.is_destaggered)
    datatypes = {c.name: c.datatype for c in scan.channels if c.datatype == 6}
    back = images.from_images(imgs, info, destaggered=image_order,
                              is_destaggered=bool(scan.is_destaggered), datatypes=datatypes,
                              column_time_offsets=scan.column_time_offsets, as_dataclass=True)
    assert ls.encode(back) == ls.encode(scan)


@given(_case())
def test_destaggered_images_follow_the_row_shifts(case: tuple[Any, Any]) -> None:
    scan, info = case
    if scan.is_destaggered:
        return
    imgs = images.to_images(scan, info, destagger=True, as_dataclass=True)
    h, w = int(scan.height), int(scan.width)
    for desc in scan.channels:
        src = ls.channel(scan, desc.name)
        img = imgs[desc.name]
        got = np.frombuffer(img.data.tobytes(), src.dtype).reshape(src.shape)
        for u in range(h):
            for v in range(w):  # destaggered column v holds measurement column (v - s_u) mod W
                want = src[u, (v - int(info.pixel_shift_by_row[u])) % w]
                assert got[u, v].tobytes() == want.tobytes()


def test_encodings_header_and_step_per_rep_118(small_info: Any) -> None:
    h, w = 4, 8
    chans = {"range": np.full((h, w), 1.5, np.float32), "intensity": np.ones((h, w), np.uint16),
             "reflectivity": np.ones((h, w), np.uint8), "mm": np.ones((h, w), np.uint32),
             "pair": np.ones((h, w, 2), np.int16), "d": np.ones((h, w), np.float64),
             "s8": np.ones((h, w), np.int8), "i32": np.ones((h, w), np.int32)}
    scan = ls.make_scan(small_info, chans, 5_000_000_123, frame_id="os_lidar",
                        as_dataclass=True)
    imgs = images.to_images(scan, small_info, as_dataclass=True)
    assert {k: v.encoding for k, v in imgs.items()} == {
        "range": "32FC1", "intensity": "16UC1", "reflectivity": "8UC1", "mm": "32SC1",
        "pair": "16SC2", "d": "64FC1", "s8": "8SC1", "i32": "32SC1"}
    assert {k: v.step for k, v in imgs.items()} == {
        "range": 32, "intensity": 16, "reflectivity": 8, "mm": 32, "pair": 32, "d": 64,
        "s8": 8, "i32": 32}
    for img in imgs.values():
        assert (img.header.stamp.sec, img.header.stamp.nanosec) == (5, 123)
        assert img.header.frame_id == "os_lidar" and (img.height, img.width) == (h, w)
        assert img.is_bigendian == 0
    back = images.from_images({"mm": imgs["mm"]}, small_info, datatypes={"mm": 6},
                              as_dataclass=True)
    assert ls.channel(back, "mm").dtype == np.dtype("<u4")
    assert ls.to_ns(back.lidar_info_time) == ls.to_ns(small_info.header.stamp)
    mono = type(imgs["intensity"])(**{**{f: getattr(imgs["intensity"], f) for f in
                                        ("header", "height", "width", "is_bigendian", "step",
                                         "data")}, "encoding": "mono16"})
    assert ls.channel(images.from_images({"i": mono}, small_info, as_dataclass=True),
                      "i").dtype == np.dtype("<u2")


def test_real_frames_roundtrip_through_rclpy_images() -> None:
    pytest.importorskip("sensor_msgs.msg")
    from converters.edge.evidence._common import load_frame, ouster_files, ouster_info
    from converters.sources.ouster.metadata import scan_from_frame
    for meta, frame_path in ouster_files():
        if frame_path is None:
            continue
        info = ouster_info(meta)
        for encoding in ("float32", "uint32_mm"):
            scan = scan_from_frame(load_frame(frame_path), info, range_encoding=encoding,
                                   as_dataclass=True)
            imgs = images.to_images(scan, info)  # rclpy messages, destaggered
            assert type(imgs["range"]).__module__.startswith("sensor_msgs")
            back = images.from_images(imgs, info, is_destaggered=False,
                                      datatypes={c.name: 6 for c in scan.channels
                                                 if c.datatype == 6},
                                      column_time_offsets=scan.column_time_offsets,
                                      as_dataclass=True)
            assert ls.encode(back) == ls.encode(scan)


def test_errors_name_the_bad_input(small_info: Any) -> None:
    scan = ls.make_scan(small_info, {"range": np.ones((4, 8), np.float32),
                                     "intensity": np.ones((4, 8), np.uint16)}, 1,
                        as_dataclass=True)
    imgs = images.to_images(scan, small_info, as_dataclass=True)
    with pytest.raises(UnknownChannelError, match="nope"):
        images.to_images(scan, small_info, channels=["nope"], as_dataclass=True)
    with pytest.raises(ConversionError, match="at least one"):
        images.from_images({}, small_info)
    bad = type(imgs["range"])(**{**{f: getattr(imgs["range"], f) for f in
                                    ("header", "height", "width", "is_bigendian", "step",
                                     "data")}, "encoding": "rgb8"})
    with pytest.raises(ConversionError, match="encoding"):
        images.from_images({"range": bad}, small_info)
    with pytest.raises(ConversionError, match="datatypes"):
        images.from_images({"range": imgs["range"]}, small_info, datatypes={"range": 4})
    other = ls.make_scan(small_info, {"x": np.ones((4, 8), np.float32)}, 2, as_dataclass=True)
    with pytest.raises(ConversionError, match="header"):
        images.from_images({"range": imgs["range"],
                            "x": images.to_images(other, small_info, as_dataclass=True)["x"]},
                           small_info)
