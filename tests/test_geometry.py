"""lidarscan.geometry against a plain-Python, per-pixel reference of the beam model.

The reference (``_ref_point``) is written from the formula in ``msgs/msg/LidarInfo.msg`` with
``math`` only: no numpy, no project code.
"""

from __future__ import annotations

import math
import sys
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import lidarscan
from lidarscan import geometry
from lidarscan.errors import ValidationError

STAMP = 1_700_000_000_123_456_789


# ----------------------------------------------------------------------------- reference

def _ref_point(p: dict[str, Any], u: int, c: int, rho: float,
               alpha: list[float] | None = None) -> tuple[float, float, float] | None:
    """Point of row u, MEASUREMENT column c, range rho (m) per LidarInfo.msg; None = no point."""
    if not (math.isfinite(rho) and rho > 0):
        return None
    width = p["width"]
    a = (alpha if alpha is not None else p["horizontal_angles"])[c]
    theta = a + p["beam_azimuth_offsets"][u]
    phi = p["vertical_angles"][u]
    if p["pixel_azimuth_angles"]:
        theta_d = p["pixel_azimuth_angles"][u * width + c]
        phi_d = p["pixel_altitude_angles"][u * width + c]
    else:
        theta_d, phi_d = theta, phi
    d = (math.cos(phi_d) * math.cos(theta_d), math.cos(phi_d) * math.sin(theta_d),
         math.sin(phi_d))
    ox, oy, oz = p["beam_origins"][3 * u: 3 * u + 3]
    rot_o = (math.cos(theta) * ox - math.sin(theta) * oy,
             math.sin(theta) * ox + math.cos(theta) * oy, oz)
    s = rho + p["beam_range_offsets"][u]
    q = [rot_o[i] + s * d[i] for i in range(3)]
    m = p["lidar_to_sensor_transform"]
    return tuple(m[4 * i] * q[0] + m[4 * i + 1] * q[1] + m[4 * i + 2] * q[2] + m[4 * i + 3]
                 for i in range(3))  # type: ignore[return-value]


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _random_params(seed: int, height: int, width: int, *, pixel_angles: bool = False,
                   transform: bool = True) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    matrix = np.eye(4)
    if transform:
        matrix[:3, :3] = _random_rotation(rng)
        matrix[:3, 3] = rng.uniform(-1, 1, 3)
    p: dict[str, Any] = {
        "height": height, "width": width,
        "vertical_angles": sorted(rng.uniform(-1.2, 1.2, height).tolist(), reverse=True),
        "horizontal_angles": rng.uniform(-7, 7, width).tolist(),
        "beam_azimuth_offsets": rng.uniform(-0.3, 0.3, height).tolist(),
        "beam_origins": rng.uniform(-0.1, 0.1, 3 * height).tolist(),
        "beam_range_offsets": rng.uniform(-0.05, 0.05, height).tolist(),
        "lidar_to_sensor_transform": matrix.reshape(-1).tolist(),
        "pixel_shift_by_row": rng.integers(-3 * width, 3 * width + 1, height).tolist(),
        "beam_time_offsets": rng.integers(-5000, 5000, height).tolist(),
        "column_time_increment": int(rng.integers(0, 100_000)),
        "pixel_azimuth_angles": [], "pixel_altitude_angles": [],
    }
    if pixel_angles:
        p["pixel_azimuth_angles"] = rng.uniform(-4, 4, height * width).tolist()
        p["pixel_altitude_angles"] = rng.uniform(-1.5, 1.5, height * width).tolist()
    return p


def _info(p: dict[str, Any], *, stamp_ns: int = STAMP, as_dataclass: bool = True) -> Any:
    fields = {k: v for k, v in p.items() if k not in ("height", "width")}
    return lidarscan.make_info(stamp_ns=stamp_ns, frame_id="base", as_dataclass=as_dataclass,
                               **fields)


def _ranges(seed: int, height: int, width: int) -> np.ndarray:
    rng = np.random.default_rng(seed + 1)
    r = rng.uniform(0.05, 120.0, (height, width)).astype(np.float32)
    holes = rng.random((height, width))
    r[holes < 0.1] = np.inf
    r[(holes >= 0.1) & (holes < 0.15)] = 0.0
    r[(holes >= 0.15) & (holes < 0.18)] = np.nan
    return r


def _reference_cloud(p: dict[str, Any], ranges: np.ndarray,
                     alpha: list[float] | None = None) -> np.ndarray:
    out = np.full(ranges.shape + (3,), np.nan)
    for u in range(p["height"]):
        for c in range(p["width"]):
            point = _ref_point(p, u, c, float(ranges[u, c]), alpha)
            if point is not None:
                out[u, c] = point
    return out


def _assert_close_f32(actual: np.ndarray, expected: np.ndarray, ranges: np.ndarray) -> None:
    """float32 tables: error bounded by a few float32 ulps of the magnitudes involved."""
    np.testing.assert_array_equal(np.isnan(actual).any(-1), np.isnan(expected).any(-1))
    valid = ~np.isnan(expected).any(-1)
    scale = 2.0 + np.abs(np.where(np.isfinite(ranges), ranges, 0.0))[valid][:, None]
    err = np.abs(actual[valid].astype(np.float64) - expected[valid])
    assert np.all(err <= 1e-6 * scale), float((err / scale).max())


# ------------------------------------------------------------------------------ projection

@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), height=st.integers(1, 5), width=st.integers(1, 9),
       pixel_angles=st.booleans(), transform=st.booleans())
def test_projector_matches_loop_reference(seed: int, height: int, width: int,
                                          pixel_angles: bool, transform: bool) -> None:
    p = _random_params(seed, height, width, pixel_angles=pixel_angles, transform=transform)
    info = _info(p)
    ranges = _ranges(seed, height, width)
    expected = _reference_cloud(p, ranges)
    projector = geometry.Projector(info)
    _assert_close_f32(projector.xyz(ranges), expected, ranges)
    # float64 path agrees to round-off
    exact = geometry.exact_xyz(info, ranges)
    np.testing.assert_allclose(exact, expected, rtol=0, atol=1e-9)
    # destaggered input: pixel (u, (c + s_u) mod W) holds measurement column c
    shifts = np.asarray(p["pixel_shift_by_row"])
    destaggered = np.empty_like(ranges)
    for u in range(height):
        for c in range(width):
            destaggered[u, (c + shifts[u]) % width] = ranges[u, c]
    expected_d = np.empty_like(expected)
    for u in range(height):
        for c in range(width):
            expected_d[u, (c + shifts[u]) % width] = expected[u, c]
    _assert_close_f32(projector.xyz(destaggered, destaggered=True), expected_d, destaggered)
    np.testing.assert_allclose(geometry.exact_xyz(info, destaggered, destaggered=True),
                               expected_d, rtol=0, atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), height=st.integers(1, 5), width=st.integers(1, 9),
       transform=st.booleans(), measured=st.booleans())
def test_beam_factors_reproduce_the_loop_reference(seed: int, height: int, width: int,
                                                   transform: bool, measured: bool) -> None:
    """The factored form (module docstring) gives the reference's points in float64."""
    p = _random_params(seed, height, width, transform=transform)
    info = _info(p)
    ranges = _ranges(seed, height, width)
    alpha = (list(np.random.default_rng(seed).uniform(-math.pi, math.pi, width))
             if measured else None)
    found = geometry.beam_factors(info, alpha)
    assert found is not None
    rows, cols, const = found
    assert (rows.shape, cols.shape, const.shape) == ((height, 6), (6, width), (6,))
    for u in range(height):
        for c in range(width):
            expected = _ref_point(p, u, c, float(ranges[u, c]), alpha)
            if expected is None:
                continue
            q = rows[u, :3] + float(ranges[u, c]) * rows[u, 3:]
            got = [cols[2 * k, c] * q[0] + cols[2 * k + 1, c] * q[1] + const[k] * q[2]
                   + const[3 + k] for k in range(3)]
            np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9)
    f32 = geometry.Projector(info).factors(alpha)
    assert f32 is not None and all(a.dtype == np.float32 and a.flags.c_contiguous for a in f32)


def test_beam_factors_none_with_per_pixel_angles() -> None:
    p = _random_params(3, 2, 3, pixel_angles=True)
    info = _info(p)
    assert geometry.beam_factors(info) is None
    assert geometry.Projector(info).factors() is None


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), height=st.integers(1, 4), width=st.integers(1, 8),
       destaggered=st.booleans())
def test_measured_column_azimuths(seed: int, height: int, width: int, destaggered: bool) -> None:
    """A scan's column_azimuth_angles replace horizontal_angles (Velodyne-style)."""
    p = _random_params(seed, height, width)
    info = _info(p)
    rng = np.random.default_rng(seed + 7)
    alpha = rng.uniform(-7, 7, width)
    ranges = _ranges(seed, height, width)
    expected = _reference_cloud(p, ranges, alpha.tolist())
    projector = geometry.make_projector(info)
    channel = projector.destagger(ranges) if destaggered else ranges
    scan = lidarscan.make_scan(info, {"range": channel}, STAMP, is_destaggered=destaggered,
                               column_azimuth_angles=alpha, as_dataclass=True)
    points = projector.project(scan)
    if destaggered:
        points = projector.restagger(points)
    _assert_close_f32(points, expected, ranges)
    np.testing.assert_allclose(geometry.exact_xyz(info, ranges, column_azimuth_angles=alpha),
                               expected, rtol=0, atol=1e-9)


def test_pixel_angle_override_uses_pixel_direction_and_beam_rotation_for_origin() -> None:
    """Hand-computed single pixel: direction from the pixel angles, origin by alpha + beta."""
    info = lidarscan.make_info(
        stamp_ns=1, frame_id="f", vertical_angles=[0.3], horizontal_angles=[0.5],
        beam_azimuth_offsets=[0.25], pixel_azimuth_angles=[-1.0], pixel_altitude_angles=[0.2],
        beam_origins=[0.1, 0.0, 0.02], beam_range_offsets=[0.01], as_dataclass=True)
    rho = 3.0
    d = np.array([math.cos(0.2) * math.cos(-1.0), math.cos(0.2) * math.sin(-1.0),
                  math.sin(0.2)])
    o = np.array([0.1 * math.cos(0.75), 0.1 * math.sin(0.75), 0.02])
    expected = o + (rho + 0.01) * d
    np.testing.assert_allclose(geometry.exact_xyz(info, [[rho]])[0, 0], expected, atol=1e-12)
    np.testing.assert_allclose(lidarscan.make_projector(info).xyz(np.array([[rho]]))[0, 0],
                               expected, atol=1e-6)


def test_invalid_ranges_give_nan_points() -> None:
    p = _random_params(3, 1, 7)
    info = _info(p)
    ranges = np.array([[np.inf, -np.inf, np.nan, 0.0, -1.0, 1e-30, 2.5]], np.float32)
    for points in (lidarscan.make_projector(info).xyz(ranges), geometry.exact_xyz(info, ranges)):
        assert np.isnan(points[0, :5]).all()
        assert np.isfinite(points[0, 5:]).all()


def test_xyz_out_argument_and_shape_errors() -> None:
    p = _random_params(4, 2, 3)
    projector = geometry.Projector(_info(p))
    ranges = np.ones((2, 3), np.float32)
    out = np.empty((2, 3, 3), np.float32)
    result = projector.xyz(ranges, out=out)
    assert result is out
    np.testing.assert_array_equal(out, projector.xyz(ranges))
    with pytest.raises(ValidationError):
        projector.xyz(np.ones((3, 2), np.float32))
    with pytest.raises(ValidationError):
        projector.xyz(ranges, out=np.empty((2, 3, 3), np.float64))


def test_ranges_are_not_modified() -> None:
    p = _random_params(5, 2, 4)
    ranges = _ranges(5, 2, 4)
    before = ranges.copy()
    geometry.Projector(_info(p)).xyz(ranges)
    geometry.exact_xyz(_info(p), ranges)
    np.testing.assert_array_equal(ranges, before)


# ------------------------------------------------------------------------------- stagger

@settings(max_examples=60, deadline=None)
@given(height=st.integers(1, 5), width=st.integers(1, 9),
       shifts=st.lists(st.integers(-40, 40), min_size=5, max_size=5), extra=st.integers(0, 3))
def test_destagger_definition_and_inverse(height: int, width: int, shifts: list[int],
                                          extra: int) -> None:
    p = _random_params(0, height, width, transform=False)
    p["pixel_shift_by_row"] = shifts[:height]
    projector = geometry.Projector(_info(p))
    shape = (height, width) + (2,) * min(extra, 1)
    image = np.arange(np.prod(shape)).reshape(shape)
    destaggered = projector.destagger(image)
    for u in range(height):
        for c in range(width):
            np.testing.assert_array_equal(destaggered[u, (c + shifts[u]) % width], image[u, c])
    np.testing.assert_array_equal(projector.restagger(destaggered), image)
    np.testing.assert_array_equal(projector.destagger(projector.restagger(image)), image)
    assert not np.shares_memory(destaggered, image)


def test_destagger_rejects_wrong_shape() -> None:
    projector = geometry.Projector(_info(_random_params(1, 2, 3)))
    with pytest.raises(ValidationError):
        projector.destagger(np.zeros((3, 3)))
    with pytest.raises(ValidationError):
        projector.restagger(np.zeros(6))


# ---------------------------------------------------------------------------------- time

@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), height=st.integers(1, 4), width=st.integers(1, 8),
       explicit=st.booleans())
def test_pixel_times(seed: int, height: int, width: int, explicit: bool) -> None:
    p = _random_params(seed, height, width)
    info = _info(p)
    rng = np.random.default_rng(seed)
    offsets = rng.integers(-10**9, 10**9, width) if explicit else None
    projector = geometry.make_projector(info)
    ranges = _ranges(seed, height, width)
    staggered = lidarscan.make_scan(info, {"range": ranges}, STAMP,
                                    column_time_offsets=offsets, as_dataclass=True)
    destaggered = lidarscan.make_scan(info, {"range": projector.destagger(ranges)}, STAMP,
                                      is_destaggered=True, column_time_offsets=offsets,
                                      as_dataclass=True)
    times = projector.pixel_times(staggered)
    for u in range(height):
        for c in range(width):
            column = int(offsets[c]) if explicit else c * p["column_time_increment"]
            assert times[u, c] == column + p["beam_time_offsets"][u]
    times_d = projector.pixel_times(destaggered)
    shifts = p["pixel_shift_by_row"]
    for u in range(height):
        for c in range(width):
            assert times_d[u, (c + shifts[u]) % width] == times[u, c]
    # same (point, time) pairs from both orders
    pts_s, pts_d = projector.project(staggered), projector.project(destaggered)

    def pairs(points: np.ndarray, t: np.ndarray) -> list[tuple[float, ...]]:
        valid = ~np.isnan(points).any(-1)
        rows = np.concatenate([points[valid].astype(np.float64), t[valid][:, None]], 1)
        return sorted(map(tuple, rows.tolist()))

    assert pairs(pts_s, times) == pairs(pts_d, times_d)
    assert times.dtype == np.int64


def test_column_time_offsets_length_checked() -> None:
    p = _random_params(2, 2, 4)
    info = _info(p)
    scan = lidarscan.types.LidarScan(height=2, width=4, column_time_offsets=np.arange(3))
    with pytest.raises(ValidationError):
        geometry.make_projector(info).column_times(scan)


# --------------------------------------------------------------------------------- cache

def test_make_projector_cache_hit_and_miss() -> None:
    p = _random_params(11, 3, 5)
    info = _info(p)
    first = geometry.make_projector(info)
    assert geometry.make_projector(info) is first
    # an equal info built separately (and as an rclpy message) hits the same entry
    assert geometry.make_projector(_info(p)) is first
    assert geometry.make_projector(_info(p, as_dataclass=False)) is first
    # same stamp, other geometry -> another projector with other tables
    q = dict(p, beam_range_offsets=[v + 0.01 for v in p["beam_range_offsets"]])
    other = geometry.make_projector(_info(q))
    assert other is not first
    assert not np.allclose(other.offsets, first.offsets)
    # same geometry, other stamp -> another projector (a new version)
    assert geometry.make_projector(_info(p, stamp_ns=STAMP + 1)) is not first
    assert geometry.info_key(info)[0] == STAMP


def test_cache_is_bounded() -> None:
    infos = [_info(_random_params(100 + i, 1, 2), stamp_ns=i) for i in range(20)]
    projectors = [geometry.make_projector(i) for i in infos]
    assert len(geometry._CACHE) <= geometry._CACHE_SIZE
    assert geometry.make_projector(infos[-1]) is projectors[-1]


def test_tables_destaggered_match_definition() -> None:
    p = _random_params(21, 4, 6)
    projector = geometry.Projector(_info(p))
    d, o = projector.tables(destaggered=True)
    for u in range(4):
        for c in range(6):
            v = (c + p["pixel_shift_by_row"][u]) % 6
            np.testing.assert_array_equal(d[u, v], projector.directions[u, c])
            np.testing.assert_array_equal(o[u, v], projector.offsets[u, c])
    assert projector.directions.dtype == np.float32 and projector.offsets.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(projector.directions, axis=-1), 1.0, atol=1e-6)


def test_geometry_and_importers_do_not_import_rclpy() -> None:
    import subprocess
    code = ("import sys, lidarscan.geometry, converters.sources.ouster.metadata, converters.sources.velodyne, "
            "converters.sources.sweep; sys.exit('rclpy' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0


def test_projector_is_not_affected_by_later_changes_to_the_info_message() -> None:
    p = _random_params(31, 2, 3)
    info = _info(p, as_dataclass=False)
    projector = geometry.Projector(info)
    alpha = np.array([0.1, 0.2, 0.3])
    before = projector._tables(alpha)
    info.vertical_angles[0] += 0.5          # rclpy array.array is mutable
    after = projector._tables(alpha)
    np.testing.assert_array_equal(before[0], after[0])
    np.testing.assert_array_equal(before[1], after[1])
