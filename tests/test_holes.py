"""Holes (negative obstacles) in LaserScan slices: a plain per-ray loop oracle, a staircase down
seen by a lidar and by a depth camera with the reported edge checked analytically, off by
default (bit-identical to the slicer without holes), a tilted sensor with target-frame limits,
backend parity, validation, and a Hypothesis property against the oracle.

``ref_slice`` below is written from the rules in the docstrings of converters/slices/holes.py and
converters/slices/spec.py (the conventions a hole edge follows), one pixel at a time. Scenes are
axis-aligned boxes ray-cast from the projector's own beam tables
(:meth:`converters.edge.demo.run.Scene.cast`), so every geometry is exact.
"""

from __future__ import annotations

import hashlib
import importlib.util
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import lidarscan
from converters.edge.demo.run import Box, Scene
from converters.sources.depth import OPTICAL_FROM_BODY, from_depth_image
from converters.slices.converter import SliceConverter, SliceSpec, to_laserscan
from lidarscan.errors import ConfigError, LidarScanError
from grid_reference import pose, ref_slice
from test_laserscan import SPECIALS, draw_image

TWO_PI = 2 * math.pi
F32 = np.float32
#: auto: the C kernel or numba where built (else numpy); numba: numba's kernels alone
BACKENDS = ["numpy", "auto"] + (["numba"] if importlib.util.find_spec("numba") else [])


# --------------------------------------------------------------------------- reference code

HOLES = {"floor_height": 0.0, "hole_depth": 0.05, "hole_range_max": None,
         "hole_no_return": True}


def arrays(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    return np.array(msg.ranges, np.float32), np.array(msg.intensities, np.float32)


def assert_same(msg: Any, ref: tuple[np.ndarray, np.ndarray]) -> None:
    got = arrays(msg)
    np.testing.assert_array_equal(got[0], ref[0])
    np.testing.assert_array_equal(got[1], ref[1])


# ------------------------------------------------------------------------------- scenes

def staircase(edge: float = 2.0, step: float = 0.18, tread: float = 0.3, steps: int = 4,
              floor_height: float = 0.0, pillar: bool = True) -> Scene:
    """Floor at ``floor_height`` for x < ``edge``, then ``steps`` steps down (+x), the last one
    reaching far; a pillar (an in-band obstacle) at about 45 degrees, in front of the edge."""
    f = floor_height
    boxes = [Box("floor", (-40.0, -40.0, f - 3.0), (edge, 40.0, f))]
    for k in range(steps):
        x1 = edge + (k + 1) * tread if k < steps - 1 else 60.0
        boxes.append(Box("step", (edge + k * tread, -40.0, f - 3.0), (x1, 40.0,
                                                                      f - (k + 1) * step)))
    if pillar:
        boxes.append(Box("pillar", (1.0, 0.9, f), (1.2, 1.1, f + 2.0)))
    return Scene(tuple(boxes))


def lidar(height: int = 24, width: int = 180, *, top: float = -4.0, bottom: float = -40.0,
          origins: bool = False, **fields: Any) -> Any:
    """A spinning lidar looking down (CW columns like Ouster's), metres, rad."""
    extra: dict[str, Any] = {"range_min": 0.1, "range_max": 80.0}
    if origins:
        extra["beam_origins"] = np.tile([0.015, 0.0, 0.0], height)
        extra["beam_range_offsets"] = np.full(height, -0.015)
    extra.update(fields)
    return lidarscan.make_info(
        stamp_ns=5_000_000_000, frame_id="lidar",
        vertical_angles=np.radians(np.linspace(top, bottom, height)),
        horizontal_angles=TWO_PI * (1 - np.arange(width) / width), as_dataclass=True, **extra)


def cast_scan(info: Any, mount: np.ndarray, scene: Scene, *, specials: float = 0.0,
              seed: int = 3) -> Any:
    """The scene seen by ``info`` at ``mount`` (target <- sensor), exact float32 ranges."""
    proj = lidarscan.make_projector(info)
    d = proj.directions.reshape(-1, 3).astype(np.float64)
    o = proj.offsets.reshape(-1, 3).astype(np.float64)
    hits = scene.cast(o @ mount[:3, :3].T + mount[:3, 3], d @ mount[:3, :3].T)
    r = hits.t.astype(np.float32)
    rng = np.random.default_rng(seed)
    if specials:
        pick = rng.choice(r.size, size=int(r.size * specials), replace=False)
        r[pick] = np.array([np.inf, np.nan, -np.inf, 0.0], np.float32)[np.arange(pick.size) % 4]
    inten = rng.integers(0, 4000, r.size).astype(np.float32)
    shape = (proj.height, proj.width)
    return lidarscan.make_scan(info, {"range": r.reshape(shape), "intensity": inten.reshape(shape)},
                               6_000_000_000, as_dataclass=True)


def camera_info(width: int = 96, height: int = 72, hfov: float = math.radians(80)) -> dict:
    """A pinhole CameraInfo (no distortion) as a mapping of its fields."""
    f = width / 2 / math.tan(hfov / 2)
    cx, cy = (width - 1) / 2, (height - 1) / 2
    return {"header": {"stamp": 1_000_000_000, "frame_id": "cam_optical"},
            "height": height, "width": width, "distortion_model": "plumb_bob",
            "d": [0.0] * 5, "k": [f, 0, cx, 0, f, cy, 0, 0, 1], "r": [1, 0, 0, 0, 1, 0, 0, 0, 1],
            "p": [f, 0, cx, 0, 0, f, cy, 0, 0, 0, 1, 0]}


def render_depth(cam: dict, base_from_optical: np.ndarray, scene: Scene) -> np.ndarray:
    """(H, W) float32 z-depth image of the scene (NaN where nothing is hit)."""
    k = cam["k"]
    v, u = np.mgrid[0:cam["height"], 0:cam["width"]].astype(np.float64)
    rays = np.stack([(u - k[2]) / k[0], (v - k[5]) / k[4], np.ones_like(u)], -1).reshape(-1, 3)
    rot, t = base_from_optical[:3, :3], base_from_optical[:3, 3]
    hits = scene.cast(np.broadcast_to(t, rays.shape), rays @ rot.T)   # t = z in the optical frame
    return hits.t.reshape(cam["height"], cam["width"]).astype(np.float32)


def camera_mount(height: float, pitch: float) -> np.ndarray:
    """base <- optical frame of a camera ``height`` m above base, pitched down by ``pitch``."""
    body = pose(z=height, pitch=pitch)
    optical = np.eye(4)
    optical[:3, :3] = OPTICAL_FROM_BODY.T                       # body <- optical
    return body @ optical


# ----------------------------------------------------------------- the staircase, analytically

def test_lidar_reports_the_staircase_edge_where_its_rays_cross_the_floor() -> None:
    """A level lidar 1 m above the floor, one column per bin, no beam origins: ray (u, c)
    crosses the floor at planar range h / tan(-alt_u) at azimuth theta_c, and goes down the stairs
    iff that crossing lies beyond the edge (x > 2). The slice must report, per bin, the nearest
    such crossing (or the pillar, where the pillar is nearer), exactly the loop oracle too."""
    info = lidar()
    h, edge = 1.0, 2.0
    mount = pose(z=h)
    scene = staircase(edge)
    scan = cast_scan(info, mount, scene)
    out = to_laserscan(scan, info, min_height=0.1, max_height=1.5, extrinsics=mount,
                       frame_id="base", holes=True, hole_range_max=6.0, backend="numpy")
    got = arrays(out)[0]
    alt = np.radians(np.linspace(-4.0, -40.0, 24))
    rho_u = h / np.tan(-alt)                                     # floor crossings of each row
    theta = -math.pi + np.arange(180) * TWO_PI / 180             # bin centres = column azimuths
    checked = 0
    for b, th in enumerate(theta):
        x_f = rho_u * math.cos(th)
        over = (x_f > edge + 1e-6) & (rho_u <= 6.0)
        expected = rho_u[over].min() if over.any() else math.inf
        pillar = out.ranges[b] < 1.7 and 0.6 < th < 0.9
        if pillar:
            continue
        if math.isinf(expected):
            assert got[b] == math.inf, b
        else:
            assert abs(got[b] - expected) < 2e-5, (b, got[b], expected)
            assert got[b] >= edge / math.cos(th) - 2e-5          # never in front of the edge
            checked += 1
    assert checked > 40
    # the pillar at 45 degrees, in front of the edge, wins its bins
    b45 = int(round((math.pi / 4 + math.pi) / (TWO_PI / 180)))
    assert 1.2 < got[b45] < 1.6
    # without holes the drop is invisible in the band: nothing finite straight ahead
    plain = arrays(to_laserscan(scan, info, min_height=0.1, max_height=1.5, extrinsics=mount,
                                frame_id="base"))[0]
    assert plain[90] == math.inf and math.isfinite(got[90])
    for backend in BACKENDS:
        with_holes = to_laserscan(scan, info, min_height=0.1, max_height=1.5, extrinsics=mount,
                                  frame_id="base", holes=True, hole_range_max=6.0,
                                  backend=backend)
        assert_same(with_holes, ref_slice(scan, info, zmin=0.1, zmax=1.5, ext=mount,
                                          holes={**HOLES, "hole_range_max": 6.0}))


@pytest.mark.parametrize("backend", BACKENDS)
def test_depth_camera_sees_the_drop_at_the_edge(backend: str) -> None:
    """A depth camera 0.8 m up, pitched 35 degrees down, in front of a staircase whose edge is
    the line x = 1.5 m: in every bin that looks at the edge the slice reports it within one row's
    floor spacing behind the true edge (never in front), and exactly the oracle's value."""
    cam = camera_info()
    h, edge = 0.8, 1.5
    mount = camera_mount(h, math.radians(35))
    scene = staircase(edge, pillar=False)
    depth = render_depth(cam, mount, scene)
    scan, info = from_depth_image(depth, cam, stamp_ns=7, encoding="32FC1", as_dataclass=True)
    inc = math.radians(1.0)
    conv = SliceConverter(info, {"cam": {"min_height": 0.05, "max_height": 1.5}},
                          extrinsics=mount, frame_id="base", angle_min=-0.6, angle_max=0.6,
                          angle_increment=inc, range_max=5.0, holes=True, hole_range_max=4.0,
                          intensity_channel=None, backend=backend)
    got = arrays(conv.convert(scan)["cam"])[0]
    ref = ref_slice(scan, info, zmin=0.05, zmax=1.5, ext=mount, amin=-0.6, amax=0.6, inc=inc,
                    rmax=5.0, holes={**HOLES, "hole_range_max": 4.0}, intensity=None)
    np.testing.assert_array_equal(got, ref[0])
    theta = -0.6 + np.arange(got.size) * inc
    fy = cam["k"][4]
    in_view = np.abs(theta) < math.radians(35)        # inside the 80 degree horizontal view
    assert in_view.sum() > 50
    for th, value in zip(theta[in_view], got[in_view]):
        true = edge / math.cos(th)
        lo = edge / math.cos(max(abs(th) - inc / 2, 0.0))
        spacing = (h * h + true * true) / h / fy * 1.5 + true * math.tan(inc) # one row, one bin
        assert lo - 1e-4 <= value <= true + spacing, (th, value, true)
    plain = SliceConverter(info, {"cam": {"min_height": 0.05, "max_height": 1.5}},
                           extrinsics=mount, frame_id="base", angle_min=-0.6, angle_max=0.6,
                           angle_increment=inc, range_max=5.0, intensity_channel=None,
                           backend=backend).convert(scan)["cam"]
    assert np.all(np.isinf(arrays(plain)[0][in_view]))   # the band alone sees nothing


def test_a_pit_shallower_than_hole_depth_is_floor_and_nan_depth_is_no_hole() -> None:
    """Inclusive depth test: a 4 cm dip is floor for hole_depth 0.05, a hole for 0.04; pixels
    without a measurement (NaN) never report a hole, with invalid=inf they do (no return)."""
    cam = camera_info(64, 48)
    mount = camera_mount(0.8, math.radians(35))
    scene = staircase(1.5, step=0.04, steps=1, pillar=False)
    depth = render_depth(cam, mount, scene)
    scan, info = from_depth_image(depth, cam, stamp_ns=7, encoding="32FC1", as_dataclass=True)
    kw: dict[str, Any] = {"min_height": 0.05, "max_height": 1.5, "extrinsics": mount,
                          "frame_id": "base", "angle_min": -0.6, "angle_max": 0.6,
                          "angle_increment": math.radians(2), "range_max": 5.0,
                          "intensity_channel": None, "holes": True}
    assert np.all(np.isinf(arrays(to_laserscan(scan, info, hole_depth=0.05, **kw))[0]))
    assert np.isfinite(arrays(to_laserscan(scan, info, hole_depth=0.04, **kw))[0]).sum() > 10
    # nothing measured beyond the edge: NaN (default) is not evidence of a hole, +Inf is
    flat = render_depth(cam, mount, Scene((Box("floor", (-40.0, -40.0, -3.0),
                                               (60.0, 40.0, 0.0)),)))
    mask = depth != flat                               # the pixels that look into the dip
    blind = np.where(mask, np.float32(0.0), depth).astype(np.float32)
    scan_nan, info_nan = from_depth_image(blind, cam, stamp_ns=8, encoding="32FC1",
                                          as_dataclass=True)
    scan_inf, info_inf = from_depth_image(blind, cam, stamp_ns=8, encoding="32FC1",
                                          invalid=math.inf, as_dataclass=True)
    assert mask.sum() > 100
    low = arrays(to_laserscan(scan_nan, info_nan, hole_depth=0.04, **kw))[0]
    assert not np.any(np.isfinite(low))
    seen = arrays(to_laserscan(scan_inf, info_inf, hole_depth=0.04, **kw))[0]
    assert np.isfinite(seen).sum() > 10
    off = arrays(to_laserscan(scan_inf, info_inf, hole_depth=0.04, hole_no_return=False,
                              **kw))[0]
    assert not np.any(np.isfinite(off))


# ------------------------------------------------------------------------- off by default

def _off_case() -> tuple[Any, Any, dict[str, Any]]:
    info = lidar(32, 256, top=15.0, bottom=-30.0, origins=True)
    mount = pose(x=0.1, z=0.9, pitch=math.radians(8), yaw=0.2)
    scan = cast_scan(info, mount, staircase(2.0), specials=0.1)
    slices = {"low": SliceSpec(0.05, 0.5), "mid": SliceSpec(0.3, 1.2, range_max=6.0),
              "all": SliceSpec(-math.inf, math.inf)}
    return info, scan, {"slices": slices, "extrinsics": mount, "frame_id": "base"}


def _digest(out: dict[str, Any]) -> str:
    h = hashlib.sha256()
    for msg in out.values():
        r, i = arrays(msg)
        h.update(r.tobytes())
        h.update(i.tobytes())
    return h.hexdigest()


#: sha256 of ranges + intensities of the three slices of ``_off_case``, computed with the slicer
#: before hole detection existed (commit 3f608f9), the same for every backend: the default must
#: not change one bit
OFF_DIGEST = "1e0c9fdec8d2535ae9cfaa9f8a71957769890da82de93a3088974752540b35ae"


@pytest.mark.parametrize("backend", BACKENDS)
def test_off_by_default_is_bit_identical_to_the_slicer_without_holes(backend: str) -> None:
    info, scan, kw = _off_case()
    default = SliceConverter(info, kw["slices"], extrinsics=kw["extrinsics"],
                             frame_id=kw["frame_id"], backend=backend).convert(scan)
    assert _digest(default) == OFF_DIGEST
    explicit = SliceConverter(info, kw["slices"], extrinsics=kw["extrinsics"],
                              frame_id=kw["frame_id"], holes=False, floor_height=0.3,
                              hole_depth=0.01, backend=backend).convert(scan)
    assert _digest(explicit) == _digest(default)
    # the scene has a drop in view: with holes on, the output does change
    on = SliceConverter(info, kw["slices"], extrinsics=kw["extrinsics"],
                        frame_id=kw["frame_id"], holes=True, backend=backend).convert(scan)
    assert _digest(on) != _digest(default)


# ------------------------------------------------------------- the one-call row kernel

@pytest.mark.skipif(not importlib.util.find_spec("numba"), reason="numba is not installed")
@pytest.mark.parametrize("origins", [False, True])
def test_row_kernel_fuses_the_holes_in_the_same_call(origins: bool, monkeypatch: Any) -> None:
    """An upright lidar at one bin per column takes the row-ordered numba kernel with holes on
    ("auto" too: the C kernel has no holes), which adds the hole edges itself (the numpy
    hole pass is never called): four slices, one without holes, two with the same edges (one
    group, tested once), one with other hole options; invalid and no-return pixels, with and
    without beam origins (points needing atan2); every slice equals the per-pixel oracle bit
    for bit."""
    def no_numpy_pass(*_: Any) -> None:
        raise AssertionError("the numpy hole pass ran: the row kernel was not used")

    monkeypatch.setattr(SliceConverter, "_add_holes", no_numpy_pass)
    info = lidar(origins=origins)
    mount = pose(z=1.0)
    scan = cast_scan(info, mount, staircase(2.0), specials=0.06)
    near = {**HOLES, "hole_range_max": 6.0}
    deep = {**HOLES, "hole_depth": 0.3, "hole_no_return": False}
    specs = {"near": (SliceSpec(0.1, 0.6, holes=True, hole_range_max=6.0), near),
             "plain": (SliceSpec(0.5, 1.5), None),
             "twin": (SliceSpec(0.6, 1.0, holes=True, hole_range_max=6.0), near),
             "deep": (SliceSpec(0.05, 2.0, holes=True, hole_depth=0.3, hole_no_return=False),
                      deep)}
    for backend in ("auto", "numba"):
        conv = SliceConverter(info, {k: v[0] for k, v in specs.items()}, extrinsics=mount,
                              frame_id="base", backend=backend)
        out = conv.convert(scan)
        t = next(iter(conv._tables.values()))
        assert t.sorted is not None and t.sorted.rows is not None
        assert t.hole_plan.pixel.size > 100 and list(t.hole_plan.slice_start) == [0, 2, 3]
        for name, (spec, holes) in specs.items():
            assert_same(out[name], ref_slice(scan, info, zmin=spec.min_height,
                                             zmax=spec.max_height, ext=mount, holes=holes))
    assert np.isfinite(arrays(out["near"])[0]).sum() > np.isfinite(arrays(out["plain"])[0]).sum()


# ------------------------------------------------------- tilted sensor, target-frame limits

@pytest.mark.parametrize("backend", BACKENDS)
def test_tilted_lidar_with_target_frame_floor_and_per_slice_options(backend: str) -> None:
    """The target frame is base_link 0.1 m above the floor (floor_height = -0.1); a rolled and
    pitched lidar with beam origins; one slice with holes (per-slice override), one without;
    destaggered columns for the tie keys. Every slice equals the loop oracle."""
    info = lidar(16, 120, top=10.0, bottom=-35.0, origins=True,
                 pixel_shift_by_row=np.array([(3 * u) % 5 for u in range(16)], np.int32))
    mount = pose(x=0.2, y=-0.1, z=0.8, roll=0.15, pitch=0.3, yaw=-0.4)
    scene = staircase(1.8, floor_height=-0.1)
    proj = lidarscan.make_projector(info)
    scan = cast_scan(info, mount, scene, specials=0.08)
    dest = lidarscan.make_scan(info, {k: proj.destagger(lidarscan.channel(scan, k))
                                      for k in ("range", "intensity")}, 6_000_000_000,
                               is_destaggered=True, as_dataclass=True)
    holes = {"floor_height": -0.1, "hole_depth": 0.08, "hole_range_max": 4.0,
             "hole_no_return": False}
    conv = SliceConverter(info, {"edge": SliceSpec(-0.05, 1.0, holes=True,
                                                   hole_range_max=4.0, hole_no_return=False),
                                 "plain": SliceSpec(-0.05, 1.0, range_max=3.0)},
                          extrinsics=mount, frame_id="base_link", floor_height=-0.1,
                          hole_depth=0.08, range_min=0.3, backend=backend)
    for s in (scan, dest):
        out = conv.convert(s)
        assert_same(out["edge"], ref_slice(s, info, zmin=-0.05, zmax=1.0, ext=mount, rmin=0.3,
                                           holes=holes))
        assert_same(out["plain"], ref_slice(s, info, zmin=-0.05, zmax=1.0, ext=mount,
                                            rmin=0.3, rmax=3.0))
    assert np.isfinite(arrays(conv.convert(scan)["edge"])[0]).sum() > \
        np.isfinite(arrays(conv.convert(scan)["plain"])[0]).sum()


def test_inclusive_limits_and_ties() -> None:
    """A point exactly at floor_height - hole_depth is in the hole; an edge exactly at
    hole_range_max is reported, one ulp beyond is not; two identical beams tie on the same edge
    and the first pixel (its intensity) wins."""
    info = lidarscan.make_info(stamp_ns=1, frame_id="l", vertical_angles=[-0.5, -0.5],
                               horizontal_angles=[0.0, math.pi / 2], as_dataclass=True)
    proj = lidarscan.make_projector(info)
    d = proj.directions.reshape(-1, 3).astype(np.float64)[0]
    oz = 1.0
    r32 = F32(3.0)
    z = float(r32) * d[2] + oz
    depth = 0.25
    floor = z + depth
    while floor - depth != z:                      # make floor - depth hit z exactly
        floor = math.nextafter(floor, math.inf if floor - depth < z else -math.inf)
    raised = floor                     # the floor lowered until z is just above floor - depth
    while raised - depth == z:
        raised = math.nextafter(raised, -math.inf)
    r_f = (floor - oz) / d[2]
    rho_f = math.hypot(r_f * d[0], r_f * d[1])
    ranges = np.array([[r32, 5.0], [r32, 5.0]], np.float32)
    scan = lidarscan.make_scan(info, {"range": ranges,
                                      "intensity": np.array([[7, 0], [9, 0]], np.float32)},
                               2, as_dataclass=True)
    kw: dict[str, Any] = {"min_height": 5.0, "max_height": 6.0, "extrinsics": pose(z=oz),
                          "frame_id": "b", "angle_increment": math.pi / 2, "holes": True,
                          "floor_height": floor, "hole_depth": depth}
    for backend in BACKENDS:
        out = to_laserscan(scan, info, hole_range_max=rho_f, backend=backend, **kw)
        r, i = arrays(out)
        assert r[2] == F32(rho_f) and i[2] == 7.0      # bin of azimuth 0; first beam wins
        out = to_laserscan(scan, info, hole_range_max=math.nextafter(rho_f, 0.0),
                           backend=backend, **kw)
        assert arrays(out)[0][2] == math.inf
        shallow = to_laserscan(scan, info, hole_range_max=math.inf, backend=backend,
                               **{**kw, "floor_height": raised})
        assert arrays(shallow)[0][2] == math.inf       # z just above floor - depth: floor


# ---------------------------------------------------------------------------- validation

@pytest.mark.parametrize(("kwargs", "field"), [
    ({"holes": "yes"}, "holes"),
    ({"holes": 1}, "holes"),
    ({"hole_depth": 0.0}, "hole_depth"),
    ({"hole_depth": -0.1}, "hole_depth"),
    ({"hole_depth": math.nan}, "hole_depth"),
    ({"hole_depth": math.inf}, "hole_depth"),
    ({"floor_height": math.nan}, "floor_height"),
    ({"floor_height": -math.inf}, "floor_height"),
    ({"floor_height": "0"}, "floor_height"),
    ({"hole_range_max": 0.0}, "hole_range_max"),
    ({"hole_range_max": math.nan}, "hole_range_max"),
    ({"hole_no_return": "false"}, "hole_no_return"),
])
def test_bad_hole_options_name_the_parameter(small_info: Any, kwargs: dict[str, Any],
                                             field: str) -> None:
    with pytest.raises(ConfigError) as err:
        SliceConverter(small_info, {"s": SliceSpec(0.0, 1.0)}, **kwargs)
    assert err.value.field == field
    assert isinstance(err.value, LidarScanError)
    with pytest.raises(ConfigError) as err:
        SliceConverter(small_info, {"s": SliceSpec(0.0, 1.0, **kwargs)})
    assert err.value.field == f"slices['s'].{field}"
    scan = lidarscan.make_scan(small_info, {"range": np.ones((4, 8), np.float32)}, 0,
                               as_dataclass=True)
    with pytest.raises(ConfigError):
        to_laserscan(scan, small_info, min_height=0.0, max_height=1.0, **kwargs)


def test_hole_options_from_a_mapping_and_infinite_edge_limit(small_info: Any) -> None:
    conv = SliceConverter(small_info, {"s": {"min_height": 0.0, "max_height": 1.0,
                                             "holes": True, "hole_range_max": math.inf}})
    assert conv.slices[0].holes is not None and conv.slices[0].holes.range_max == math.inf
    conv = SliceConverter(small_info, {"s": {"min_height": 0.0, "max_height": 1.0}},
                          holes=True, range_max=7.0)
    assert conv.slices[0].holes is not None and conv.slices[0].holes.range_max == 7.0
    assert SliceConverter(small_info, {"s": SliceSpec(0.0, 1.0)}).slices[0].holes is None


# ------------------------------------------------------------------------------ property

@st.composite
def hole_case(draw: Any) -> tuple[Any, Any, dict[str, Any]]:
    height = draw(st.integers(1, 5))
    width = draw(st.integers(3, 20))
    vert = sorted(draw(st.lists(st.floats(-1.2, 0.4), min_size=height, max_size=height)),
                  reverse=True)
    fields: dict[str, Any] = {"range_min": draw(st.sampled_from([0.0, 0.2]))}
    if draw(st.booleans()):
        fields["beam_origins"] = draw(st.lists(st.floats(-0.05, 0.05), min_size=3 * height,
                                               max_size=3 * height))
    info = lidarscan.make_info(stamp_ns=3, frame_id="l", vertical_angles=vert,
                               horizontal_angles=TWO_PI * (1 - np.arange(width) / width)
                               + draw(st.floats(-1, 1)), as_dataclass=True, **fields)
    r = draw_image(draw, height, width, st.one_of(st.floats(0.015625, 10, width=32),
                                                  st.sampled_from(SPECIALS)), np.float32)
    inten = draw_image(draw, height, width, st.integers(0, 3), np.float32)
    scan = lidarscan.make_scan(info, {"range": r, "intensity": inten}, 0, as_dataclass=True)
    zmin = draw(st.floats(-0.5, 1.5))
    amin = draw(st.floats(-4, 1))
    opts = {"zmin": zmin, "zmax": zmin + draw(st.sampled_from([0.0, 0.3, math.inf])),
            "ext": pose(draw(st.floats(-0.5, 0.5)), draw(st.floats(-0.5, 0.5)),
                        draw(st.floats(0.2, 2.0)), draw(st.floats(-4, 4)),
                        draw(st.floats(-0.4, 0.4)), draw(st.floats(-0.4, 0.4))),
            "amin": amin, "amax": amin + draw(st.sampled_from([TWO_PI, 0.5, 3.0])),
            "inc": draw(st.floats(0.03, 0.7)), "rmin": draw(st.sampled_from([0.0, 0.5])),
            "rmax": draw(st.sampled_from([math.inf, 5.0])),
            "holes": {"floor_height": draw(st.floats(-0.5, 0.5)),
                      "hole_depth": draw(st.sampled_from([0.01, 0.05, 0.5])),
                      "hole_range_max": draw(st.sampled_from([None, 2.0, math.inf])),
                      "hole_no_return": draw(st.booleans())}}
    return info, scan, opts


@given(hole_case())
def test_property_matches_the_loop_oracle(case: Any) -> None:
    info, scan, o = case
    ref = ref_slice(scan, info, **o)
    for backend in ["numpy"] + (["auto"] if importlib.util.find_spec("numba") else []):
        got = to_laserscan(scan, info, min_height=o["zmin"], max_height=o["zmax"],
                           extrinsics=o["ext"], frame_id="b", angle_min=o["amin"],
                           angle_max=o["amax"], angle_increment=o["inc"], range_min=o["rmin"],
                           range_max=o["rmax"], holes=True, backend=backend, **o["holes"])
        assert_same(got, ref)


# ------------------------------------------------------------------------ configuration files

def test_node_parameters_and_slices_file_pass_the_hole_options(small_info: Any) -> None:
    from pathlib import Path

    from converters.edge.nodes import converter_node
    from converters.edge.nodes.params import load_slices_file

    node, per_slice = converter_node._specs()
    values = {s.name: s.default for s in node}
    values["slice_names"] = ["low"]
    values.update({t.for_name("low").name: t.default for t in per_slice})
    values.update({"slices.low.min_height": 0.0, "slices.low.max_height": 1.0,
                   "slices.low.holes": True, "slices.low.floor_height": -0.1,
                   "slices.low.hole_range_max": 2.5})
    spec = converter_node.settings(values)["slices"][0].spec()
    assert (spec.holes, spec.floor_height, spec.hole_depth, spec.hole_range_max,
            spec.hole_no_return) == (True, -0.1, None, 2.5, True)
    values["slices.low.hole_depth"] = 0.0
    bad = converter_node.settings(values)["slices"][0].spec()
    with pytest.raises(ConfigError, match="hole_depth"):
        SliceConverter(small_info, {"low": bad})
    config = Path(__file__).resolve().parent.parent / "config" / "slices.yaml"
    specs = {s.name: s.spec() for s in load_slices_file(config)}
    conv = SliceConverter(small_info, specs)
    holes = {s.name: s.holes for s in conv.slices}
    assert holes["drop_ahead"] is not None and holes["drop_ahead"].range_max == 3.0
    assert holes["costmap_obstacles"] is None
