"""Shared oracles and inputs of the PointCloud2 tests (test_pointcloud2*.py, test_cloud_import.py).

A slow struct.unpack reader of any cloud (the oracle for values), a cloud builder from a
structured array (any padding, byte order), the real Ouster frames of ``tests/data/ouster`` as
LidarInfo / LidarScan / the cloud ouster-ros would publish, and the ``os2`` / ``tiny`` fixtures
(import them into a test module to use them).
"""

from __future__ import annotations

import importlib.util
import json
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import lidarscan
from converters.pointcloud2 import converter as pc
from converters._kernels import cloud as kc

DATA = Path(__file__).parent / "data" / "ouster"
OS2 = "OS-2-128-U1_v2.3.0_1024x10"
OS0 = "OS-0-32-U1_v2.2.0_1024x10"

F32, F64, U16, U32 = 7, 8, 4, 6
_STRUCT = {1: "b", 2: "B", 3: "h", 4: "H", 5: "i", 6: "I", 7: "f", 8: "d"}


# --------------------------------------------------------------------------- oracles / helpers

def loop_read(cloud: Any) -> list[dict[str, Any]]:
    """Every point of any PointCloud2 as a dict, one struct.unpack per field (slow, obvious)."""
    order = ">" if cloud.is_bigendian else "<"
    data = bytes(cloud.data)
    points = []
    for row in range(cloud.height):
        for col in range(cloud.width):
            base = row * cloud.row_step + col * cloud.point_step
            point = {}
            for f in cloud.fields:
                values = struct.unpack_from(order + _STRUCT[f.datatype] * f.count, data,
                                            base + f.offset)
                point[f.name] = values[0] if f.count == 1 else values
            points.append(point)
    return points


def make_cloud(points: np.ndarray, *, height: int, width: int, stamp_ns: int = 0,
               frame_id: str = "lidar", row_pad: int = 0, bigendian: bool = False) -> Any:
    """A PointCloud2 from a structured array (fields from its dtype), built here by hand."""
    from builtin_interfaces.msg import Time
    from sensor_msgs.msg import PointCloud2, PointField
    from std_msgs.msg import Header

    codes = {"i1": 1, "u1": 2, "i2": 3, "u2": 4, "i4": 5, "u4": 6, "f4": 7, "f8": 8}
    dtype = points.dtype
    fields = []
    for name in dtype.names:
        base, offset = dtype.fields[name][:2]
        count = int(np.prod(base.shape)) if base.shape else 1
        sub = base.base if base.shape else base
        fields.append(PointField(name=name, offset=offset, datatype=codes[sub.str[1:]],
                                 count=count))
    arr = points.reshape(height, width)
    if bigendian:
        arr = arr.astype(arr.dtype.newbyteorder(">"))
    raw = arr.tobytes()
    step = dtype.itemsize
    if row_pad:
        rows = [raw[i * width * step:(i + 1) * width * step] + b"\xab" * row_pad
                for i in range(height)]
        raw = b"".join(rows)
    sec, nsec = divmod(stamp_ns, 10**9)
    return PointCloud2(header=Header(stamp=Time(sec=sec, nanosec=nsec), frame_id=frame_id),
                       height=height, width=width, fields=fields, is_bigendian=bigendian,
                       point_step=step, row_step=width * step + row_pad, data=raw,
                       is_dense=False)


def load_frame(name: str) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    meta = json.loads((DATA / f"{name}.json").read_text())
    frame = next(DATA.glob(f"{name}_frame*.npz"))
    with np.load(frame, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    return meta, arrays


def ouster_info(meta: dict[str, Any], stamp_ns: int = 1) -> Any:
    """LidarInfo of the metadata: converters.sources.ouster.metadata when present, else built here."""
    if importlib.util.find_spec("converters.sources.ouster.metadata") is not None:
        from converters.sources.ouster.metadata import info_from_metadata
        return info_from_metadata(meta, stamp_ns=stamp_ns)
    alt = np.radians(meta["beam_altitude_angles"])
    beta = -np.radians(meta["beam_azimuth_angles"])
    width = int(meta["data_format"]["columns_per_frame"])
    n = float(meta["lidar_origin_to_beam_origin_mm"]) / 1000
    transform = np.array(meta["lidar_to_sensor_transform"], float).reshape(4, 4)
    transform[:3, 3] /= 1000
    fps = int(str(meta["lidar_mode"]).split("x")[1])
    return lidarscan.make_info(
        stamp_ns=stamp_ns, frame_id="os_sensor", vertical_angles=alt,
        horizontal_angles=2 * np.pi * (1 - np.arange(width) / width),
        beam_azimuth_offsets=beta,
        beam_origins=np.stack([n * np.cos(beta), -n * np.sin(beta), 0 * beta], -1).ravel(),
        beam_range_offsets=np.full(alt.size, -n), lidar_to_sensor_transform=transform.ravel(),
        pixel_shift_by_row=meta["data_format"]["pixel_shift_by_row"],
        column_time_increment=10**9 // (fps * width), range_multiplier=0.001)


def ouster_scan(frame: dict[str, np.ndarray], info: Any, second: bool = False) -> Any:
    """LidarScan of a decoded frame (channels range f32, intensity, reflectivity, ambient)."""
    suffix = "2" if second else ""
    mm = frame[f"range{suffix}_mm"]
    ts = frame["timestamps_ns"].astype(np.int64)
    channels = {
        "range": np.where(mm > 0, mm * 1e-3, np.inf).astype(np.float32),
        "intensity": frame[f"signal{suffix}"].astype(np.uint16),
        "reflectivity": frame[f"reflectivity{suffix}"].astype(np.uint8),
        "ambient": frame["near_ir"].astype(np.uint16),
    }
    return lidarscan.make_scan(info, channels, int(ts[0]), column_time_offsets=ts - ts[0])


def ouster_ros_cloud(meta: dict[str, Any], frame: dict[str, np.ndarray], *, full: bool = True,
                     second: bool = False) -> Any:
    """What ouster-ros publishes for a frame, from the vendor formula (prior-art (b)/(c)).

    full: the "original" 48-byte point (os_point.h), else the 16-byte XYZI point.
    """
    suffix = "2" if second else ""
    mm = frame[f"range{suffix}_mm"].astype(np.float64)
    height, width = mm.shape
    theta_e = 2 * np.pi - np.arange(width) * 2 * np.pi / width
    theta_a = -np.radians(meta["beam_azimuth_angles"])
    phi = np.radians(meta["beam_altitude_angles"])
    n = float(meta["lidar_origin_to_beam_origin_mm"])
    t = np.array(meta["lidar_to_sensor_transform"], float).reshape(4, 4)
    ang = theta_e[None, :] + theta_a[:, None]
    direction = np.stack([np.cos(ang) * np.cos(phi)[:, None], np.sin(ang) * np.cos(phi)[:, None],
                          np.broadcast_to(np.sin(phi)[:, None], ang.shape)], -1)
    offset = np.stack([n * np.cos(theta_e)[None, :] - n * direction[..., 0],
                       n * np.sin(theta_e)[None, :] - n * direction[..., 1],
                       -n * direction[..., 2]], -1)
    xyz = 0.001 * (mm[..., None] * direction @ t[:3, :3].T + offset @ t[:3, :3].T + t[:3, 3])
    xyz[mm == 0] = np.nan
    shifts = np.asarray(meta["data_format"]["pixel_shift_by_row"])
    src = (np.arange(width)[None, :] - shifts[:, None]) % width       # c of pixel (u, v)
    rows = np.arange(height)[:, None]
    ts = frame["timestamps_ns"].astype(np.int64)
    if full:
        dtype = np.dtype({"names": ["x", "y", "z", "intensity", "t", "reflectivity", "ring",
                                    "ambient", "range"],
                          "formats": ["<f4", "<f4", "<f4", "<f4", "<u4", "<u2", "<u2", "<u2",
                                      "<u4"],
                          "offsets": [0, 4, 8, 16, 20, 24, 26, 28, 32], "itemsize": 48})
    else:
        dtype = np.dtype({"names": ["x", "y", "z", "intensity"], "formats": ["<f4"] * 4,
                          "offsets": [0, 4, 8, 12], "itemsize": 16})
    pts = np.zeros((height, width), dtype)
    for k, name in enumerate("xyz"):
        pts[name] = xyz[rows, src, k]
    pts["intensity"] = frame[f"signal{suffix}"][rows, src]
    if full:
        pts["t"] = ts[src] - ts[0]
        pts["reflectivity"] = frame[f"reflectivity{suffix}"][rows, src]
        pts["ring"] = np.broadcast_to(np.arange(height)[:, None], (height, width))
        pts["ambient"] = frame["near_ir"][rows, src]
        pts["range"] = frame[f"range{suffix}_mm"][rows, src]
    return make_cloud(pts.ravel(), height=height, width=width, stamp_ns=int(ts[0]),
                      frame_id="os_sensor")


def fields_of(cloud: Any) -> list[tuple[str, int, int, int]]:
    return [(f.name, f.datatype, f.offset, f.count) for f in cloud.fields]


def xyz_of(cloud: Any) -> np.ndarray:
    pts = pc.read_points(cloud)
    return np.stack([pts[n].astype(np.float64) for n in "xyz"], -1)


#: Two float32 evaluations of the beam model (the projector's r * D + O and the compiled
#: kernel's factored form) differ by a few float32 ulps of the point's distance: 1e-6 of it is
#: about 8 ulps.
POINT_RTOL = 1e-6


def assert_points_close(actual: Any, desired: Any) -> None:
    """(..., 3) points equal up to float32 rounding: per point |a - d| <= 1e-6 (|d| + 1) m
    (POINT_RTOL), NaN exactly where the other is NaN."""
    a = np.asarray(actual, np.float64).reshape(-1, 3)
    d = np.asarray(desired, np.float64).reshape(-1, 3)
    assert a.shape == d.shape
    nan_a, nan_d = np.isnan(a), np.isnan(d)
    np.testing.assert_array_equal(nan_a, nan_d)
    ok = ~nan_d.any(axis=1)
    scale = np.linalg.norm(d[ok], axis=1) + 1.0
    err = np.abs(a[ok] - d[ok]).max(axis=1, initial=0.0)
    worst = int(np.argmax(err / scale)) if err.size else 0
    assert np.all(err <= POINT_RTOL * scale), (
        f"point {worst}: {a[ok][worst]} vs {d[ok][worst]}" if err.size else "")


# ------------------------------------------------------------------------------------ fixtures

@pytest.fixture(scope="module")
def os2() -> tuple[dict[str, Any], dict[str, np.ndarray], Any, Any]:
    meta, frame = load_frame(OS2)
    info = ouster_info(meta)
    return meta, frame, info, ouster_scan(frame, info)


@pytest.fixture
def tiny() -> tuple[Any, Any]:
    """A 4 x 12 staggered sensor with beam origins, transform, beam times; float ranges with
    every kind of no-return value, channels of several dtypes."""
    rng = np.random.default_rng(5)
    height, width = 4, 12
    info = lidarscan.make_info(
        stamp_ns=7, frame_id="lidar", vertical_angles=np.radians([10.0, 3.0, -3.0, -10.0]),
        horizontal_angles=2 * np.pi * (1 - np.arange(width) / width),
        beam_azimuth_offsets=np.radians([2.0, -1.0, 1.5, -2.5]),
        beam_origins=rng.normal(0, 0.01, 3 * height), beam_range_offsets=[-0.01] * height,
        lidar_to_sensor_transform=[-1, 0, 0, 0.01, 0, -1, 0, 0, 0, 0, 1, 0.03, 0, 0, 0, 1],
        pixel_shift_by_row=[3, 2, 1, 0], beam_time_offsets=[0, 100, 200, 300],
        column_time_increment=1000, beam_ids=[12, 11, 10, 9])
    ranges = rng.uniform(0.5, 50, (height, width)).astype(np.float32)
    ranges[0, 1], ranges[1, 2], ranges[2, 3], ranges[3, 4] = np.inf, np.nan, 0.0, -np.inf
    channels = {"range": ranges,
                "intensity": rng.integers(0, 60000, (height, width)).astype(np.uint16),
                "reflectivity": rng.integers(0, 255, (height, width)).astype(np.uint8),
                "ambient": rng.integers(0, 60000, (height, width)).astype(np.uint16),
                "label": rng.integers(-5, 5, (height, width)).astype(np.int16)}
    scan = lidarscan.make_scan(info, channels, 5_000_000_123,
                               column_time_offsets=np.arange(width) * 1000 + 17)
    return info, scan


def destaggered(scan: Any, info: Any) -> Any:
    proj = lidarscan.make_projector(info)
    channels = {c.name: proj.destagger(lidarscan.channel(scan, c.name)) for c in scan.channels}
    return lidarscan.make_scan(info, channels, lidarscan.to_ns(scan.header.stamp),
                               is_destaggered=True, column_time_offsets=scan.column_time_offsets)


def info_fields(info: Any) -> dict[str, Any]:
    """make_info keyword arguments rebuilding ``info`` (change some to make a variant)."""
    names = ["vertical_angles", "horizontal_angles", "beam_azimuth_offsets", "beam_origins",
             "beam_range_offsets", "lidar_to_sensor_transform", "pixel_shift_by_row",
             "beam_time_offsets", "column_time_increment", "beam_ids"]
    out = {n: getattr(info, n) for n in names}
    out["vertical_angles"] = np.asarray(out["vertical_angles"])
    out["horizontal_angles"] = np.asarray(out["horizontal_angles"])
    return {"stamp_ns": lidarscan.to_ns(info.header.stamp), "frame_id": info.header.frame_id,
            **out}


# ------------------------------------------------------------ compiled kernel against numpy

KERNEL = pc.kernel_available()
needs_kernel = pytest.mark.skipif(not KERNEL, reason="compiled kernel "
                                  "converters/_kernels/_cloudkernel.c not built (pip install -e .)")


class Spy:
    """Counts the calls of the kernel function (proves a comparison really used it)."""

    def __init__(self, fn: Any) -> None:
        self.fn, self.calls = fn, 0

    def __call__(self, *args: Any) -> Any:
        self.calls += 1
        return self.fn(*args)


def kernel_and_numpy(scan: Any, info: Any, **options: Any) -> tuple[Any, Any, int]:
    """(cloud from the kernel, cloud from numpy only, number of kernel calls, either form)."""
    conv = pc.PointCloud2Converter(info, kernel=True, **options)
    spies = Spy(conv._kfn.project), Spy(conv._kfn.project_rc)
    conv._kfn = kc.Kernels(*spies)
    with_kernel = conv.convert(scan)
    without = pc.PointCloud2Converter(info, kernel=False, **options).convert(scan)
    return with_kernel, without, spies[0].calls + spies[1].calls


def assert_same_layout(a: Any, b: Any) -> None:
    """Same header, fields, shape and flags."""
    assert fields_of(a) == fields_of(b)
    assert (a.height, a.width, a.point_step, a.row_step, a.is_dense, a.is_bigendian) == (
        b.height, b.width, b.point_step, b.row_step, b.is_dense, b.is_bigendian)
    assert (a.header.stamp.sec, a.header.stamp.nanosec, a.header.frame_id) == (
        b.header.stamp.sec, b.header.stamp.nanosec, b.header.frame_id)


def assert_identical(a: Any, b: Any) -> None:
    """Same message, byte for byte (NaN payloads and signs of zero included)."""
    assert_same_layout(a, b)
    assert bytes(a.data) == bytes(b.data)


def assert_equivalent(a: Any, b: Any) -> None:
    """Same message up to float32 rounding of x, y, z (the kernel's factored form against the
    numpy path's tables): every other byte identical, NaN points the same canonical NaN."""
    assert_same_layout(a, b)
    da, db = np.frombuffer(bytes(a.data), np.uint8), np.frombuffer(bytes(b.data), np.uint8)
    assert da.size == db.size
    points = da.size // a.point_step
    xyz = np.zeros(a.point_step, bool)
    for f in a.fields:
        if f.name in ("x", "y", "z"):
            xyz[f.offset:f.offset + 4] = True
    other = np.tile(~xyz, points)
    np.testing.assert_array_equal(da[other], db[other])
    pa, pb = xyz_of(a).reshape(-1, 3), xyz_of(b).reshape(-1, 3)
    assert_points_close(pa, pb)
    for cloud in (a, b):
        pts = pc.read_points(cloud)
        for n in "xyz":
            bits = np.ascontiguousarray(pts[n]).view(np.uint32)
            assert np.all(bits[np.isnan(pts[n])] == 0x7FC00000), n


def with_channels(scan: Any, info: Any, **changes: np.ndarray) -> Any:
    chans = {c.name: np.asarray(lidarscan.channel(scan, c.name)) for c in scan.channels}
    chans.update(changes)
    return lidarscan.make_scan(info, chans, lidarscan.to_ns(scan.header.stamp),
                               is_destaggered=bool(scan.is_destaggered),
                               column_time_offsets=scan.column_time_offsets)
