"""LaserScanMerger and the shared angle grid: conventions, value classes, sync, odometry.

Oracles: ``ref_grid`` / ``ref_bin`` / ``ref_merge`` below are plain loops written from the
documented rules (converters/slices/spec.py and converters/merger.py docstrings).
"""

from __future__ import annotations

import array
import importlib.util
import math
import pathlib
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import lidarscan
from converters.slices import spec as _grid
from converters.slices.spec import AngleGrid
from converters.merger import LaserScanMerger, MergerInput, Pose, interpolate_pose
from lidarscan.errors import ConfigError, ValidationError
from lidarscan.types import Header, Time, message_class
from grid_reference import RANK, pose, ref_bin, ref_grid, ref_qualify

DATA = pathlib.Path(__file__).parent / "data" / "laserscan"
MCAP = DATA / "scan_tools_laser_scan_matcher_demo.mcap"
LaserScanDC = message_class("sensor_msgs/msg/LaserScan")
TWO_PI = 2 * math.pi  # as in grid_reference
F32 = np.float32


# ------------------------------------------------------------------------------ reference code

def ref_fuse(cands: dict[int, tuple[Any, ...]], b: int, cls: str, value: float, key: int,
             intensity: float) -> None:
    v32 = float(F32(value)) if cls == "finite" else 0.0
    cand = (RANK[cls], v32, key, intensity)
    if b not in cands or cand[:3] < cands[b][:3]:
        cands[b] = cand


def ref_output(cands: dict[int, tuple[Any, ...]], n: int, *, range_max: float = math.inf,
               use_inf: bool = True, eps: float = 1.0, fill: float | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    inf_value = math.inf if use_inf else range_max + eps
    fill_value = inf_value if fill is None else fill
    ranges = np.full(n, fill_value, np.float32)
    ints = np.zeros(n, np.float32)
    for b, (rank, v32, _key, inten) in cands.items():
        ranges[b] = [v32, -math.inf, inf_value, math.nan][rank]
        ints[b] = inten
    return ranges, ints


def ref_merge(inputs: dict[str, MergerInput], scans: dict[str, Any], *, amin: float = -math.pi,
              amax: float = math.pi, inc: float = math.radians(0.25), rmin: float = 0.0,
              rmax: float = math.inf, use_inf: bool = True, fill: float | None = None,
              matrices: dict[str, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    grid = ref_grid(amin, amax, inc)
    cands: dict[int, tuple[Any, ...]] = {}
    key = 0
    for name, cfg in inputs.items():
        if name not in scans:
            continue
        scan = scans[name]
        m = (matrices or {}).get(name)
        if m is None:
            m = np.eye(4) if cfg.extrinsics is None else np.asarray(cfg.extrinsics, float)
        ranges = [float(v) for v in np.asarray(scan.ranges, np.float32)]
        inten = [float(v) for v in np.asarray(scan.intensities, np.float32)]
        if len(inten) != len(ranges):
            inten = [0.0] * len(ranges)
        smin = float(scan.range_min) if float(scan.range_min) > 0 else 0.0
        smax = float(scan.range_max) if float(scan.range_max) > 0 else math.inf
        a0, da = float(scan.angle_min), float(scan.angle_increment)
        for i, r in enumerate(ranges):
            k = key + i
            theta = a0 + i * da
            if cfg.angle_min is not None:
                rel = (theta - cfg.angle_min) % TWO_PI
                if rel > (cfg.angle_max - cfg.angle_min) % TWO_PI \
                        and cfg.angle_max - cfg.angle_min < TWO_PI:
                    continue
            if math.isnan(r):
                cls = "nan"
            elif r == math.inf:
                cls = "pos"
            elif r == -math.inf:
                cls = "neg"
            elif r < smin or r <= 0:
                cls = "nan"
            elif r > min(smax, cfg.range_max):
                cls = "pos"
            elif r < cfg.range_min:
                continue
            else:
                cls = "point"
            c, s = math.cos(theta), math.sin(theta)
            d = tuple(m[j, 0] * c + m[j, 1] * s for j in range(3))
            o = (m[0, 3], m[1, 3], m[2, 3])
            if cls == "point":
                x, y, z = (r * d[j] + o[j] for j in range(3))
                if not cfg.min_height <= z <= cfg.max_height:
                    continue
                b = ref_bin(math.atan2(y, x), grid)
                if b is None:
                    continue
                rho = math.sqrt(x * x + y * y)
                out = "neg" if rho < rmin else "pos" if rho > rmax else "finite"
                ref_fuse(cands, b, out, rho, k, inten[i])
                continue
            if d[0] == 0 and d[1] == 0:
                continue
            far, near_ok = ref_qualify(d, o, cfg.min_height, cfg.max_height, rmin, rmax, smin)
            if (cls == "neg" and not near_ok) or (cls != "neg" and not far):
                continue
            b = ref_bin(math.atan2(d[1], d[0]), grid)
            if b is not None:
                ref_fuse(cands, b, cls, 0.0, k, inten[i])
        key += len(ranges)
    return ref_output(cands, grid[2], range_max=rmax, use_inf=use_inf, fill=fill)


# ----------------------------------------------------------------------------------- helpers

BACKENDS = ["numpy", pytest.param("numba", marks=pytest.mark.skipif(
    importlib.util.find_spec("numba") is None, reason="numba not installed"))]


def backends() -> list[str]:
    return ["numpy"] + (["numba"] if importlib.util.find_spec("numba") else [])


def make_scan(ranges: Any, *, angle_min: float = -math.pi, inc: float | None = None,
              stamp: int = 1_000_000_000, intensities: Any = (), range_min: float = 0.0,
              range_max: float = 100.0, frame: str = "base_link", kind: str = "dc") -> Any:
    """A LaserScan (dataclass with numpy arrays, or rclpy with array.array)."""
    ranges = np.asarray(ranges, np.float32)
    n = ranges.size
    if inc is None:
        inc = TWO_PI / max(n, 1)
    sec, nsec = divmod(stamp, 10**9)
    fields = {"angle_min": float(F32(angle_min)),
                  "angle_max": float(F32(angle_min + (n - 1) * inc)),
                  "angle_increment": float(F32(inc)), "time_increment": 0.0, "scan_time": 0.1,
                  "range_min": float(F32(range_min)), "range_max": float(F32(range_max))}
    if kind == "rclpy":
        from builtin_interfaces.msg import Time as RTime
        from sensor_msgs.msg import LaserScan
        from std_msgs.msg import Header as RHeader
        msg = LaserScan(header=RHeader(stamp=RTime(sec=sec, nanosec=nsec), frame_id=frame),
                        **fields)
        msg.ranges = array.array("f", ranges.tobytes())
        msg.intensities = array.array("f", np.asarray(intensities, np.float32).tobytes())
        return msg
    if kind == "list":
        return LaserScanDC(header=Header(Time(sec, nsec), frame), ranges=ranges.tolist(),
                           intensities=list(np.asarray(intensities, float)), **fields)
    return LaserScanDC(header=Header(Time(sec, nsec), frame), ranges=ranges,
                       intensities=np.asarray(intensities, np.float32), **fields)


def out_arrays(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    return np.array(msg.ranges, np.float32), np.array(msg.intensities, np.float32)


def assert_same(msg: Any, expected: tuple[np.ndarray, np.ndarray]) -> None:
    ranges, ints = out_arrays(msg)
    np.testing.assert_array_equal(ranges, expected[0])
    np.testing.assert_array_equal(ints, expected[1])


@pytest.fixture(scope="module")
def real_scans() -> list[Any]:
    from mcap.reader import make_reader
    out = []
    with open(MCAP, "rb") as f:
        for _schema, _channel, message in make_reader(f).iter_messages(topics=["/scan"]):
            out.append(lidarscan.decode(message.data, "sensor_msgs/msg/LaserScan"))
    return out


# -------------------------------------------------------------------------------- the grid

class TestGrid:
    def test_full_circle_default(self) -> None:
        g = AngleGrid.create(-math.pi, math.pi, math.radians(0.25))
        assert (g.size, g.full_circle) == (1440, True)
        amin, amax, inc = g.header()
        assert amin == float(F32(-math.pi))
        assert amax == float(F32(-math.pi + 1439 * math.radians(0.25)))
        assert inc == float(F32(math.radians(0.25)))

    def test_published_header_of_a_full_circle_configures_the_same_grid(self) -> None:
        inc = TWO_PI / 360
        g = AngleGrid.create(-math.pi, -math.pi + 359 * inc, inc)
        assert (g.size, g.full_circle) == (360, True)
        g2 = AngleGrid.create(-math.pi, -math.pi + 358 * inc, inc)
        assert (g2.size, g2.full_circle) == (359, False)

    def test_float32_pi_limits_are_a_full_circle(self) -> None:
        g = AngleGrid.create(float(F32(-math.pi)), float(F32(math.pi)), math.radians(1))
        assert (g.size, g.full_circle) == (360, True)

    def test_span_not_a_multiple_of_the_increment(self) -> None:
        # prior art (g) 3: -pi/2..pi/2 at 0.0087 -> 362 = round(span/inc) + 1
        g = AngleGrid.create(-math.pi / 2, math.pi / 2, 0.0087)
        assert (g.size, g.full_circle) == (362, False)
        assert g.angle_max == pytest.approx(-math.pi / 2 + 361 * 0.0087)
        assert g.header()[1] == float(F32(-math.pi / 2 + 361 * 0.0087))

    def test_full_circle_snaps_the_increment(self) -> None:
        g = AngleGrid.create(-math.pi, math.pi, 0.0058)
        assert g.size == round(TWO_PI / 0.0058) == 1083
        assert g.increment == TWO_PI / 1083

    def test_single_ray_sector(self) -> None:
        g = AngleGrid.create(0.5, 0.5, 0.25)
        assert (g.size, g.full_circle) == (1, False)
        # bin 0 covers (0.375, 0.625]: both edges exact in binary
        assert g.bins(np.array([0.5, 0.625, 0.375, 0.376, 0.626])).tolist() == [0, 0, -1, 0, -1]

    @pytest.mark.parametrize("args, field", [
        ((0.0, 1.0, 0.0), "angle_increment"), ((0.0, 1.0, -0.1), "angle_increment"),
        ((1.0, 0.0, 0.1), "angle_max"), ((0.0, 7.0, 0.1), "angle_max - angle_min"),
        ((math.nan, 1.0, 0.1), "angle_min"), ((0.0, math.inf, 0.1), "angle_max"),
        ((0.0, 1.0, 1e-9), "angle_increment")])
    def test_errors(self, args: tuple[float, float, float], field: str) -> None:
        with pytest.raises(ConfigError) as err:
            AngleGrid.create(*args)
        assert err.value.field == field

    def test_plus_and_minus_pi_share_a_bin(self) -> None:
        g = AngleGrid.create(-math.pi, math.pi, math.radians(1))
        theta = np.array([math.atan2(0.0, -1.0), math.atan2(-0.0, -1.0),
                          math.pi - 1e-7, -math.pi + 1e-7])
        assert theta[0] == math.pi and theta[1] == -math.pi
        assert g.bins(theta).tolist() == [0, 0, 0, 0]

    def test_half_bin_goes_to_the_lower_index(self) -> None:
        g = AngleGrid.create(0.0, 1.0, 0.25)        # sector, exact binary fractions
        theta = np.array([0.125, 0.375, 0.0, 0.25, 0.124999, 0.375000001, 1.125, -0.125])
        assert g.bins(theta).tolist() == [0, 1, 0, 1, 0, 2, 4, -1]
        # numpy's half-to-even would put 0.375 (t = 1.5) into bin 2: not our rule
        assert np.round(1.5) == 2

    def test_half_bin_at_the_seam_of_a_full_circle(self) -> None:
        g = AngleGrid.create(0.0, TWO_PI, math.pi / 2)   # 4 bins
        assert (g.size, g.full_circle) == (4, True)
        # -pi/4 is exactly between bin 3 (3pi/2) and bin 0: the smaller angle, bin 3
        assert g.bins(np.array([-math.pi / 4, math.pi / 4, 3 * math.pi / 4])).tolist() == \
            [3, 0, 1]

    def test_window_beyond_pi(self) -> None:
        g = AngleGrid.create(0.0, 1.5 * math.pi, math.pi / 4)     # sector of 7 bins, 0..3pi/2
        assert (g.size, g.full_circle) == (7, False)
        theta = np.array([-math.pi / 2, -math.pi / 2 + 0.1, math.pi, -3.0, -0.7, -0.8, 0.1])
        # -pi/2 == 3pi/2 -> bin 6; -0.7 and -0.8 (5.58, 5.48 rad) lie beyond the last bin's
        # upper edge 6.5 pi/4 = 5.105 -> outside
        assert g.bins(theta).tolist() == [6, 6, 4, 4, -1, -1, 0]
        # bin 0's lower edge -pi/8 is outside (half-bin rule), just above it is inside
        assert g.bins(np.array([-math.pi / 8, -math.pi / 8 + 1e-9])).tolist() == [-1, 0]
        full = AngleGrid.create(0.0, 1.5 * math.pi, math.pi / 2)   # 4 bins cover the circle
        assert (full.size, full.full_circle) == (4, True)

    def test_window_straddling_pi(self) -> None:
        g = AngleGrid.create(3 * math.pi / 4, 5 * math.pi / 4, math.pi / 4)   # 3 bins
        assert (g.size, g.full_circle) == (3, False)
        theta = np.array([math.pi, -math.pi, -3 * math.pi / 4, 3 * math.pi / 4, 0.0])
        assert g.bins(theta).tolist() == [1, 1, 2, 0, -1]

    @given(st.floats(-4.0, 4.0), st.floats(0.001, 0.5), st.floats(0.0, TWO_PI),
           st.lists(st.floats(-10.0, 10.0), min_size=1, max_size=30))
    def test_bins_match_reference(self, amin: float, inc: float, span: float,
                                  thetas: list[float]) -> None:
        g = AngleGrid.create(amin, amin + span, inc)
        ref = ref_grid(amin, amin + span, inc)
        assert (g.angle_min, g.increment, g.size, g.full_circle) == ref
        got = g.bins(np.array(thetas)).tolist()
        assert got == [-1 if (b := ref_bin(t, ref)) is None else b for t in thetas]

    @given(st.floats(-math.pi, math.pi), st.floats(0.001, 0.3))
    def test_full_circle_is_periodic(self, theta: float, inc: float) -> None:
        g = AngleGrid.create(-math.pi, math.pi, inc)
        b = g.bins(np.array([theta]))[0]
        centre = g.angle_min + b * g.increment
        assert abs(math.remainder(theta - centre, TWO_PI)) <= g.increment / 2 + 1e-12

    def test_qualify_against_sampled_rays(self, rng: np.random.Generator) -> None:
        """The closed-form +Inf/-Inf qualification agrees with dense sampling along rays."""
        n = 300
        d = rng.normal(size=(n, 3))
        d /= np.linalg.norm(d, axis=1)[:, None]
        o = rng.normal(scale=0.5, size=(n, 3))
        q_far, q_near = _grid.qualify(d, o, -0.2, 0.3, 0.5, 4.0, 0.4)
        r = np.linspace(0, 60, 200001)
        for i in range(n):
            p = r[:, None] * d[i] + o[i]
            band = (p[:, 2] >= -0.2) & (p[:, 2] <= 0.3)
            rho = np.hypot(p[:, 0], p[:, 1])
            far = np.any(band & (rho >= 0.5) & (rho <= 4.0))
            near = np.any(band & (r <= 0.4))
            assert far == q_far[i], i
            assert near == q_near[i], i


# ------------------------------------------------------------------------- merge: geometry

def test_output_is_an_rclpy_laserscan_with_array_fields() -> None:
    from sensor_msgs.msg import LaserScan
    m = LaserScanMerger({"a": MergerInput()}, frame_id="base_link")
    out = m.merge({"a": make_scan(np.ones(360), stamp=5_000_000_123)})
    assert isinstance(out, LaserScan)
    assert isinstance(out.ranges, array.array) and out.ranges.typecode == "f"
    assert len(out.ranges) == len(out.intensities) == 1440
    assert (out.header.stamp.sec, out.header.stamp.nanosec) == (5, 123)
    assert out.header.frame_id == "base_link"
    assert out.time_increment == 0.0 and out.scan_time == pytest.approx(0.1)


@pytest.mark.parametrize("kind", ["dc", "rclpy", "list"])
def test_input_kinds_agree(kind: str, rng: np.random.Generator) -> None:
    ranges = rng.uniform(0.1, 10, 720).astype(np.float32)
    ints = rng.uniform(0, 100, 720).astype(np.float32)
    inputs = {"a": MergerInput(extrinsics=pose(0.2, -0.1, 0, 0.3))}
    scan = make_scan(ranges, intensities=ints, kind=kind)
    got = LaserScanMerger(inputs).merge({"a": scan})
    assert_same(got, ref_merge(inputs, {"a": make_scan(ranges, intensities=ints)}))


def test_same_grid_round_trip_is_identity(rng: np.random.Generator) -> None:
    ranges = rng.uniform(0.5, 20, 1440).astype(np.float32)
    got = LaserScanMerger({"a": MergerInput()}).merge({"a": make_scan(ranges)})
    np.testing.assert_array_equal(out_arrays(got)[0], ranges)


def test_negative_increment_equals_reversed_scan(rng: np.random.Generator) -> None:
    ranges = rng.uniform(0.5, 20, 500).astype(np.float32)
    inc = math.radians(0.5)
    fwd = make_scan(ranges, angle_min=-1.2, inc=inc)
    back = make_scan(ranges[::-1], angle_min=-1.2 + 499 * inc, inc=-inc)
    m = LaserScanMerger({"a": MergerInput()}, angle_increment=math.radians(0.5))
    a, b = out_arrays(m.merge({"a": fwd}))[0], out_arrays(m.merge({"a": back}))[0]
    assert np.isfinite(a).sum() == 500
    # float32 angle fields differ slightly between the two headers: compare with a tolerance
    np.testing.assert_array_equal(np.isfinite(a), np.isfinite(b))
    np.testing.assert_allclose(a[np.isfinite(a)], b[np.isfinite(b)])


def test_upside_down_mount_mirrors_the_scan() -> None:
    ranges = np.full(360, np.inf, np.float32)
    ranges[45] = 2.0                    # ray at -pi + 45 deg = -135 deg in the sensor frame
    inputs = {"a": MergerInput(extrinsics=pose(roll=math.pi))}
    out = out_arrays(LaserScanMerger(inputs, angle_increment=math.radians(1)).merge(
        {"a": make_scan(ranges)}))[0]
    assert np.flatnonzero(np.isfinite(out)).tolist() == [315]       # +135 deg
    assert out[315] == pytest.approx(2.0)
    assert_same(LaserScanMerger(inputs, angle_increment=math.radians(1)).merge(
        {"a": make_scan(ranges)}), ref_merge(inputs, {"a": make_scan(ranges)},
                                             inc=math.radians(1)))


def test_offset_sensors_occlusion() -> None:
    """A near obstacle seen only by the rear sensor hides the far wall the front sensor sees in
    the same output direction: each endpoint is binned by its own output azimuth, min wins."""
    front = np.full(360, np.inf, np.float32)
    rear = np.full(360, np.inf, np.float32)
    front[180] = 5.0                    # front sensor at x=+1 sees a wall point 5 m ahead: x=6
    rear[180 + 0] = 3.0                 # rear sensor at x=-1 sees an obstacle at x=2
    inputs = {"front": MergerInput(extrinsics=pose(1.0)), "rear": MergerInput(extrinsics=pose(-1))}
    m = LaserScanMerger(inputs, angle_increment=math.radians(1))
    out = out_arrays(m.merge({"front": make_scan(front), "rear": make_scan(rear)}))[0]
    assert out[180] == pytest.approx(2.0)
    assert np.isinf(out[0])             # +Inf rays of both sensors keep free space
    # rays that cross: a point at y=+1 seen from x=+1 (90 deg) sits at 45 deg in base_link
    front2 = np.full(360, np.inf, np.float32)
    front2[270] = 1.0
    out2 = out_arrays(m.merge({"front": make_scan(front2)}))[0]
    assert out2[225] == pytest.approx(math.sqrt(2.0))


def test_mixed_resolutions_min_on_downsampling_no_duplication(rng: np.random.Generator) -> None:
    coarse = rng.uniform(1, 10, 360).astype(np.float32)
    fine = rng.uniform(1, 10, 1440).astype(np.float32)
    inputs = {"coarse": MergerInput(), "fine": MergerInput()}
    scans = {"coarse": make_scan(coarse), "fine": make_scan(fine)}
    m = LaserScanMerger(inputs, angle_increment=math.radians(0.5))
    got = m.merge(scans)
    assert_same(got, ref_merge(inputs, scans, inc=math.radians(0.5)))
    out = out_arrays(got)[0]
    # down-sampling: a 0.5 deg bin holds the min of its fine rays (the one at its centre and
    # one at a half-bin) and of the coarse ray at every other bin
    assert np.all(out <= fine[0::2]) and np.all(out[0::2] <= coarse)
    assert np.all(np.isfinite(out))
    # up-sampling a 360-ray scan to 1440 bins: 360 bins hit, the others are fill (+Inf)
    up = out_arrays(LaserScanMerger({"coarse": MergerInput()}).merge(
        {"coarse": make_scan(coarse)}))[0]
    assert np.isfinite(up).sum() == 360 and np.all(np.isinf(up[~np.isfinite(up)]))


@pytest.mark.parametrize("backend", BACKENDS)
def test_input_value_classes_and_limits(backend: str) -> None:
    # scan limits 0.1 .. 10 (sensor), user filter 0.3 .. 8, output planar limits 0.2 .. 9
    values = [math.nan, math.inf, -math.inf, 0.0, -1.0, 0.05, 0.1, 0.2, 0.3, 5.0, 8.0, 8.5,
              10.0, 10.5]
    ranges = np.full(360, np.nan, np.float32)
    for k, v in enumerate(values):
        ranges[20 * k] = v
    inputs = {"a": MergerInput(range_min=0.3, range_max=8.0)}
    scan = make_scan(ranges, range_min=0.1, range_max=10.0)
    got = LaserScanMerger(inputs, angle_increment=math.radians(1), range_min=0.2,
                          range_max=9.0, fill=-7.0, backend=backend).merge({"a": scan})
    out = out_arrays(got)[0]
    expect = [math.nan, math.inf, -math.inf, math.nan, math.nan, math.nan, -7.0, -7.0, 0.3,
              5.0, 8.0, math.inf, math.inf, math.inf]
    got_vals = [float(out[20 * k]) for k in range(len(values))]
    np.testing.assert_array_equal(np.array(got_vals, np.float32), np.array(expect, np.float32))
    assert_same(got, ref_merge(inputs, {"a": scan}, inc=math.radians(1), rmin=0.2, rmax=9.0,
                               fill=-7.0))


@pytest.mark.parametrize("backend", BACKENDS)
def test_scan_range_limits_are_inclusive(backend: str) -> None:
    # exactly the scan's range_min / range_max (float32 fields) are valid points
    scan = make_scan([0.5, 8.0, 0.25, 9.0], range_min=0.5, range_max=8.0)
    m = LaserScanMerger({"a": MergerInput()}, angle_increment=math.pi / 2, backend=backend)
    out = out_arrays(m.merge({"a": scan}))[0]
    np.testing.assert_array_equal(out, np.array([0.5, 8.0, np.nan, np.inf], np.float32))


@pytest.mark.parametrize("backend", BACKENDS)
def test_output_range_limits_are_inclusive_and_classify(backend: str) -> None:
    ranges = np.full(4, np.inf, np.float32)
    ranges[:] = [1.0, 2.0, 0.5, 2.5]
    m = LaserScanMerger({"a": MergerInput()}, angle_increment=math.pi / 2, range_min=1.0,
                        range_max=2.0, backend=backend)
    out = out_arrays(m.merge({"a": make_scan(ranges)}))[0]
    assert out.tolist() == [1.0, 2.0, -math.inf, math.inf]


def test_use_inf_false_and_fill() -> None:
    ranges = np.array([math.inf, 1.0, math.nan, -math.inf], np.float32)
    m = LaserScanMerger({"a": MergerInput()}, angle_increment=math.pi / 4, range_max=5.0,
                        use_inf=False, inf_epsilon=0.5)
    out = out_arrays(m.merge({"a": make_scan(ranges)}))[0]
    # 4 rays on an 8-bin grid: bins 0, 2, 4, 6 hit; empty bins get range_max + eps too
    assert out[0] == 5.5 and out[2] == 1.0 and math.isnan(out[4]) and out[6] == -math.inf
    assert np.all(out[1::2] == 5.5)
    m2 = LaserScanMerger({"a": MergerInput()}, angle_increment=math.pi / 4, fill=math.nan)
    out2 = out_arrays(m2.merge({"a": make_scan(ranges)}))[0]
    assert out2[0] == math.inf and np.all(np.isnan(out2[1::2]))   # free vs "no data"


def test_class_precedence_in_one_bin() -> None:
    order = [("finite", 3.0), ("neg", -math.inf), ("pos", math.inf), ("nan", math.nan)]
    for i, (_, expect) in enumerate(order):
        inputs = {f"s{k}": MergerInput() for k in range(4)}
        scans = {}
        for k, (_, value) in enumerate(order[i:]):
            scans[f"s{k}"] = make_scan(np.full(4, value, np.float32))
        out = out_arrays(LaserScanMerger(inputs, angle_increment=math.pi / 2).merge(scans))[0]
        np.testing.assert_array_equal(out, np.full(4, expect, np.float32))


def test_ties_go_to_the_first_input_and_intensity_follows_the_minimum() -> None:
    inputs = {"a": MergerInput(), "b": MergerInput()}
    a = make_scan([2.0, 1.0, 3.0, 4.0], intensities=[10, 11, 12, 13])
    b = make_scan([2.0, 2.0, 1.0, 4.0], intensities=[20, 21, 22, 23])
    m = LaserScanMerger(inputs, angle_increment=math.pi / 2)
    ranges, ints = out_arrays(m.merge({"a": a, "b": b}))
    assert ranges.tolist() == [2.0, 1.0, 1.0, 4.0]
    assert ints.tolist() == [10, 11, 22, 13]
    m2 = LaserScanMerger({"b": MergerInput(), "a": MergerInput()}, angle_increment=math.pi / 2)
    assert out_arrays(m2.merge({"a": a, "b": b}))[1].tolist() == [20, 11, 22, 23]


def test_intensities_missing_or_mismatched() -> None:
    inputs = {"a": MergerInput(), "b": MergerInput()}
    a = make_scan([1.0, 5.0, 5.0, 5.0], intensities=[])
    b = make_scan([5.0, 1.0, 5.0, 5.0], intensities=[7.0, 8.0])        # wrong length: ignored
    ranges, ints = out_arrays(LaserScanMerger(inputs, angle_increment=math.pi / 2).merge(
        {"a": a, "b": b}))
    assert ranges.tolist() == [1, 1, 5, 5] and ints.tolist() == [0, 0, 0, 0]
    assert len(LaserScanMerger(inputs, intensities=False).merge({"a": a}).intensities) == 0


def test_zero_and_one_ray_scans() -> None:
    m = LaserScanMerger({"a": MergerInput(), "b": MergerInput()}, angle_increment=math.pi / 2)
    empty = make_scan(np.zeros(0, np.float32), inc=0.0)
    out = out_arrays(m.merge({"a": empty}))[0]
    assert np.all(np.isinf(out))
    one = make_scan([2.0], angle_min=0.0, inc=0.0)
    out = out_arrays(m.merge({"a": empty, "b": one}))[0]
    assert out.tolist() == [math.inf, math.inf, 2.0, math.inf]      # bins -pi, -pi/2, 0, pi/2


def test_angle_window_wraps_across_pi_inclusive() -> None:
    ranges = np.full(8, 1.0, np.float32)             # rays at -pi + k*pi/4
    cfg = MergerInput(angle_min=3 * math.pi / 4, angle_max=-3 * math.pi / 4)
    scan = make_scan(ranges, inc=math.pi / 4)
    out = out_arrays(LaserScanMerger({"a": cfg}, angle_increment=math.pi / 4).merge(
        {"a": scan}))[0]
    # rays at -pi (=pi) and -3pi/4 are inside; the window's ends are inclusive, but float32 of
    # the scan's angle_min moves ray 7 (3pi/4) just outside or inside: compare with the oracle
    assert out[0] == 1.0 and out[1] == 1.0 and np.all(np.isinf(out[2:7]))
    assert_same(LaserScanMerger({"a": cfg}, angle_increment=math.pi / 4).merge({"a": scan}),
                ref_merge({"a": cfg}, {"a": scan}, inc=math.pi / 4))


def test_angle_window_ends_are_inclusive() -> None:
    # rays at exactly -1.0, -0.5, ..., 1.5 (all exact in float32); window [-1, 1]
    scan = make_scan(np.full(6, 2.0, np.float32), angle_min=-1.0, inc=0.5)
    m = LaserScanMerger({"a": MergerInput(angle_min=-1.0, angle_max=1.0)},
                        angle_increment=math.radians(1))
    assert np.count_nonzero(np.isfinite(out_arrays(m.merge({"a": scan}))[0])) == 5
    m2 = LaserScanMerger({"a": MergerInput(angle_min=1.0, angle_max=-1.0)},   # the other arc
                         angle_increment=math.radians(1))
    assert np.count_nonzero(np.isfinite(out_arrays(m2.merge({"a": scan}))[0])) == 3


def test_height_band_for_a_tilted_input() -> None:
    """A 2D lidar pitched down 30 deg at 1 m height: rays ahead hit z = 1 - r sin(30)."""
    ranges = np.full(360, 1.5, np.float32)
    cfg = MergerInput(extrinsics=pose(z=1.0, pitch=math.radians(30)), min_height=0.2,
                      max_height=0.5)
    scan = make_scan(ranges, range_max=30.0)
    m = LaserScanMerger({"a": cfg}, angle_increment=math.radians(1))
    got = m.merge({"a": scan})
    out = out_arrays(got)[0]
    assert np.isfinite(out[180])                   # straight ahead: z = 0.25, in the band
    assert not np.isfinite(out[0])                 # behind: z = 1.75
    assert_same(got, ref_merge({"a": cfg}, {"a": scan}, inc=math.radians(1)))


def test_frame_and_name_checks() -> None:
    m = LaserScanMerger({"a": MergerInput(frame_id="laser", extrinsics=np.eye(4))})
    with pytest.raises(ValidationError):
        m.merge({"a": make_scan([1.0], frame="other")})
    m.merge({"a": make_scan([1.0], frame="laser")})
    with pytest.raises(ConfigError):
        m.merge({"zzz": make_scan([1.0])})
    with pytest.raises(ValidationError):
        m.merge({})
    with pytest.raises(ValidationError):
        m.merge({"a": make_scan([1.0, 2.0], inc=0.0)})


@pytest.mark.parametrize("kwargs", [
    {"policy": "maybe"}, {"reference": "middle"}, {"slop_ns": -1}, {"queue_size": 0},
    {"angle_increment": 0.0}, {"range_min": -1.0}, {"range_max": -1.0}, {"frame_id": ""},
    {"slop_ns": 0.5}])
def test_merger_option_errors(kwargs: dict[str, Any]) -> None:
    with pytest.raises(ConfigError):
        LaserScanMerger({"a": MergerInput()}, **kwargs)


@pytest.mark.parametrize("cfg", [
    MergerInput(extrinsics=np.ones((4, 4))), MergerInput(extrinsics=np.eye(3)),
    MergerInput(range_min=2.0, range_max=1.0), MergerInput(min_height=1.0, max_height=0.0),
    MergerInput(angle_min=0.0), MergerInput(timeout_ns=0), MergerInput(min_height=math.nan)])
def test_input_option_errors(cfg: MergerInput) -> None:
    with pytest.raises(ConfigError):
        LaserScanMerger({"a": cfg})


def test_no_mutation_of_inputs(rng: np.random.Generator) -> None:
    ranges = rng.uniform(0, 5, 360).astype(np.float32)
    ranges[::7] = np.nan
    scan = make_scan(ranges.copy(), kind="rclpy")
    before = bytes(scan.ranges)
    LaserScanMerger({"a": MergerInput(range_min=1.0)}).merge({"a": scan})
    assert bytes(scan.ranges) == before


# ------------------------------------------------------------------------ properties

_values = st.one_of(st.floats(0.0, 12.0, width=32), st.sampled_from(
    [math.inf, -math.inf, math.nan, 0.0, -1.0, 0.1, 10.0]))


@st.composite
def merge_case(draw: Any) -> tuple[dict[str, MergerInput], dict[str, Any], dict[str, Any]]:
    n_inputs = draw(st.integers(1, 3))
    inputs, scans = {}, {}
    for k in range(n_inputs):
        n = draw(st.integers(0, 40))
        ranges = draw(st.lists(_values, min_size=n, max_size=n))
        ints = draw(st.lists(st.floats(0, 100, width=32), min_size=n, max_size=n)) \
            if draw(st.booleans()) else []
        inc = draw(st.sampled_from([1.0, -1.0])) * draw(st.floats(0.01, 0.3))
        scans[f"s{k}"] = make_scan(ranges, angle_min=draw(st.floats(-4, 4)), inc=inc,
                                   intensities=ints, range_min=draw(st.sampled_from([0, 0.1])),
                                   range_max=draw(st.sampled_from([10.0, 0.0])))
        ext = pose(draw(st.floats(-1, 1)), draw(st.floats(-1, 1)), draw(st.floats(-0.5, 0.5)),
                   draw(st.floats(-4, 4)), draw(st.sampled_from([0.0, math.pi, 0.2])),
                   draw(st.sampled_from([0.0, 0.3])))
        window = draw(st.sampled_from([(None, None), (2.5, -2.5), (-1.0, 1.0)]))
        band = draw(st.sampled_from([(-math.inf, math.inf), (-0.5, 0.5), (0.0, 0.0)]))
        inputs[f"s{k}"] = MergerInput(
            extrinsics=ext, range_min=draw(st.sampled_from([0.0, 0.5])),
            range_max=draw(st.sampled_from([math.inf, 8.0])), angle_min=window[0],
            angle_max=window[1], min_height=band[0], max_height=band[1])
    amin = draw(st.floats(-4, 0))
    options = {"angle_min": amin, "angle_max": amin + draw(st.sampled_from([TWO_PI, 1.0, 4.0])),
                   "angle_increment": draw(st.floats(0.02, 0.5)),
                   "range_min": draw(st.sampled_from([0.0, 0.3])),
                   "range_max": draw(st.sampled_from([math.inf, 6.0]))}
    return inputs, scans, options


@given(merge_case())
def test_merge_matches_reference(case: Any) -> None:
    inputs, scans, o = case
    ref = ref_merge(inputs, scans, amin=o["angle_min"], amax=o["angle_max"],
                    inc=o["angle_increment"], rmin=o["range_min"], rmax=o["range_max"])
    for backend in backends():
        assert_same(LaserScanMerger(inputs, backend=backend, **o).merge(scans), ref)


@given(merge_case())
def test_merging_a_scan_with_itself_is_idempotent(case: Any) -> None:
    inputs, scans, o = case
    name, cfg = next(iter(inputs.items()))
    once = LaserScanMerger({name: cfg}, **o).merge({name: scans[name]})
    twice = LaserScanMerger({name: cfg, "copy": cfg}, **o).merge(
        {name: scans[name], "copy": scans[name]})
    np.testing.assert_array_equal(out_arrays(once)[0], out_arrays(twice)[0])
    np.testing.assert_array_equal(out_arrays(once)[1], out_arrays(twice)[1])


@given(merge_case(), st.randoms(use_true_random=False))
def test_permuting_inputs_changes_only_tied_intensities(case: Any, random: Any) -> None:
    inputs, scans, o = case
    names = list(inputs)
    random.shuffle(names)
    a = out_arrays(LaserScanMerger(inputs, **o).merge(scans))
    b = out_arrays(LaserScanMerger({n: inputs[n] for n in names}, **o).merge(scans))
    np.testing.assert_array_equal(a[0], b[0])


# --------------------------------------------------------------------------- real data

def test_real_scan_same_grid_and_self_merge(real_scans: list[Any]) -> None:
    scan = real_scans[0]
    src = np.asarray(scan.ranges, np.float32)
    assert src.size == 681 and np.count_nonzero(src == 0.0) > 0
    grid = {"angle_min": scan.angle_min, "angle_max": scan.angle_max,
            "angle_increment": scan.angle_increment, "frame_id": scan.header.frame_id}
    single = LaserScanMerger({"a": MergerInput()}, **grid).merge({"a": scan})
    ranges = out_arrays(single)[0]
    assert ranges.size == 681 and single.angle_max == pytest.approx(scan.angle_max, abs=1e-6)
    # 0.0 (< range_min 0.02) means "no valid return" in this driver: NaN, everything else kept
    np.testing.assert_array_equal(ranges, np.where(src < scan.range_min, np.nan, src))
    double = LaserScanMerger({"a": MergerInput(), "b": MergerInput()}, **grid).merge(
        {"a": scan, "b": scan})
    np.testing.assert_array_equal(out_arrays(double)[0], ranges)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("inc_deg", [0.1, 0.25, 0.5, 1.0])
def test_real_scan_rebinned(real_scans: list[Any], inc_deg: float, backend: str) -> None:
    scan = real_scans[100]
    inputs = {"a": MergerInput(extrinsics=pose(0.1, 0.05, 0.3, 0.2))}
    got = LaserScanMerger(inputs, angle_increment=math.radians(inc_deg),
                          backend=backend).merge({"a": scan})
    assert_same(got, ref_merge(inputs, {"a": scan}, inc=math.radians(inc_deg)))


@pytest.mark.parametrize("backend", BACKENDS)
def test_real_scan_with_a_rotated_copy(real_scans: list[Any], backend: str) -> None:
    scan = real_scans[200]
    here = np.eye(4)                                # the laser at base_link
    inputs = {"front": MergerInput(extrinsics=here),
              "back": MergerInput(extrinsics=pose(yaw=math.pi))}
    got = LaserScanMerger(inputs, backend=backend).merge({"front": scan, "back": scan})
    assert_same(got, ref_merge(inputs, {"front": scan, "back": scan}))
    ranges = out_arrays(got)[0]
    # the Hokuyo sees 239 deg; a copy turned by 180 deg covers the rest of the circle
    alone = out_arrays(LaserScanMerger({"front": MergerInput(extrinsics=here)}).merge(
        {"front": scan}))[0]
    assert np.count_nonzero(np.isfinite(ranges)) > 1.4 * np.count_nonzero(np.isfinite(alone))
    # 90 deg turn: the overlapping arc holds min of both
    inputs90 = {"a": MergerInput(extrinsics=here),
                "b": MergerInput(extrinsics=pose(yaw=math.pi / 2))}
    assert_same(LaserScanMerger(inputs90).merge({"a": scan, "b": scan}),
                ref_merge(inputs90, {"a": scan, "b": scan}))


def test_real_stream_push(real_scans: list[Any]) -> None:
    """Two inputs fed the real stream (the second 3 ms later): every pair merges once."""
    m = LaserScanMerger({"a": MergerInput(extrinsics=np.eye(4)),      # the laser at base_link
                         "b": MergerInput(extrinsics=pose(yaw=math.pi))}, slop_ns=5_000_000)
    outs = []
    for scan in real_scans[:50]:
        t = lidarscan.to_ns(scan.header.stamp)
        late = LaserScanDC(**{f: getattr(scan, f) for f in LaserScanDC.__dataclass_fields__
                              if f != "header"},
                           header=Header(Time(*divmod(t + 3_000_000, 10**9)), "/laser"))
        for name, s in (("a", scan), ("b", late)):
            out = m.push(name, s)
            if out is not None:
                outs.append(out)
    assert len(outs) == 50
    assert m.stats["merged"] == 50 and m.stats["dropped_unmatched"] == 0
    first = outs[0].header.stamp
    assert first.sec * 10**9 + first.nanosec == lidarscan.to_ns(real_scans[0].header.stamp) + \
        3_000_000


# --------------------------------------------------------------------------------- sync

def _s(stamp: int, value: float = 1.0) -> Any:
    return make_scan(np.full(4, value, np.float32), stamp=stamp)


def _stamp(msg: Any) -> int:
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec


class TestSync:
    def make(self, **kwargs: Any) -> LaserScanMerger:
        kwargs.setdefault("slop_ns", 10)
        return LaserScanMerger({"a": MergerInput(), "b": MergerInput()},
                               angle_increment=math.pi / 2, **kwargs)

    def test_slop_is_inclusive(self) -> None:
        m = self.make()
        assert m.push("a", _s(1000)) is None
        out = m.push("b", _s(1010))
        assert out is not None and _stamp(out) == 1010

    def test_just_above_slop_does_not_match_and_consumes_nothing_matchable(self) -> None:
        m = self.make()
        m.push("a", _s(1000))
        assert m.push("b", _s(1011)) is None
        # a@1000 can never match any more (b's head is 1011): dropped; b@1011 kept
        assert m.stats["dropped_unmatched"] == 1
        out = m.push("a", _s(1015))
        assert out is not None and _stamp(out) == 1015

    def test_nothing_is_consumed_unless_all_inputs_match(self) -> None:
        m = LaserScanMerger({"a": MergerInput(), "b": MergerInput(), "c": MergerInput()},
                            slop_ns=10, angle_increment=math.pi / 2)
        m.push("a", _s(1000))
        m.push("b", _s(1002))
        assert m.stats["merged"] == 0 and m.stats["dropped_unmatched"] == 0
        out = m.push("c", _s(1001))
        assert out is not None and _stamp(out) == 1002 and m.last_inputs == ("a", "b", "c")

    def test_reference_oldest(self) -> None:
        m = self.make(reference="oldest")
        m.push("a", _s(1000))
        assert _stamp(m.push("b", _s(1007))) == 1000

    def test_ns_precision(self) -> None:
        m = self.make(slop_ns=0)
        base = 1_700_000_000_123_456_789
        m.push("a", _s(base))
        assert m.push("b", _s(base + 1)) is None
        out = m.push("b", _s(base))                     # exact match, 1 ns resolution
        assert out is None or _stamp(out) == base
        m2 = self.make(slop_ns=0)
        m2.push("a", _s(base))
        assert _stamp(m2.push("b", _s(base))) == base

    def test_constant_offset_above_slop_never_matches_and_queues_stay_bounded(self) -> None:
        m = self.make(queue_size=3)
        for k in range(20):
            assert m.push("a", _s(1000 + 100 * k)) is None
            assert m.push("b", _s(1050 + 100 * k)) is None
        assert m.stats["merged"] == 0
        assert all(len(s.queue) <= 3 for s in m._inputs.values())

    def test_nearest_pick_and_older_scans_dropped(self) -> None:
        m = self.make()
        m.push("a", _s(995))
        m.push("a", _s(1000))
        out = m.push("b", _s(999))
        # pivot = newest head = 999; a's nearest is 1000 (|1|) not 995 (|4|)
        assert _stamp(out) == 1000 and m.stats["dropped_unmatched"] == 1

    def test_dead_input_blocks_with_wait(self) -> None:
        m = self.make(policy="wait", timeout_ns=100)
        for k in range(5):
            assert m.push("a", _s(1000 + 50 * k)) is None

    def test_dead_input_is_left_out_after_timeout(self) -> None:
        m = self.make(policy="timeout", timeout_ns=100)
        assert m.push("a", _s(1000)) is None             # b may still come
        assert m.push("a", _s(1050)) is None
        out = m.push("a", _s(1101))                       # b silent > 100 ns: dead
        # three complete sets of "a" alone: the newest is merged, no latency builds up
        assert out is not None and _stamp(out) == 1101 and m.last_inputs == ("a",)
        assert m.stats["partial"] == 1 and m.stats["dropped_backlog"] == 2
        assert _stamp(m.push("a", _s(1150))) == 1150

    def test_revived_input_is_waited_for_again(self) -> None:
        m = self.make(policy="timeout", timeout_ns=100)
        m.push("a", _s(1000))
        while m.push("a", _s(1300)) is not None:
            pass
        assert m.push("b", _s(1400)) is None              # b alive again, a alive: wait
        out = m.push("a", _s(1405))
        assert out is not None and m.last_inputs == ("a", "b") and _stamp(out) == 1405

    def test_per_input_timeout(self) -> None:
        m = LaserScanMerger({"a": MergerInput(), "b": MergerInput(timeout_ns=10_000)},
                            slop_ns=10, policy="timeout", timeout_ns=100,
                            angle_increment=math.pi / 2)
        m.push("b", _s(1000))
        assert m.push("a", _s(1500)) is None            # b alive for 10 us: wait for it

    def test_out_of_order_duplicate_and_late(self) -> None:
        m = self.make()
        m.push("a", _s(2000))
        m.push("a", _s(1000))                            # out of order: queued in order
        assert [t for t, _ in m._inputs["a"].queue] == [1000, 2000]
        m.push("a", _s(1000))
        assert m.stats["dropped_duplicate"] == 1
        out = m.push("b", _s(1005))
        assert _stamp(out) == 1005
        assert m.push("a", _s(900)) is None and m.stats["dropped_late"] == 1

    def test_zero_stamps(self) -> None:
        m = self.make()
        m.push("a", _s(0))
        out = m.push("b", _s(0))
        assert out is not None and _stamp(out) == 0

    def test_unknown_input(self) -> None:
        with pytest.raises(ConfigError):
            self.make().push("zzz", _s(0))


# ------------------------------------------------------------------------ clock jumps back

JB = 1_000_000_000          # jump_back_ns (the default)
P = 100_000_000             # 10 Hz
T = 500 * 10**9


def _tagged(name: str, stamp: int, tag: int) -> Any:
    """Input "a" fills output bin 0, "b" bin 1, with ``1 + tag / 1000`` metres (bins 2, 3: +Inf)."""
    ranges = np.full(4, np.inf, np.float32)
    ranges[0 if name == "a" else 1] = 1.0 + tag / 1000
    return make_scan(ranges, stamp=stamp)


def _tags(out: Any) -> tuple[int | None, int | None]:
    """(tag of a, tag of b) fused into an output (None: that input is not in it)."""
    r = np.asarray(out.ranges, np.float64)
    return tuple(round((v - 1.0) * 1000) if math.isfinite(v) else None  # type: ignore
                 for v in r[:2])


class TestClockJump:
    def make(self, **kwargs: Any) -> LaserScanMerger:
        kwargs.setdefault("slop_ns", 10_000_000)
        kwargs.setdefault("policy", "timeout")
        kwargs.setdefault("timeout_ns", 500_000_000)
        return LaserScanMerger({"a": MergerInput(), "b": MergerInput()},
                               angle_increment=math.pi / 2, **kwargs)

    def run(self, m: LaserScanMerger, events: list[tuple[str, int, int]]
            ) -> list[tuple[int, int | None, int | None]]:
        """Push (name, stamp, tag) events; returns (stamp, tag a, tag b) of every output."""
        outs = []
        for name, stamp, tag in events:
            out = m.push(name, _tagged(name, stamp, tag))
            if out is not None:
                outs.append((_stamp(out), *_tags(out)))
        return outs

    @staticmethod
    def loop(n: int, loops: int, offset_b: int = 1_000_000) -> list[tuple[str, int, int]]:
        """A recording of n pairs played ``loops`` times; tag = loop * 1000 + index... / 10."""
        return [(name, T + i * P + (offset_b if name == "b" else 0), loop * 100 + i)
                for loop in range(loops) for i in range(n) for name in ("a", "b")]

    @pytest.mark.parametrize("policy", ["timeout", "wait"])
    def test_looping_recording_resumes_after_one_scan_per_input(self, policy: str) -> None:
        m = self.make(policy=policy)
        outs = self.run(m, self.loop(30, 3))
        for loop in range(3):
            tags = [a for _, a, b in outs if a is not None and a // 100 == loop]
            # the first scan of each input after a jump is held (unconfirmed) and dropped
            assert tags == list(range(loop * 100 + (1 if loop else 0), loop * 100 + 30))
        assert all(a == b for _, a, b in outs)          # never fused across the jump
        assert m.stats["time_resets"] == 4 and m.stats["dropped_late"] == 4
        assert m.stats["dropped_jump"] == 0 and m.stats["partial"] == 0
        assert m.last_reset is None and m.last_drop is None

    def test_reset_is_reported(self) -> None:
        m = self.make()
        self.run(m, self.loop(20, 1))
        assert m.push("a", _tagged("a", T, 500)) is None and m.last_reset is None
        assert "late" in m.last_drop and "confirm" in m.last_drop  # type: ignore[operator]
        assert m.push("a", _tagged("a", T + P, 501)) is None
        assert m.last_reset == ("a", T + 19 * P, T + P) and m.last_drop is None
        assert [t for t, _ in m._inputs["a"].queue] == [T + P]

    @pytest.mark.parametrize("stale", [0, T - 5 * JB, T + P + 1_000_000])
    def test_one_stale_or_zero_stamped_scan_resets_nothing(self, stale: int) -> None:
        m = self.make()
        events = []
        for i in range(40):
            events += [("a", T + i * P, i), ("b", T + i * P + 1_000_000, i)]
            if i % 3 == 2:
                events.append(("b", stale, 900 + i))     # zero, far past or replayed
        outs = self.run(m, events)
        assert m.stats["time_resets"] == 0 and m.stats["dropped_jump"] == 0
        assert [a for _, a, _ in outs] == list(range(40)) and all(a == b for _, a, b in outs)
        bad = len([e for e in events if e[2] >= 900])
        assert m.stats["dropped_late"] == bad

    def test_repeated_zero_or_replayed_stamps_never_confirm_a_jump(self) -> None:
        m = self.make()
        self.run(m, self.loop(20, 1))
        for k in range(10):                   # a stream of stamps that do not rise
            assert m.push("b", _tagged("b", 0 if k % 2 else T + P, 900)) is None
        assert m.stats["time_resets"] == 0
        outs = self.run(m, [("a", T + 20 * P, 20), ("b", T + 20 * P, 20)])
        assert [(a, b) for _, a, b in outs] == [(20, 20)]

    def test_a_lagging_input_is_not_a_jump(self) -> None:
        m = self.make()
        events = []
        held = []
        for i in range(60):
            events.append(("a", T + i * P, i))
            if 20 <= i < 35:                  # b stalls for 1.5 s, then delivers its backlog
                held.append(("b", T + i * P + 1_000_000, i))
                continue
            events += held + [("b", T + i * P + 1_000_000, i)]
            held = []
        outs = self.run(m, events)
        assert m.stats["time_resets"] == 0
        assert [a for _, a, b in outs if b is not None and a >= 35] == list(range(36, 60))
        assert all(b is None or a == b for _, a, b in outs)

    def test_one_input_resets_alone_the_others_go_on(self) -> None:
        """Only a's clock is reset: a's new timeline is never fused with b's (other) time."""
        m = self.make()
        self.run(m, self.loop(20, 1))
        events = []
        for i in range(20, 40):
            events += [("a", T - 10 * JB + i * P, 100 + i), ("b", T + i * P, i)]
        outs = self.run(m, events)
        assert m.stats["time_resets"] == 1
        assert all(a is None for _, a, b in outs)            # b alone once a left b's time
        # b's scan queued when a's reset was confirmed looked like the timeline a left
        assert [b for _, a, b in outs] == list(range(21, 40)) and m.stats["dropped_jump"] == 1

    def test_scans_of_the_abandoned_timeline_are_dropped(self) -> None:
        m = self.make(policy="wait")
        self.run(m, self.loop(20, 1))
        m.push("b", _tagged("b", T + 20 * P, 20))           # queued, its pair never comes
        assert [t for t, _ in m._inputs["b"].queue] == [T + 20 * P]
        assert m.push("a", _tagged("a", T, 100)) is None
        assert m.push("a", _tagged("a", T + P, 101)) is None
        assert m._inputs["b"].queue == [] and m.stats["dropped_jump"] == 1
        # b jumps too: fusion resumes with the new timeline only
        outs = self.run(m, [("b", T, 100), ("b", T + P, 101), ("a", T + 2 * P, 102),
                            ("b", T + 2 * P, 102)])
        assert [(a, b) for _, a, b in outs] == [(101, 101), (102, 102)]

    def test_a_dead_input_does_not_block_the_new_timeline(self) -> None:
        """b died on the old timeline: its old newest stamp must not keep the clock there."""
        m = self.make()
        self.run(m, self.loop(20, 1))
        outs = self.run(m, [("a", T + i * P, 100 + i) for i in range(20)])
        # a's first scan back is held, a alone once b's timeout has run out on the new time
        assert outs and all(b is None for _, a, b in outs)
        assert outs[0][1] <= 101 + 500_000_000 // P + 1 and outs[-1][1] == 119

    def test_a_future_stamped_scan_costs_one_output(self) -> None:
        m = self.make()
        events = []
        for i in range(30):
            events += [("a", T + i * P, i), ("b", T + i * P + 1_000_000, i)]
            if i == 10:
                events.append(("b", T + 3600 * JB, 999))       # corrupt: one hour ahead
        outs = self.run(m, events)
        fused = [a for _, a, b in outs if a is not None and a == b]
        assert len(fused) >= 27 and all(b in (a, None, 999) for _, a, b in outs)
        assert m.stats["time_resets"] == 1

    def test_disabled(self) -> None:
        m = self.make(jump_back_ns=None)
        outs = self.run(m, self.loop(20, 2))
        assert len(outs) == 20 and m.stats["time_resets"] == 0   # the loop is "late" forever

    @pytest.mark.parametrize("bad", [0, -1, True, 1.5, "1"])
    def test_bad_option(self, bad: Any) -> None:
        with pytest.raises(ConfigError):
            self.make(jump_back_ns=bad)

    def test_odometry_jump(self) -> None:
        m = self.make(motion_compensation=True, odom_queue_size=20)
        for k in range(30):
            m.push_odometry(_odom(T + k * P, 0.1 * k, 0.0, 0.0))
        m.push_odometry(_odom(0, 9.0, 9.0, 0.0))            # one bad sample: dropped
        assert m.stats["odometry_resets"] == 0 and m.stats["dropped_odometry"] == 1
        assert m.pose_at(T + 29 * P).position[0] == pytest.approx(2.9)
        m.push_odometry(_odom(T + 29 * P + P, 3.0, 0.0, 0.0))  # history continues
        for k in range(3):                                    # the recording loops
            m.push_odometry(_odom(T + k * P, -0.1 * k, 0.0, 0.0))
        assert m.stats["odometry_resets"] == 1
        assert m.pose_at(T + 2 * P).position[0] == pytest.approx(-0.2)
        assert m.pose_at(T + 29 * P) is None                   # the old history is gone

    def test_malformed_scan_is_rejected_before_touching_the_queues(self) -> None:
        m = self.make()
        m.push("a", _tagged("a", T, 1))
        bad = make_scan(np.ones(4, np.float32), stamp=T + P, inc=0.0)
        with pytest.raises(ValidationError):
            m.push("b", bad)
        assert [t for t, _ in m._inputs["a"].queue] == [T] and m._inputs["b"].queue == []
        assert _tags(m.push("b", _tagged("b", T, 1))) == (1, 1)


# ----------------------------------------------------------------------------- odometry

def _quat_yaw(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def _odom(stamp: int, x: float, y: float, yaw: float, sign: float = 1.0,
          child: str = "base_link") -> Any:
    Odom = message_class("nav_msgs/msg/Odometry")
    PoseWC = message_class("geometry_msgs/msg/PoseWithCovariance")
    PoseM = message_class("geometry_msgs/msg/Pose")
    Point = message_class("geometry_msgs/msg/Point")
    Quat = message_class("geometry_msgs/msg/Quaternion")
    q = [sign * v for v in _quat_yaw(yaw)]
    return Odom(header=Header(Time(*divmod(stamp, 10**9)), "odom"), child_frame_id=child,
                pose=PoseWC(pose=PoseM(position=Point(x=x, y=y, z=0.0),
                                       orientation=Quat(x=q[0], y=q[1], z=q[2], w=q[3])),
                            covariance=np.zeros(36)),
                twist=None)


def _yaw(p: Pose) -> float:
    x, y, z, w = p.orientation
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


class TestOdometry:
    def poses(self) -> tuple[list[int], list[Pose]]:
        stamps = [100, 200, 300]
        poses = [Pose(100, (0.0, 0.0, 0.0), _quat_yaw(0.0)),
                 Pose(200, (1.0, 0.0, 0.0), _quat_yaw(0.5)),
                 Pose(300, (1.0, 2.0, 0.0), _quat_yaw(1.0))]
        return stamps, poses

    def test_exact_sample(self) -> None:
        stamps, poses = self.poses()
        assert interpolate_pose(stamps, poses, 200, 1000) is poses[1]

    def test_between_samples(self) -> None:
        stamps, poses = self.poses()
        p = interpolate_pose(stamps, poses, 250, 1000)
        assert p is not None and p.position == pytest.approx((1.0, 1.0, 0.0))
        assert _yaw(p) == pytest.approx(0.75)

    def test_clamp_outside_the_window_up_to_max_gap(self) -> None:
        stamps, poses = self.poses()
        assert interpolate_pose(stamps, poses, 50, 100) is poses[0]
        assert interpolate_pose(stamps, poses, 390, 100) is poses[2]
        assert interpolate_pose(stamps, poses, 401, 100) is None
        assert interpolate_pose(stamps, poses, 150, 99) is None      # gap 100 > 99
        assert interpolate_pose([], [], 150, 99) is None

    def test_antipodal_quaternions_take_the_short_arc(self) -> None:
        a = Pose(0, (0, 0, 0), _quat_yaw(math.radians(170)))
        b = Pose(10, (0, 0, 0), tuple(-v for v in _quat_yaw(math.radians(-170))))  # type: ignore
        mid = interpolate_pose([0, 10], [a, b], 5, 100)
        assert mid is not None and abs(abs(_yaw(mid)) - math.pi) < 1e-9
        c = Pose(10, (0, 0, 0), _quat_yaw(math.radians(-170)))
        mid2 = interpolate_pose([0, 10], [a, c], 5, 100)
        assert mid2 is not None and abs(abs(_yaw(mid2)) - math.pi) < 1e-9

    @pytest.mark.parametrize("backend", BACKENDS)
    def test_compensation_at_heading_not_zero(self, backend: str) -> None:
        """A robot driving and turning sees one fixed landmark in two scans taken at different
        times; compensation puts both observations at the same place in the output frame at
        the reference stamp, and matches p' = R(-dth) p - R(-th_ref) dt."""
        landmark = np.array([5.0, 3.0])
        t0, t1 = 1_000_000_000, 1_100_000_000
        odo = [(t0, 2.0, 1.0, 2.0), (t1, 2.3, 1.4, 2.2)]           # heading ~115..126 deg

        def observe(x: float, y: float, th: float) -> tuple[float, float]:
            rel = landmark - (x, y)
            c, s = math.cos(-th), math.sin(-th)
            px, py = c * rel[0] - s * rel[1], s * rel[0] + c * rel[1]
            return math.hypot(px, py), math.atan2(py, px)

        m = LaserScanMerger({"old": MergerInput(), "new": MergerInput()},
                            angle_increment=math.radians(0.1), backend=backend)
        for t, x, y, th in odo:
            m.push_odometry(_odom(t, x, y, th))
        scans = {}
        for name, (t, x, y, th) in zip(("old", "new"), odo):
            r, a = observe(x, y, th)
            scans[name] = make_scan([r], angle_min=a, inc=0.0, stamp=t)
        out = out_arrays(m.merge(scans))[0]
        hits = np.flatnonzero(np.isfinite(out))
        assert hits.size == 1                           # both observations in one bin
        r_ref, _a_ref = observe(*odo[1][1:])
        assert out[hits[0]] == pytest.approx(r_ref, abs=1e-5)
        # the formula from the brief, for the old scan
        r0, a0 = observe(*odo[0][1:])
        p = np.array([r0 * math.cos(a0), r0 * math.sin(a0)])
        dth = odo[1][3] - odo[0][3]
        dt = np.array(odo[1][1:3]) - np.array(odo[0][1:3])

        def rot(a: float) -> np.ndarray:
            return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])

        moved = rot(-dth) @ p - rot(-odo[1][3]) @ dt
        assert math.hypot(*moved) == pytest.approx(r_ref, abs=1e-9)
        # the toolbox's bug (dt unrotated) would be far off at this heading
        wrong = rot(-dth) @ p - dt
        assert abs(math.hypot(*wrong) - r_ref) > 0.1

    def test_no_odometry_or_big_gap_leaves_scans_uncompensated(self) -> None:
        m = LaserScanMerger({"a": MergerInput(), "b": MergerInput()}, odom_max_gap_ns=10)
        scans = {"a": _s(1000), "b": _s(2000)}
        plain = out_arrays(m.merge(scans))[0]
        m.push_odometry(_odom(0, 0, 0, 0))
        m.push_odometry(_odom(5000, 1, 0, 0))
        np.testing.assert_array_equal(out_arrays(m.merge(scans))[0], plain)
        assert m.stats["uncompensated"] >= 1

    def test_odometry_checks(self) -> None:
        m = LaserScanMerger({"a": MergerInput()})
        with pytest.raises(ValidationError):
            m.push_odometry(_odom(0, 0, 0, 0, child="other"))
        bad = _odom(0, 0, 0, 0, sign=0.0)
        with pytest.raises(ValidationError):
            m.push_odometry(bad)
        for k in range(300):
            m.push_odometry(_odom(k, 0, 0, 0))
        assert len(m._odom_t) == m.odom_queue_size

    def test_odometry_rclpy_message(self) -> None:
        from nav_msgs.msg import Odometry
        msg = Odometry()
        msg.header.stamp.sec = 3
        msg.child_frame_id = "base_link"
        msg.pose.pose.position.x = 1.5
        msg.pose.pose.orientation.w = 1.0
        m = LaserScanMerger({"a": MergerInput()})
        m.push_odometry(msg)
        p = m.pose_at(3 * 10**9)
        assert p is not None and p.position == (1.5, 0.0, 0.0)


def test_import_does_not_import_rclpy() -> None:
    import subprocess
    import sys
    code = ("import sys, converters.merger, converters.slices.converter; "
            "sys.exit(1 if 'rclpy' in sys.modules else 0)")
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0


def test_a_scan_in_another_frame_needs_extrinsics() -> None:
    """Without extrinsics identity is only right in the output frame: a scan in another frame
    is refused (naming the input, its frame and the output frame), by merge and by push,
    before it touches a queue; the same frame, or explicit extrinsics, are fine."""
    m = LaserScanMerger({"a": MergerInput(), "b": MergerInput(extrinsics=np.eye(4))},
                        frame_id="base_link")
    for call in (lambda: m.merge({"a": make_scan([1.0], frame="laser")}),
                 lambda: m.push("a", make_scan([1.0], frame="laser"))):
        with pytest.raises(ValidationError) as err:
            call()
        assert err.value.field == "a.header.frame_id" and err.value.value == "laser"
        assert "'base_link'" in str(err.value)
    assert not m._inputs["a"].queue
    m.merge({"a": make_scan([1.0], frame="base_link"), "b": make_scan([1.0], frame="laser")})
    with pytest.raises(ConfigError) as cfg_err:
        LaserScanMerger({"a": MergerInput(frame_id="laser")}, frame_id="base_link")
    assert cfg_err.value.field == "inputs['a'].frame_id"
