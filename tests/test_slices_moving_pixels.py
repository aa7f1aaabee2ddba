"""Moving-mount slices with a pose per pixel (per-beam time offsets, an irregular ``t``
channel): with a :class:`converters.TransformTrack` and the compiled kernels each ray's pose is
interpolated in the compiled pass (``Compiled.track_rays``) instead of one
``TransformTrack.lookup_many`` pose per distinct pixel time.

Oracles: the per-time path (``SliceConverter._per_pixel = False``: ``np.unique`` of the pixel
times, ``lookup_many``, :func:`converters.shared.frames.transform_rays`' arithmetic), which the
pixel-loop oracle of tests/test_moving_slices.py checks, and the numpy backend. The stated bound:
the kernel's float64 rotation may differ from numpy's in its last bits, so a float32 ray
component is the reference's or its float32 neighbour (1 ulp), and almost always the same bits.
"""

from __future__ import annotations

import importlib.util
from typing import Any

import numpy as np
import pytest

import lidarscan
from converters.shared.frames import transform_rays
from converters.slices.converter import SliceConverter, SliceSpec
from converters.shared.transforms import (
    OutOfSpanError,
    TransformTrack,
    interpolate_poses,
    segment_rotvecs,
)
from grid_reference import pose
from test_laserscan import arrays, assert_same, make_sensor
from test_moving_slices import (
    BAND,
    MOVING_SPECS,
    MS,
    STAMP,
    mount_track,
    moving_room_scan,
    sweep_track,
)

NUMBA = pytest.mark.skipif(importlib.util.find_spec("numba") is None,
                           reason="numba not installed")

def random_track(rng: np.random.Generator, stamps: np.ndarray, tolerance: int = 0
                 ) -> TransformTrack:
    """Random poses at ``stamps``: steps of a few degrees (the series) and of up to 2.5 rad
    (libm's sin and cos) alternate, with translations of metres."""
    track = TransformTrack(tolerance_ns=tolerance)
    angles = np.zeros(3)
    for k, t in enumerate(stamps):
        angles = angles + rng.normal(size=3) * (0.05 if k % 3 else 1.2)
        track.add(int(t), pose(*rng.normal(size=3) * 3.0, roll=angles[0], pitch=angles[1],
                               yaw=angles[2]))
    return track


@NUMBA
def test_track_rays_equal_the_per_time_poses_within_one_float32_ulp() -> None:
    """Every ray moved by the kernel's pose equals the reference (the pose of ``lookup_many``
    at the ray's time, then ``transform_rays``) within one float32 ulp per component, and
    bit for bit at the samples' own stamps and where the newest pose is held."""
    from converters._kernels.slices_numba import kernels

    rng = np.random.default_rng(21)
    stamps = STAMP + np.cumsum(rng.integers(1, 8, 40)) * MS
    track = random_track(rng, stamps, tolerance=3 * MS)
    n = 60_000
    d = rng.normal(size=(n, 3)).astype(np.float32)
    o = (rng.normal(size=(n, 3)) * rng.choice([1e-3, 1.0, 30.0], (n, 1))).astype(np.float32)
    stamp = int(stamps[0])
    # rows of rays forward in time, as a scan's; some at the samples' stamps, some held
    relative = np.sort(rng.integers(0, int(stamps[-1]) + 3 * MS - stamp, (60, n // 60)), axis=1)
    relative.reshape(-1)[::97] = (stamps[rng.integers(0, 40, relative.size)] - stamp)[::97]
    relative = relative.reshape(-1)
    relative[-50:] = int(stamps[-1]) - stamp + rng.integers(1, 3 * MS, 50)    # held
    times, poses = track.samples(stamp + int(relative.min()), stamp + int(relative.max()))
    got = kernels().track_rays(np.ascontiguousarray(d.T), np.ascontiguousarray(o.T), relative,
                               stamp, times, poses, segment_rotvecs(poses[:-1], poses[1:]))
    want_d, want_o = transform_rays(d, o, track.lookup_many(stamp + relative), np.arange(n))
    want = np.concatenate([want_d.T, want_o.T])
    got = np.stack(got)
    ulp = np.spacing(np.abs(want))
    assert np.all(np.abs(got - want) <= ulp)
    assert np.mean(got == want) > 0.9999
    exact = np.isin(stamp + relative, stamps) | (stamp + relative > stamps[-1])
    assert exact.sum() > 500
    np.testing.assert_array_equal(got[:, exact], want[:, exact])


@NUMBA
@pytest.mark.parametrize("specs", list(MOVING_SPECS))
def test_per_pixel_poses_give_the_slices_of_the_per_time_path(specs: str) -> None:
    """A destaggered scan with per-beam time offsets: slices from poses interpolated per ray
    equal the per-time path's (compiled) and the numpy reference's, over scans of one
    converter (its kept pixel times reused). Beam offsets and a ``t`` channel without
    destaggering: tests/test_moving_slices.py::test_per_scan_rays_equal_the_full_tables,
    whose compiled converter takes this path too (asserted here)."""
    from converters.slices.tables import _MovingRays

    info = make_sensor(16, 256, shifts=True,
                       beam_time_offsets=(np.arange(16) * 31_000).astype(np.int64))
    track = sweep_track(info, margin=60 * MS, yaw_rate=-4.0, nod=0.3, speed=0.8, step=3 * MS)
    spec = MOVING_SPECS[specs]
    converters = [SliceConverter(info, spec, extrinsics=track, frame_id="base_link",
                                 backend=backend) for backend in ("numba", "numba", "numpy")]
    converters[1]._per_pixel = False
    rng = np.random.default_rng(17)
    for stamp in (STAMP, STAMP + 30 * MS):
        scan = moving_room_scan(info, track, destagger=True, rng=rng, stamp=stamp)
        flat = np.ascontiguousarray(lidarscan.range_m(scan, info)).reshape(-1)
        assert converters[0]._pose_times(scan, distinct=False)[1] is None  # a time per pixel
        assert isinstance(converters[0]._moving_tables(scan, flat), _MovingRays)
        got, *others = (c.convert(scan) for c in converters)
        for other in others:
            for name in spec:
                assert_same(got[name], arrays(other[name]))
    # the full-tables test's scenes take the per-pixel path
    for fields, delays in (({"beam_time_offsets": np.arange(16) * 23_000}, None),
                           ({}, rng.integers(0, 700_000, (16, 256)))):
        info = make_sensor(16, 256, **fields)
        scan = moving_room_scan(info, track, delays=delays)
        conv = SliceConverter(info, spec, extrinsics=track, frame_id="base_link")
        assert conv._pose_times(scan, distinct=False)[1] is None


@pytest.mark.parametrize("destagger", [False, True])
def test_a_t_channel_constant_along_columns_gives_one_pose_per_column(destagger: bool) -> None:
    """Pixel times that depend on the measurement column only (a ``t`` channel constant along
    each column) are found exactly: W distinct times, no per-pixel poses; the slices are those
    of the pixel-loop-checked numpy path. Varying one pixel's delay gives a time per pixel."""
    info = make_sensor(16, 128, shifts=destagger)
    track = sweep_track(info)
    delays = np.broadcast_to(np.random.default_rng(2).integers(0, 400_000, 128), (16, 128))
    scan = moving_room_scan(info, track, destagger=destagger, delays=np.array(delays))
    conv = SliceConverter(info, {"s": SliceSpec(*BAND)}, extrinsics=track, frame_id="base_link")
    times, index = conv._pose_times(scan, distinct=False)
    assert index is not None and len(times) == len(np.unique(delays[0] + np.arange(128)
                                                             * int(info.column_time_increment)))
    poses, index = conv.mount_poses(scan)
    want = lidarscan.make_projector(info).pixel_times(scan).reshape(-1) + STAMP
    np.testing.assert_array_equal(poses[index], track.lookup_many(want))
    ref = SliceConverter(info, {"s": SliceSpec(*BAND)}, extrinsics=track, frame_id="base_link",
                         backend="numpy").convert(scan)["s"]
    assert_same(conv.convert(scan)["s"], arrays(ref))
    uneven = np.array(delays)
    uneven[5, 7] += 1
    scan = moving_room_scan(info, track, destagger=destagger, delays=uneven)
    assert conv._pose_times(scan, distinct=False)[1] is None


@NUMBA
def test_out_of_span_names_the_stamp_of_the_per_time_path() -> None:
    info = make_sensor(8, 64, beam_time_offsets=(np.arange(8) * 1000).astype(np.int64))
    scan = moving_room_scan(info, lambda t: pose(z=0.6))
    errors = []
    for per_pixel in (True, False):
        short = mount_track(STAMP, STAMP + 50 * MS)      # ends in the middle of the sweep
        conv = SliceConverter(info, {"s": SliceSpec(*BAND)}, extrinsics=short,
                              frame_id="base_link", backend="numba")
        conv._per_pixel = per_pixel
        with pytest.raises(OutOfSpanError) as err:
            conv.convert(scan)
        errors.append((err.value.stamp_ns, err.value.span))
    assert errors[0] == errors[1] and errors[0][0] > STAMP + 50 * MS


@pytest.mark.parametrize("backend", ["numpy", pytest.param("numba", marks=NUMBA)])
def test_a_still_track_with_beam_times_gets_the_fixed_tables(backend: str) -> None:
    info = make_sensor(16, 128, beam_time_offsets=(np.arange(16) * 5000).astype(np.int64))
    fixed = pose(0.1, 0.0, 0.6, yaw=0.4, pitch=0.1)
    track = TransformTrack()
    track.add(0, fixed)
    track.add(10 * STAMP, fixed)
    scan = moving_room_scan(info, lambda t: fixed)
    conv = SliceConverter(info, {"s": SliceSpec(*BAND)}, extrinsics=track,
                          frame_id="base_link", backend=backend)
    got = conv.convert(scan)["s"]
    kept = conv._moving_cache
    assert kept is not None
    conv.convert(scan)
    assert conv._moving_cache is kept
    ref = SliceConverter(info, {"s": SliceSpec(*BAND)}, extrinsics=fixed, frame_id="base_link",
                         backend=backend).convert(scan)["s"]
    assert_same(got, arrays(ref))


def test_track_samples_bracket_every_stamp_of_an_interval() -> None:
    """``samples(first, last)``: the samples around every stamp of the interval, whose
    interpolation is ``lookup_many``'s; out-of-span stamps raise as lookups do."""
    rng = np.random.default_rng(8)
    stamps = np.cumsum(rng.integers(1, 50, 30)) * 1000
    track = random_track(rng, stamps, tolerance=5000)
    for first, last in ((stamps[3] + 1, stamps[9] - 1), (stamps[3], stamps[9]),
                        (stamps[0], stamps[-1] + 5000), (stamps[4] + 7, stamps[4] + 9)):
        times, poses = track.samples(int(first), int(last))
        assert times[0] <= first and (times[-1] >= last or times[-1] == stamps[-1])
        assert np.all(np.isin(times, stamps)) and np.all(np.diff(times) > 0)
        assert times.size == 1 or (times[1] > first and times[-2] < last)
        t = np.unique(rng.integers(first, last + 1, 200))
        want = track.lookup_many(t)
        k = np.clip(np.searchsorted(times, t, side="right") - 1, 0, times.size - 1)
        inside = (t != times[k]) & (k + 1 < times.size)
        u = (t[inside] - times[k[inside]]) / (times[k[inside] + 1] - times[k[inside]])
        got = interpolate_poses(poses[:-1], poses[1:], u, k[inside]) if inside.any() else None
        if got is not None:
            np.testing.assert_array_equal(got, want[inside])
        np.testing.assert_array_equal(poses[k[~inside]], want[~inside])
    with pytest.raises(OutOfSpanError) as err:
        track.samples(int(stamps[0]) - 1, int(stamps[5]))
    assert err.value.stamp_ns == stamps[0] - 1
    with pytest.raises(OutOfSpanError) as err:
        track.samples(int(stamps[0]), int(stamps[-1]) + 5001)
    assert err.value.stamp_ns == stamps[-1] + 5001
    with pytest.raises(OutOfSpanError):
        TransformTrack().samples(0, 1)
