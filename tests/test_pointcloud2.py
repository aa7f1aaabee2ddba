"""LidarScan <-> PointCloud2 (converters.pointcloud2.converter).

Layers: exact preset layouts (pinned from the driver sources named in prior-art); a slow
struct.unpack reader written here as the oracle for values; an independent numpy version of the
ouster-ros point formula (prior-art (b): xyz = 0.001 (r R dir + R off + t)) applied to REAL Ouster
frames; round trips; Hypothesis properties over random small scans; output buffer recycling,
optional channels, byte order and per-pixel delays. The oracles and fixtures are in
``cloud_oracles.py``; the import path (from_pointcloud2) is tested in ``test_cloud_import.py``,
the compiled kernel in ``test_pointcloud2_kernel.py``.
"""

from __future__ import annotations

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

from converters.pointcloud2 import converter as pc
from converters._kernels import cloud as kc
from cloud_oracles import (  # noqa: E402  (os2, tiny: fixtures)
    F32,
    F64,
    U16,
    U32,
    Spy,
    assert_identical,
    assert_points_close,
    destaggered,
    fields_of,
    info_fields,
    loop_read,
    needs_kernel,
    os2,  # noqa: F401 (fixture)
    ouster_ros_cloud,
    tiny,  # noqa: F401 (fixture)
    with_channels,
    xyz_of,
)


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
    info = lidarscan.make_info(**{**info_fields(info), "range_multiplier": 0.001})
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


def test_second_return_cloud_reads_the_second_returns_channels(tiny: tuple[Any, Any]) -> None:
    """range_channel="range2": intensity comes from intensity2 (the same return), a channel
    measured once per pixel (ambient) is shared; each field checked against its source."""
    info, scan = tiny
    rng_m = np.asarray(lidarscan.channel(scan, "range"))
    inten = np.asarray(lidarscan.channel(scan, "intensity"), dtype=np.float32)
    ambient = np.arange(inten.size, dtype=np.uint16).reshape(inten.shape)
    chans = {"range": rng_m, "intensity": inten, "range2": rng_m * 1.5,
             "intensity2": inten + 1000.0, "ambient": ambient}
    dual = lidarscan.make_scan(info, chans, 5_000_000_123,
                               column_time_offsets=scan.column_time_offsets)
    proj = lidarscan.make_projector(info)
    for name, want in (("range", inten), ("range2", inten + 1000.0)):
        pts = pc.read_points(pc.to_pointcloud2(dual, info, range_channel=name,
                                               fields=("x", "y", "z", "intensity", "ambient")))
        np.testing.assert_array_equal(pts["intensity"], proj.destagger(want))
        np.testing.assert_array_equal(pts["ambient"], proj.destagger(ambient))


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
    other = lidarscan.make_info(**{**info_fields(info), "stamp_ns": 8})
    with pytest.raises(LinkageError):
        pc.to_pointcloud2(scan, other)
    early = lidarscan.make_info(**{**info_fields(info), "beam_time_offsets": [-500, 0, 0, 0]})
    escan = lidarscan.make_scan(early, {"range": np.ones((4, 12), np.float32)}, 0)
    with pytest.raises(ConversionError):                  # t is u32 ns >= 0 after the stamp
        pc.to_pointcloud2(escan, early, preset="ouster")
    cloud = pc.to_pointcloud2(escan, early, preset="ouster", time_reference="first")
    assert pc.read_points(cloud)["t"].min() == 0


def test_import_does_not_load_rclpy() -> None:
    code = ("import sys, converters.pointcloud2.converter, converters.shared.deskew; "
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
    """The converter fills message slots directly (lidarscan.rosmsg.bare_message): the result
    must equal the message rosidl's constructor builds from the same values."""
    from sensor_msgs.msg import PointCloud2

    from lidarscan.rosmsg import bare_message

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
    info2 = lidarscan.make_info(**{**info_fields(info), "range_multiplier": 0.001})
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
                spies = Spy(conv._kfn.project), Spy(conv._kfn.project_rc)
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
