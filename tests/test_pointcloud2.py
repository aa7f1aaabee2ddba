"""LidarScan <-> PointCloud2 (converters.pointcloud2).

Layers: exact preset layouts (pinned from the driver sources named in prior-art); a slow
struct.unpack reader written here as the oracle for values; an independent numpy version of the
ouster-ros point formula (prior-art (b): xyz = 0.001 (r R dir + R off + t)) applied to REAL Ouster
frames; a VLP-16-like ring cloud generated here from the Velodyne beam model; round trips;
Hypothesis properties over random small scans.
"""

from __future__ import annotations

import importlib.util
import json
import struct
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import lidarscan
from lidarscan.errors import (
    ConfigError,
    ConversionError,
    LinkageError,
    UnknownChannelError,
)

pytest.importorskip("sensor_msgs.msg")

from converters import pointcloud2 as pc
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
    """LidarInfo of the metadata: converters.ouster when present, else built here."""
    if importlib.util.find_spec("converters.ouster") is not None:
        from converters.ouster import info_from_metadata
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


# --------------------------------------------------------------------------------- layouts

EXPECTED = {
    # ouster-ros include/ouster_ros/os_point.h: PCL_ADD_POINT4D (x,y,z + pad) then the fields,
    # EIGEN_ALIGN16 -> 48 bytes
    "ouster": (48, [("x", F32, 0, 1), ("y", F32, 4, 1), ("z", F32, 8, 1),
                    ("intensity", F32, 16, 1), ("t", U32, 20, 1), ("reflectivity", U16, 24, 1),
                    ("ring", U16, 26, 1), ("ambient", U16, 28, 1), ("range", U32, 32, 1)]),
    # ouster-ros common_point_types.h _Ouster_PointXYZI: union of float[4]
    "ouster_xyzi": (16, [("x", F32, 0, 1), ("y", F32, 4, 1), ("z", F32, 8, 1),
                         ("intensity", F32, 12, 1)]),
    # ouster-ros PointXYZIR: PCL_ADD_POINT4D, intensity, ring, EIGEN_ALIGN16 -> 32 bytes
    "ouster_xyzir": (32, [("x", F32, 0, 1), ("y", F32, 4, 1), ("z", F32, 8, 1),
                          ("intensity", F32, 16, 1), ("ring", U16, 20, 1)]),
    # velodyne_pointcloud pointcloudXYZIRT.cpp: packed
    "velodyne": (22, [("x", F32, 0, 1), ("y", F32, 4, 1), ("z", F32, 8, 1),
                      ("intensity", F32, 12, 1), ("ring", U16, 16, 1), ("time", F32, 18, 1)]),
    # HesaiLidar_ROS_2.0 source_driver_ros2.hpp addPointField sequence
    "hesai": (26, [("x", F32, 0, 1), ("y", F32, 4, 1), ("z", F32, 8, 1),
                   ("intensity", F32, 12, 1), ("ring", U16, 16, 1), ("timestamp", F64, 18, 1)]),
    # rslidar_sdk source_pointcloud_ros.hpp (XYZIRT)
    "robosense": (26, [("x", F32, 0, 1), ("y", F32, 4, 1), ("z", F32, 8, 1),
                       ("intensity", F32, 12, 1), ("ring", U16, 16, 1),
                       ("timestamp", F64, 18, 1)]),
    "xyzi": (16, [("x", F32, 0, 1), ("y", F32, 4, 1), ("z", F32, 8, 1),
                  ("intensity", F32, 12, 1)]),
}


def test_every_preset_is_pinned() -> None:
    assert set(pc.PRESETS) == set(EXPECTED)


@pytest.mark.parametrize("preset", sorted(EXPECTED))
def test_preset_layout(preset: str, tiny: tuple[Any, Any]) -> None:
    info, scan = tiny
    step, fields = EXPECTED[preset]
    cloud = pc.to_pointcloud2(scan, info, preset=preset)
    assert fields_of(cloud) == fields
    assert cloud.point_step == step
    assert cloud.row_step == step * cloud.width
    assert len(cloud.data) == cloud.row_step * cloud.height
    assert cloud.is_bigendian is False
    valid = int(np.sum(np.isfinite(lidarscan.range_m(scan, info))
                       & (lidarscan.range_m(scan, info) > 0)))
    xyz = xyz_of(cloud)
    if preset.startswith("ouster") or preset == "xyzi":          # organized H x W, NaN holes
        assert (cloud.height, cloud.width) == (4, 12)
        assert cloud.is_dense is False
        assert int(np.isnan(xyz[..., 0]).sum()) == 48 - valid
        assert np.isnan(xyz).any(-1).sum() == np.isnan(xyz).all(-1).sum()   # all three NaN
    else:                                                          # unorganized, dense
        assert (cloud.height, cloud.width) == (1, valid)
        assert cloud.is_dense is True
        assert np.isfinite(xyz).all()


@pytest.mark.parametrize("preset", ["velodyne", "hesai", "robosense"])
def test_firing_presets_organized_are_firings_by_lasers(preset: str, tiny: tuple[Any, Any]
                                                        ) -> None:
    info, scan = tiny
    cloud = pc.to_pointcloud2(scan, info, preset=preset, organized=True)
    assert (cloud.height, cloud.width) == (12, 4)                  # firings x lasers
    assert cloud.is_dense is False
    pts = pc.read_points(cloud)
    rings = pts["ring"]
    assert np.all(np.diff(rings.astype(int), axis=1) != 0)
    proj = lidarscan.make_projector(info)
    ref = proj.project(scan, info)                                 # measurement order
    order = np.argsort(pc.PointCloud2Converter(info, preset=preset)._ring_values)
    for c in range(12):
        for k, u in enumerate(order):
            assert_points_close([pts[n][c, k] for n in "xyz"], ref[u, c])


def test_generic_fields_layout_and_dtypes(tiny: tuple[Any, Any]) -> None:
    info, scan = tiny
    cloud = pc.to_pointcloud2(scan, info, fields=("x", "y", "z", "reflectivity", "label", "ring",
                                                  "t", "timestamp", "range", "time"))
    assert fields_of(cloud) == [("x", F32, 0, 1), ("y", F32, 4, 1), ("z", F32, 8, 1),
                                ("reflectivity", 2, 12, 1), ("label", 3, 14, 1),
                                ("ring", U16, 16, 1), ("t", U32, 20, 1),
                                ("timestamp", F64, 24, 1), ("range", F32, 32, 1),
                                ("time", F32, 36, 1)]
    assert cloud.point_step == 40


# -------------------------------------------------------------------- values (loop reader)

@pytest.mark.parametrize("dataclass_scan", [False, True])
def test_loop_reader_matches_projector(tiny: tuple[Any, Any], dataclass_scan: bool) -> None:
    info, scan = tiny
    if dataclass_scan:
        scan = lidarscan.decode_scan(lidarscan.encode(scan))
    proj = lidarscan.make_projector(info)
    ref = proj.destagger(proj.project(scan, info))
    times = proj.destagger(proj.pixel_times(scan))
    rng_m = proj.destagger(np.asarray(lidarscan.range_m(scan, info)))
    chans = {n: proj.destagger(np.asarray(lidarscan.channel(scan, n)))
             for n in ("intensity", "reflectivity", "ambient")}
    stamp = lidarscan.to_ns(scan.header.stamp)
    cloud = pc.to_pointcloud2(scan, info, preset="ouster")
    assert lidarscan.to_ns(cloud.header.stamp) == stamp
    points = loop_read(cloud)
    for i, p in enumerate(points):
        u, v = divmod(i, 12)
        if np.isnan(ref[u, v, 0]):
            assert all(np.isnan(p[n]) for n in "xyz")
            assert p["range"] == 0
        else:
            assert_points_close([p["x"], p["y"], p["z"]], ref[u, v])
            assert p["range"] == round(float(rng_m[u, v]) * 1000)
        assert p["t"] == times[u, v]
        assert p["ring"] == u
        assert p["intensity"] == float(chans["intensity"][u, v])
        assert p["reflectivity"] == chans["reflectivity"][u, v]
        assert p["ambient"] == chans["ambient"][u, v]


def test_velodyne_time_and_ring_conventions(tiny: tuple[Any, Any]) -> None:
    info, scan = tiny
    proj = lidarscan.make_projector(info)
    times = proj.pixel_times(scan)                                   # measurement order
    stamp = lidarscan.to_ns(scan.header.stamp)
    cloud = pc.to_pointcloud2(scan, info, preset="velodyne")
    last = stamp + int(times.max())
    assert lidarscan.to_ns(cloud.header.stamp) == last              # stamp of the LAST firing
    points = loop_read(cloud)
    valid = np.isfinite(proj.project(scan, info)[..., 0])
    expected = []                                                   # firing order, ring order
    for c in range(12):
        for u in (3, 2, 1, 0):
            if valid[u, c]:
                expected.append((u, c))
    assert len(points) == len(expected)
    ref = proj.project(scan, info)
    for p, (u, c) in zip(points, expected):
        assert p["ring"] == 3 - u                                    # 0 = lowest beam
        assert p["time"] == pytest.approx((times[u, c] + stamp - last) * 1e-9, abs=1e-9)
        assert p["time"] <= 0
        assert_points_close([p["x"], p["y"], p["z"]], ref[u, c])


@pytest.mark.parametrize("preset", ["hesai", "robosense"])
def test_absolute_timestamp_presets(preset: str, tiny: tuple[Any, Any]) -> None:
    info, scan = tiny
    proj = lidarscan.make_projector(info)
    times = proj.pixel_times(scan)
    stamp = lidarscan.to_ns(scan.header.stamp)
    cloud = pc.to_pointcloud2(scan, info, preset=preset)
    assert lidarscan.to_ns(cloud.header.stamp) == stamp + int(times.min())   # first point
    points = loop_read(cloud)
    valid = np.isfinite(proj.project(scan, info)[..., 0])
    expected = [(u, c) for c in range(12) for u in (3, 2, 1, 0) if valid[u, c]]
    ids = [12, 11, 10, 9]
    for p, (u, c) in zip(points, expected):
        assert p["timestamp"] == pytest.approx((stamp + times[u, c]) * 1e-9, abs=1e-7)
        assert p["ring"] == (ids[u] if preset == "hesai" else 3 - u)


def test_unorganized_generic_drops_invalid_in_row_order(tiny: tuple[Any, Any]) -> None:
    info, scan = tiny
    proj = lidarscan.make_projector(info)
    ref = proj.destagger(proj.project(scan, info)).reshape(-1, 3)
    keep = np.isfinite(ref[:, 0])
    cloud = pc.to_pointcloud2(scan, info, organized=False)
    assert (cloud.height, cloud.width, cloud.is_dense) == (1, int(keep.sum()), True)
    assert_points_close(xyz_of(cloud)[0], ref[keep])


def test_measurement_order_output(tiny: tuple[Any, Any]) -> None:
    info, scan = tiny
    proj = lidarscan.make_projector(info)
    cloud = pc.to_pointcloud2(scan, info, destagger=False)
    assert_points_close(xyz_of(cloud), proj.project(scan, info))


def test_staggered_and_destaggered_scans_give_identical_clouds(tiny: tuple[Any, Any]) -> None:
    info, scan = tiny
    dscan = destaggered(scan, info)
    for kwargs in ({"preset": "ouster"}, {"preset": "velodyne"}, {"preset": "hesai"},
                   {"fields": ("x", "y", "z", "t", "time", "label")},
                   {"preset": "ouster", "destagger": False}):
        a = pc.to_pointcloud2(scan, info, **kwargs)
        b = pc.to_pointcloud2(dscan, info, **kwargs)
        assert bytes(a.data) == bytes(b.data), kwargs
        assert a.header == b.header


def test_integer_range_channel_and_uint32_mm_field(tiny: tuple[Any, Any]) -> None:
    info, scan = tiny
    info = lidarscan.make_info(**{**_fields(info), "range_multiplier": 0.001})
    rng_m = np.asarray(lidarscan.range_m(scan, info))
    mm = np.where(np.isfinite(rng_m) & (rng_m > 0), np.rint(rng_m * 1000), 0).astype(np.uint32)
    iscan = lidarscan.make_scan(info, {"range": mm, "intensity": lidarscan.channel(scan,
                                                                                   "intensity")},
                                5_000_000_123, column_time_offsets=scan.column_time_offsets)
    cloud = pc.to_pointcloud2(iscan, info, preset="ouster")
    proj = lidarscan.make_projector(info)
    pts = pc.read_points(cloud)
    np.testing.assert_array_equal(pts["range"], proj.destagger(mm))
    assert_points_close(xyz_of(cloud), proj.destagger(proj.project(iscan, info)))
    assert np.array_equal(np.isnan(xyz_of(cloud)[..., 0]), proj.destagger(mm) == 0)
    assert np.all(pts["ambient"] == 0)               # preset channel missing -> zero-filled


def _fields(info: Any) -> dict[str, Any]:
    names = ["vertical_angles", "horizontal_angles", "beam_azimuth_offsets", "beam_origins",
             "beam_range_offsets", "lidar_to_sensor_transform", "pixel_shift_by_row",
             "beam_time_offsets", "column_time_increment", "beam_ids"]
    out = {n: getattr(info, n) for n in names}
    out["vertical_angles"] = np.asarray(out["vertical_angles"])
    out["horizontal_angles"] = np.asarray(out["horizontal_angles"])
    return {"stamp_ns": lidarscan.to_ns(info.header.stamp), "frame_id": info.header.frame_id,
            **out}


def test_measured_column_azimuths_are_used(tiny: tuple[Any, Any]) -> None:
    info, scan = tiny
    az = np.asarray(info.horizontal_angles) + np.linspace(0, 0.01, 12)
    chans = {c.name: lidarscan.channel(scan, c.name) for c in scan.channels}
    mscan = lidarscan.make_scan(info, chans, 5_000_000_123, column_azimuth_angles=az)
    proj = lidarscan.make_projector(info)
    cloud = pc.to_pointcloud2(mscan, info)
    assert_points_close(xyz_of(cloud), proj.destagger(proj.project(mscan, info)))


def test_messages_are_independent_and_input_untouched(tiny: tuple[Any, Any]) -> None:
    info, scan = tiny
    before = bytes(scan.data)
    conv = pc.PointCloud2Converter(info, preset="ouster")
    first = conv.convert(scan)
    snapshot = bytes(first.data)
    chans = {c.name: np.asarray(lidarscan.channel(scan, c.name)) for c in scan.channels}
    chans["range"] = chans["range"] * 2
    other = lidarscan.make_scan(info, chans, 5_000_000_123)
    second = conv.convert(other)
    assert bytes(first.data) == snapshot != bytes(second.data)
    assert bytes(scan.data) == before
    assert type(first.data).__name__ == "array"


@pytest.mark.parametrize("preset", [None, "ouster", "velodyne", "hesai"])
def test_threads_give_identical_clouds(tiny: tuple[Any, Any], preset: str | None) -> None:
    info, scan = tiny
    one = pc.PointCloud2Converter(info, preset=preset).convert(scan)
    three = pc.PointCloud2Converter(info, preset=preset, threads=3)
    assert len(three._blocks) == 3
    assert bytes(three.convert(scan).data) == bytes(one.data)
    with pytest.raises(ConfigError):
        pc.PointCloud2Converter(info, threads=0)


def test_errors(tiny: tuple[Any, Any]) -> None:
    info, scan = tiny
    with pytest.raises(ConfigError):
        pc.PointCloud2Converter(info, preset="nope")
    with pytest.raises(ConfigError):
        pc.PointCloud2Converter(info, preset="ouster", fields=("x", "y", "z"))
    with pytest.raises(ConfigError):
        pc.PointCloud2Converter(info, fields=("x", "y"))
    with pytest.raises(ConfigError):
        pc.PointCloud2Converter(info, time_reference="middle")
    with pytest.raises(UnknownChannelError):
        pc.to_pointcloud2(scan, info, fields=("x", "y", "z", "nothing"))
    other = lidarscan.make_info(**{**_fields(info), "stamp_ns": 8})
    with pytest.raises(LinkageError):
        pc.to_pointcloud2(scan, other)
    early = lidarscan.make_info(**{**_fields(info), "beam_time_offsets": [-500, 0, 0, 0]})
    escan = lidarscan.make_scan(early, {"range": np.ones((4, 12), np.float32)}, 0)
    with pytest.raises(ConversionError):                  # t is u32 ns >= 0 after the stamp
        pc.to_pointcloud2(escan, early, preset="ouster")
    cloud = pc.to_pointcloud2(escan, early, preset="ouster", time_reference="first")
    assert pc.read_points(cloud)["t"].min() == 0


def test_import_does_not_load_rclpy() -> None:
    code = ("import sys, converters.pointcloud2, converters.deskew; "
            "assert 'rclpy' not in sys.modules, 'rclpy imported'")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=Path(__file__).parents[1])


# ------------------------------------------------------------------------------ real Ouster

def test_ouster_preset_matches_ouster_ros_formula_on_real_frame(os2: Any) -> None:
    meta, frame, info, scan = os2
    ours = pc.to_pointcloud2(scan, info, preset="ouster")
    ref = ouster_ros_cloud(meta, frame)
    assert fields_of(ours) == fields_of(ref)
    assert (ours.height, ours.width, ours.point_step, ours.row_step) == \
        (ref.height, ref.width, ref.point_step, ref.row_step)
    assert ours.header.stamp == ref.header.stamp
    a, b = pc.read_points(ours), pc.read_points(ref)
    for name in ("intensity", "t", "reflectivity", "ring", "ambient", "range"):
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    xa, xb = xyz_of(ours), xyz_of(ref)
    assert np.array_equal(np.isnan(xa), np.isnan(xb))
    assert np.nanmax(np.abs(xa - xb)) < 1e-4                          # < 0.1 mm


@pytest.mark.parametrize("full", [True, False])
def test_estimate_from_real_ouster_ros_cloud(os2: Any, full: bool) -> None:
    meta, frame, _, _ = os2
    cloud = ouster_ros_cloud(meta, frame, full=full)
    before = bytes(cloud.data)
    scan, est = pc.from_pointcloud2(cloud)
    assert bytes(cloud.data) == before
    err = pc.estimation_error(cloud, scan, est)
    assert err.points == int((frame["range_mm"] > 0).sum()) == err.matched
    assert err.max_m < 1e-4 and err.rms_m < 1e-5, err                 # sub-0.1 mm (real data)
    # rows top to bottom, elevations as in the metadata
    np.testing.assert_allclose(est.vertical_angles, np.radians(meta["beam_altitude_angles"]),
                               atol=2e-6)
    if full:
        # ranges come back exactly (mm), stagger and column times recovered from t
        shifts = np.asarray(meta["data_format"]["pixel_shift_by_row"])
        np.testing.assert_array_equal(np.asarray(est.pixel_shift_by_row) % 1024, shifts)
        proj = lidarscan.make_projector(est)
        rng_m = proj.restagger(np.asarray(lidarscan.range_m(scan, est)))
        mm = frame["range_mm"]
        np.testing.assert_allclose(rng_m[mm > 0], mm[mm > 0] * 1e-3, rtol=1e-7)
        assert np.all(np.isinf(rng_m[mm == 0]))
        ts = frame["timestamps_ns"].astype(np.int64)
        np.testing.assert_array_equal(np.asarray(scan.column_time_offsets), ts - ts[0])
        assert err.max_time_ns == 0
        np.testing.assert_array_equal(lidarscan.channel(scan, "reflectivity"),
                                      pc.read_points(cloud)["reflectivity"])


def test_estimate_from_real_dual_return_os0_second_returns_too() -> None:
    meta, frame = load_frame(OS0)
    for second in (False, True):
        cloud = ouster_ros_cloud(meta, frame, full=True, second=second)
        scan, est = pc.from_pointcloud2(cloud)
        err = pc.estimation_error(cloud, scan, est)
        assert err.matched == err.points > 100
        assert err.max_m < 1e-4, (second, err)


def test_round_trip_scan_cloud_scan_reproduces_ranges(os2: Any) -> None:
    _, _, info, scan = os2
    cloud = pc.to_pointcloud2(scan, info, preset="ouster")
    back, est = pc.from_pointcloud2(cloud, as_dataclass=True)
    proj, pback = lidarscan.make_projector(info), lidarscan.make_projector(est)
    original = np.asarray(lidarscan.range_m(scan, info))
    again = pback.restagger(np.asarray(lidarscan.range_m(back, est)))
    shift = (np.asarray(est.pixel_shift_by_row) - np.asarray(info.pixel_shift_by_row)) % 1024
    assert np.all(shift == 0)
    np.testing.assert_array_equal(again, original)                  # bin for bin, exactly
    # the rebuilt scan converts to the same points
    cloud2 = pc.to_pointcloud2(back, est, preset="ouster")
    assert np.nanmax(np.abs(xyz_of(cloud2) - xyz_of(cloud))) < 1e-4
    assert np.array_equal(pc.read_points(cloud2)["t"], pc.read_points(cloud)["t"])
    assert proj.height == pback.height


@pytest.mark.parametrize("preset", ["velodyne", "hesai", "robosense", "ouster_xyzir"])
def test_estimate_from_our_driver_style_clouds(os2: Any, preset: str) -> None:
    _, _, info, scan = os2
    cloud = pc.to_pointcloud2(scan, info, preset=preset, organized=False)
    back, est = pc.from_pointcloud2(cloud)
    err = pc.estimation_error(cloud, back, est)
    assert err.matched == err.points
    assert err.max_m < 1e-4, err
    if err.max_time_ns is not None:
        assert err.max_time_ns < 1000


# -------------------------------------------------------------------- byte order, f64, padding

def test_big_endian_float64_padded_input(os2: Any) -> None:
    meta, frame, _, _ = os2
    little = ouster_ros_cloud(meta, frame)
    pts = pc.read_points(little)
    dtype = np.dtype({"names": ["pad", "z", "x", "y", "intensity", "t", "range"],
                      "formats": ["<u4", "<f8", "<f8", "<f8", "<f4", "<u4", "<u4"],
                      "offsets": [0, 8, 16, 24, 32, 36, 40], "itemsize": 56})
    wide = np.zeros(pts.shape, dtype)
    for name in ("x", "y", "z", "intensity", "t", "range"):
        wide[name] = pts[name]
    big = make_cloud(wide.ravel(), height=little.height, width=little.width,
                     stamp_ns=lidarscan.to_ns(little.header.stamp), row_pad=24, bigendian=True)
    raw = bytes(big.data)
    scan_b, est_b = pc.from_pointcloud2(big)
    assert bytes(big.data) == raw                                   # never byteswapped
    scan_l, est_l = pc.from_pointcloud2(little)
    np.testing.assert_array_equal(lidarscan.range_m(scan_b, est_b),
                                  lidarscan.range_m(scan_l, est_l))
    np.testing.assert_allclose(est_b.vertical_angles, est_l.vertical_angles, atol=1e-9)
    err = pc.estimation_error(big, scan_b, est_b)
    assert err.max_m < 1e-4
    assert lidarscan.channel(scan_b, "intensity").dtype.byteorder in "=<|"


def test_read_points_checks_sizes() -> None:
    pts = np.zeros(4, np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4")]))
    cloud = make_cloud(pts, height=2, width=2)
    cloud.data = bytes(cloud.data)[:-1]
    with pytest.raises(ConversionError):
        pc.read_points(cloud)


def test_from_pointcloud2_errors() -> None:
    pts = np.zeros(8, np.dtype([("x", "<f4"), ("y", "<f4")]))
    with pytest.raises(ConversionError):
        pc.from_pointcloud2(make_cloud(pts, height=1, width=8))
    xyz = np.ones(8, np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4")]))
    with pytest.raises(ConversionError):                # unorganized without ring
        pc.from_pointcloud2(make_cloud(xyz, height=1, width=8))
    with pytest.raises(ConfigError):
        pc.from_pointcloud2(make_cloud(xyz, height=2, width=4), layout="grid")
    empty = make_cloud(xyz[:0], height=2, width=0)
    with pytest.raises(ConversionError):
        pc.from_pointcloud2(empty)
    huge = make_cloud(xyz, height=1, width=8)
    huge.point_step = 2**31
    with pytest.raises(ConversionError):
        pc.from_pointcloud2(huge)
    # beam numbers that cannot be LidarInfo.beam_ids (uint16): NaN in a float ring field made
    # np.bincount raise ValueError once (tests/test_fuzz.py, pointcloud2 inconsistency property)
    rings = np.zeros(8, np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("ring", "<f4")]))
    rings["x"], rings["ring"] = 1.0, np.repeat([0.0, 1.0], 4)
    for layout, (h, w) in (("organized", (2, 4)), ("ring", (1, 8))):
        for bad in (np.nan, -1.0, 65536.0):
            wrong = rings.copy()
            wrong["ring"][5] = bad
            with pytest.raises(ConversionError, match="ring="):
                pc.from_pointcloud2(make_cloud(wrong, height=h, width=w), layout=layout)


# ---------------------------------------------------------------------- VLP-16-like ring cloud

def vlp16_cloud(*, absolute: bool, seed: int = 3) -> tuple[Any, dict[str, Any]]:
    """A VLP-16-like sweep from the Velodyne beam model (prior-art (b)), noise-free geometry.

    16 lasers at -15..15 deg firing every 2.304 us in the VLP-16 interleaved order, one firing
    sequence per 55.296 us, 1800 firings with a slightly uneven measured azimuth, per-laser
    rot_correction / vert_offset / horiz_offset / dist_correction, 10 % no return (dropped, as
    velodyne_pointcloud does), points in firing order. absolute: Hesai/RoboSense style
    ``timestamp`` f64 s; else velodyne ``time`` f32 s relative to the stamp of the last firing.
    """
    rng = np.random.default_rng(seed)
    lasers = np.arange(16)
    elev_deg = np.where(lasers % 2 == 0, -15 + lasers, lasers)          # -15, 1, -13, 3, ...
    phi = np.radians(elev_deg)
    ring = np.argsort(np.argsort(elev_deg))                             # 0 = lowest
    rot = np.radians(rng.uniform(-0.3, 0.3, 16))
    vert = rng.uniform(-0.02, 0.02, 16)
    horiz = rng.uniform(-0.03, 0.03, 16)
    dist = rng.uniform(-0.05, 0.05, 16)
    n_fire = 1800
    azimuth = np.unwrap(np.radians(np.arange(n_fire) * 0.2 + rng.normal(0, 0.004, n_fire)))
    t0 = 1_700_000_000_000_000_000
    fire_t = t0 + np.arange(n_fire) * 55_296
    rows = []
    for c in range(n_fire):
        for k in lasers:
            rho = rng.uniform(1.0, 60.0)
            if rng.random() < 0.1:
                continue
            theta = -azimuth[c] + rot[k]
            cp, sp = np.cos(phi[k]), np.sin(phi[k])
            o = np.array([-vert[k] * sp, horiz[k], vert[k] * cp])
            d = np.array([cp * np.cos(theta), cp * np.sin(theta), sp])
            rz = np.array([[np.cos(theta), -np.sin(theta), 0], [np.sin(theta), np.cos(theta), 0],
                           [0, 0, 1]])
            p = rz @ o + (rho + dist[k]) * d
            rows.append((p, ring[k], fire_t[c] + k * 2304, rng.uniform(0, 255)))
    last = int(fire_t[-1])
    if absolute:
        dtype = np.dtype({"names": ["x", "y", "z", "intensity", "ring", "timestamp"],
                          "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f8"],
                          "offsets": [0, 4, 8, 12, 16, 18], "itemsize": 26})
        stamp = t0
    else:
        dtype = np.dtype({"names": ["x", "y", "z", "intensity", "ring", "time"],
                          "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f4"],
                          "offsets": [0, 4, 8, 12, 16, 18], "itemsize": 22})
        stamp = last
    pts = np.zeros(len(rows), dtype)
    for i, (p, r, t, inten) in enumerate(rows):
        pts[i]["x"], pts[i]["y"], pts[i]["z"] = p
        pts[i]["ring"], pts[i]["intensity"] = r, inten
        if absolute:
            pts[i]["timestamp"] = t * 1e-9
        else:
            pts[i]["time"] = (t - last) * 1e-9
    truth = {"phi": np.sort(phi)[::-1], "t0": t0}
    return make_cloud(pts, height=1, width=len(rows), stamp_ns=stamp, frame_id="velodyne"), truth


@pytest.mark.parametrize("absolute", [False, True])
def test_estimate_vlp16_like_ring_cloud(absolute: bool) -> None:
    cloud, truth = vlp16_cloud(absolute=absolute)
    scan, info = pc.from_pointcloud2(cloud)
    assert (scan.height, scan.width) == (16, 1800)
    np.testing.assert_array_equal(np.asarray(info.beam_ids), np.arange(16)[::-1])
    np.testing.assert_allclose(info.vertical_angles, truth["phi"], atol=1e-6)
    assert lidarscan.to_ns(scan.header.stamp) == pytest.approx(truth["t0"], abs=100)
    assert np.asarray(scan.column_azimuth_angles).size == 1800
    err = pc.estimation_error(cloud, scan, info)
    assert err.matched == err.points == cloud.width
    assert err.max_m < 1e-4 and err.rms_m < 2e-5, err
    assert err.max_time_ns < (300 if absolute else 100), err      # f64 abs s: ~0.24 us grid
    np.testing.assert_allclose(np.asarray(info.beam_time_offsets).max(), 15 * 2304, atol=300)


def test_velodyne_driver_azimuth_rounding_bound() -> None:
    """velodyne_pointcloud (rawdata.cpp, VLP-16) interpolates each laser's azimuth inside a
    block from integer 0.01 deg block azimuths and rounds it back to 0.01 deg: a per-point
    pattern no per-column + per-beam model holds. Documented bound: ~1.3e-4 rad x range."""
    rng = np.random.default_rng(0)
    elev = np.where(np.arange(16) % 2 == 0, -15 + np.arange(16), np.arange(16)).astype(float)
    phi, ring = np.radians(elev), np.argsort(np.argsort(elev))
    blocks, t_block = 900, 110.592                                 # us per block (2 firings)
    az_block = np.round(np.arange(blocks + 1) * t_block * 3.6e-3 * 100).astype(int) % 36000
    dtype = np.dtype({"names": ["x", "y", "z", "intensity", "ring", "time"],
                      "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f4"],
                      "offsets": [0, 4, 8, 12, 16, 18], "itemsize": 22})
    pts = np.zeros(blocks * 32, dtype)
    last_us = (blocks - 1) * t_block + 55.296 + 15 * 2.304
    i = 0
    for b in range(blocks):
        diff = (az_block[b + 1] - az_block[b]) % 36000
        for firing in range(2):
            for dsr in range(16):
                offset_us = dsr * 2.304 + firing * 55.296
                azc = round(az_block[b] + diff * offset_us / 110.592) % 36000
                rho, theta = rng.uniform(1, 60), -np.radians(azc / 100)
                pts[i]["x"] = rho * np.cos(phi[dsr]) * np.cos(theta)
                pts[i]["y"] = rho * np.cos(phi[dsr]) * np.sin(theta)
                pts[i]["z"] = rho * np.sin(phi[dsr])
                pts[i]["ring"] = ring[dsr]
                pts[i]["time"] = (b * t_block + offset_us - last_us) * 1e-6
                i += 1
    cloud = make_cloud(pts, height=1, width=pts.size, stamp_ns=10**18)
    scan, info = pc.from_pointcloud2(cloud)
    assert (scan.height, scan.width) == (16, 1800)
    err = pc.estimation_error(cloud, scan, info)
    assert err.matched == err.points
    assert err.max_m < 1.5e-4 * 60 and err.rms_m < 3e-3, err
    assert err.max_m > 1e-3                       # the rounding really is not representable
    assert err.max_time_ns < 100


# ---------------------------------------------------------------------------------- hypothesis

@settings(max_examples=50, deadline=None)
@given(height=st.integers(1, 5), width=st.integers(2, 10), seed=st.integers(0, 2**31 - 1),
       organized=st.booleans(), destagger=st.booleans(), staggered_input=st.booleans())
def test_random_small_scans(height: int, width: int, seed: int, organized: bool,
                            destagger: bool, staggered_input: bool) -> None:
    rng = np.random.default_rng(seed)
    info = lidarscan.make_info(
        as_dataclass=True,
        stamp_ns=3, frame_id="f", vertical_angles=np.sort(rng.uniform(-0.5, 0.5, height))[::-1],
        horizontal_angles=rng.uniform(-np.pi, np.pi, width),
        beam_azimuth_offsets=rng.uniform(-0.1, 0.1, height),
        beam_origins=rng.normal(0, 0.02, 3 * height),
        pixel_shift_by_row=rng.integers(-width, width, height),
        beam_time_offsets=rng.integers(0, 50, height), column_time_increment=100)
    ranges = rng.uniform(0.1, 20, (height, width)).astype(np.float32)
    bad = rng.random((height, width))
    ranges[bad < 0.1] = np.inf
    ranges[(bad >= 0.1) & (bad < 0.15)] = np.nan
    ranges[(bad >= 0.15) & (bad < 0.2)] = 0
    intensity = rng.integers(0, 65535, (height, width)).astype(np.uint16)
    scan = lidarscan.make_scan(info, {"range": ranges, "intensity": intensity}, 10**9,
                               as_dataclass=True)
    proj = lidarscan.make_projector(info)
    if not staggered_input:
        scan = destaggered(scan, info)
    ref = proj.project(scan, info)
    times = proj.pixel_times(scan)
    inten = np.asarray(lidarscan.channel(scan, "intensity"), np.float32)
    if bool(scan.is_destaggered) != destagger:
        fix = proj.destagger if destagger else proj.restagger
        ref, times, inten = fix(ref), fix(times), fix(inten)
    cloud = pc.to_pointcloud2(scan, info, fields=("x", "y", "z", "intensity", "t"),
                              organized=organized, destagger=destagger)
    pts = pc.read_points(cloud)
    keep = np.isfinite(ref[..., 0])
    if organized:
        assert (cloud.height, cloud.width) == (height, width)
        assert cloud.is_dense == bool(keep.all())
        got = np.stack([pts[n] for n in "xyz"], -1)
        np.testing.assert_allclose(got, ref, atol=1e-5, equal_nan=True)
        np.testing.assert_array_equal(pts["t"], times)
        np.testing.assert_array_equal(pts["intensity"], inten)
    else:
        assert (cloud.height, cloud.width, cloud.is_dense) == (1, int(keep.sum()), True)
        got = np.stack([pts[n][0] for n in "xyz"], -1)
        np.testing.assert_allclose(got, ref[keep], atol=1e-5)
        np.testing.assert_array_equal(pts["t"][0], times[keep])
        np.testing.assert_array_equal(pts["intensity"][0], inten[keep])


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), missing=st.floats(0.0, 0.3))
def test_round_trip_random_ranges_on_ouster_geometry(os2: Any, seed: int, missing: float
                                                     ) -> None:
    _, _, info, _ = os2
    rng = np.random.default_rng(seed)
    rows = slice(0, 128, 8)
    sub = lidarscan.make_info(
        stamp_ns=11, frame_id="os_sensor",
        vertical_angles=np.asarray(info.vertical_angles)[rows],
        horizontal_angles=np.asarray(info.horizontal_angles)[::16],
        beam_azimuth_offsets=np.asarray(info.beam_azimuth_offsets)[rows],
        beam_origins=np.asarray(info.beam_origins).reshape(-1, 3)[rows].ravel(),
        beam_range_offsets=np.asarray(info.beam_range_offsets)[rows],
        lidar_to_sensor_transform=info.lidar_to_sensor_transform,
        pixel_shift_by_row=np.asarray(info.pixel_shift_by_row)[rows] // 4,
        column_time_increment=1_562_500, range_multiplier=0.001)
    mm = rng.integers(300, 150_000, (16, 64)).astype(np.uint32)
    mm[rng.random(mm.shape) < missing] = 0
    scan = lidarscan.make_scan(sub, {"range": mm}, 10**9)
    cloud = pc.to_pointcloud2(scan, sub, preset="ouster")
    back, est = pc.from_pointcloud2(cloud)
    err = pc.estimation_error(cloud, back, est)
    assert err.matched == err.points == int((mm > 0).sum())
    assert err.max_m < 1e-4, err
    again = lidarscan.make_projector(est).restagger(np.asarray(lidarscan.range_m(back, est)))
    np.testing.assert_allclose(again[mm > 0], mm[mm > 0] * 1e-3, rtol=1e-7)


# ------------------------------------------------------------------------- compiled kernel

KERNEL = pc.kernel_available()
needs_kernel = pytest.mark.skipif(not KERNEL, reason="compiled kernel "
                                  "converters/_kernels/_cloudkernel.c not built (pip install -e .)")


class _Spy:
    """Counts the calls of the kernel function (proves a comparison really used it)."""

    def __init__(self, fn: Any) -> None:
        self.fn, self.calls = fn, 0

    def __call__(self, *args: Any) -> Any:
        self.calls += 1
        return self.fn(*args)


def kernel_and_numpy(scan: Any, info: Any, **options: Any) -> tuple[Any, Any, int]:
    """(cloud from the kernel, cloud from numpy only, number of kernel calls, either form)."""
    conv = pc.PointCloud2Converter(info, kernel=True, **options)
    spies = _Spy(conv._kfn.project), _Spy(conv._kfn.project_rc)
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


@needs_kernel
@pytest.mark.parametrize("preset", [None, *sorted(pc.PRESETS)])
def test_kernel_bit_identical_every_preset_and_order(tiny: tuple[Any, Any], preset: str | None
                                                     ) -> None:
    info, scan = tiny
    for source in (scan, destaggered(scan, info)):
        for organized in (True, False):
            for destagger in (True, False):
                a, b, calls = kernel_and_numpy(source, info, preset=preset, organized=organized,
                                               destagger=destagger)
                assert calls == 1
                assert_equivalent(a, b)
                assert a.is_dense == (not organized)       # tiny has no-return pixels


@needs_kernel
@pytest.mark.parametrize("fields", [("x", "y", "z"), ("x", "y", "z", "intensity"),
                                    ("intensity", "x", "y", "z", "range"),
                                    ("x", "y", "z", "label", "ring", "t", "range"),
                                    ("range", "z", "x", "y")])
def test_kernel_bit_identical_generic_fields(tiny: tuple[Any, Any], fields: tuple[str, ...]
                                             ) -> None:
    info, scan = tiny
    for organized in (True, False):
        for threads in (1, 3):
            a, b, calls = kernel_and_numpy(scan, info, fields=fields, organized=organized,
                                           threads=threads)
            assert_equivalent(a, b)
            # (z, x, y) is not x, y, z consecutive: numpy does it all
            expected = 0 if fields[1:] == ("z", "x", "y") else (
                1 if not organized and fields in (("x", "y", "z"), ("x", "y", "z", "intensity"))
                else threads)
            assert calls == expected, (fields, organized, threads)


@needs_kernel
def test_kernel_writes_every_no_return_as_canonical_nan(tiny: tuple[Any, Any]) -> None:
    info, scan = tiny
    raw = np.asarray(lidarscan.channel(scan, "range")).copy()
    payload = np.array([0xFFC00001, 0x7FC12345], np.uint32).view(np.float32)  # -NaN, NaN payload
    raw[0, 5], raw[1, 6] = payload
    raw[2, 7], raw[3, 8] = -0.0, np.float32(1e-45)                # -0: none; denormal: a point
    scan = with_channels(scan, info, range=raw)
    a, b, calls = kernel_and_numpy(scan, info, fields=("x", "y", "z", "range"), destagger=False)
    assert calls == 1
    assert_equivalent(a, b)
    pts = pc.read_points(a)
    bad = ~((raw > 0) & (raw < np.inf))
    for name in ("x", "y", "z", "range"):
        bits = np.ascontiguousarray(pts[name]).view(np.uint32)
        assert np.all(bits[bad] == 0x7FC00000), name
        assert not np.any(np.isnan(pts[name][~bad])), name
    assert pts["range"][3, 8] == np.float32(1e-45)


@needs_kernel
@pytest.mark.filterwarnings("ignore:overflow encountered in cast")   # f8 1e300 -> f4 +Inf
@pytest.mark.parametrize("range_dtype", ["f4", "f8", "u2", "u4", "i4", "u1", "i2"])
@pytest.mark.parametrize("extra_dtype", ["u1", "u2", "u4", "i1", "i2", "i4", "f4", "f8"])
def test_kernel_bit_identical_source_dtypes(tiny: tuple[Any, Any], range_dtype: str,
                                            extra_dtype: str) -> None:
    info, scan = tiny
    rng = np.random.default_rng(hash((range_dtype, extra_dtype)) % 2**32)
    shape = (int(info.height), int(info.width))
    kind = np.dtype(range_dtype)
    if kind.kind == "f":
        raw = rng.uniform(-5, 400, shape).astype(kind)
        raw.flat[:4] = [np.inf, -np.inf, np.nan, 0.0]
        raw.flat[4] = 1e300 if kind.itemsize == 8 else 3e38        # f8: overflows to +Inf
    else:
        top = min(np.iinfo(kind).max, 200_000)
        raw = rng.integers(max(np.iinfo(kind).min, -1000), top, shape).astype(kind)
        raw.flat[:3] = 0
    if np.dtype(extra_dtype).kind == "f":
        extra = (rng.standard_normal(shape) * 1e3).astype(extra_dtype)
        extra.flat[:2] = [np.nan, -np.inf]
    else:
        info_e = np.iinfo(extra_dtype)
        extra = rng.integers(info_e.min, info_e.max, shape, endpoint=True).astype(extra_dtype)
    for mult, offset in ((0.001, 0.0), (1.0, 0.0), (0.0037, -0.25), (2.0, 1.5)):
        info2 = lidarscan.make_info(**{**_fields(info), "range_multiplier": mult,
                                       "range_offset": offset})
        scan2 = lidarscan.make_scan(info2, {"range": raw, "intensity": extra}, 10**9,
                                    column_time_offsets=scan.column_time_offsets)
        for organized in (True, False):
            a, b, calls = kernel_and_numpy(scan2, info2, organized=organized)
            assert calls == 1
            assert_equivalent(a, b)
        if kind.kind == "f":
            break                                  # multiplier and offset apply to integers


@needs_kernel
def test_kernel_bit_identical_on_real_ouster_frame(os2: Any) -> None:
    _, frame, info, scan = os2
    cases: list[tuple[Any, dict[str, Any]]] = []
    for source in (scan, destaggered(scan, info)):
        for preset in ("ouster", "ouster_xyzi", "xyzi", "velodyne"):
            cases.append((source, {"preset": preset}))
        cases.append((source, {"organized": False}))
        cases.append((source, {"destagger": False, "threads": 2}))
    mm = frame["range_mm"].astype(np.uint32)
    cases.append((with_channels(scan, info, range=mm), {"preset": "ouster"}))
    cases.append((with_channels(scan, info, range=mm), {"organized": False}))
    for source, options in cases:
        a, b, calls = kernel_and_numpy(source, info, **options)
        assert calls >= 1, options
        assert_equivalent(a, b)
    # and the kernel's xyz is the projector's (float32, same formula) on the real geometry
    cloud = pc.PointCloud2Converter(info, kernel=True).convert(scan)
    ref = lidarscan.make_projector(info).project(scan, info)
    ref = lidarscan.make_projector(info).destagger(ref)
    assert_points_close(xyz_of(cloud), ref)


@needs_kernel
@settings(max_examples=40, deadline=None)
@given(height=st.integers(1, 6), width=st.integers(1, 300), seed=st.integers(0, 2**31 - 1),
       organized=st.booleans(), destagger=st.booleans(), staggered_input=st.booleans(),
       threads=st.integers(1, 3))
def test_kernel_random_scans(height: int, width: int, seed: int, organized: bool,
                             destagger: bool, staggered_input: bool, threads: int) -> None:
    rng = np.random.default_rng(seed)
    info = lidarscan.make_info(
        as_dataclass=True, stamp_ns=3, frame_id="f",
        vertical_angles=np.sort(rng.uniform(-0.5, 0.5, height))[::-1],
        horizontal_angles=rng.uniform(-np.pi, np.pi, width),
        beam_azimuth_offsets=rng.uniform(-0.1, 0.1, height),
        beam_origins=rng.normal(0, 0.02, 3 * height) * (rng.random(3 * height) < 0.7),
        lidar_to_sensor_transform=[1, 0, 0, 0.0, 0, 1, 0, -0.0, 0, 0, 1, 0.05, 0, 0, 0, 1],
        pixel_shift_by_row=rng.integers(-2 * width, 2 * width, height),
        column_time_increment=100)
    ranges = rng.uniform(0.0, 300, (height, width)).astype(np.float32)
    bad = rng.random((height, width))
    ranges[bad < 0.1] = np.inf
    ranges[(bad >= 0.1) & (bad < 0.15)] = np.nan
    ranges[(bad >= 0.15) & (bad < 0.2)] = 0
    ranges[(bad >= 0.2) & (bad < 0.25)] = -1
    intensity = rng.integers(0, 65535, (height, width)).astype(np.uint16)
    scan = lidarscan.make_scan(info, {"range": ranges, "intensity": intensity}, 10**9,
                               as_dataclass=True)
    if not staggered_input:
        scan = destaggered(scan, info)
    a, b, calls = kernel_and_numpy(scan, info, organized=organized, destagger=destagger,
                                   threads=threads)
    assert calls >= 1
    assert_equivalent(a, b)


def _kernel_oracle(out: bytearray, step: int, xoff: int, ranges: np.ndarray,
                   index: np.ndarray, d: np.ndarray, o: np.ndarray, extra: np.ndarray,
                   eoff: int, dense: bool) -> int:
    """The kernel's contract, one pixel at a time (float32 scalars: rounded product, rounded
    sum; canonical NaN for no return)."""
    nan = np.array([0x7FC00000], np.uint32).view(np.float32)[0]
    valid = 0
    for j in range(index.size):
        r = np.float32(ranges[index[j]])
        r = r if 0 < r < np.inf else nan
        if dense and np.isnan(r):
            continue
        p = (valid if dense else j) * step
        with np.errstate(invalid="ignore"):
            xyz = [np.float32(np.float32(r * d[j, k]) + o[j, k]) for k in range(3)]
        struct.pack_into("<3f", out, p + xoff, *xyz)
        struct.pack_into("<f", out, p + eoff, np.float32(extra[index[j]]))
        valid += not np.isnan(r)
    return valid


@needs_kernel
@pytest.mark.parametrize("dense", [False, True])
def test_kernel_contract_gather_unaligned_and_r_out(dense: bool) -> None:
    """lsk_project called directly: gather index, an odd point step and offset, r_out."""
    fn = kc.kernel().project
    rng = np.random.default_rng(11)
    n, step, xoff, eoff = 301, 23, 3, 17
    ranges = rng.uniform(-1, 80, n).astype(np.float32)
    ranges[::7] = np.inf
    ranges[::11] = np.nan
    index = rng.permutation(n).astype(np.int64)
    d = rng.standard_normal((n, 3)).astype(np.float32)
    o = (rng.standard_normal((n, 3)) * 0.05).astype(np.float32)
    extra = rng.integers(0, 2**32 - 1, n, dtype=np.uint32)
    out = np.zeros(n * step, np.uint8)
    r_out = np.full(n, -7, np.float32)
    count = fn(out.ctypes.data, step, xoff, 0, n, ranges.ctypes.data, 0, index.ctypes.data,
               None, 0, 0, 1.0, 0.0, d.ctypes.data, o.ctypes.data, extra.ctypes.data, 4, eoff,
               r_out.ctypes.data, int(dense))
    expected = bytearray(n * step)
    assert count == _kernel_oracle(expected, step, xoff, ranges, index, d, o, extra, eoff, dense)
    assert bytes(out) == bytes(expected)
    ok = (ranges[index] > 0) & (ranges[index] < np.inf)
    assert count == int(ok.sum())
    np.testing.assert_array_equal(r_out[ok], ranges[index][ok])
    assert np.all(r_out.view(np.uint32)[~ok] == 0x7FC00000)
    # a block in the middle (start > 0) touches only its own points
    out2 = np.zeros(n * step, np.uint8)
    fn(out2.ctypes.data, step, xoff, 100, 50, ranges.ctypes.data, 0, index.ctypes.data, None,
       0, 0, 1.0, 0.0, d.ctypes.data, o.ctypes.data, None, 0, 0, None, 0)
    assert not out2[:100 * step].any() and not out2[150 * step:].any()
    assert bytes(out2[100 * step:150 * step]).replace(b"\0", b"") != b""
    # an unknown type code is refused
    assert fn(out.ctypes.data, step, xoff, 0, n, ranges.ctypes.data, 99, None, None, 0, 0, 1.0,
              0.0, d.ctypes.data, o.ctypes.data, None, 0, 0, None, 0) == -1


@needs_kernel
def test_kernel_roll_matches_gather() -> None:
    """Rolled rows (the destagger fast path) read the same pixels as the equivalent gather."""
    fn = kc.kernel().project
    rng = np.random.default_rng(2)
    height, width = 5, 300                         # 300: runs cross the 256-pixel chunks
    n = height * width
    ranges = rng.uniform(0.5, 50, n).astype(np.float32)
    roll = rng.integers(0, width, height).astype(np.int64)
    roll[0] = 0
    cols = (np.arange(width)[None, :] - roll[:, None]) % width
    gather = (cols + np.arange(height)[:, None] * width).reshape(-1).astype(np.int64)
    d = rng.standard_normal((n, 3)).astype(np.float32)
    o = rng.standard_normal((n, 3)).astype(np.float32)
    extra = rng.integers(0, 60000, n).astype(np.uint16)
    outs = []
    for g, r in ((gather, None), (None, roll)):
        out = np.zeros(n * 16, np.uint8)
        for start in range(0, n, 700):             # blocks starting mid-row too
            fn(out.ctypes.data, 16, 0, start, min(700, n - start), ranges.ctypes.data, 0,
               None if g is None else g.ctypes.data, None if r is None else r.ctypes.data,
               width, 0, 1.0, 0.0, d.ctypes.data, o.ctypes.data, extra.ctypes.data, 3, 12,
               None, 0)
        outs.append(out.view(np.float32).reshape(n, 4))
    np.testing.assert_array_equal(outs[0], outs[1])
    np.testing.assert_array_equal(outs[1][:, 3], extra[gather].astype(np.float32))


def test_kernel_option_and_env_switch(tiny: tuple[Any, Any], monkeypatch: Any) -> None:
    info, _ = tiny
    with pytest.raises(ConfigError):
        pc.PointCloud2Converter(info, kernel="yes")  # type: ignore[arg-type]
    assert pc.PointCloud2Converter(info, kernel=False)._kfn is None
    monkeypatch.setenv("LIDARSCAN_NO_KERNEL", "1")
    assert kc.load() is None
    monkeypatch.setenv("LIDARSCAN_NO_KERNEL", "0")
    built = importlib.util.find_spec("converters._kernels._cloudkernel") is not None
    assert (kc.load() is not None) == built
    monkeypatch.setattr(kc, "ABI", kc.ABI + 1)   # a stale build is not used
    assert kc.load() is None


def fallback_case() -> tuple[Any, Any]:
    """(info, scan) of the LIDARSCAN_NO_KERNEL test, built alike in the test and its child."""
    info = lidarscan.make_info(
        stamp_ns=7, frame_id="lidar", vertical_angles=np.radians([10.0, 3.0, -3.0, -10.0]),
        horizontal_angles=2 * np.pi * (1 - np.arange(12) / 12),
        beam_origins=np.linspace(-0.02, 0.02, 12), pixel_shift_by_row=[3, 2, 1, 0],
        column_time_increment=1000)
    rng = np.random.default_rng(5)
    ranges = rng.uniform(0.5, 50, (4, 12)).astype(np.float32)
    ranges[0, 1], ranges[1, 2], ranges[2, 3], ranges[3, 4] = np.inf, np.nan, 0.0, -np.inf
    scan = lidarscan.make_scan(
        info, {"range": ranges, "intensity": rng.integers(0, 999, (4, 12)).astype(np.uint16)},
        10**9)
    return info, scan


_NO_KERNEL_SCRIPT = """
import hashlib, sys
import numpy as np
import lidarscan
from converters import pointcloud2 as pc
from converters._kernels import cloud as kc
from lidarscan.errors import ConfigError
sys.path.insert(0, sys.argv[1])
from test_pointcloud2 import destaggered, fallback_case
info, scan = fallback_case()
assert not pc.kernel_available()
try:
    pc.PointCloud2Converter(info, kernel=True)
    raise SystemExit("kernel=True accepted without a kernel")
except ConfigError:
    pass
conv = pc.PointCloud2Converter(info)
assert conv._kfn is None
for source in (scan, destaggered(scan, info)):
    for options in ({}, {"organized": False}, {"preset": "ouster"}, {"preset": "velodyne"}):
        cloud = pc.PointCloud2Converter(info, **options).convert(source)
        print(hashlib.sha256(bytes(cloud.data)).hexdigest(), cloud.height, cloud.width)
"""


def test_numpy_fallback_with_no_kernel_env(tmp_path: Path) -> None:
    """LIDARSCAN_NO_KERNEL=1: the kernel is not loaded; the child's clouds are the same bytes
    as numpy's here (and equivalent to the kernel's)."""
    import hashlib
    import os

    env = {**os.environ, "LIDARSCAN_NO_KERNEL": "1"}
    script = tmp_path / "child.py"
    script.write_text(_NO_KERNEL_SCRIPT)
    out = subprocess.run([sys.executable, str(script), str(Path(__file__).parent)], env=env,
                         capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == 0, out.stderr
    child = out.stdout.split("\n")[:-1]
    assert len(child) == 8
    info, scan = fallback_case()
    mine = []
    for source in (scan, destaggered(scan, info)):
        for options in ({}, {"organized": False}, {"preset": "ouster"}, {"preset": "velodyne"}):
            cloud = pc.PointCloud2Converter(info, **options).convert(source)
            ref = pc.PointCloud2Converter(info, kernel=False, **options).convert(source)
            mine.append(f"{hashlib.sha256(bytes(ref.data)).hexdigest()} {ref.height} "
                        f"{ref.width}")
            assert_equivalent(cloud, ref)
    assert child == mine
    # and the fallback is correct, not just consistent: x, y, z of the projector
    cloud = pc.PointCloud2Converter(info, kernel=False).convert(scan)
    proj = lidarscan.make_projector(info)
    np.testing.assert_allclose(xyz_of(cloud), proj.destagger(proj.project(scan, info)),
                               atol=1e-5, equal_nan=True)


@needs_kernel
def test_kernel_bit_identical_with_signed_zero_tables(tiny: tuple[Any, Any], monkeypatch: Any
                                                      ) -> None:
    """Directions / offsets with -0 (x + iy as one complex product in numpy would round the
    sign of zero differently from per-axis r * D + O without the +0 normalisation)."""
    info, scan = tiny
    height, width = int(info.height), int(info.width)
    signs = np.array([0.0, -0.0, 1.0, -1.0], np.float32)
    grid = np.stack(np.meshgrid(signs, signs, signs, indexing="ij"), -1).reshape(-1, 3)
    d = np.resize(grid, (height * width, 3)).reshape(height, width, 3)
    o = np.full((height, width, 3), -0.0, np.float32)           # -0 offsets, some +-0.25
    o[::2, ::3] = np.float32(0.25) * np.sign(d[::2, ::3] - np.float32(0.5))
    proj = lidarscan.make_projector(info)
    monkeypatch.setattr(proj, "tables", lambda destaggered=False: (d, o))
    monkeypatch.setattr(proj, "factors", lambda *args: None)       # the kernel's table form
    for organized in (True, False):
        a, b, calls = kernel_and_numpy(scan, info, organized=organized, destagger=False)
        assert calls == 1
        assert_identical(a, b)
    pts = pc.read_points(a)
    ok = np.isfinite(pts["x"][0])
    assert not np.any(np.signbit(pts["x"][0][ok]) & (pts["x"][0][ok] == 0))


def factored_oracle(info: Any, metres: np.ndarray, grid_destaggered: bool,
                    azimuths: Any = None) -> np.ndarray:
    """The factored kernel's arithmetic in numpy float32, operation by operation (see
    lsk_rc_xyz in converters/_cloudkernel.c): (H, W, 3) points of grid-order ranges ``metres``
    (float32, NaN = no return)."""
    from lidarscan.geometry import beam_factors

    rows, cols, const = (a.astype(np.float32) for a in beam_factors(info, azimuths))
    height, width = metres.shape
    c = np.broadcast_to(np.arange(width), (height, width))
    if grid_destaggered:
        shifts = np.asarray(lidarscan.make_projector(info).shifts)
        c = (np.arange(width)[None, :] - shifts[:, None]) % width
    r = metres.astype(np.float32)
    q = [rows[:, k, None] + r * rows[:, 3 + k, None] for k in range(3)]
    out = np.empty((height, width, 3), np.float32)
    for k in range(3):
        out[..., k] = ((cols[2 * k][c] * q[0] + cols[2 * k + 1][c] * q[1])
                       + (const[k] * q[2] + const[3 + k]))
    return out


@needs_kernel
@settings(max_examples=40, deadline=None)
@given(height=st.integers(1, 5), width=st.integers(1, 600), seed=st.integers(0, 2**31 - 1),
       destagger=st.booleans(), staggered_input=st.booleans(), measured=st.booleans(),
       range_dtype=st.sampled_from(["f4", "f8", "u2", "u4", "i4", "u1", "i2"]),
       extra_dtype=st.sampled_from(["u1", "u2", "u4", "i1", "i2", "i4", "f4", "f8"]),
       organized=st.booleans(), threads=st.integers(1, 3),
       layout=st.sampled_from([("x", "y", "z"), ("x", "y", "z", "intensity"),
                               ("x", "y", "z", "intensity", "ring"),
                               ("intensity", "x", "y", "z")]))
def test_factored_kernel_is_bit_exact_to_its_float32_oracle(
        height: int, width: int, seed: int, destagger: bool, staggered_input: bool,
        measured: bool, range_dtype: str, extra_dtype: str, organized: bool, threads: int,
        layout: tuple[str, ...]) -> None:
    """lsk_project_rc, through the converter: every byte of x, y, z equals the numpy oracle of
    its arithmetic (rows over several runs and chunks, column wrap-around of the destagger, a
    scan's measured azimuths, every source type, integer ranges with multiplier and offset,
    dense output; the layouts with the channel right after z, 16 and 18 bytes per point, take
    the 16-pixel AVX-512 path, which converts the sources itself, where the CPU has it)."""
    rng = np.random.default_rng(seed)
    integer = np.dtype(range_dtype).kind != "f"
    yaw = rng.uniform(-np.pi, np.pi)
    tilt = rng.uniform(-0.3, 0.3)
    rot = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    rot = rot @ np.array([[1, 0, 0], [0, np.cos(tilt), -np.sin(tilt)],
                          [0, np.sin(tilt), np.cos(tilt)]])
    transform = np.eye(4)
    transform[:3, :3], transform[:3, 3] = rot, rng.normal(0, 0.1, 3)
    info = lidarscan.make_info(
        as_dataclass=True, stamp_ns=3, frame_id="f",
        vertical_angles=np.sort(rng.uniform(-0.5, 0.5, height))[::-1],
        horizontal_angles=np.sort(rng.uniform(-np.pi, np.pi, width))[::-1],
        beam_azimuth_offsets=rng.uniform(-0.1, 0.1, height),
        beam_origins=rng.normal(0, 0.02, 3 * height), beam_range_offsets=rng.normal(0, 0.01,
                                                                                    height),
        lidar_to_sensor_transform=transform.ravel(),
        pixel_shift_by_row=rng.integers(-2 * width, 2 * width, height),
        range_multiplier=0.004 if integer else 1.0, range_offset=-0.5 if integer else 0.0,
        column_time_increment=100)
    kind = np.dtype(range_dtype)
    if integer:
        limits = np.iinfo(kind)
        raw = rng.integers(max(limits.min, -1000), min(limits.max, 100_000), (height, width),
                           endpoint=True).astype(kind)
        raw[rng.random((height, width)) < 0.1] = 0
        metres = raw.astype(np.float32) * np.float32(0.004) + np.float32(-0.5)
        metres[raw == 0] = np.nan
    else:
        raw = rng.uniform(-5.0, 400, (height, width)).astype(kind)
        raw[rng.random((height, width)) < 0.1] = np.inf
        raw[rng.random((height, width)) < 0.05] = np.nan
        raw[rng.random((height, width)) < 0.05] = 0.0          # zero: no return
        raw[rng.random((height, width)) < 0.02] = -0.0
        raw[rng.random((height, width)) < 0.02] = -np.inf
        with np.errstate(invalid="ignore"):
            r32 = raw.astype(np.float32)
            metres = np.where((r32 > 0) & (r32 < np.inf), r32, np.float32(np.nan))
        metres = metres.astype(np.float32)
    azimuths = rng.uniform(-np.pi, np.pi, width) if measured else None
    if np.dtype(extra_dtype).kind == "f":
        intensity = (rng.standard_normal((height, width)) * 1e3).astype(extra_dtype)
    else:
        limits = np.iinfo(extra_dtype)
        intensity = rng.integers(limits.min, limits.max, (height, width),
                                 endpoint=True).astype(extra_dtype)
    scan = lidarscan.make_scan(info, {"range": raw, "intensity": intensity}, 10**9,
                               as_dataclass=True, column_azimuth_angles=azimuths)
    proj = lidarscan.make_projector(info)
    if not staggered_input:
        scan = lidarscan.make_scan(info, {"range": proj.destagger(raw),
                                          "intensity": proj.destagger(intensity)}, 10**9,
                                   as_dataclass=True, is_destaggered=True,
                                   column_azimuth_angles=azimuths)
    grid_dest = destagger and bool(np.any(proj.shifts % width))
    conv = pc.PointCloud2Converter(info, fields=layout, organized=organized,
                                   destagger=destagger, threads=threads, kernel=True)
    spy = _Spy(conv._kfn.project_rc)
    conv._kfn = kc.Kernels(conv._kfn.project, spy)
    cloud = conv.convert(scan)
    assert spy.calls >= 1
    expected = factored_oracle(info, proj.destagger(metres) if grid_dest else metres, grid_dest,
                               azimuths).reshape(-1, 3)
    inten = (proj.destagger(intensity) if grid_dest else intensity).reshape(-1)
    if not organized:
        keep = ~np.isnan(expected[:, 0])
        expected, inten = expected[keep], inten[keep]
    pts = pc.read_points(cloud).reshape(-1)
    got = np.stack([pts[n] for n in "xyz"], -1)
    np.testing.assert_array_equal(got.view(np.uint32), expected.view(np.uint32))
    if "intensity" in layout:
        np.testing.assert_array_equal(pts["intensity"].view(np.uint32),
                                      inten.astype(np.float32).view(np.uint32))


@needs_kernel
def test_factored_kernel_on_real_frame_is_within_a_tenth_of_a_millimetre(os2: Any) -> None:
    """The kernel's cloud of a real OS-2 frame against the float64 beam model, every pixel."""
    _, frame, info, scan = os2
    cloud = pc.PointCloud2Converter(info, kernel=True).convert(scan)
    exact = lidarscan.geometry.exact_xyz(info, lidarscan.range_m(scan, info))
    exact = lidarscan.make_projector(info).destagger(exact)
    got = xyz_of(cloud)
    ok = ~np.isnan(exact[..., 0])
    np.testing.assert_array_equal(np.isnan(got[..., 0]), ~ok)
    assert ok.sum() > 0.5 * ok.size
    assert np.abs(got[ok] - exact[ok]).max() < 5e-5                 # measured ~2e-5 m


@needs_kernel
def test_per_pixel_angles_use_the_table_kernel_bit_identical_to_numpy(
        tiny: tuple[Any, Any]) -> None:
    info, scan = tiny
    height, width = int(info.height), int(info.width)
    rng = np.random.default_rng(9)
    fields = {f: getattr(info, f) for f in info.get_fields_and_field_types()}
    fields.pop("header")
    fields.update(stamp_ns=7, frame_id="lidar",
                  pixel_azimuth_angles=rng.uniform(-np.pi, np.pi, height * width),
                  pixel_altitude_angles=rng.uniform(-0.3, 0.3, height * width))
    pinfo = lidarscan.make_info(**fields)
    assert lidarscan.make_projector(pinfo).factors() is None
    for organized in (True, False):
        conv = pc.PointCloud2Converter(pinfo, kernel=True, organized=organized)
        spies = _Spy(conv._kfn.project), _Spy(conv._kfn.project_rc)
        conv._kfn = kc.Kernels(*spies)
        cloud = conv.convert(scan)
        assert (spies[0].calls, spies[1].calls) == (1, 0)
        assert_identical(cloud, pc.PointCloud2Converter(pinfo, kernel=False,
                                                        organized=organized).convert(scan))


# ------------------------------------------------------------------ output buffer recycling

@pytest.mark.parametrize("kernel", [None, False])
def test_dropped_message_buffer_is_recycled_and_fully_rewritten(tiny: tuple[Any, Any],
                                                                 kernel: bool | None) -> None:
    info, scan = tiny
    other = with_channels(scan, info, range=np.asarray(lidarscan.channel(scan, "range")) * 2)
    for preset in (None, "ouster_xyzi", "velodyne"):
        organized = {"velodyne": True}.get(preset or "", None)
        expected = [bytes(pc.PointCloud2Converter(info, preset=preset, organized=organized,
                                                  kernel=kernel).convert(s).data)
                    for s in (scan, other)]
        conv = pc.PointCloud2Converter(info, preset=preset, organized=organized, kernel=kernel)
        cloud = conv.convert(scan)
        first_id = id(cloud.data)
        data = cloud.data
        data[:] = array_of(b"\xa5" * len(data))          # a consumer scribbles, then drops it
        del cloud, data
        cloud = conv.convert(other)
        if preset == "velodyne":                         # firing order: copied out, new
            assert conv._spares == []
        else:                                            # (the pool keeps the id unique)
            assert cloud.data is conv._spares[0] and id(cloud.data) == first_id, preset
        assert bytes(cloud.data) == expected[1]
        kept = cloud
        again = conv.convert(scan)                       # kept still referenced: a new buffer
        assert again.data is not kept.data
        assert bytes(kept.data) == expected[1] and bytes(again.data) == expected[0]


def test_recycling_pool_serves_a_caller_that_keeps_the_last_messages(
        tiny: tuple[Any, Any]) -> None:
    info, scan = tiny
    conv = pc.PointCloud2Converter(info)
    expected = bytes(pc.PointCloud2Converter(info).convert(scan).data)
    kept: list[Any] = []
    ids = []
    for _ in range(12):                                  # the caller keeps the last two
        cloud = conv.convert(scan)
        assert bytes(cloud.data) == expected
        assert all(cloud.data is not k.data for k in kept)
        ids.append(id(cloud.data))
        kept = [*kept, cloud][-2:]
        del cloud
    assert len(set(ids[3:])) == pc._POOL                 # three buffers take turns, no more
    assert len(conv._spares) <= pc._POOL


def array_of(data: bytes) -> Any:
    import array
    return array.array("B", data)


def test_buffer_held_through_a_view_is_not_recycled(tiny: tuple[Any, Any]) -> None:
    info, scan = tiny
    conv = pc.PointCloud2Converter(info)
    view = np.frombuffer(conv.convert(scan).data, np.uint8)   # the message is gone, a view stays
    snapshot = view.copy()
    other = with_channels(scan, info, range=np.asarray(lidarscan.channel(scan, "range")) + 1)
    conv.convert(other)
    np.testing.assert_array_equal(view, snapshot)


def test_layouts_with_padding_never_recycle(tiny: tuple[Any, Any]) -> None:
    info, scan = tiny
    conv = pc.PointCloud2Converter(info, preset="ouster")      # 48-byte points with padding
    ids = set()
    for _ in range(3):
        cloud = conv.convert(scan)
        ids.add(id(cloud.data))
        assert conv._spares == []
        assert not any(np.frombuffer(cloud.data, np.uint8).reshape(-1, 48)[:, 12:16].ravel())
        del cloud


def test_cloud_messages_equal_normally_built_ones(tiny: tuple[Any, Any]) -> None:
    """The converter fills message slots directly (converters._rosmsg.bare_message): the result
    must equal the message rosidl's constructor builds from the same values."""
    from sensor_msgs.msg import PointCloud2

    from converters._rosmsg import bare_message

    info, scan = tiny
    cloud = pc.to_pointcloud2(scan, info, preset="ouster")
    normal = PointCloud2(header=cloud.header, height=cloud.height, width=cloud.width,
                         fields=list(cloud.fields), is_bigendian=cloud.is_bigendian,
                         point_step=cloud.point_step, row_step=cloud.row_step,
                         data=bytes(cloud.data), is_dense=cloud.is_dense)
    assert cloud == normal
    kind = "sensor_msgs/msg/PointCloud2"             # (rclpy leaves padding uninitialised)
    assert lidarscan.encode(cloud, kind) == lidarscan.encode(normal, kind)
    assert cloud._check_fields == normal._check_fields     # honours ROS_PYTHON_CHECK_FIELDS
    with pytest.raises(ConversionError, match="height"):
        bare_message(PointCloud2, width=3)                  # every field or nothing


# ------------------------------------------- optional channels and byte order (issue 17)

def convert(scan: Any, info: Any, **options: Any) -> Any:
    return pc.PointCloud2Converter(info, **options).convert(scan)


@pytest.mark.parametrize("kernel", [False, pytest.param(True, marks=needs_kernel)])
def test_range_only_scan_with_the_defaults_and_every_preset(tiny: tuple[Any, Any],
                                                            kernel: bool) -> None:
    """A valid scan with only a range channel converts with the defaults (x, y, z) and with
    every preset: the preset's channel fields it cannot fill are zero (documented)."""
    info, scan = tiny
    only = lidarscan.make_scan(info, {"range": lidarscan.channel(scan, "range")},
                               lidarscan.to_ns(scan.header.stamp),
                               column_time_offsets=scan.column_time_offsets)
    cloud = convert(only, info, kernel=kernel)
    assert [f.name for f in cloud.fields] == ["x", "y", "z"]
    plain = convert(scan, info, fields=("x", "y", "z"), kernel=kernel)
    np.testing.assert_array_equal(xyz_of(cloud), xyz_of(plain))
    for name, preset in pc.PRESETS.items():
        cloud = convert(only, info, preset=name, kernel=kernel)
        pts = pc.read_points(cloud)
        for spec in preset.fields:
            if spec.source == "channel":
                assert not np.any(pts[spec.name]), (name, spec.name)
    with pytest.raises(UnknownChannelError):                   # named explicitly: required
        convert(only, info, fields=("x", "y", "z", "intensity"), kernel=kernel)


@pytest.mark.parametrize("range_dtype", ["f4", "f8", "u2", "u4"])
@pytest.mark.parametrize("kernel", [False, pytest.param(True, marks=needs_kernel)])
def test_big_endian_scans_give_identical_clouds(tiny: tuple[Any, Any], range_dtype: str,
                                                kernel: bool) -> None:
    """Byte order is a property of the message: big- and little-endian scans with every channel
    datatype give byte-identical clouds on each path (the kernel runs for both), and the
    caller's buffer is left alone."""
    info, scan = tiny
    rng = np.random.default_rng(11)
    shape = (int(info.height), int(info.width))
    r = np.asarray(lidarscan.channel(scan, "range"))
    info2 = lidarscan.make_info(**{**_fields(info), "range_multiplier": 0.001})
    if np.dtype(range_dtype).kind == "f":
        ranges = r.astype(range_dtype)
    else:
        ranges = np.where(np.isfinite(r) & (r > 0), np.round(r * 1000), 0).astype(range_dtype)
    channels: dict[str, Any] = {"range": ranges}
    for dtype in ("u1", "u2", "u4", "i1", "i2", "i4", "f4", "f8"):
        kind = np.dtype(dtype)
        channels["c_" + dtype] = (rng.uniform(-1e3, 1e3, shape).astype(kind) if kind.kind == "f"
                                  else rng.integers(np.iinfo(kind).min, np.iinfo(kind).max,
                                                    shape, endpoint=True).astype(kind))
    fields = ("x", "y", "z", "range", "t", *[n for n in channels if n != "range"])
    clouds = {}
    for intensity in ("c_u2", "c_f8", "c_i1"):                 # the kernel's one channel field
        chans = {**channels, "intensity": channels[intensity]}
        for big in (False, True):
            one = lidarscan.make_scan(info2, chans, 10**9, is_bigendian=big,
                                      column_time_offsets=scan.column_time_offsets)
            before = bytes(one.data)
            conv = pc.PointCloud2Converter(info2, kernel=kernel, fields=("intensity", *fields))
            if kernel:
                spies = _Spy(conv._kfn.project), _Spy(conv._kfn.project_rc)
                conv._kfn = kc.Kernels(*spies)
            clouds[big] = conv.convert(one)
            if kernel:
                assert spies[0].calls + spies[1].calls == 1
            assert bytes(one.data) == before
            for preset in ("ouster", "hesai"):
                clouds[big, preset] = convert(one, info2, preset=preset, kernel=kernel)
        assert_identical(clouds[False], clouds[True])
        for preset in ("ouster", "hesai"):
            assert_identical(clouds[False, preset], clouds[True, preset])


# ----------------------------------------------------------- per-pixel delays (channel "t")

@pytest.mark.parametrize("scan_destaggered", [False, True])
@pytest.mark.parametrize("grid_destagger", [False, True])
def test_per_pixel_delay_channel_adds_to_every_pixel_time(
        tiny: tuple[Any, Any], scan_destaggered: bool, grid_destagger: bool) -> None:
    """A scan's integer ``t`` channel (irregular pixel timing, e.g. the Hesai PandarQT128) is
    added to each pixel's column + beam time: by the projector and in the cloud's ``t`` field,
    whatever order the scan is stored in and the cloud is laid out in. Oracle: a loop over
    measurement pixels."""
    info, scan = tiny
    height, width = int(info.height), int(info.width)
    delays = np.random.default_rng(3).integers(0, 50_000, (height, width)).astype(np.int32)
    cot, bto = np.asarray(scan.column_time_offsets), np.asarray(info.beam_time_offsets)
    expected = np.empty((height, width), np.int64)               # measurement order
    for u in range(height):
        for c in range(width):
            expected[u, c] = int(cot[c]) + int(bto[u]) + int(delays[u, c])
    proj = lidarscan.make_projector(info)
    channels = {c.name: lidarscan.channel(scan, c.name) for c in scan.channels}
    channels["t"] = delays
    if scan_destaggered:
        channels = {n: proj.destagger(v) for n, v in channels.items()}
    with_t = lidarscan.make_scan(info, channels, lidarscan.to_ns(scan.header.stamp),
                                 is_destaggered=scan_destaggered, column_time_offsets=cot)
    stored = proj.destagger(expected) if scan_destaggered else expected
    assert np.array_equal(proj.pixel_times(with_t), stored)
    cloud = pc.to_pointcloud2(with_t, info, fields=("x", "y", "z", "t"), organized=True,
                              destagger=grid_destagger)
    got = np.array([p["t"] for p in loop_read(cloud)], np.int64).reshape(height, width)
    assert np.array_equal(got, proj.destagger(expected) if grid_destagger else expected)
    # without the channel the same cloud has the column + beam times only
    plain = pc.to_pointcloud2(scan, info, fields=("x", "y", "z", "t"), organized=True,
                              destagger=grid_destagger)
    base = np.array([p["t"] for p in loop_read(plain)], np.int64).reshape(height, width)
    assert np.array_equal(got - base, proj.destagger(delays) if grid_destagger else delays)
