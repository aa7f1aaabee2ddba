"""LidarScan slices from a lidar on a moving mount (pan unit, nodding head): ``extrinsics`` as a
TransformTrack or a callable ``stamp_ns -> 4x4``, looked up at every pixel's own time.

Oracles: the per-pixel slice loop of ``grid_reference.ref_slice`` fed with one pose per pixel,
whose time the test computes itself from the documented rule (stamp + measurement column *
column_time_increment + beam_time_offsets[row] + the ``t`` channel); a static synthetic room
ray-cast per pixel from the mount's pose at that pixel's time, whose slice must show the room's
walls where a horizontal 2D ray cast from the target frame's origin finds them (and clearly
not when the motion is ignored).
"""

from __future__ import annotations

import importlib.util
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import lidarscan
from converters.slices.converter import SliceConverter, SliceSpec, to_laserscan
from converters.shared.transforms import OutOfSpanError, TransformLookupError, TransformTrack
from lidarscan.errors import ConfigError, ValidationError
from grid_reference import pose, ref_slice
from test_laserscan import BACKENDS, arrays, assert_same, make_sensor, raycast

MS = 1_000_000
STAMP = 10**9


def mount_track(start: int, stop: int, *, yaw_rate: float = 2.0 * math.pi, nod: float = 0.2,
                speed: float = 0.0, step: int = 5 * MS) -> TransformTrack:
    """base_link <- sensor of a pan-tilt head at (0.1, 0, 0.6): yawing at ``yaw_rate`` rad/s,
    nodding (pitch) ``nod`` rad at 5 Hz, sliding along x at ``speed`` m/s; sampled every
    ``step`` ns over [start, stop]."""
    track = TransformTrack(name="base_link <- os_sensor")
    for t in range(start, stop + step, step):
        s = (t - STAMP) * 1e-9
        track.add(t, pose(0.1 + speed * s, 0.0, 0.6, yaw=yaw_rate * s,
                          pitch=nod * math.sin(2 * math.pi * 5 * s)))
    return track


def pixel_times(info: Any, scan: Any) -> np.ndarray:
    """(H, W) absolute int ns of every stored pixel, from the documented rule (loops)."""
    height, width = int(info.height), int(info.width)
    shifts = np.asarray(info.pixel_shift_by_row, np.int64) if len(info.pixel_shift_by_row) \
        else np.zeros(height, np.int64)
    beam = np.asarray(info.beam_time_offsets, np.int64) if len(info.beam_time_offsets) \
        else np.zeros(height, np.int64)
    names = [c.name for c in scan.channels]
    delays = lidarscan.channel(scan, "t") if "t" in names else None
    out = np.empty((height, width), np.int64)
    for u in range(height):
        for v in range(width):
            c = (v - int(shifts[u])) % width if scan.is_destaggered else v
            t = STAMP + c * int(info.column_time_increment) + int(beam[u])
            out[u, v] = t + (int(delays[u, v]) if delays is not None else 0)
    return out


def moving_room_scan(info: Any, mount: Any, *, destagger: bool = False,
                     delays: np.ndarray | None = None, specials: bool = True,
                     rng: np.random.Generator | None = None, stamp: int = STAMP) -> Any:
    """The static room (tests/test_laserscan.py) seen pixel by pixel from ``mount(t)`` at each
    pixel's time (measurement order, then destaggered if asked), stamped ``stamp``."""
    proj = lidarscan.make_projector(info)
    height, width = proj.height, proj.width
    d = proj.directions.reshape(-1, 3).astype(np.float64)
    o = proj.offsets.reshape(-1, 3).astype(np.float64)
    times = (stamp + np.arange(width)[None, :] * int(info.column_time_increment)
             + np.asarray(proj.beam_time_offsets, np.int64)[:, None])
    if delays is not None:                      # given in measurement order
        times = times + delays
    unique, inverse = np.unique(times.reshape(-1), return_inverse=True)
    mats = np.stack([mount(int(t)) for t in unique])[inverse.reshape(-1)]
    dw = np.einsum("nij,nj->ni", mats[:, :3, :3], d)
    ow = np.einsum("nij,nj->ni", mats[:, :3, :3], o) + mats[:, :3, 3]
    r = raycast(ow, dw / np.linalg.norm(dw, axis=1)[:, None]).reshape(height, width)
    r = r.astype(np.float32)
    rng = rng or np.random.default_rng(3)
    if specials:
        flat = r.reshape(-1)
        pick = rng.choice(flat.size, size=flat.size // 10, replace=False)
        flat[pick] = np.array([np.inf, np.nan, -np.inf, 0.0], np.float32)[np.arange(pick.size) % 4]
    channels: dict[str, np.ndarray] = {
        "range": r, "intensity": rng.integers(0, 4000, r.shape).astype(np.float32)}
    if delays is not None:
        channels["t"] = delays.astype(np.uint32)
    if destagger:
        channels = {k: proj.destagger(v) for k, v in channels.items()}
    return lidarscan.make_scan(info, channels, stamp, is_destaggered=destagger,
                               as_dataclass=True)


def sweep_track(info: Any, margin: int = 10 * MS, **kwargs: Any) -> TransformTrack:
    return mount_track(STAMP - margin, STAMP + 100 * MS + margin, **kwargs)


BAND = (0.9, 1.5)      # walls and the pillar; below the ceiling, above the table top


# ------------------------------------------------------------------------- loop oracle

@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("variant", ["plain", "destaggered", "beam_times", "t_channel", "holes"])
def test_moving_mount_matches_the_pixel_loop_oracle(backend: str, variant: str) -> None:
    fields: dict[str, Any] = {}
    if variant == "beam_times":
        fields["beam_time_offsets"] = (np.arange(16) * 23_000).astype(np.int64)
    info = make_sensor(16, 128, shifts=variant == "destaggered", **fields)
    track = sweep_track(info)
    delays = None
    if variant == "t_channel":
        delays = np.random.default_rng(4).integers(0, 700_000, (16, 128))
    scan = moving_room_scan(info, track, destagger=variant == "destaggered", delays=delays)
    times = pixel_times(info, scan)
    holes = variant == "holes"
    conv = SliceConverter(info, {"s": SliceSpec(*BAND)}, extrinsics=track, frame_id="base_link",
                          holes=holes, floor_height=0.0, hole_depth=0.05, backend=backend)
    got = conv.convert(scan)["s"]
    assert got.header.frame_id == "base_link"
    ref = ref_slice(scan, info, zmin=BAND[0], zmax=BAND[1],
                    ext=lambda u, v: track.lookup(int(times[u, v])),
                    holes={"floor_height": 0.0, "hole_depth": 0.05, "hole_range_max": None,
                           "hole_no_return": True} if holes else None)
    assert_same(got, ref)
    # the mount's poses: one per distinct pixel time, in the documented order
    poses, index = conv.mount_poses(scan)
    assert len(poses) == len(np.unique(times))
    np.testing.assert_array_equal(poses[index], track.lookup_many(times.reshape(-1)))


@settings(max_examples=12, deadline=None)
@given(yaw_rate=st.floats(-12.0, 12.0), nod=st.floats(0.0, 0.4), speed=st.floats(-2.0, 2.0),
       step_ms=st.integers(1, 60))
def test_any_smooth_motion_matches_the_oracle(yaw_rate: float, nod: float, speed: float,
                                              step_ms: int) -> None:
    info = make_sensor(8, 64)
    track = sweep_track(info, margin=60 * MS, yaw_rate=yaw_rate, nod=nod, speed=speed,
                        step=step_ms * MS)
    scan = moving_room_scan(info, track)
    times = pixel_times(info, scan)
    got = SliceConverter(info, {"s": SliceSpec(0.3, 2.0)}, extrinsics=track,
                         frame_id="base_link").convert(scan)["s"]
    assert_same(got, ref_slice(scan, info, zmin=0.3, zmax=2.0,
                               ext=lambda u, v: track.lookup(int(times[u, v]))))


# -------------------------------------------------------------------- static-scene truth

def wall_truth(grid_angles: np.ndarray, height: float) -> np.ndarray:
    """Planar distance from base_link's z axis to the room at ``height`` along each angle."""
    d = np.stack([np.cos(grid_angles), np.sin(grid_angles), np.zeros_like(grid_angles)], 1)
    o = np.tile([0.0, 0.0, height], (len(grid_angles), 1))
    return raycast(o, d)


@pytest.mark.parametrize("backend", BACKENDS)
def test_rotating_mount_slice_shows_the_static_room(backend: str) -> None:
    """A lidar on a pan unit turning at 1 turn/s (36 degrees during its 100 ms sweep) and
    nodding: with the track, every slice bin lies on the room's walls; with the pose at the
    stamp only (motion ignored), most do not."""
    info = make_sensor(32, 512, fov=40.0)
    track = mount_track(STAMP - 10 * MS, STAMP + 110 * MS, yaw_rate=2 * math.pi, nod=0.1,
                        step=2 * MS)
    scan = moving_room_scan(info, track, specials=False)
    spec = {"s": SliceSpec(*BAND)}
    moving = SliceConverter(info, spec, extrinsics=track, frame_id="base_link",
                            backend=backend).convert(scan)["s"]
    ignored = SliceConverter(info, spec, extrinsics=track.lookup(STAMP), frame_id="base_link",
                             backend=backend).convert(scan)["s"]
    angles = moving.angle_min + np.arange(len(moving.ranges)) * moving.angle_increment
    truth = wall_truth(angles, 1.2)
    # a bin spans 0.7 degrees: the wall's distance changes across it, most near corners
    tolerance = 0.02 + truth * np.radians(0.7) * 2
    r_moving, r_ignored = arrays(moving)[0], arrays(ignored)[0]
    ok = np.isfinite(r_moving)
    # the head turns against the sensor's clockwise sweep: the sweep covers 360 - 36 degrees
    assert 0.85 < ok.mean() < 0.95
    err = np.abs(r_moving[ok] - truth[ok])
    assert np.median(err) < 0.015 and np.mean(err <= tolerance[ok]) > 0.99, np.sort(err)[-10:]
    bad = np.isfinite(r_ignored)
    err_ignored = np.abs(r_ignored[bad] - truth[bad])
    assert np.median(err_ignored) > 0.15 and np.mean(err_ignored <= tolerance[bad]) < 0.5


# ----------------------------------------------------------------------- forms and errors

def test_callable_and_track_give_the_same_slices() -> None:
    info = make_sensor(16, 128, beam_time_offsets=(np.arange(16) * 1000).astype(np.int64))
    track = sweep_track(info)
    scan = moving_room_scan(info, track)
    calls: list[int] = []

    def mount(t: int) -> np.ndarray:
        calls.append(t)
        return track.lookup(t)

    spec = {"a": SliceSpec(*BAND), "b": SliceSpec(0.2, 0.8, angle_increment=0.02)}
    by_track = SliceConverter(info, spec, extrinsics=track, frame_id="base_link").convert(scan)
    by_call = SliceConverter(info, spec, extrinsics=mount, frame_id="base_link").convert(scan)
    for name in spec:
        assert_same(by_call[name], arrays(by_track[name]))
    times = pixel_times(info, scan)
    assert sorted(calls) == sorted(set(times.reshape(-1).tolist()))     # once per distinct time
    # to_laserscan takes the same forms (cached per mount object)
    for ext in (track, mount):
        one = to_laserscan(scan, info, min_height=BAND[0], max_height=BAND[1], extrinsics=ext,
                           frame_id="base_link")
        assert_same(one, arrays(by_track["a"]))


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_still_mount_equals_the_fixed_extrinsics(backend: str) -> None:
    """A track that holds one pose over the scan gives the fixed-mount slices bit for bit, and
    its tables are reused by the next scan at the same pose."""
    info = make_sensor(16, 128, shifts=True)
    fixed = pose(0.1, 0.0, 0.6, yaw=0.4, pitch=0.1)
    track = TransformTrack()
    track.add(0, fixed)
    track.add(10 * STAMP, fixed)
    scan = moving_room_scan(info, lambda t: fixed, destagger=True)
    spec = {"s": SliceSpec(*BAND), "h": SliceSpec(0.2, 0.8, holes=True, floor_height=0.0)}
    conv = SliceConverter(info, spec, extrinsics=track, frame_id="base_link", backend=backend)
    got = conv.convert(scan)
    ref = SliceConverter(info, spec, extrinsics=fixed, frame_id="base_link",
                         backend=backend).convert(scan)
    for name in spec:
        assert_same(got[name], arrays(ref[name]))
    tables = conv._moving_cache
    assert tables is not None
    conv.convert(scan)
    assert conv._moving_cache is tables                     # same pose: tables reused


def test_out_of_span_and_lookup_errors_are_raised() -> None:
    info = make_sensor(8, 64)
    scan = moving_room_scan(info, lambda t: pose(z=0.6))
    spec = {"s": SliceSpec(*BAND)}
    short = mount_track(STAMP, STAMP + 50 * MS)           # ends in the middle of the sweep
    with pytest.raises(OutOfSpanError) as err:
        SliceConverter(info, spec, extrinsics=short, frame_id="base_link").convert(scan)
    assert err.value.stamp_ns > STAMP + 50 * MS and err.value.span == (STAMP, STAMP + 50 * MS)
    with pytest.raises(OutOfSpanError):
        to_laserscan(scan, info, min_height=0.9, max_height=1.5, extrinsics=TransformTrack(),
                     frame_id="base_link")
    late = mount_track(STAMP + MS, STAMP + 200 * MS)      # starts after the first column
    with pytest.raises(OutOfSpanError):
        SliceConverter(info, spec, extrinsics=late, frame_id="base_link").convert(scan)

    def unknown(t: int) -> np.ndarray:
        raise TransformLookupError("base_link <- os_sensor", t, "a known time")

    with pytest.raises(TransformLookupError):
        SliceConverter(info, spec, extrinsics=unknown, frame_id="base_link").convert(scan)
    for bad in (lambda t: np.diag([2.0, 1, 1, 1]), lambda t: np.eye(3),
                lambda t: np.full((4, 4), np.nan)):
        with pytest.raises(ValidationError):
            SliceConverter(info, spec, extrinsics=bad, frame_id="base_link").convert(scan)


def test_a_moving_mount_needs_the_target_frame() -> None:
    info = make_sensor(8, 64)
    with pytest.raises(ConfigError, match="frame_id"):
        SliceConverter(info, {"s": SliceSpec(*BAND)}, extrinsics=lambda t: np.eye(4))
    with pytest.raises(ConfigError, match="frame_id"):
        to_laserscan(moving_room_scan(info, lambda t: np.eye(4)), info, min_height=0.0,
                     max_height=1.0, extrinsics=TransformTrack())


# ------------------------------------------------------- the per-scan path vs the full tables

NUMBA = pytest.mark.skipif(importlib.util.find_spec("numba") is None,
                           reason="numba not installed")

MOVING_SPECS = {
    "one": {"s": SliceSpec(*BAND)},
    "grids": {"a": SliceSpec(*BAND), "b": SliceSpec(0.2, 0.8, angle_increment=0.02),
              "sector": SliceSpec(0.0, 2.0, angle_min=-1.0, angle_max=1.5, range_max=3.0)},
    "nine": {f"s{i}": SliceSpec(0.1 * i, 0.1 * i + 0.6) for i in range(9)},
    "holes": {"s": SliceSpec(*BAND), "h": SliceSpec(0.2, 0.8, holes=True, floor_height=0.0)},
}


@NUMBA
@pytest.mark.parametrize("specs", list(MOVING_SPECS))
@pytest.mark.parametrize("variant", ["plain", "destaggered", "beam_times", "t_channel"])
def test_per_scan_rays_equal_the_full_tables(specs: str, variant: str) -> None:
    """The moving mount's per-scan path (:class:`converters.slices.converter._MovingRays`: rays moved
    by the compiled transform, atan2 for every in-band point, qualifiers of the specials only)
    gives the slices of the full per-scan tables (the path before it, kept as the oracle) and
    of the numpy reference, bit for bit, over several scans of one converter."""
    from converters.slices.converter import _MovingRays

    fields: dict[str, Any] = {}
    if variant == "beam_times":
        fields["beam_time_offsets"] = (np.arange(16) * 23_000).astype(np.int64)
    info = make_sensor(16, 256, shifts=variant == "destaggered", **fields)
    track = sweep_track(info, margin=60 * MS, yaw_rate=5.0, nod=0.3, speed=0.5)
    spec = MOVING_SPECS[specs]
    fast = SliceConverter(info, spec, extrinsics=track, frame_id="base_link", backend="numba")
    full = SliceConverter(info, spec, extrinsics=track, frame_id="base_link", backend="numba")
    full._reference_tables = True
    ref = SliceConverter(info, spec, extrinsics=track, frame_id="base_link", backend="numpy")
    rng = np.random.default_rng(7)
    for k in range(3):
        delays = rng.integers(0, 700_000, (16, 256)) if variant == "t_channel" else None
        scan = moving_room_scan(info, track, destagger=variant == "destaggered", delays=delays,
                                rng=rng, stamp=STAMP + k * 10 * MS)   # the track: +-60 ms
        r = np.ascontiguousarray(lidarscan.range_m(scan, info)).reshape(-1)
        assert isinstance(fast._moving_tables(scan, r), _MovingRays)
        got, want, oracle = fast.convert(scan), full.convert(scan), ref.convert(scan)
        for name in spec:
            assert_same(got[name], arrays(want[name]))
            assert_same(got[name], arrays(oracle[name]))


@NUMBA
def test_compiled_transform_gives_the_bits_of_transform_rays() -> None:
    from converters._kernels.slices_numba import kernels
    from converters.shared.frames import transform_rays

    rng = np.random.default_rng(11)
    n, p = 5000, 37
    d = rng.normal(size=(n, 3)).astype(np.float32)
    o = (rng.normal(size=(n, 3)) * rng.choice([1e-3, 1.0, 1e3], (n, 1))).astype(np.float32)
    poses = np.stack([pose(*rng.normal(size=3) * 10, roll=a, pitch=b, yaw=c)
                      for a, b, c in rng.uniform(-3, 3, (p, 3))])
    index = rng.integers(0, p, n)
    want = transform_rays(d, o, poses, index)
    got = kernels().transform_rays(d, o, poses, index)
    for k in range(3):
        np.testing.assert_array_equal(got[k].view(np.int32), want[0][:, k].view(np.int32))
        np.testing.assert_array_equal(got[3 + k].view(np.int32), want[1][:, k].view(np.int32))


def test_pixel_times_are_kept_per_column_times() -> None:
    """The distinct pixel times (and each pixel's) are computed once per column timing, not per
    scan; a scan with a ``t`` channel computes its own."""
    info = make_sensor(8, 64, beam_time_offsets=(np.arange(8) * 1000).astype(np.int64))
    track = sweep_track(info, margin=60 * MS)
    conv = SliceConverter(info, {"s": SliceSpec(*BAND)}, extrinsics=track, frame_id="base_link")
    scan = moving_room_scan(info, track)
    conv.convert(scan)
    kept = conv._time_cache
    assert kept is not None and len(kept[1][0]) == 8 * 64
    poses, index = conv.mount_poses(moving_room_scan(info, track, stamp=STAMP + 20 * MS))
    assert conv._time_cache is kept
    times = pixel_times(info, scan) + 20 * MS
    np.testing.assert_array_equal(poses[index], track.lookup_many(times.reshape(-1)))
    delayed = moving_room_scan(info, track, delays=np.full((8, 64), 5000))
    conv.convert(delayed)
    assert conv._time_cache is None


@NUMBA
def test_slice_warm_up_leaves_nothing_to_compile_for_a_moving_mount() -> None:
    """The slice warm-up (as a node runs it) reaches the moving mount's kernels, so the first
    scan of a real sensor on a moving mount (the OS-2-128 frame, read-only views of a
    message) compiles nothing."""
    from test_startup import _numba, _run

    _numba()
    got = _run("""
        import json, numpy as np, lidarscan
        from converters import TransformTrack
        from converters._kernels import warm
        from converters.slices.converter import SliceConverter
        from converters.sources.ouster.metadata import info_from_metadata, scan_from_frame

        warm.warm(("slices",))
        warmed = warm.specialisations()
        D = "tests/data/ouster/"
        info = info_from_metadata(D + "OS-2-128-U1_v2.3.0_1024x10.json", stamp_ns=1,
                                  as_dataclass=True)
        frame = dict(np.load(D + "OS-2-128-U1_v2.3.0_1024x10_frame1259.npz"))
        scan = lidarscan.decode_scan(lidarscan.encode(scan_from_frame(frame, info)))
        stamp = int(scan.header.stamp.sec) * 10**9 + int(scan.header.stamp.nanosec)
        track = TransformTrack()
        for k in range(-2, 25):
            c, s = np.cos(0.05 * k), np.sin(0.05 * k)
            track.add(stamp + k * 5_000_000, np.array([[c, -s, 0, 0], [s, c, 0, 0],
                                                       [0, 0, 1, 0.5], [0, 0, 0, 1.0]]))
        conv = SliceConverter(info, {"a": {"min_height": 0.0, "max_height": 1.0}},
                              extrinsics=track, frame_id="base_link")
        conv.convert(scan)
        print(json.dumps([warmed, warm.specialisations()]))
    """)
    warmed, after = got
    assert warmed["transform_rays"] == 1 and after == warmed, got


@NUMBA
def test_compiled_special_tables_equal_far_field_and_qualify() -> None:
    """The moving path's far-field bins and qualifiers of the special pixels equal the numpy
    functions of the fixed-mount tables (converters.slices.spec.far_field, qualify) on random rays
    with horizontal, vertical and axis-aligned ones, open bands, sectors and range limits."""
    from converters.slices import spec as _grid
    from converters.slices.spec import AngleGrid, OutputOptions
    from converters._kernels.slices_numba import Bands, kernels

    rng = np.random.default_rng(5)
    n = 20000
    d = rng.normal(size=(n, 3))
    d[::7, 2] = 0.0                                   # horizontal
    d[3::11, :2] = 0.0                                # vertical
    d[5::13, 1] = 0.0                                 # along x
    o = rng.normal(size=(n, 3)) * [0.3, 0.3, 1.0]
    o[::5, :2] = 0.0                                  # on the z axis
    d32, o32 = d.astype(np.float32), o.astype(np.float32)
    d64, o64 = d32.astype(np.float64), o32.astype(np.float64)
    grids = [AngleGrid.create(-math.pi, math.pi, 2 * math.pi / 360),
             AngleGrid.create(-1.0, 1.5, 0.01)]
    slices = [(0.0, 1.0, OutputOptions.create(0.1, 30.0, True, 1.0, None), 0),
              (-math.inf, 0.2, OutputOptions.create(0.0, math.inf, True, 1.0, None), 1),
              (0.5, math.inf, OutputOptions.create(1.0, 2.0, False, 1.0, None), 0),
              (-0.3, -0.3, OutputOptions.create(0.0, 5.0, True, 1.0, None), 1)]
    bands = Bands.create(slices, grids)
    near = 0.4
    bin_far = np.full((2, n), -1, np.int32)
    qual = np.zeros((4, n), np.uint8)
    special = np.arange(0, n, 2)
    rays = tuple(np.ascontiguousarray(a[:, k]) for a in (d32, o32) for k in range(3))
    kernels().special_tables(special, rays, bands, near, bin_far, qual)
    far = [_grid.far_field(d64, o64, g)[0] for g in grids]
    for g in range(2):
        np.testing.assert_array_equal(bin_far[g, special], far[g][special])
        assert np.all(bin_far[g, 1::2] == -1)
    for s, (lo, hi, opts, g) in enumerate(slices):
        q_far, q_near = _grid.qualify(d64, o64, lo, hi, opts.range_min, opts.range_max, near)
        ok = far[g] >= 0
        want = (q_far & ok).astype(np.uint8) | ((q_near & ok).astype(np.uint8) << 1)
        np.testing.assert_array_equal(qual[s, special], want[special])
        assert want[special].any() and np.all(qual[s, 1::2] == 0)
