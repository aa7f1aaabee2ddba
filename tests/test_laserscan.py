"""Height slices of LidarScans: against a plain-loop oracle, physics of a synthetic room, and
every convention (REP 117 classes, inclusive limits, ties, staggering, time fields, errors).

``ref_slice`` below is written from the rules in converters/slices/spec.py, one pixel at a time.
Scenes are ray-cast analytically from the projector's own beam tables, so a point's height and
range are known exactly.
"""

from __future__ import annotations

import array
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

import lidarscan
from converters.slices.converter import SliceConverter, SliceSpec, to_laserscan
from lidarscan.errors import ConfigError, InfoMismatchError, LinkageError, UnknownChannelError
from grid_reference import pose, ref_slice
from helpers import numba_usable

TWO_PI = 2 * math.pi  # as in grid_reference
F32 = np.float32


# --------------------------------------------------------------------------- reference code

# ------------------------------------------------------------------------------- scenes

def make_sensor(height: int = 16, width: int = 128, *, fov: float = 30.0, origins: bool = True,
                shifts: bool = False, stamp: int = 7_000_000_000, **fields: Any) -> Any:
    """An Ouster-like LidarInfo: CW columns, small beam azimuth offsets and origins."""
    inc = TWO_PI / width
    beta = np.where(np.arange(height) % 2 == 0, 0.3, -0.2) * inc
    extra: dict[str, Any] = {"beam_azimuth_offsets": beta, "range_min": 0.1, "range_max": 120.0,
                                 "column_time_increment": 100_000_000 // width}
    if origins:
        n = 0.015
        extra["beam_origins"] = np.stack([n * np.cos(beta), -n * np.sin(beta),
                                          np.zeros(height)], 1).reshape(-1)
        extra["beam_range_offsets"] = np.full(height, -n)
        extra["lidar_to_sensor_transform"] = pose(z=0.036, yaw=math.pi).reshape(-1)
    if shifts:
        extra["pixel_shift_by_row"] = np.array([(3 * u) % 7 for u in range(height)], np.int32)
    extra.update(fields)
    return lidarscan.make_info(
        stamp_ns=stamp, frame_id="os_sensor",
        vertical_angles=np.radians(np.linspace(fov / 2, -fov / 2, height)),
        horizontal_angles=TWO_PI * (1 - np.arange(width) / width), as_dataclass=True, **extra)


ROOM = (np.array([-4.0, -3.0, 0.0]), np.array([4.0, 3.0, 2.5]))
SOLIDS = [(np.array([1.0, -0.5, 0.70]), np.array([2.0, 0.5, 0.75])),      # table top
          (np.array([-2.0, 1.0, 0.0]), np.array([-1.7, 1.3, 2.5]))]       # pillar


def raycast(o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Range along unit rays (N, 3) from origins (N, 3) to the room's walls or a solid."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1, t2 = (ROOM[0] - o) * inv, (ROOM[1] - o) * inv
        best = np.nanmin(np.maximum(t1, t2), axis=1)                   # exit of the room
        for lo, hi in SOLIDS:
            a, b = (lo - o) * inv, (hi - o) * inv
            t_in = np.nanmax(np.minimum(a, b), axis=1)
            t_out = np.nanmin(np.maximum(a, b), axis=1)
            hit = (t_in <= t_out) & (t_in > 0)
            best = np.where(hit & (t_in < best), t_in, best)
    return best


def room_scan(info: Any, ext: np.ndarray, *, rng: np.random.Generator | None = None,
              stamp: int = 10**9, destagger: bool = False, specials: bool = True,
              intensity_dtype: Any = np.float32) -> Any:
    """The room seen by ``info`` mounted at ``ext`` in the room frame (measurement order)."""
    proj = lidarscan.make_projector(info)
    d = proj.directions.reshape(-1, 3).astype(np.float64)
    o = proj.offsets.reshape(-1, 3).astype(np.float64)
    dw = d @ ext[:3, :3].T
    ow = o @ ext[:3, :3].T + ext[:3, 3]
    r = raycast(ow, dw / np.linalg.norm(dw, axis=1)[:, None]).reshape(proj.height, proj.width)
    r = r.astype(np.float32)
    rng = rng or np.random.default_rng(1)
    if specials:
        flat = r.reshape(-1)
        pick = rng.choice(flat.size, size=flat.size // 10, replace=False)
        kinds = np.array([np.inf, np.nan, -np.inf, 0.0], np.float32)
        flat[pick] = kinds[np.arange(pick.size) % 4]
    inten = rng.integers(0, 4000, r.shape).astype(intensity_dtype)
    channels = {"range": r, "intensity": inten}
    if destagger:
        channels = {k: proj.destagger(v) for k, v in channels.items()}
    return lidarscan.make_scan(info, channels, stamp, is_destaggered=destagger,
                               as_dataclass=True)


def arrays(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    return np.array(msg.ranges, np.float32), np.array(msg.intensities, np.float32)


def assert_same(msg: Any, ref: tuple[np.ndarray, np.ndarray]) -> None:
    got = arrays(msg)
    np.testing.assert_array_equal(got[0], ref[0])
    np.testing.assert_array_equal(got[1], ref[1])


MOUNTS = {
    "level": pose(z=0.5),
    "tilted": pose(z=1.0, pitch=math.radians(20)),
    "upside_down": pose(z=1.5, roll=math.pi, yaw=0.3),
    "offset": pose(x=0.3, y=0.1, z=0.6, yaw=0.4),
}
BANDS = {"floor_to_knee": (0.05, 0.5), "table": (0.6, 0.8), "above": (0.9, 2.0)}


@pytest.fixture(scope="module")
def sensor() -> Any:
    return make_sensor()


BACKENDS = ["numpy", pytest.param("numba", marks=pytest.mark.skipif(
    not numba_usable(), reason="numba is not installed or LIDARSCAN_NUMBA=0"))]


def backends() -> list[str]:
    """Backends available here (for loops inside Hypothesis tests)."""
    return ["numpy"] + (["numba"] if numba_usable() else [])


# ------------------------------------------------------------------ oracle on the room scene

@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("mount", list(MOUNTS))
def test_slices_match_the_reference(sensor: Any, mount: str, backend: str) -> None:
    ext = MOUNTS[mount]
    scan = room_scan(sensor, ext)
    conv = SliceConverter(sensor, {k: SliceSpec(*v) for k, v in BANDS.items()}, extrinsics=ext,
                          frame_id="base_link", backend=backend)
    out = conv.convert(scan)
    assert list(out) == list(BANDS)
    for name, (zmin, zmax) in BANDS.items():
        assert_same(out[name], ref_slice(scan, sensor, zmin=zmin, zmax=zmax, ext=ext))
        assert out[name].header.frame_id == "base_link"


@pytest.mark.skipif(not numba_usable(),
                    reason="numba is not installed or LIDARSCAN_NUMBA=0")
@pytest.mark.parametrize("mount", ["level", "tilted", "offset"])
def test_compiled_paths_agree(sensor: Any, mount: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """The compiled kernels have three drivers: the bin-ordered kernel (one grid, shared range
    limits), and without it one call for small inputs and three passes for large ones; all
    match the oracle."""
    from converters._kernels import slices_numba as _grid
    ext = MOUNTS[mount]
    scan = room_scan(sensor, ext)
    grids = {"default": {}, "sector": {"angle_min": -2.0, "angle_max": 1.5, "angle_increment": 0.03}}
    for sorted_path in (True, False):
        for small in ((1 << 30, 0) if not sorted_path else (1 << 30,)):
            monkeypatch.setattr(_grid, "_SMALL", small)
            for name, kw in grids.items():
                conv = SliceConverter(sensor, {"a": SliceSpec(0.05, 0.5),
                                               "b": SliceSpec(0.3, 1.5)},
                                      extrinsics=ext, frame_id="b", backend="numba", **kw)
                tables = conv._tables_for(scan)
                assert tables.sorted is not None
                if not sorted_path:
                    tables.sorted = None
                out = conv.convert(scan)
                for key, (zmin, zmax) in (("a", (0.05, 0.5)), ("b", (0.3, 1.5))):
                    ref = ref_slice(scan, sensor, zmin=zmin, zmax=zmax, ext=ext,
                                    amin=kw.get("angle_min", -math.pi),
                                    amax=kw.get("angle_max"), inc=kw.get("angle_increment"))
                    assert_same(out[key], ref)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("n_slices", [5, 10])
def test_many_slices_in_one_pass(sensor: Any, backend: str, n_slices: int) -> None:
    """More slices than one block of the bin-ordered kernel (4) and than 8 qualifier bits, on
    a sector seen from an offset mount (points that need atan2) with specials in every band."""
    ext = MOUNTS["offset"]
    scan = room_scan(sensor, ext)
    bands = {f"s{i}": (-0.2 + 0.25 * i, 0.1 + 0.3 * i) for i in range(n_slices)}
    kw = {"angle_min": -2.5, "angle_max": 2.0, "angle_increment": 0.05}
    conv = SliceConverter(sensor, {k: SliceSpec(*v) for k, v in bands.items()}, extrinsics=ext,
                          frame_id="b", range_min=0.3, range_max=3.5, backend=backend, **kw)
    out = conv.convert(scan)
    if backend == "numba":
        assert next(iter(conv._tables.values())).sorted is not None
    for name, (zmin, zmax) in bands.items():
        assert_same(out[name], ref_slice(scan, sensor, zmin=zmin, zmax=zmax, ext=ext, rmin=0.3,
                                         rmax=3.5, amin=kw["angle_min"], amax=kw["angle_max"],
                                         inc=kw["angle_increment"]))


def test_level_mount_sees_walls_and_table(sensor: Any) -> None:
    """Physics, no oracle: walls of the 8 x 6 m room and the 0.70-0.75 m table top at x = 1."""
    ext = pose(z=0.5)
    scan = room_scan(sensor, ext, specials=False)
    conv = SliceConverter(sensor, {"low": SliceSpec(0.05, 0.5), "table": SliceSpec(0.6, 0.8)},
                          extrinsics=ext, frame_id="base_link", intensity_channel=None)
    out = conv.convert(scan)
    low, table = arrays(out["low"])[0], arrays(out["table"])[0]
    assert low.size == 128 and len(out["low"].intensities) == 0
    centre = 64                              # bin of angle 0 on a [-pi, pi) grid of 128
    assert low[centre] == pytest.approx(4.0, abs=0.02)             # wall at x = 4
    assert low[0] == pytest.approx(4.0, abs=0.02)                  # wall at x = -4 (angle pi)
    assert low[centre + 32] == pytest.approx(3.0, abs=0.02)        # wall at y = 3
    assert table[centre] == pytest.approx(1.0, abs=0.05)           # table edge at x = 1
    assert np.all(np.isfinite(low))


def test_laserscan_messages_equal_normally_built_ones(sensor: Any) -> None:
    """Slices fill message slots directly (lidarscan.rosmsg.bare_message): each must equal
    the message rosidl's constructor builds from the same values, and serialize alike."""
    from sensor_msgs.msg import LaserScan

    ext = pose(z=0.5)
    conv = SliceConverter(sensor, {"low": SliceSpec(0.05, 0.5)}, extrinsics=ext,
                          frame_id="base_link")
    for msg in conv.convert(room_scan(sensor, ext)).values():
        normal = LaserScan(**{name: getattr(msg, name)
                              for name in LaserScan.get_fields_and_field_types()})
        # (bytes, not ==: a NaN range would make equal messages compare unequal; our encoder,
        # not rclpy's, whose padding bytes are uninitialised)
        assert lidarscan.encode(msg, "sensor_msgs/msg/LaserScan") == lidarscan.encode(
            normal, "sensor_msgs/msg/LaserScan")
        assert type(msg.ranges) is type(normal.ranges) is array.array
        assert msg._check_fields == normal._check_fields


def test_tilted_ring_crosses_the_band_on_part_of_its_azimuth(sensor: Any) -> None:
    ext = MOUNTS["tilted"]
    scan = room_scan(sensor, ext, specials=False)
    proj = lidarscan.make_projector(sensor)
    r = lidarscan.range_m(scan, sensor).astype(np.float64)
    ring = sensor.height // 2
    p = r[ring, :, None] * proj.directions[ring] + proj.offsets[ring]
    z = p @ ext[2, :3] + ext[2, 3]
    in_band = (z >= 0.05) & (z <= 0.5)
    assert 0 < in_band.mean() < 0.8
    got = to_laserscan(scan, sensor, min_height=0.05, max_height=0.5, extrinsics=ext,
                       frame_id="base_link")
    assert_same(got, ref_slice(scan, sensor, zmin=0.05, zmax=0.5, ext=ext))


def test_upside_down_mount_mirrors_azimuth() -> None:
    """Rolled by pi, the sensor's +y is the target's -y: a wall seen at +90 deg in the sensor
    frame is at -90 deg in the target frame."""
    info = make_sensor(4, 64, origins=False)
    ext = pose(z=1.0, roll=math.pi)
    r = np.full((4, 64), np.inf, np.float32)
    proj = lidarscan.make_projector(info)
    az = np.arctan2(proj.directions[..., 1], proj.directions[..., 0])
    r[np.abs(az - math.pi / 2) < 0.03] = 2.0
    scan = lidarscan.make_scan(info, {"range": r, "intensity": np.ones_like(r)}, 0,
                               as_dataclass=True)
    out = arrays(to_laserscan(scan, info, min_height=-10, max_height=10, extrinsics=ext,
                              frame_id="base_link"))[0]
    hits = np.flatnonzero(np.isfinite(out))
    angles = -math.pi + hits * TWO_PI / 64
    assert hits.size and np.all(np.abs(angles + math.pi / 2) < 0.1)


@pytest.mark.parametrize("backend", BACKENDS)
def test_many_pixels_and_measured_azimuths(rng: np.random.Generator, backend: str) -> None:
    info = make_sensor(8, 256, origins=True)
    az = TWO_PI * (1 - np.arange(256) / 256) + rng.normal(0, 0.002, 256)
    proj = lidarscan.make_projector(info)
    r = rng.uniform(0.05, 8.0, (8, 256)).astype(np.float32)
    scan = lidarscan.make_scan(info, {"range": r, "intensity": r * 2}, 5, as_dataclass=True,
                               column_azimuth_angles=az)
    ext = pose(0.05, -0.02, 0.4, 1.0)
    conv = SliceConverter(info, {"a": SliceSpec(-0.5, 1.0), "b": SliceSpec(0.35, 0.45)},
                          extrinsics=ext, frame_id="base_link", range_min=0.3, range_max=6.0,
                          backend=backend)
    out = conv.convert(scan)
    for name, (zmin, zmax) in (("a", (-0.5, 1.0)), ("b", (0.35, 0.45))):
        assert_same(out[name], ref_slice(scan, info, zmin=zmin, zmax=zmax, ext=ext, rmin=0.3,
                                         rmax=6.0))
    assert proj.width == 256


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("mount", ["level", "tilted"])
def test_staggered_and_destaggered_scans_give_identical_slices(backend: str, mount: str) -> None:
    info = make_sensor(16, 64, shifts=True)
    ext = MOUNTS[mount]
    stag = room_scan(info, ext)
    destag = room_scan(info, ext, destagger=True)
    conv = SliceConverter(info, {"s": SliceSpec(0.05, 1.2)}, extrinsics=ext, frame_id="base",
                          backend=backend)
    a, b = conv.convert(stag)["s"], conv.convert(destag)["s"]
    assert_same(a, arrays(b))
    assert_same(b, ref_slice(destag, info, zmin=0.05, zmax=1.2, ext=ext))


def test_integer_range_channel(sensor: Any) -> None:
    info = make_sensor(range_multiplier=0.001)
    ext = MOUNTS["level"]
    scan_f = room_scan(info, ext, specials=False)
    r = lidarscan.range_m(scan_f, info)
    mm = np.round(r.astype(np.float64) * 1000).astype(np.uint32)
    mm[::5, ::3] = 0                                              # raw 0 = no return
    scan_i = lidarscan.make_scan(info, {"range": mm, "intensity": np.ones_like(r)}, 10**9,
                                 as_dataclass=True)
    scan_ref = lidarscan.make_scan(info, {"range": lidarscan.range_m(scan_i, info),
                                          "intensity": np.ones_like(r)}, 10**9,
                                   as_dataclass=True)
    kw = {"min_height": 0.05, "max_height": 0.6, "extrinsics": ext, "frame_id": "b"}
    assert_same(to_laserscan(scan_i, info, **kw), arrays(to_laserscan(scan_ref, info, **kw)))


# ----------------------------------------------------------------------- value classes

def flat_sensor(height: int = 1, width: int = 8, *, elevation: float = 0.0, **fields: Any) -> Any:
    return lidarscan.make_info(stamp_ns=1, frame_id="l",
                               vertical_angles=np.full(height, elevation),
                               horizontal_angles=-math.pi + TWO_PI * np.arange(width) / width,
                               as_dataclass=True, **fields)


def flat_scan(info: Any, ranges: Any, intensity: Any = None) -> Any:
    r = np.asarray(ranges, np.float32).reshape(int(info.height), int(info.width))
    inten = np.arange(r.size, dtype=np.float32).reshape(r.shape) if intensity is None \
        else np.asarray(intensity, np.float32).reshape(r.shape)
    return lidarscan.make_scan(info, {"range": r, "intensity": inten}, 0, as_dataclass=True)


@pytest.mark.parametrize("row_values, expected", [
    ([3.0, -np.inf, np.inf, np.nan], 3.0),
    ([np.nan, np.inf, -np.inf], -np.inf),
    ([np.nan, np.inf, 0.0], np.inf),
    ([np.nan, 0.0, -1.0], np.nan),
    ([5.0, 4.0, 4.5], 4.0),
])
@pytest.mark.parametrize("backend", BACKENDS)
def test_class_precedence_within_a_bin(row_values: list[float], expected: float,
                                       backend: str) -> None:
    """Pixels of one column (same azimuth, all in the band) fight for one bin."""
    info = flat_sensor(len(row_values), 4)
    ranges = np.repeat(np.asarray(row_values, np.float32)[:, None], 4, axis=1)
    out = arrays(to_laserscan(flat_scan(info, ranges), info, min_height=-1, max_height=1,
                              backend=backend))[0]
    np.testing.assert_array_equal(out, np.full(4, expected, np.float32))


def test_min_range_carries_its_intensity_and_ties_go_to_the_first_pixel() -> None:
    info = flat_sensor(3, 4)
    ranges = [[2, 2, 5, 1], [1, 2, 4, 1], [3, 2, 3, 1]]
    inten = [[10, 11, 12, 13], [20, 21, 22, 23], [30, 31, 32, 33]]
    rng_, ints = arrays(to_laserscan(flat_scan(info, ranges, inten), info, min_height=-1,
                                     max_height=1))
    assert rng_.tolist() == [1, 2, 3, 1]
    assert ints.tolist() == [20, 11, 32, 13]


def test_no_return_keeps_inf_only_if_the_ray_crosses_the_band() -> None:
    """Sensor at z = 1: an upward beam (+10 deg) never reaches the band 0..0.5, a downward one
    (-10 deg) does (at 2.8..5.7 m): +Inf there marks free space, elsewhere the bin is empty."""
    info = lidarscan.make_info(stamp_ns=1, frame_id="l",
                               vertical_angles=np.radians([10.0, -10.0]),
                               horizontal_angles=-math.pi + TWO_PI * np.arange(4) / 4,
                               as_dataclass=True)
    ranges = np.full((2, 4), np.inf, np.float32)
    ranges[1, 2] = 3.0                            # downward ray hits the floor... z = 0.48
    scan = flat_scan(info, ranges)
    kw = {"min_height": 0.0, "max_height": 0.5, "extrinsics": pose(z=1.0), "frame_id": "b",
              "fill": -1.0}
    out = arrays(to_laserscan(scan, info, **kw))[0]
    assert out[0] == np.inf and out[1] == np.inf and out[3] == np.inf
    assert out[2] == pytest.approx(3.0 * math.cos(math.radians(10)))
    only_up = ranges.copy()
    only_up[1] = np.nan                            # the downward ray is invalid
    out2 = arrays(to_laserscan(flat_scan(info, only_up), info, **kw))[0]
    assert np.all(np.isnan(out2))                  # invalid beats empty; +Inf up there: nothing
    # range_max below the band's reach: the downward ray never gets into range -> empty
    out3 = arrays(to_laserscan(flat_scan(info, ranges), info, range_max=2.0, **kw))[0]
    assert out3.tolist() == [-1.0, -1.0, np.inf, -1.0]          # the 3 m point is beyond 2 m


def test_too_close_only_if_the_band_is_near_the_sensor() -> None:
    info = flat_sensor(1, 4, range_min=0.2)
    ranges = np.full((1, 4), -np.inf, np.float32)
    scan = flat_scan(info, ranges)
    inside = arrays(to_laserscan(scan, info, min_height=-0.1, max_height=0.1, fill=7.0))[0]
    assert np.all(inside == -np.inf)
    above = arrays(to_laserscan(scan, info, min_height=0.5, max_height=1.0, fill=7.0))[0]
    assert np.all(above == 7.0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_planar_range_limits_are_inclusive(backend: str) -> None:
    info = flat_sensor(1, 4)
    scan = flat_scan(info, [[1.0, 2.0, 3.0, 4.0]])
    out = arrays(to_laserscan(scan, info, min_height=0, max_height=0, range_min=2.0,
                              range_max=3.0, backend=backend))[0]
    assert out.tolist() == [-np.inf, 2.0, 3.0, np.inf]
    out = arrays(to_laserscan(scan, info, min_height=0, max_height=0,
                              range_min=float(np.nextafter(2.0, 3.0)),
                              range_max=float(np.nextafter(3.0, 2.0)), backend=backend))[0]
    assert out.tolist() == [-np.inf, -np.inf, np.inf, np.inf]


@pytest.mark.parametrize("backend", BACKENDS)
def test_height_limits_are_inclusive_and_a_flat_cloud_at_zero_is_kept(backend: str) -> None:
    """pointcloud_to_laserscan's min_height = DBL_MIN dropped every point at z = 0."""
    info = flat_sensor(1, 8)
    scan = flat_scan(info, np.full(8, 2.5))
    at_zero = arrays(to_laserscan(scan, info, min_height=0.0, max_height=0.0,
                                  backend=backend))[0]
    assert np.all(at_zero == 2.5)
    ext = pose(z=0.25)                                          # z = 0.25 exactly
    for zmin, zmax, kept in [(0.25, 0.25, True), (0.0, 0.25, True), (0.25, 1.0, True),
                             (float(np.nextafter(0.25, 1)), 1.0, False),
                             (0.0, float(np.nextafter(0.25, 0)), False)]:
        out = arrays(to_laserscan(scan, info, min_height=zmin, max_height=zmax, extrinsics=ext,
                                  frame_id="b", fill=-1.0, backend=backend))[0]
        assert np.all(out == (2.5 if kept else -1.0)), (zmin, zmax)      # -1: empty (fill)


def test_plus_and_minus_pi_columns_share_bin_zero() -> None:
    info = lidarscan.make_info(stamp_ns=1, frame_id="l", vertical_angles=[0.0, 0.0],
                               horizontal_angles=[math.pi, 0.0],
                               beam_azimuth_offsets=[0.0, 0.0], as_dataclass=True)
    info2 = lidarscan.make_info(stamp_ns=1, frame_id="l", vertical_angles=[0.0, 0.0],
                                horizontal_angles=[-math.pi, 0.0], as_dataclass=True)
    for inf_ in (info, info2):
        scan = flat_scan(inf_, [[3.0, 5.0], [4.0, 6.0]])
        out = arrays(to_laserscan(scan, inf_, min_height=-1, max_height=1))[0]
        assert out.tolist() == [3.0, 5.0]


def test_use_inf_false_and_fill_policies() -> None:
    info = flat_sensor(1, 4)
    scan = flat_scan(info, [[np.inf, 1.0, np.nan, 9.0]])
    out = arrays(to_laserscan(scan, info, min_height=0, max_height=0, range_max=5.0,
                              use_inf=False, inf_epsilon=0.25, angle_increment=math.pi / 4))[0]
    assert out.tolist()[:2] == [5.25, 5.25] and out[2] == 1.0 and math.isnan(out[4])
    assert out[6] == 5.25                     # 9 m > range_max: +Inf class, then max + eps
    nan_fill = arrays(to_laserscan(scan, info, min_height=0, max_height=0,
                                   angle_increment=math.pi / 4, fill=math.nan))[0]
    assert nan_fill[0] == np.inf and np.all(np.isnan(nan_fill[1::2]))


# ------------------------------------------------------------------------- header, grid

def test_header_fields_and_default_grid(sensor: Any) -> None:
    from sensor_msgs.msg import LaserScan
    scan = room_scan(sensor, MOUNTS["level"], stamp=1_234_567_891_011)
    msg = to_laserscan(scan, sensor, min_height=0.0, max_height=1.0, extrinsics=MOUNTS["level"],
                       frame_id="base_link")
    assert isinstance(msg, LaserScan)
    assert isinstance(msg.ranges, array.array) and msg.ranges.typecode == "f"
    assert len(msg.ranges) == len(msg.intensities) == 128
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1234, 567_891_011)
    assert msg.angle_min == float(F32(-math.pi))
    assert msg.angle_increment == float(F32(TWO_PI / 128))
    assert msg.angle_max == float(F32(-math.pi + 127 * TWO_PI / 128))
    assert msg.range_min == float(F32(0.1)) and msg.range_max == 120.0
    assert msg.scan_time == pytest.approx(0.1, rel=1e-6)
    # Ouster-like columns sweep clockwise: negative time increment, |dt| = T / N
    assert msg.time_increment == pytest.approx(-0.1 / 128, rel=1e-5)


def test_sector_grid(sensor: Any) -> None:
    scan = room_scan(sensor, MOUNTS["level"])
    kw = {"extrinsics": MOUNTS["level"], "frame_id": "b", "angle_min": -math.pi / 2,
              "angle_max": math.pi / 2, "angle_increment": 0.0087}
    msg = to_laserscan(scan, sensor, min_height=0.0, max_height=1.0, **kw)
    assert len(msg.ranges) == 362
    assert msg.angle_max == float(F32(-math.pi / 2 + 361 * 0.0087))
    assert_same(msg, ref_slice(scan, sensor, zmin=0.0, zmax=1.0, ext=MOUNTS["level"],
                               amin=-math.pi / 2, amax=math.pi / 2, inc=0.0087))


def test_window_straddling_pi_and_beyond(sensor: Any) -> None:
    scan = room_scan(sensor, MOUNTS["offset"])
    for amin, amax in ((2.5, 3.8), (0.0, TWO_PI), (0.0, 4.0)):
        msg = to_laserscan(scan, sensor, min_height=0.0, max_height=1.0,
                           extrinsics=MOUNTS["offset"], frame_id="b", angle_min=amin,
                           angle_max=amax, angle_increment=0.01)
        assert_same(msg, ref_slice(scan, sensor, zmin=0.0, zmax=1.0, ext=MOUNTS["offset"],
                                   amin=amin, amax=amax, inc=0.01))


def test_per_slice_overrides_and_one_pass_equals_separate_calls(sensor: Any) -> None:
    ext = MOUNTS["tilted"]
    scan = room_scan(sensor, ext)
    specs = {"coarse": {"min_height": 0.0, "max_height": 0.5, "angle_increment": 0.1,
                        "range_max": 3.0},
             "fine": SliceSpec(0.2, 1.0, angle_increment=0.02, fill=math.nan),
             "same": SliceSpec(0.2, 1.0)}
    out = SliceConverter(sensor, specs, extrinsics=ext, frame_id="b").convert(scan)
    assert len(out["coarse"].ranges) == 63 and len(out["fine"].ranges) == 314
    assert out["coarse"].range_max == 3.0
    single = to_laserscan(scan, sensor, min_height=0.2, max_height=1.0, extrinsics=ext,
                          frame_id="b", angle_increment=0.02, fill=math.nan)
    assert_same(out["fine"], arrays(single))
    assert_same(out["coarse"], ref_slice(scan, sensor, zmin=0.0, zmax=0.5, ext=ext, inc=0.1,
                                         rmax=3.0))


def test_intensity_channel_dtype_and_none(sensor: Any) -> None:
    ext = MOUNTS["level"]
    scan = room_scan(sensor, ext, intensity_dtype=np.uint16)
    msg = to_laserscan(scan, sensor, min_height=0.0, max_height=1.0, extrinsics=ext,
                       frame_id="b")
    assert_same(msg, ref_slice(scan, sensor, zmin=0.0, zmax=1.0, ext=ext))
    assert np.all(np.mod(arrays(msg)[1], 1) == 0)
    with pytest.raises(UnknownChannelError):
        to_laserscan(scan, sensor, min_height=0.0, max_height=1.0, intensity_channel="nope")


def test_info_versions_and_linkage(sensor: Any) -> None:
    ext = MOUNTS["level"]
    conv = SliceConverter(sensor, {"s": SliceSpec(0.0, 1.0)}, extrinsics=ext, frame_id="b")
    other = make_sensor(stamp=8_000_000_000, fov=20.0)
    scan2 = room_scan(other, ext)
    with pytest.raises(LinkageError):
        conv.convert(scan2)
    msg = conv.convert(scan2, other)
    assert_same(msg["s"], ref_slice(scan2, other, zmin=0.0, zmax=1.0, ext=ext))
    small = make_sensor(4, 32, stamp=8_000_000_000)
    with pytest.raises(InfoMismatchError):
        conv.convert(room_scan(small, ext))


def test_no_mutation_of_the_scan(sensor: Any) -> None:
    scan = lidarscan.make_scan(sensor, {"range": np.full((16, 128), 3.0, np.float32),
                                        "intensity": np.zeros((16, 128), np.float32)}, 0)
    before = bytes(scan.data)
    to_laserscan(scan, sensor, min_height=-1.0, max_height=1.0)      # rclpy scan
    assert bytes(scan.data) == before


@pytest.mark.parametrize("kwargs, field", [
    ({"min_height": 1.0, "max_height": 0.0}, "slices['slice'].max_height"),
    ({"min_height": math.nan, "max_height": 0.0}, "slices['slice'].min_height"),
    ({"min_height": 0.0, "max_height": 1.0, "angle_increment": 0.0}, "angle_increment"),
    ({"min_height": 0.0, "max_height": 1.0, "angle_increment": -0.01}, "angle_increment"),
    ({"min_height": 0.0, "max_height": 1.0, "angle_min": 1.0, "angle_max": 0.0}, "angle_max"),
    ({"min_height": 0.0, "max_height": 1.0, "range_min": 2.0, "range_max": 1.0}, "range_max"),
    ({"min_height": 0.0, "max_height": 1.0, "range_min": -1.0}, "range_min"),
    ({"min_height": 0.0, "max_height": 1.0, "extrinsics": np.eye(4)}, "frame_id"),
    ({"min_height": 0.0, "max_height": 1.0, "extrinsics": np.eye(4) * 2, "frame_id": "b"},
     "extrinsics"),
])
def test_option_errors(sensor: Any, kwargs: dict[str, Any], field: str) -> None:
    scan = room_scan(sensor, MOUNTS["level"])
    with pytest.raises(ConfigError) as err:
        to_laserscan(scan, sensor, **kwargs)
    assert err.value.field == field


def test_converter_config_errors(sensor: Any) -> None:
    with pytest.raises(ConfigError):
        SliceConverter(sensor, {})
    with pytest.raises(ConfigError):
        SliceConverter(sensor, {"a": {"min_height": 0.0}})
    with pytest.raises(ConfigError):
        SliceConverter(sensor, {"a": {"min_height": 0.0, "max_height": 1.0, "colour": 1}})
    with pytest.raises(ConfigError):
        SliceConverter(sensor, {"": SliceSpec(0, 1)})


def test_far_field_tables_avoid_atan2_for_most_pixels(sensor: Any) -> None:
    """With the sensor on the target's z axis only near pixels need atan2."""
    ext = MOUNTS["level"]
    scan = room_scan(sensor, ext, specials=False)
    conv = SliceConverter(sensor, {"s": SliceSpec(0.0, 1.0)}, extrinsics=ext, frame_id="b")
    conv.convert(scan)
    tables = next(iter(conv._tables.values()))
    r = lidarscan.range_m(scan, sensor).reshape(-1).astype(np.float64)
    assert tables.near_fraction(r, 0) < 0.05


@pytest.mark.parametrize("backend", BACKENDS)
def test_points_at_their_far_field_threshold(sensor: Any, backend: str) -> None:
    """Pixels an ulp below / at their far-field threshold ``r_thr`` (atan2 path / far-field
    bin) in a few runs of bins, the rest far: the compiled kernel reads the thresholds only
    for runs of bins where some range is below the run's largest threshold (``bin_thr``)."""
    ext = MOUNTS["offset"]
    scan = room_scan(sensor, ext)
    conv = SliceConverter(sensor, {"all": SliceSpec(-1.0, 3.0), "low": SliceSpec(0.0, 0.62)},
                          extrinsics=ext, frame_id="b", range_min=0.0, backend=backend)
    tables = conv._tables_for(scan)
    thr = tables.k_r_thr[0]                                    # float32, per pixel
    r = lidarscan.range_m(scan, sensor).reshape(-1).copy()
    pick = np.flatnonzero(np.isfinite(thr) & (thr > 0))[::97][:40]
    below = np.nextafter(thr[pick[::2]], np.float32(0))
    r[pick[::2]] = below
    r[pick[1::2]] = thr[pick[1::2]]
    scan = lidarscan.make_scan(sensor, {"range": r.reshape(sensor.height, sensor.width),
                                        "intensity": lidarscan.channel(scan, "intensity")},
                               lidarscan.stamps.to_ns(scan.header.stamp), as_dataclass=True)
    if tables.sorted is not None:
        t = tables.sorted
        for b in range(conv._grids[0].size + 1):
            seg = t.cols[6][t.bin_start[b]:t.bin_start[b + 1]]
            assert t.bin_thr[b] == (seg.max() if seg.size else 0)
    out = conv.convert(scan)
    assert np.any(r[pick] < thr[pick]) and np.any(r[pick] >= thr[pick])
    for name, (zmin, zmax) in (("all", (-1.0, 3.0)), ("low", (0.0, 0.62))):
        assert_same(out[name], ref_slice(scan, sensor, zmin=zmin, zmax=zmax, ext=ext, rmin=0.0))


# ---------------------------------------------------------------------------- properties

SPECIALS = [np.inf, -np.inf, np.nan, 0.0, -2.0]      # every non-point range class


def draw_image(draw: Any, height: int, width: int, values: Any, dtype: Any) -> np.ndarray:
    """A (height, width) image of ``dtype`` drawn element by element from ``values``."""
    return np.array(draw(st.lists(values, min_size=height * width, max_size=height * width)),
                    dtype).reshape(height, width)


@st.composite
def slice_case(draw: Any) -> tuple[Any, Any, dict[str, Any]]:
    height = draw(st.integers(1, 5))
    width = draw(st.integers(3, 24))
    vert = sorted(draw(st.lists(st.floats(-0.6, 0.6), min_size=height, max_size=height)),
                  reverse=True)
    fields: dict[str, Any] = {"range_min": draw(st.sampled_from([0.0, 0.2]))}
    if draw(st.booleans()):
        fields["beam_origins"] = draw(st.lists(st.floats(-0.05, 0.05), min_size=3 * height,
                                               max_size=3 * height))
        fields["beam_azimuth_offsets"] = draw(st.lists(st.floats(-0.05, 0.05),
                                                       min_size=height, max_size=height))
    info = lidarscan.make_info(stamp_ns=3, frame_id="l", vertical_angles=vert,
                               horizontal_angles=TWO_PI * (1 - np.arange(width) / width)
                               + draw(st.floats(-1, 1)), as_dataclass=True, **fields)
    r = draw_image(draw, height, width, st.one_of(st.floats(0.015625, 10, width=32),
                                                  st.sampled_from(SPECIALS)), np.float32)
    inten = draw_image(draw, height, width, st.integers(0, 3), np.float32)
    scan = lidarscan.make_scan(info, {"range": r, "intensity": inten}, 0, as_dataclass=True)
    zmin = draw(st.floats(-1.5, 1.5))
    amin = draw(st.floats(-4, 1))
    opts = {"zmin": zmin, "zmax": zmin + draw(st.sampled_from([0.0, 0.2, 1.0, math.inf])),
                "ext": pose(draw(st.floats(-0.5, 0.5)), draw(st.floats(-0.5, 0.5)),
                         draw(st.floats(-1, 1)), draw(st.floats(-4, 4)),
                         draw(st.sampled_from([0.0, 0.3, math.pi])),
                         draw(st.sampled_from([0.0, -0.4]))),
                "amin": amin, "amax": amin + draw(st.sampled_from([TWO_PI, 0.5, 3.0])),
                "inc": draw(st.floats(0.03, 0.7)), "rmin": draw(st.sampled_from([0.0, 0.5])),
                "rmax": draw(st.sampled_from([math.inf, 5.0]))}
    return info, scan, opts


@given(slice_case())
def test_property_matches_reference(case: Any) -> None:
    info, scan, o = case
    ref = ref_slice(scan, info, **o)
    for backend in backends():
        got = to_laserscan(scan, info, min_height=o["zmin"], max_height=o["zmax"],
                           extrinsics=o["ext"], frame_id="b", angle_min=o["amin"],
                           angle_max=o["amax"], angle_increment=o["inc"], range_min=o["rmin"],
                           range_max=o["rmax"], backend=backend)
        assert_same(got, ref)


@given(slice_case())
def test_property_full_circle_wrap(case: Any) -> None:
    """Rotating the grid start by a whole number of bins rotates the output (full circle)."""
    info, scan, o = case
    inc = TWO_PI / int(info.width)
    # exact half-bins are decided by float rounding of t, which differs between the two grid
    # starts: keep to cases where no point is within 1e-6 bins of an edge
    proj = lidarscan.make_projector(info)
    r = lidarscan.range_m(scan, info).astype(np.float64)[..., None]
    with np.errstate(invalid="ignore"):
        p = np.where(np.isfinite(r) & (r > 0), r, 1.0) * proj.directions + proj.offsets
    p = p.reshape(-1, 3) @ o["ext"][:3, :3].T + o["ext"][:3, 3]
    d = proj.directions.reshape(-1, 3) @ o["ext"][:3, :3].T      # far field of non-points
    t = (np.arctan2(np.r_[p[:, 1], d[:, 1]], np.r_[p[:, 0], d[:, 0]]) + math.pi) / inc
    assume(np.all(np.abs(t - np.floor(t) - 0.5) > 1e-6))
    kw = {"min_height": o["zmin"], "max_height": o["zmax"], "extrinsics": o["ext"], "frame_id": "b",
              "intensity_channel": None}
    a = arrays(to_laserscan(scan, info, angle_min=-math.pi, **kw))[0]
    b = arrays(to_laserscan(scan, info, angle_min=-math.pi + 3 * inc, **kw))[0]
    ra = ref_slice(scan, info, zmin=o["zmin"], zmax=o["zmax"], ext=o["ext"],
                   intensity=None)[0]
    rb = ref_slice(scan, info, zmin=o["zmin"], zmax=o["zmax"], ext=o["ext"],
                   amin=-math.pi + 3 * inc, intensity=None)[0]
    np.testing.assert_array_equal(a, ra)
    np.testing.assert_array_equal(b, rb)
    np.testing.assert_array_equal(np.roll(a, -3), b)


def test_numba_is_optional() -> None:
    """With the compiled kernels disabled (numba missing, the C kernel not built) everything
    runs on numpy."""
    import subprocess
    import sys
    code = ("import numpy as np, math, lidarscan\n"
            "from converters._kernels import slices_numba\n"
            "from converters.slices.converter import to_laserscan\n"
            "from converters._kernels import slices as _slicec\n"
            "assert slices_numba.kernels() is None and not _slicec.available()\n"
            "info = lidarscan.make_info(stamp_ns=1, frame_id='l', vertical_angles=[0.0],\n"
            "    horizontal_angles=[0.0, math.pi], as_dataclass=True)\n"
            "scan = lidarscan.make_scan(info, {'range': np.ones((1, 2), np.float32)}, 0,\n"
            "    as_dataclass=True)\n"
            "out = to_laserscan(scan, info, min_height=-1, max_height=1, intensity_channel=None)\n"
            "assert list(out.ranges) == [1.0, 1.0]\n")
    env = {**__import__("os").environ, "LIDARSCAN_NUMBA": "0", "LIDARSCAN_NO_KERNEL": "1"}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                          check=False)
    assert done.returncode == 0, done.stderr


# ------------------------------------------------- row-ordered kernel (exact band intervals)

def _z(r: np.ndarray, dz: np.ndarray, oz: np.ndarray) -> np.ndarray:
    """Height of float32 ranges as the kernels compute it (float64, no fused multiply-add)."""
    with np.errstate(invalid="ignore", over="ignore"):
        return r.astype(np.float64) * dz.astype(np.float64) + oz.astype(np.float64)


def test_band_intervals_are_exact_float32_intervals() -> None:
    """lo <= r <= hi iff the float64 height of r is in the band, for every float32 r next to
    the interval ends and at random, including bands whose limits are exactly the height of
    some float32 range (inclusive boundaries), flat rays (+-0), downward rays, open and empty
    bands; non-points (+-Inf, NaN, 0, negative) are never inside."""
    from converters.slices import spec as _grid
    rng = np.random.default_rng(5)
    n = 400
    dz = rng.normal(0.0, 0.5, n).astype(np.float32)
    dz[:20] = 0.0
    dz[20:40] = -0.0
    dz[40:60] = rng.choice([1e-30, -1e-30, 1.0, -1.0], 20).astype(np.float32)
    oz = rng.normal(0.0, 1.0, n).astype(np.float32)
    oz[60:80] = 0.0
    # bands at the exact height of a float32 range of some ray (boundary hits)
    r_hit = np.float32(rng.uniform(0.1, 50.0, 4)).astype(np.float32)
    z_hit = _z(r_hit, dz[100:104], oz[100:104])
    zmin = np.array([0.05, -np.inf, z_hit[0], -1.0, 0.5, np.inf, 0.3, z_hit[2]])
    zmax = np.array([0.5, 0.0, z_hit[0] + 5.0, z_hit[1], 0.5, -np.inf, np.inf, z_hit[2]])
    zmin[3] = min(zmin[3], zmax[3])
    lo, hi = _grid.band_intervals_f32(dz, oz, zmin, zmax)
    assert lo.dtype == np.float32 and lo.shape == (len(zmin), n)
    tiny = np.float32(1e-45)
    big = np.finfo(np.float32).max
    specials = np.array([np.inf, -np.inf, np.nan, 0.0, -0.0, -1.0], np.float32)
    for s in range(len(zmin)):
        cands = [lo[s], hi[s], np.nextafter(lo[s], np.float32(0)), np.nextafter(hi[s], big),
                 np.nextafter(lo[s], big), np.nextafter(hi[s], np.float32(0)),
                 np.full(n, tiny), np.full(n, big),
                 rng.uniform(0, 100, n).astype(np.float32)]
        cands += [np.full(n, r, np.float32) for r in r_hit]
        for r in cands:
            r = r.astype(np.float32)
            point = np.isfinite(r) & (r > 0)
            z = _z(r, dz, oz)
            expect = point & (z >= zmin[s]) & (z <= zmax[s])
            np.testing.assert_array_equal((r >= lo[s]) & (r <= hi[s]), expect)
        for r in specials:
            assert not np.any((r >= lo[s]) & (r <= hi[s]))
    # ranges whose height is exactly a band limit are inside (inclusive limits), also for a
    # band of zero thickness
    assert lo[2, 100] <= r_hit[0] <= hi[2, 100]
    assert lo[3, 101] <= r_hit[1] <= hi[3, 101]
    assert lo[7, 102] <= r_hit[2] <= hi[7, 102]


def _row_layout(conv: SliceConverter, scan: Any) -> Any:
    tables = conv._tables_for(scan)
    assert tables.sorted is not None
    return tables.sorted.rows


@pytest.mark.skipif(not numba_usable(),
                    reason="numba is not installed or LIDARSCAN_NUMBA=0")
@pytest.mark.parametrize(("mount", "n_slices", "destagger"), [
    ("level", 1, False), ("level", 3, True), ("level", 5, False), ("level", 9, True),
    ("offset", 3, False), ("offset", 5, True), ("upside_down", 2, False),
    ("upside_down", 5, True)])
def test_row_kernel_matches_general_kernel_and_oracle(mount: str, n_slices: int,
                                                      destagger: bool) -> None:
    """An upright (or upside-down) mount on the default grid takes the row-ordered kernel
    (per-row float32 band intervals); it equals the general bin-ordered kernel, the numpy backend and the oracle, for
    slice counts that are not a multiple of 4 or above 4, staggered or destaggered scans, and
    an off-axis mount (points closer than their far-field threshold: the atan2 path). One band
    ends exactly at the height of a pixel (inclusive boundaries)."""
    from converters.slices import spec as _grid
    sensor = make_sensor(shifts=True)
    ext = MOUNTS[mount]
    scan = room_scan(sensor, ext, destagger=destagger)
    # a band edge exactly at the height of one pixel of the scan
    proj = lidarscan.make_projector(sensor)
    d32, o32 = proj.tables_for(scan)
    r = lidarscan.range_m(scan, sensor).reshape(-1)
    z = r.astype(np.float64) * np.float64(ext[2, 2]) * d32.reshape(-1, 3)[:, 2] \
        + (np.float32(o32.reshape(-1, 3)[:, 2] + ext[2, 3]))
    finite = np.flatnonzero(np.isfinite(z) & (z > 0.2) & (z < 0.6))
    edge = float(z[finite[len(finite) // 2]])
    bands = {f"s{i}": (-0.2 + 0.3 * i, 0.35 + 0.3 * i) for i in range(n_slices)}
    bands["s0"] = (0.05, edge)
    specs = {k: SliceSpec(*v) for k, v in bands.items()}
    conv = SliceConverter(sensor, specs, extrinsics=ext, frame_id="b", backend="numba")
    rows = _row_layout(conv, scan)
    assert rows is not None and rows.lo.shape == (n_slices + (-n_slices % 4), sensor.height)
    fast = conv.convert(scan)
    again = conv.convert(scan)                # tables are reused: same result
    # the reduction array of the row kernel alone (SliceConverter._fuse) decodes the same
    flat = np.ascontiguousarray(lidarscan.range_m(scan, sensor)).reshape(-1)
    best = conv._fuse(flat, conv._tables_for(scan))
    if mount == "offset":                     # the row kernel's atan2 path did run
        assert conv._tables_for(scan).near_fraction(flat.astype(np.float64)) > 0.1
    for s, off in zip(conv.slices, conv._offsets):
        ranges = _grid.decode(best[off:off + s.grid.size], s.options)[0]
        np.testing.assert_array_equal(ranges, arrays(fast[s.name])[0])
        assert_same(again[s.name], arrays(fast[s.name]))
    conv._tables_for(scan).sorted.rows = None
    general = conv.convert(scan)
    numpy = SliceConverter(sensor, specs, extrinsics=ext, frame_id="b",
                           backend="numpy").convert(scan)
    for name, (zmin, zmax) in bands.items():
        ref = ref_slice(scan, sensor, zmin=zmin, zmax=zmax, ext=ext)
        assert_same(fast[name], ref)
        assert_same(general[name], ref)
        assert_same(numpy[name], ref)


@pytest.mark.skipif(not numba_usable(),
                    reason="numba is not installed or LIDARSCAN_NUMBA=0")
def test_row_kernel_per_position_qualifiers() -> None:
    """The row kernel reads +Inf/NaN/-Inf qualifiers per row when they are the same in every
    bin, else per position; both give the same slices (here forced on the same tables)."""
    from converters.slices import spec as _grid
    sensor = make_sensor()
    ext = MOUNTS["level"]
    scan = room_scan(sensor, ext)
    specs = {"a": SliceSpec(0.05, 0.5), "b": SliceSpec(0.3, 1.5), "c": SliceSpec(-1.0, 0.2)}
    conv = SliceConverter(sensor, specs, extrinsics=ext, frame_id="b", backend="numba",
                          range_min=0.5, range_max=3.0)
    rows = _row_layout(conv, scan)
    assert rows is not None
    out = conv.convert(scan)
    st_ = conv._tables_for(scan).sorted
    conv._tables_for(scan).sorted.rows = type(rows)(rows.src, rows.keys, rows.lo, rows.hi,
                                                    False, st_.qf, st_.qn)
    per_position = conv.convert(scan)
    for name, (zmin, zmax) in (("a", (0.05, 0.5)), ("b", (0.3, 1.5)), ("c", (-1.0, 0.2))):
        ref = ref_slice(scan, sensor, zmin=zmin, zmax=zmax, ext=ext, rmin=0.5, rmax=3.0)
        assert_same(out[name], ref)
        assert_same(per_position[name], ref)
    assert _grid.EMPTY > 0


@pytest.mark.skipif(not numba_usable(),
                    reason="numba is not installed or LIDARSCAN_NUMBA=0")
@pytest.mark.parametrize("case", ["tilted", "coarse_grid", "fine_grid", "many_slices"])
def test_row_kernel_falls_back_when_it_does_not_apply(case: str) -> None:
    """A tilted mount (dz, oz vary along a row), grids other than one bin per column,
    and more than 32 slices use the general bin-ordered kernel; results match the oracle."""
    sensor = make_sensor()
    ext = MOUNTS["level"] if case not in MOUNTS else MOUNTS[case]
    scan = room_scan(sensor, ext)
    kw: dict[str, Any] = {}
    if case == "coarse_grid":
        kw["angle_increment"] = 2 * TWO_PI / sensor.width
    elif case == "fine_grid":
        kw["angle_increment"] = TWO_PI / sensor.width / 2
    n = 33 if case == "many_slices" else 2
    bands = {f"s{i}": (0.05 * i, 0.3 + 0.05 * i) for i in range(n)}
    conv = SliceConverter(sensor, {k: SliceSpec(*v) for k, v in bands.items()}, extrinsics=ext,
                          frame_id="b", backend="numba", **kw)
    assert _row_layout(conv, scan) is None
    out = conv.convert(scan)
    for name in list(bands)[:2] + list(bands)[-1:]:
        zmin, zmax = bands[name]
        assert_same(out[name], ref_slice(scan, sensor, zmin=zmin, zmax=zmax, ext=ext,
                                         inc=kw.get("angle_increment")))


# ------------------------------------------- optional channels and byte order (issue 17)

def test_range_only_scan_slices_with_the_defaults(sensor: Any) -> None:
    """The default intensity channel means "intensity if the scan has one": a range-only scan
    gives empty intensities and the same ranges; a channel named explicitly stays required."""
    full = room_scan(sensor, MOUNTS["level"])
    r = lidarscan.channel(full, "range")
    only = lidarscan.make_scan(sensor, {"range": r}, 10**9, as_dataclass=True)
    for backend in backends():
        got = to_laserscan(only, sensor, min_height=0.0, max_height=1.0, backend=backend)
        ref = to_laserscan(full, sensor, min_height=0.0, max_height=1.0, backend=backend)
        np.testing.assert_array_equal(arrays(got)[0], arrays(ref)[0])
        assert len(got.intensities) == 0 and len(ref.intensities) == len(ref.ranges)
        conv = SliceConverter(sensor, {"a": SliceSpec(0.0, 1.0)}, backend=backend)
        assert len(conv.convert(only)["a"].intensities) == 0
    for call in (lambda: to_laserscan(only, sensor, min_height=0.0, max_height=1.0,
                                      intensity_channel="intensity"),
                 lambda: SliceConverter(sensor, {"a": SliceSpec(0.0, 1.0)},
                                        intensity_channel="intensity").convert(only)):
        with pytest.raises(UnknownChannelError):
            call()


CHANNEL_DTYPES = [np.int8, np.uint8, np.int16, np.uint16, np.int32, np.uint32, np.float32,
                  np.float64]


def slice_backends() -> list[str]:
    """numpy, numba (when installed) and the C kernel (when built, forced on)."""
    from converters._kernels import slices as _slicec
    return backends() + (["c"] if _slicec.available() else [])


def backend_converter(backend: str, info: Any, specs: Any, **kw: Any) -> SliceConverter:
    conv = SliceConverter(info, specs, backend="auto" if backend == "c" else backend, **kw)
    if backend == "c":
        conv._c_kernel = True            # also where "auto" prefers numba (no AVX-512)
    return conv


@pytest.mark.parametrize("geometry", ["level", "tilted", "pixel_angles"])
def test_big_endian_scans_give_identical_slices_on_every_backend(geometry: str) -> None:
    """Byte order is a property of the message: every channel datatype, as range (float, or
    integer with the info's multiplier) and as intensity, big- and little-endian, through every
    backend, gives bit-identical slices; the little-endian specialisation is compiled first."""
    fields: dict[str, Any] = {"range_multiplier": 0.001}
    if geometry == "pixel_angles":
        h, w = 16, 128
        fields["pixel_azimuth_angles"] = np.tile(TWO_PI * (1 - np.arange(w) / w), h) + 0.001
        fields["pixel_altitude_angles"] = np.repeat(np.radians(np.linspace(15, -15, h)), w)
    info = make_sensor(**fields)
    ext = MOUNTS["tilted" if geometry == "tilted" else "level"]
    base = room_scan(info, ext)
    r = np.array(lidarscan.channel(base, "range"))
    rng = np.random.default_rng(5)
    specs = {"a": SliceSpec(0.05, 0.5), "b": SliceSpec(0.6, 2.0)}
    for dtype in CHANNEL_DTYPES:
        kind = np.dtype(dtype).kind
        if kind == "f":
            inten = rng.uniform(-1e3, 1e3, r.shape).astype(dtype)
            ranges = r.astype(dtype)
        else:
            lo, hi = np.iinfo(dtype).min, np.iinfo(dtype).max
            inten = rng.integers(lo, hi, r.shape, endpoint=True).astype(dtype)
            mm = np.where(np.isfinite(r) & (r > 0), np.round(r * 1000), 0)   # 0 = no return
            ranges = np.clip(mm, 0, hi).astype(dtype) if kind == "u" else r
        channels = {"range": ranges, "intensity": inten}
        out: dict[str, Any] = {}
        for backend in slice_backends():
            for big in (False, True):
                scan = lidarscan.make_scan(info, channels, 10**9, is_bigendian=big,
                                           as_dataclass=True)
                before = bytes(scan.data)
                conv = backend_converter(backend, info, specs, extrinsics=ext, frame_id="base")
                out[backend, big] = [arrays(m) for m in conv.convert(scan).values()]
                one = to_laserscan(scan, info, min_height=0.05, max_height=0.5, extrinsics=ext,
                                   frame_id="base",
                                   backend="auto" if backend == "c" else backend)
                assert bytes(scan.data) == before                 # the caller's buffer
                np.testing.assert_array_equal(arrays(one)[0].view(np.int32),
                                              out[backend, big][0][0].view(np.int32))
            for (ra, ia), (rb, ib) in zip(out[backend, False], out[backend, True]):
                np.testing.assert_array_equal(ra.view(np.int32), rb.view(np.int32))
                np.testing.assert_array_equal(ia.view(np.int32), ib.view(np.int32))
