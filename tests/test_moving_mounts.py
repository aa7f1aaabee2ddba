"""Moving mounts in the merger: TransformTrack (interpolation, span, history) and per-ray
de-skew of a 2D laser on a pan unit turning during its sweep, in a static synthetic scene.

Oracles: quaternion slerp written out with its sine formula (the track uses the rotation-vector
form of :mod:`converters.shared.deskew`), the normalised quaternion sum for the geodesic midpoint, and an
analytic ray caster that knows the pan unit's true angle at every ray's time.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import converters
from converters.merger import LaserScanMerger, MergerInput
from converters.edge.nodes.tf import matrix_from_quaternion, matrix_from_xyz_rpy, quaternion_from_matrix
from converters.shared.transforms import OutOfSpanError, TransformLookupError, TransformTrack
from lidarscan.errors import ConfigError, LidarScanError, ValidationError
from lidarscan.types import Header, Time, message_class
from grid_reference import ref_bin, ref_grid
from test_nodes import graph  # noqa: F401 - the rclpy graph fixture

LaserScanDC = message_class("sensor_msgs/msg/LaserScan")
F32 = np.float32
MS = 1_000_000


# ------------------------------------------------------------------------------ references

def ref_slerp(q0: Any, q1: Any, u: float) -> np.ndarray:
    """Textbook quaternion slerp (shortest arc), one pair at a time."""
    a, b = np.asarray(q0, float), np.asarray(q1, float)
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    dot = float(a @ b)
    if dot < 0:
        b, dot = -b, -dot
    theta = math.acos(min(1.0, dot))
    if theta < 1e-12:
        return a
    return (math.sin((1 - u) * theta) * a + math.sin(u * theta) * b) / math.sin(theta)


def ref_track_lookup(stamps: list[int], poses: list[np.ndarray], t: int) -> np.ndarray:
    """Loop oracle: find the bracketing pair, lerp the translation, slerp the quaternion."""
    for k in range(len(stamps) - 1):
        if stamps[k] <= t <= stamps[k + 1]:
            u = (t - stamps[k]) / (stamps[k + 1] - stamps[k])
            p = poses[k][:3, 3] + u * (poses[k + 1][:3, 3] - poses[k][:3, 3])
            q = ref_slerp(quaternion_from_matrix(poses[k]), quaternion_from_matrix(poses[k + 1]),
                          u)
            return matrix_from_quaternion(q, p)
    raise AssertionError("outside")


def random_pose(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return matrix_from_quaternion(q, rng.uniform(-3, 3, 3))


# -------------------------------------------------------------------------- pan-unit scene

ROOM = ((0.0, 0.0), 6.0)                           # circle room centred on base_link, radius
PILLARS = (((2.0, 1.0), 0.4), ((-1.5, -2.5), 0.6), ((0.5, -3.0), 0.3))
PIVOT = np.array([0.30, 0.10, 0.25])               # pan axis (vertical) in base_link
ARM = np.array([0.08, 0.0, 0.0])                   # laser origin on the pan unit, off the axis
OMEGA = 3.0                                        # rad/s: the pan unit turns during the sweep
T0 = 5 * 10**9
SCAN_NS = 100 * MS                                 # 10 Hz sweep
N_RAYS = 720


def pan_pose(t_ns: int) -> np.ndarray:
    """True base_link <- laser at time t: yaw about the pivot's vertical axis."""
    yaw = 0.4 + OMEGA * (t_ns - T0) * 1e-9
    m = matrix_from_xyz_rpy(yaw=yaw)
    m[:3, 3] = PIVOT + m[:3, :3] @ ARM
    return m


def cast(origin: np.ndarray, direction: np.ndarray) -> float:
    """Planar distance to the first surface (room wall from inside, pillars from outside)."""
    o, d = origin[:2], direction[:2] / np.linalg.norm(direction[:2])
    (cx, cy), radius = ROOM
    oc = o - (cx, cy)
    b = float(d @ oc)
    best = -b + math.sqrt(b * b - (oc @ oc - radius * radius))
    for (px, py), r in PILLARS:
        oc = o - (px, py)
        b = float(d @ oc)
        disc = b * b - (oc @ oc - r * r)
        if disc >= 0:
            t = -b - math.sqrt(disc)
            if 0 < t < best:
                best = t
    return best


def pan_scan(stamp: int, frame: str = "pan_laser", n: int = N_RAYS) -> tuple[Any, np.ndarray]:
    """A sweep from the turning laser (ray i at stamp + i * time_increment, float32 fields),
    and the true base_link endpoint of every ray."""
    inc = F32(2 * math.pi / N_RAYS)
    tinc = F32(SCAN_NS / N_RAYS * 1e-9)
    amin = F32(-math.pi)
    ranges = np.empty(n, F32)
    ends = np.empty((n, 3))
    for i in range(n):
        t = stamp + round(i * float(tinc) * 1e9)
        m = pan_pose(t)
        theta = float(amin) + i * float(inc)
        d = m[:3, :3] @ [math.cos(theta), math.sin(theta), 0.0]
        r = cast(m[:3, 3], d)
        ranges[i] = r
        ends[i] = m[:3, 3] + float(F32(r)) * d
    scan = LaserScanDC(header=Header(stamp=Time(sec=stamp // 10**9, nanosec=stamp % 10**9),
                                     frame_id=frame),
                       angle_min=float(amin), angle_max=float(amin + (n - 1) * inc),
                       angle_increment=float(inc), time_increment=float(tinc),
                       scan_time=SCAN_NS * 1e-9, range_min=0.05, range_max=30.0,
                       ranges=ranges, intensities=np.zeros(0, F32))
    return scan, ends


def pan_track(start: int, stop: int, step: int = 10 * MS, **kwargs: Any) -> TransformTrack:
    track = TransformTrack(name="base_link <- pan_laser", **kwargs)
    for t in range(start, stop + 1, step):
        track.add(t, pan_pose(t))
    return track


INC_OUT = math.radians(0.5)


def truth(ends: np.ndarray) -> np.ndarray:
    """Expected merged ranges: each true endpoint binned by its azimuth, minimum per bin
    (grid -pi..pi, INC_OUT; empty bins +Inf)."""
    grid = ref_grid(-math.pi, math.pi, INC_OUT)
    out = np.full(grid[2], np.inf)
    for x, y, _ in ends:
        b = ref_bin(math.atan2(y, x), grid)
        assert b is not None
        out[b] = min(out[b], math.hypot(x, y))
    return out


def merger(extrinsics: Any, backend: str, **kwargs: Any) -> LaserScanMerger:
    return LaserScanMerger({"pan": MergerInput(extrinsics=extrinsics, **kwargs)},
                           angle_increment=INC_OUT, backend=backend)


BACKENDS = ["numpy", "auto"]


# ------------------------------------------------------------------------------------ track

def test_track_is_exported_lazily_and_callable() -> None:
    assert converters.TransformTrack is TransformTrack
    track = TransformTrack()
    track.add(0, np.eye(4))
    track.add(10, (0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 2.0))      # quaternion normalised
    assert np.allclose(track(5)[:3, 3], [0, 0.5, 0])
    assert track.span == (0, 10) and len(track) == 2
    assert issubclass(OutOfSpanError, LidarScanError)


def test_track_loop_oracle_slerp(rng: np.random.Generator) -> None:
    stamps = sorted(int(t) for t in rng.choice(10**9, 12, replace=False))
    poses = [random_pose(rng) for _ in stamps]
    track = TransformTrack()
    for t, p in zip(reversed(stamps), reversed(poses)):       # any insertion order
        track.add(t, p)
    queries = np.concatenate([rng.integers(stamps[0], stamps[-1], 300), stamps])
    got = track.lookup_many(queries)
    for t, m in zip(queries, got):
        assert np.allclose(m, ref_track_lookup(stamps, poses, int(t)), atol=1e-9)
        assert np.allclose(m, track.lookup(int(t)), atol=0)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=14, max_size=14),
       st.integers(1, 10**10), st.integers(0, 10**12))
def test_track_knots_exact_and_midpoint_geodesic(values: list[float], gap: int,
                                                 start: int) -> None:
    q0, q1 = np.array(values[:4]), np.array(values[4:8])
    if np.linalg.norm(q0) < 0.1 or np.linalg.norm(q1) < 0.1:
        return
    a = matrix_from_quaternion(q0, values[8:11])
    b = matrix_from_quaternion(q1, values[11:14])
    qa, qb = np.array(quaternion_from_matrix(a)), np.array(quaternion_from_matrix(b))
    if abs(float(qa @ qb)) < 1e-3:                            # relative angle ~pi: no unique arc
        return
    track = TransformTrack(max_age_ns=2 * 10**10)               # both samples kept
    track.add(start, a)
    track.add(start + 2 * gap, b)
    assert np.array_equal(track.lookup(start), a)
    assert np.array_equal(track.lookup(start + 2 * gap), b)
    mid = track.lookup(start + gap)
    if qa @ qb < 0:
        qb = -qb
    q_mid = (qa + qb) / np.linalg.norm(qa + qb)               # geodesic midpoint on S^3
    expected = matrix_from_quaternion(q_mid, (a[:3, 3] + b[:3, 3]) / 2)
    assert np.allclose(mid, expected, atol=1e-9)


def test_track_out_of_span_never_extrapolates() -> None:
    track = TransformTrack(name="base_link <- pan")
    with pytest.raises(OutOfSpanError, match="holds no pose"):
        track.lookup(5)
    track.add(100, np.eye(4))
    assert np.array_equal(track.lookup(100), np.eye(4))       # one sample: its own stamp only
    with pytest.raises(OutOfSpanError) as err:
        track.lookup(101)
    assert err.value.stamp_ns == 101 and err.value.span == (100, 100)
    assert "base_link <- pan" in str(err.value) and "after the newest" in str(err.value)
    track.add(200, matrix_from_xyz_rpy(1.0, 0, 0))
    with pytest.raises(OutOfSpanError, match="before the oldest") as err:
        track.lookup_many([150, 99, 250])
    assert err.value.stamp_ns == 99 and err.value.span == (100, 200)
    held = TransformTrack(tolerance_ns=30)
    held.add(100, np.eye(4))
    held.add(200, matrix_from_xyz_rpy(1.0, 0, 0))
    assert np.array_equal(held.lookup(230), held.lookup(200))  # held, not extrapolated
    with pytest.raises(OutOfSpanError, match="tolerance"):
        held.lookup(231)
    with pytest.raises(OutOfSpanError):
        held.lookup(99)                                         # no tolerance before the oldest


def test_track_history_is_bounded() -> None:
    track = TransformTrack(max_samples=5, max_age_ns=1000)
    for t in range(0, 100, 10):
        track.add(t, matrix_from_xyz_rpy(t, 0, 0))
    assert track.span == (50, 90) and track.forgotten == 5
    track.add(2000, np.eye(4))                                  # newest - 1000 drops the rest
    assert track.span == (2000, 2000)
    track.add(500, np.eye(4))                                   # older than the age window
    assert track.span == (2000, 2000) and track.forgotten == 11
    track.add(2000, matrix_from_xyz_rpy(0, 1, 0))               # same stamp: replaced
    assert track.lookup(2000)[1, 3] == 1.0
    track.clear()
    assert track.span is None


@pytest.mark.parametrize("kwargs", [{"max_samples": 1}, {"max_age_ns": 0},
                                    {"tolerance_ns": -1}, {"max_samples": 2.5}])
def test_track_option_errors(kwargs: dict[str, Any]) -> None:
    with pytest.raises(ConfigError):
        TransformTrack(**kwargs)


def test_track_refuses_bad_poses_and_keeps_no_reference() -> None:
    track = TransformTrack()
    for bad in (np.zeros((4, 4)), np.full((4, 4), np.nan), ((0, 0), (0, 0, 0, 1))):
        with pytest.raises(ConfigError):
            track.add(0, bad)
    m = np.eye(4)
    track.add(0, m)
    m[0, 3] = 5.0                                              # the caller's array changes
    assert track.lookup(0)[0, 3] == 0.0


# ------------------------------------------------------------------------ merger, pan unit

@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("kind", ["track", "callable"])
def test_pan_unit_sweep_is_deskewed_to_the_static_truth(kind: str, backend: str) -> None:
    scan, ends = pan_scan(T0)
    extrinsics = pan_track(T0 - 20 * MS, T0 + SCAN_NS + 20 * MS) if kind == "track" \
        else pan_pose
    out = merger(extrinsics, backend).merge({"pan": scan})
    got = np.asarray(out.ranges, np.float64)
    expected = truth(ends)
    assert np.array_equal(np.isinf(got), np.isinf(expected))
    finite = np.isfinite(expected)
    assert finite.sum() > 600
    assert np.max(np.abs(got[finite] - expected[finite])) < 1e-4
    # the same poses for every ray (deskew off) put the scene elsewhere: this test can fail
    rigid = merger(extrinsics, backend, deskew=False).merge({"pan": scan})
    worse = np.asarray(rigid.ranges, np.float64)
    both = finite & np.isfinite(worse)
    assert np.max(np.abs(worse[both] - expected[both])) > 0.1


def test_reversed_sweep_with_negative_time_increment() -> None:
    """The same rays stored last-measured first (negative angle and time increments, the stamp
    of the last-measured ray) give the same merged scan."""
    scan, ends = pan_scan(T0)
    n = N_RAYS
    tinc = float(scan.time_increment)
    stamp = T0 + round((n - 1) * tinc * 1e9)
    rev = LaserScanDC(header=Header(stamp=Time(*divmod(stamp, 10**9)), frame_id="pan_laser"),
                      angle_min=float(F32(scan.angle_max)), angle_max=scan.angle_min,
                      angle_increment=-scan.angle_increment, time_increment=-tinc,
                      scan_time=scan.scan_time, range_min=0.05, range_max=30.0,
                      ranges=np.asarray(scan.ranges)[::-1].copy(), intensities=np.zeros(0, F32))
    out = merger(pan_pose, "numpy").merge({"pan": rev})
    expected = truth(ends)
    finite = np.isfinite(expected)
    got = np.asarray(out.ranges, np.float64)
    assert np.array_equal(np.isfinite(got), finite)
    assert np.max(np.abs(got[finite] - expected[finite])) < 1e-4


def test_pan_unit_every_endpoint_on_the_scene() -> None:
    """The truth itself: the de-skewed endpoints lie on the room wall or a pillar."""
    _, ends = pan_scan(T0)
    (cx, cy), radius = ROOM
    for x, y, _ in ends:
        dist = abs(math.hypot(x - cx, y - cy) - radius)
        for (px, py), r in PILLARS:
            dist = min(dist, abs(math.hypot(x - px, y - py) - r))
        assert dist < 1e-5


def test_static_input_and_one_pose_scans_unchanged() -> None:
    """A track that does not move gives the rigid merger's result bit for bit."""
    scan, _ = pan_scan(T0)
    mount = pan_pose(T0)
    track = TransformTrack()
    track.add(T0 - MS, mount)
    track.add(T0 + SCAN_NS + MS, mount)
    a = merger(track, "numpy").merge({"pan": scan})
    b = merger(mount, "numpy").merge({"pan": scan})
    assert np.allclose(np.asarray(a.ranges), np.asarray(b.ranges), atol=1e-6, equal_nan=True)


def test_callable_is_called_once_per_ray_time_and_checked() -> None:
    scan, _ = pan_scan(T0)
    calls: list[int] = []

    def mount(t: int) -> np.ndarray:
        calls.append(t)
        return pan_pose(t)

    merger(mount, "numpy").merge({"pan": scan})
    assert len(calls) == N_RAYS and calls[0] == T0 and len(set(calls)) == N_RAYS
    calls.clear()
    merger(mount, "numpy", deskew=False).merge({"pan": scan})
    assert calls == [T0]
    with pytest.raises(ValidationError, match=r"extrinsics\(stamp_ns\)"):
        merger(lambda t: np.zeros((4, 4)), "numpy").merge({"pan": scan})
    with pytest.raises(ValidationError):
        merger(lambda t: np.eye(3), "numpy").merge({"pan": scan})
    with pytest.raises(ConfigError, match="deskew"):
        merger(mount, "numpy", deskew="yes")


def test_merge_raises_outside_the_span() -> None:
    scan, _ = pan_scan(T0)
    short = pan_track(T0, T0 + SCAN_NS // 2)                   # ends mid-sweep
    with pytest.raises(OutOfSpanError) as err:
        merger(short, "numpy").merge({"pan": scan})
    assert err.value.span == (T0, T0 + SCAN_NS // 2)


def test_push_counts_a_scan_without_pose_and_merges_the_others() -> None:
    track = pan_track(T0 - 20 * MS, T0 + SCAN_NS + 20 * MS)
    m = LaserScanMerger({"pan": MergerInput(extrinsics=track),
                         "fixed": MergerInput(extrinsics=matrix_from_xyz_rpy(-0.2, 0, 0.1))},
                        angle_increment=INC_OUT, slop_ns=60 * MS)
    fixed_scan, _ = pan_scan(T0, "rear")
    scan, _ = pan_scan(T0)
    assert m.push("pan", scan) is None
    assert m.push("fixed", fixed_scan) is not None
    assert m.stats["dropped_no_pose"] == 0 and m.last_inputs == ("pan", "fixed")
    late, _ = pan_scan(T0 + SCAN_NS)                            # beyond the track
    fixed_late, _ = pan_scan(T0 + SCAN_NS, "rear")
    assert m.push("pan", late) is None
    out = m.push("fixed", fixed_late)
    assert out is not None and m.last_inputs == ("fixed",)
    assert m.stats["dropped_no_pose"] == 1 and m.stats["partial"] == 1
    assert "'pan'" in (m.last_no_pose or "") and "after the newest" in (m.last_no_pose or "")
    alone = LaserScanMerger({"pan": MergerInput(extrinsics=track)}, angle_increment=INC_OUT)
    assert alone.push("pan", late) is None and alone.stats["merged"] == 0
    assert alone.stats["dropped_no_pose"] == 1


def test_a_callable_lookup_error_is_a_counted_drop() -> None:
    def unknown(t: int) -> np.ndarray:
        raise TransformLookupError("base_link <- pan_laser", t, "a known pose")

    m = LaserScanMerger({"pan": MergerInput(extrinsics=unknown)})
    scan, _ = pan_scan(T0)
    assert m.push("pan", scan) is None and m.stats["dropped_no_pose"] == 1


def test_moving_mount_with_odometry_compensation() -> None:
    """Odometry (one pose per scan) composes with the per-ray mount poses: the robot turns and
    drives between the pan scan and the output stamp (an empty scan of a second input)."""
    Odom = message_class("nav_msgs/msg/Odometry")
    PoseWC = message_class("geometry_msgs/msg/PoseWithCovariance")
    PoseM = message_class("geometry_msgs/msg/Pose")
    Point = message_class("geometry_msgs/msg/Point")
    Quat = message_class("geometry_msgs/msg/Quaternion")

    def robot(t: int) -> np.ndarray:                           # odom <- base_link
        u = (t - T0) * 1e-9
        return matrix_from_xyz_rpy(0.5 * u, 0.1 * u, 0.0, yaw=0.8 * u)

    m = LaserScanMerger({"pan": MergerInput(extrinsics=pan_track(T0 - 20 * MS, T0 + 120 * MS)),
                         "other": MergerInput()}, angle_increment=INC_OUT, slop_ns=80 * MS)
    for t in range(T0 - 100 * MS, T0 + 200 * MS, 20 * MS):      # exact for this motion
        x, y, z, w = quaternion_from_matrix(robot(t))
        p = robot(t)[:3, 3]
        m.push_odometry(Odom(header=Header(Time(*divmod(t, 10**9)), "odom"),
                             child_frame_id="base_link",
                             pose=PoseWC(pose=PoseM(position=Point(x=p[0], y=p[1], z=p[2]),
                                                    orientation=Quat(x=x, y=y, z=z, w=w)),
                                         covariance=np.zeros(36)), twist=None))
    scan, ends = pan_scan(T0)
    ref = T0 + 60 * MS
    empty, _ = pan_scan(ref, "base_link", n=0)
    out = m.merge({"pan": scan, "other": empty})
    assert m.stats["uncompensated"] == 0
    move = np.linalg.inv(robot(ref)) @ robot(T0)
    expected = truth(ends @ move[:3, :3].T + move[:3, 3])
    finite = np.isfinite(expected)
    got = np.asarray(out.ranges, np.float64)
    assert np.array_equal(np.isfinite(got), finite)
    assert np.max(np.abs(got[finite] - expected[finite])) < 1e-4


# ----------------------------------------------------------------------------- node parts

def tf_buffer_with_pan(stamps: range) -> Any:
    """TransformBuffer: base_link -> pan_link (moving, /tf) -> pan_laser (static arm)."""
    from converters.edge.nodes.tf import TransformBuffer

    buf = TransformBuffer()
    arm = np.eye(4)
    arm[:3, 3] = ARM
    buf.set_transform("pan_link", "pan_laser", arm, static=True)
    for t in stamps:
        buf.set_transform("base_link", "pan_link", pan_pose(t) @ np.linalg.inv(arm), t)
    return buf


def test_transform_buffer_samples_chain_static_and_moving_edges() -> None:
    buf = tf_buffer_with_pan(range(T0, T0 + 50 * MS, 10 * MS))
    samples = buf.samples("base_link", "pan_laser")
    assert [t for t, _ in samples] == list(range(T0, T0 + 50 * MS, 10 * MS))
    for t, m in samples:
        assert np.allclose(m, pan_pose(t), atol=1e-12)
    assert [t for t, _ in buf.samples("base_link", "pan_laser", after_ns=T0 + 20 * MS)] == \
        [T0 + 30 * MS, T0 + 40 * MS]
    assert buf.samples("pan_link", "pan_laser") == []          # all static
    assert buf.samples("base_link", "nowhere") == []


def test_transform_buffer_samples_two_moving_joints() -> None:
    """Stamps of both joints, each composite from the other joint interpolated; a stamp the
    other joint cannot reach (beyond the buffer's tolerance) is left out."""
    from converters.edge.nodes.tf import TransformBuffer

    buf = TransformBuffer(tolerance_ns=5)
    for t in (0, 100):
        buf.set_transform("base", "a", matrix_from_xyz_rpy(t / 100, 0, 0), t)
    for t in (50, 300):
        buf.set_transform("a", "b", matrix_from_xyz_rpy(0, 0, 0, yaw=t / 100), t)
    samples = buf.samples("base", "b")
    assert [t for t, _ in samples] == [50, 100]                   # 0: b unknown, 300: a unknown
    assert np.allclose(samples[0][1], matrix_from_xyz_rpy(0.5, 0, 0, yaw=0.5))
    assert np.allclose(samples[1][1], matrix_from_xyz_rpy(1.0, 0, 0, yaw=1.0))


def test_merger_core_moving_input_waits_for_tf_then_matches_truth() -> None:
    from converters.edge.nodes.merger_node import MergerCore
    from converters.edge.nodes.tf import TransformBuffer

    buf = TransformBuffer()
    arm = np.eye(4)
    arm[:3, 3] = ARM
    buf.set_transform("pan_link", "pan_laser", arm, static=True)
    core = MergerCore({"pan": {}}, moving=["pan"], tf_samples=buf.samples,
                      angle_increment=INC_OUT, frame_id="base_link")
    scan, ends = pan_scan(T0)
    assert core.push("pan", scan) == []                          # no /tf yet: waits
    out: list[Any] = []
    for t in range(T0 - 30 * MS, T0 + SCAN_NS + 30 * MS, 10 * MS):
        buf.set_transform("base_link", "pan_link", pan_pose(t) @ np.linalg.inv(arm), t)
        got = core.update_tracks()
        if t < T0 + SCAN_NS:
            assert got == []                                     # sweep not covered yet
        out += got
    assert len(out) == 1
    expected = truth(ends)
    finite = np.isfinite(expected)
    ranges = np.asarray(out[0].ranges, np.float64)
    assert np.array_equal(np.isfinite(ranges), finite)
    assert np.max(np.abs(ranges[finite] - expected[finite])) < 1e-4
    # no /tf any more: the next scans wait tf_wait (data time), then are dropped, counted
    for k in (1, 2, 3):
        later, _ = pan_scan(T0 + k * SCAN_NS)
        assert core.push("pan", later) == []
    assert core.merger.stats["dropped_no_pose"] >= 1
    with pytest.raises(ConfigError, match="use_tf"):
        MergerCore({"pan": {}}, moving=["pan"])
    with pytest.raises(ConfigError):
        MergerCore({"pan": {}}, moving=["nope"], tf_samples=buf.samples)


def _tf_message(parent: str, child: str, matrix: np.ndarray, stamp: int) -> Any:
    from geometry_msgs.msg import TransformStamped

    from lidarscan.stamps import time_msg

    t = TransformStamped()
    t.header.frame_id, t.child_frame_id = parent, child
    t.header.stamp = time_msg(stamp)
    t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = \
        (float(v) for v in matrix[:3, 3])
    q = quaternion_from_matrix(matrix)
    t.transform.rotation.x, t.transform.rotation.y = q[0], q[1]
    t.transform.rotation.z, t.transform.rotation.w = q[2], q[3]
    return t


def _rclpy_scan(scan: Any) -> Any:
    import array

    from sensor_msgs.msg import LaserScan

    from lidarscan.stamps import time_msg

    msg = LaserScan()
    msg.header.stamp = time_msg(scan.header.stamp.sec * 10**9 + scan.header.stamp.nanosec)
    msg.header.frame_id = scan.header.frame_id
    for key in ("angle_min", "angle_max", "angle_increment", "time_increment", "scan_time",
                "range_min", "range_max"):
        setattr(msg, key, float(getattr(scan, key)))
    msg.ranges = array.array("f", np.asarray(scan.ranges, F32).tobytes())
    return msg


@pytest.mark.ros
def test_merger_node_merges_a_moving_input_from_tf(graph: Any) -> None:
    """The real node: /tf_static (arm) + /tf (pan joint at 100 Hz, data time) and the pan
    laser's sweeps; the merged scan equals the static-scene truth."""
    from sensor_msgs.msg import LaserScan

    from converters.edge.nodes.merger_node import MergerNode
    from test_nodes import overrides

    tf2_msgs = pytest.importorskip("tf2_msgs.msg")
    arm = np.eye(4)
    arm[:3, 3] = ARM
    out = graph.collect(LaserScan, "scan_merged")
    static_pub = graph.publisher(tf2_msgs.TFMessage, "/tf_static", "latched")
    tf_pub = graph.publisher(tf2_msgs.TFMessage, "/tf", "reliable")
    scan_pub = graph.publisher(LaserScan, "pan/scan", "reliable")
    static_pub.publish(tf2_msgs.TFMessage(transforms=[
        _tf_message("pan_link", "pan_laser", arm, 0)]))
    node = graph.add(MergerNode(context=graph.context, parameter_overrides=overrides(
        input_names=["pan"], inputs__pan__topic="pan/scan", inputs__pan__qos="reliable",
        inputs__pan__moving=True, angle_increment=INC_OUT, tf_wait=0.5)))
    assert graph.wait(lambda: node.tf_buffer.can_transform("pan_link", "pan_laser") and
                      tf_pub.get_subscription_count() > 0 and
                      scan_pub.get_subscription_count() > 0 and
                      node.pub.get_subscription_count() > 0)
    expected = {}
    for k in range(3):
        stamp = T0 + k * SCAN_NS
        scan, ends = pan_scan(stamp)
        expected[stamp] = truth(ends)
        scan_pub.publish(_rclpy_scan(scan))                      # the sweep before its /tf
        for t in range(stamp - 10 * MS if k == 0 else stamp + 10 * MS,
                       stamp + SCAN_NS + 10 * MS, 10 * MS):
            tf_pub.publish(tf2_msgs.TFMessage(transforms=[
                _tf_message("base_link", "pan_link", pan_pose(t) @ np.linalg.inv(arm), t)]))
    assert graph.wait(lambda: len(out) >= 3, timeout=15.0)
    for msg in out:
        stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        want = expected[stamp]
        finite = np.isfinite(want)
        got = np.asarray(msg.ranges, np.float64)
        assert msg.header.frame_id == "base_link"
        assert np.array_equal(np.isfinite(got), finite)
        assert np.max(np.abs(got[finite] - want[finite])) < 1e-4
    assert node.core.merger.stats["dropped_no_pose"] == 0
