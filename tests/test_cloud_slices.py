"""Slices of unstructured PointCloud2s (converters.slices.cloud): against a plain per-point loop
written from the documented rules, against the structured slicer on a scan's own cloud, on
every point layout (Livox 26-byte points, big-endian, float64 xyz), empty and all-NaN clouds,
configuration errors, the compiled kernel's binning, and Hypothesis cases.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from converters._kernels import cloud_slices as cloud_kernel
from converters.slices.cloud import CloudSliceConverter, cloud_points, cloud_to_laserscan
from converters.slices.converter import SliceSpec
from grid_reference import RANK, pose, ref_bin, ref_grid, ref_output
from helpers import messages_by_topic
from lidarscan.errors import ConfigError, ConversionError, LidarScanError
from test_nodes import graph  # noqa: F401 - the DDS graph fixture of the node tests

F32 = np.float32
HAVE_KERNEL = cloud_kernel.available()
#: the numpy reference, the C kernel's AVX2 build (where the CPU has it) and its scalar build
VARIANTS = ["numpy", "kernel", "kernel scalar"]


@contextlib.contextmanager
def variant(name: str) -> Iterator[str]:
    """The ``backend=`` of variant ``name``, with the kernel's build chosen (skips the test
    when the kernel is not built)."""
    if name == "numpy":
        yield "numpy"
        return
    if not HAVE_KERNEL:
        pytest.skip("the C cloud slices kernel is not built")
    old = cloud_kernel.SIMD
    cloud_kernel.SIMD = int(name == "kernel")
    try:
        yield "auto"
    finally:
        cloud_kernel.SIMD = old


@pytest.fixture(params=VARIANTS)
def backend(request: pytest.FixtureRequest) -> Iterator[str]:
    """Each variant in turn (:func:`variant`)."""
    with variant(request.param) as name:
        yield name


def variants() -> list[str]:
    return ["numpy"] + (["kernel", "kernel scalar"] if HAVE_KERNEL else [])


# ----------------------------------------------------------------------------- clouds

#: Livox (livox_ros_driver2 PointCloud2): x y z intensity float32, tag line uint8, timestamp f64
LIVOX = [("x", 7, 0), ("y", 7, 4), ("z", 7, 8), ("intensity", 7, 12), ("tag", 2, 16),
         ("line", 2, 17), ("timestamp", 8, 18)]
XYZI = [("x", 7, 0), ("y", 7, 4), ("z", 7, 8), ("intensity", 7, 12)]
_NUMPY = {1: "i1", 2: "u1", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


def make_cloud(xyz: Any, intensity: Any = None, *, layout: Any = None, step: int | None = None,
               bigendian: bool = False, height: int = 1, frame: str = "livox",
               stamp: tuple[int, int] = (12, 345)) -> Any:
    """An rclpy PointCloud2 of ``xyz`` (n, 3) in ``layout`` [(name, datatype, offset)]."""
    from sensor_msgs.msg import PointCloud2, PointField

    layout = XYZI if layout is None else layout
    xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
    n = xyz.shape[0]
    end = ">" if bigendian else "<"
    step = step or max(o + np.dtype(_NUMPY[t]).itemsize for _, t, o in layout)
    dtype = np.dtype({"names": [f for f, _, _ in layout],
                      "formats": [end + _NUMPY[t] for _, t, _ in layout],
                      "offsets": [o for _, _, o in layout], "itemsize": step})
    arr = np.zeros(n, dtype)
    for k, axis in enumerate("xyz"):
        arr[axis] = xyz[:, k]
    if "intensity" in dtype.names:
        arr["intensity"] = np.arange(n) if intensity is None else intensity
    cloud = PointCloud2()
    cloud.header.frame_id = frame
    cloud.header.stamp.sec, cloud.header.stamp.nanosec = stamp
    cloud.height, cloud.width = height, n // height
    cloud.fields = [PointField(name=f, offset=o, datatype=t, count=1) for f, t, o in layout]
    cloud.is_bigendian = bigendian
    cloud.point_step, cloud.row_step = step, step * (n // height)
    cloud.data = arr.tobytes()
    cloud.is_dense = False
    return cloud


def arrays(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    return np.array(msg.ranges, np.float32), np.array(msg.intensities, np.float32)


# --------------------------------------------------------------------------- the oracle

def ref_cloud_slice(xyz: Any, intensity: Any, *, zmin: float, zmax: float, ext: Any = None,
                    amin: float = -math.pi, amax: float | None = None,
                    inc: float = math.pi / 360, rmin: float = 0.0, rmax: float = math.inf,
                    use_inf: bool = True, eps: float = 1.0, fill: float | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """One slice, point by point, from the rules of converters/slices/cloud.py's docstring.

    ``xyz``: the coordinates as stored in the cloud (float32 or float64 values)."""
    m = np.eye(4) if ext is None else np.asarray(ext, float)
    grid = ref_grid(amin, amin + 2 * math.pi if amax is None else amax, inc)
    cands: dict[int, tuple[Any, ...]] = {}
    for i, point in enumerate(np.asarray(xyz, np.float64).reshape(-1, 3)):
        x, y, z = (float(v) for v in point)
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            continue
        px, py, pz = (m[k, 0] * x + m[k, 1] * y + m[k, 2] * z + m[k, 3] for k in range(3))
        if not zmin <= pz <= zmax:
            continue
        b = ref_bin(math.atan2(py, px), grid)
        if b is None:
            continue
        rho = math.sqrt(px * px + py * py)
        beyond = rho > float(np.finfo(np.float32).max)
        cls = "neg" if rho < rmin else "pos" if rho > rmax or beyond else "finite"
        cand = (RANK[cls], float(F32(rho)) if cls == "finite" else 0.0, i,
                0.0 if intensity is None else float(F32(intensity[i])))
        if b not in cands or cand[:3] < cands[b][:3]:
            cands[b] = cand
    return ref_output(cands, grid[2], rmax, use_inf=use_inf, eps=eps, fill=fill)


def assert_same(msg: Any, ref: tuple[np.ndarray, np.ndarray]) -> None:
    got = arrays(msg)
    np.testing.assert_array_equal(got[0], ref[0])
    np.testing.assert_array_equal(got[1], ref[1])


def random_points(rng: np.random.Generator, n: int) -> np.ndarray:
    """Points in a 10 m box with NaN / inf coordinates, duplicates (ties) and the origin."""
    xyz = rng.uniform(-5, 5, (n, 3))
    xyz[:, 2] = rng.uniform(-1, 2, n)
    xyz[rng.random(n) < 0.05, rng.integers(0, 3)] = np.nan
    xyz[rng.random(n) < 0.02, 0] = np.inf
    xyz[5:10] = xyz[0:5]                        # exact duplicates: the first one wins
    xyz[10] = (0.0, 0.0, 0.5)                   # on the z axis: atan2(0, 0) = 0
    return xyz.astype(np.float32)


ORACLE_CASES = {
    "level": ({}, None),
    "mounted": ({"rmin": 0.5, "rmax": 4.0}, pose(x=0.2, y=-0.1, z=0.4, yaw=0.7)),
    "tilted sector": ({"amin": 2.5, "amax": 3.8, "inc": 0.05},
                      pose(z=1.0, pitch=0.3, roll=-0.2)),
    "upside down, no inf": ({"use_inf": False, "eps": 0.5, "rmax": 3.0, "inc": 0.02},
                            pose(z=1.5, roll=math.pi, yaw=0.3)),
    "fill nan": ({"fill": math.nan, "inc": 0.01}, pose(z=0.3)),
}


@pytest.mark.parametrize("case", list(ORACLE_CASES))
def test_slices_match_the_loop_oracle(case: str, backend: str,
                                      rng: np.random.Generator) -> None:
    opts, ext = ORACLE_CASES[case]
    xyz = random_points(rng, 3000)
    inten = rng.integers(0, 200, len(xyz)).astype(np.float32)
    cloud = make_cloud(xyz, inten)
    bands = {"low": (-0.2, 0.3), "mid": (0.3, 1.0), "all": (-math.inf, math.inf)}
    kw = {"angle_min": opts.get("amin"), "angle_max": opts.get("amax"),
          "angle_increment": opts.get("inc"), "range_min": opts.get("rmin"),
          "range_max": opts.get("rmax"), "use_inf": opts.get("use_inf", True),
          "inf_epsilon": opts.get("eps", 1.0), "fill": opts.get("fill")}
    conv = CloudSliceConverter({k: SliceSpec(*v) for k, v in bands.items()}, extrinsics=ext,
                               frame_id=None if ext is None else "base_link", backend=backend,
                               **kw)
    out = conv.convert(cloud)
    assert list(out) == list(bands)
    for name, (zmin, zmax) in bands.items():
        ref = ref_cloud_slice(xyz, inten, zmin=zmin, zmax=zmax, ext=ext, **opts)
        assert_same(out[name], ref)
        # one slice at a time gives the same (several slices cost one pass, same result)
        assert_same(cloud_to_laserscan(cloud, min_height=zmin, max_height=zmax,
                                       extrinsics=ext,
                                       frame_id=None if ext is None else "base_link",
                                       backend=backend, **kw), ref)


def os2_cloud() -> Any:
    """The real OS-2-128 frame (tests/data/ouster) as one unstructured (height 1) cloud: x, y,
    z, intensity float32 in 16-byte points, NaN points where there is no return."""
    from converters.edge.evidence._common import load_frame, ouster_files, ouster_info
    from converters.sources.ouster.metadata import scan_from_frame
    from converters.pointcloud2.converter import to_pointcloud2

    meta, path = next((m, p) for m, p in ouster_files() if p is not None and "OS-2" in m.name)
    info = ouster_info(meta)
    cloud = to_pointcloud2(scan_from_frame(load_frame(path), info, as_dataclass=True), info)
    n = cloud.height * cloud.width
    cloud.height, cloud.width, cloud.row_step = 1, n, n * cloud.point_step
    return cloud


OS2_SLICES = {"floor": SliceSpec(0.05, 0.5), "table": SliceSpec(0.5, 0.8),
              "head": SliceSpec(0.8, 1.8), "sector": SliceSpec(-0.2, 0.3, angle_min=-1.0,
                                                                angle_max=1.0),
              "near": SliceSpec(0.0, 1.0, range_min=0.5, range_max=4.0)}


@pytest.mark.parametrize("mount", ["upright", "tilted"])
def test_backends_agree_on_the_real_os2_frame(mount: str) -> None:
    """The real OS-2-128 frame: both builds of the C kernel == the numpy reference, bit for bit
    (reduction arrays, ranges and intensities), upright (the height from z alone) and tilted."""
    if not HAVE_KERNEL:
        pytest.skip("the C cloud slices kernel is not built")
    cloud = os2_cloud()
    ext = pose(z=1.8, yaw=0.1) if mount == "upright" else pose(z=1.8, pitch=0.05, roll=-0.03)
    common = {"extrinsics": ext, "frame_id": "base_link", "angle_increment": 2 * math.pi / 1024}
    b = CloudSliceConverter(OS2_SLICES, backend="numpy", **common)
    ref_best, ref = b.fuse(cloud), b.convert(cloud)
    assert np.count_nonzero(ref_best != np.iinfo(np.int64).max) > 2000   # bins not empty
    for name in ("kernel", "kernel scalar"):
        with variant(name) as backend:
            a = CloudSliceConverter(OS2_SLICES, backend=backend, **common)
            assert a._plan is not None
            np.testing.assert_array_equal(a.fuse(cloud), ref_best)
            for key, msg in a.convert(cloud).items():
                assert_same(msg, arrays(ref[key]))


#: PointField layouts [(name, datatype, offset)], point_step: every x/y/z type, intensity
#: types, odd offsets and steps
LAYOUTS = {
    "xyzi f32": (XYZI, 16),
    "livox packed": (LIVOX, 26),
    "f64 xyz, u16 intensity, padded": ([("intensity", 4, 0), ("z", 8, 2), ("x", 8, 10),
                                        ("y", 8, 18)], 29),
    "f32 xyz, f64 intensity, odd step": ([("y", 7, 1), ("x", 7, 5), ("z", 7, 9),
                                          ("intensity", 8, 13)], 23),
    "mixed x f64, y z f32, i8 intensity": ([("x", 8, 0), ("y", 7, 8), ("z", 7, 12),
                                            ("intensity", 1, 16)], 17),
    "u32 intensity": ([("x", 7, 0), ("y", 7, 4), ("z", 7, 8), ("intensity", 6, 12)], 16),
    "i32 intensity, no padding": ([("x", 7, 0), ("y", 7, 4), ("z", 7, 8),
                                   ("intensity", 5, 12)], 16),
}


@pytest.mark.parametrize("bigendian", [False, True])
@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_kernel_equals_numpy_on_every_layout(layout: str, bigendian: bool,
                                             rng: np.random.Generator) -> None:
    """Random clouds with NaN / Inf coordinates, exact duplicates (ties), points at the
    origin, on the z axis and exactly on bin edges, organized with padded rows, in every field
    layout and byte order: both builds of the kernel give the numpy reference's reduction
    array, ranges and intensities bit for bit."""
    if not HAVE_KERNEL:
        pytest.skip("the C cloud slices kernel is not built")
    fields, step = LAYOUTS[layout]
    n = 4 * 1500
    xyz = random_points(rng, n).astype(np.float64)
    theta = (np.arange(200) + 0.5) * (2 * math.pi / 360) - math.pi     # on bin edges
    xyz[100:300, 0], xyz[100:300, 1] = 2.0 * np.cos(theta), 2.0 * np.sin(theta)
    xyz[300:310] = (0.0, 0.0, 0.4)                                    # the z axis
    xyz[310:320] = xyz[320:330]                                       # more ties
    xyz[330:340, 2] = -np.inf
    inten = rng.integers(0, 120, n)
    cloud = make_cloud(xyz, inten, layout=fields, step=step, bigendian=bigendian, height=4)
    cloud.row_step = step * (n // 4) + 7                               # padded rows
    data = np.zeros(cloud.row_step * 4, np.uint8)
    packed = np.frombuffer(bytes(cloud.data), np.uint8).reshape(4, -1)
    data.reshape(4, -1)[:, :packed.shape[1]] = packed
    cloud.data = data.tobytes()
    before = bytes(cloud.data)
    specs = {"low": SliceSpec(-0.2, 0.3), "mid": SliceSpec(0.3, 1.0),
             "all": SliceSpec(-math.inf, math.inf, range_min=0.5, range_max=3.0),
             "sector": SliceSpec(0.0, 2.0, angle_min=2.5, angle_max=3.8, angle_increment=0.05),
             "fine": SliceSpec(-1.0, 1.0, angle_increment=2 * math.pi / 360, fill=math.nan,
                               use_inf=False)}
    for ext in (None, pose(x=0.2, y=-0.1, z=0.4, yaw=0.7), pose(z=1.0, pitch=0.3, roll=-0.2)):
        kw = {"extrinsics": ext, "frame_id": None if ext is None else "base_link"}
        ref = CloudSliceConverter(specs, backend="numpy", **kw)
        ref_best, ref_out = ref.fuse(cloud), ref.convert(cloud)
        for name in ("kernel", "kernel scalar"):
            with variant(name) as backend:
                conv = CloudSliceConverter(specs, backend=backend, **kw)
                np.testing.assert_array_equal(conv.fuse(cloud), ref_best)
                for key, msg in conv.convert(cloud).items():
                    assert_same(msg, arrays(ref_out[key]))
    assert bytes(cloud.data) == before


# ---------------------------------------------------------- the structured slicer's cloud

def test_agrees_with_to_laserscan_on_a_structured_scans_own_cloud() -> None:
    """A LidarScan's slices and its own cloud's slices (the same grid, band, limits).

    Tolerance: the cloud stores each point as float32 x, y, z (rounded once, then transformed
    in float64), while the structured slicer evaluates r * D + O from float32 ray tables already
    in the target frame. The two points differ by a few float32 ulps (about 1e-6 m at 5 m), so
    planar ranges agree within 4e-6 relative, and a point within about 1e-6 rad of a bin edge
    or 1e-6 m of a band edge may land on the other side: at most 1 % of the bins may differ
    beyond that (here: none or a handful of 128 * 3). No-return pixels are +Inf in the scan's
    slices and missing (NaN points) in the cloud, whose empty bins get the default fill, +Inf:
    the published values agree there too."""
    from converters.slices.converter import SliceConverter
    from converters.pointcloud2.converter import to_pointcloud2
    from test_laserscan import BANDS, MOUNTS, make_sensor, room_scan

    info = make_sensor()
    ext = MOUNTS["level"]
    scan = room_scan(info, ext, specials=False)
    specs = {k: SliceSpec(*v) for k, v in BANDS.items()}
    grid = {"angle_increment": 2 * math.pi / int(info.width), "range_min": 0.1,
            "range_max": 120.0}
    structured = SliceConverter(info, specs, extrinsics=ext, frame_id="base_link",
                                intensity_channel=None, **grid).convert(scan)
    cloud = to_pointcloud2(scan, info, fields=("x", "y", "z"))
    mine = CloudSliceConverter(specs, extrinsics=ext, frame_id="base_link", **grid)
    for name, msg in mine.convert(cloud).items():
        a, b = arrays(msg)[0], arrays(structured[name])[0]
        assert msg.angle_min == structured[name].angle_min
        assert msg.angle_increment == structured[name].angle_increment
        close = np.isclose(a, b, rtol=4e-6, atol=0.0) | (a == b)
        assert np.mean(close) >= 0.99, (name, np.flatnonzero(~close), a[~close], b[~close])
        assert np.isfinite(a).sum() > 50


# ---------------------------------------------------------------------------- layouts

def test_livox_26_byte_points(backend: str, rng: np.random.Generator) -> None:
    xyz = random_points(rng, 500)
    inten = rng.integers(0, 255, len(xyz)).astype(np.float32)
    cloud = make_cloud(xyz, inten, layout=LIVOX)
    assert cloud.point_step == 26
    got = cloud_to_laserscan(cloud, min_height=0.0, max_height=1.0, backend=backend)
    assert_same(got, ref_cloud_slice(xyz, inten, zmin=0.0, zmax=1.0))
    assert got.header.frame_id == "livox"
    assert (got.header.stamp.sec, got.header.stamp.nanosec) == (12, 345)
    assert got.scan_time == 0.0 and got.time_increment == 0.0


def test_big_endian_cloud_gives_identical_slices(backend: str,
                                                 rng: np.random.Generator) -> None:
    xyz = random_points(rng, 800)
    inten = rng.integers(0, 99, len(xyz)).astype(np.float32)
    little = make_cloud(xyz, inten, layout=LIVOX)
    big = make_cloud(xyz, inten, layout=LIVOX, bigendian=True)
    assert bytes(big.data) != bytes(little.data)
    before = bytes(big.data)
    kw = {"min_height": -0.5, "max_height": 1.5, "extrinsics": pose(z=0.2, yaw=1.0),
          "frame_id": "b", "backend": backend}
    assert_same(cloud_to_laserscan(big, **kw), arrays(cloud_to_laserscan(little, **kw)))
    assert bytes(big.data) == before                       # the caller's buffer is untouched


def test_float64_xyz_padding_and_organized_rows(backend: str,
                                                rng: np.random.Generator) -> None:
    xyz = rng.uniform(-3, 3, (6 * 50, 3))
    layout = [("x", 8, 0), ("y", 8, 8), ("z", 8, 16), ("intensity", 4, 28)]
    cloud = make_cloud(xyz, np.arange(len(xyz)) % 7, layout=layout, step=40, height=6)
    x, y, z = cloud_points(cloud)
    assert x.dtype == np.float64 and np.array_equal(z, xyz[:, 2])      # not rounded to f32
    got = cloud_to_laserscan(cloud, min_height=-1.0, max_height=1.0, backend=backend)
    assert_same(got, ref_cloud_slice(xyz, np.arange(len(xyz)) % 7, zmin=-1.0, zmax=1.0))


@pytest.mark.parametrize("kind", ["empty", "all NaN", "none in the band"])
def test_clouds_without_points_in_the_band(kind: str, backend: str) -> None:
    xyz = {"empty": np.zeros((0, 3)), "all NaN": np.full((40, 3), np.nan),
           "none in the band": np.tile([1.0, 1.0, 5.0], (40, 1))}[kind]
    cloud = make_cloud(xyz)
    got = cloud_to_laserscan(cloud, min_height=0.0, max_height=1.0, backend=backend)
    ranges, ints = arrays(got)
    assert len(ranges) == 720 and np.all(ranges == np.inf) and np.all(ints == 0)
    nan_fill = cloud_to_laserscan(cloud, min_height=0.0, max_height=1.0, fill=math.nan,
                                  use_inf=False, backend=backend)
    assert np.all(np.isnan(arrays(nan_fill)[0]))


# ------------------------------------------------------------------------- conventions

def test_inclusive_limits_ties_and_classes(backend: str) -> None:
    # bin of angle 0 (x axis); rho 1.0 twice (tie: the first point, intensity 7, wins),
    # a point at z == max_height and rho == range_max, one too close, one beyond
    xyz = [(1.0, 0.0, 0.5), (1.0, 0.0, 0.2), (3.0, 0.0, 1.0), (0.0, 2.0, 0.0),
           (0.05, 0.0, 0.0), (0.0, -9.0, 0.0), (0.0, 3.0, 1.0000001)]
    cloud = make_cloud(xyz, [7.0, 8.0, 9.0, 1.0, 2.0, 3.0, 4.0])
    got = cloud_to_laserscan(cloud, min_height=0.0, max_height=1.0, angle_increment=math.pi / 2,
                             range_min=0.1, range_max=2.0, backend=backend)
    ranges, ints = arrays(got)
    # bins: -pi, -pi/2, 0, pi/2
    assert ranges[2] == 1.0 and ints[2] == 7.0              # min wins, tie to the first
    assert ranges[3] == 2.0 and ints[3] == 1.0              # rho == range_max is kept
    assert ranges[1] == np.inf and ints[1] == 3.0           # beyond range_max: +Inf
    assert ranges[0] == np.inf and ints[0] == 0.0           # empty: fill (+Inf)
    alone = cloud_to_laserscan(make_cloud([(0.05, 0.0, 0.0)]), min_height=0.0, max_height=1.0,
                               angle_increment=math.pi / 2, range_min=0.1, backend=backend)
    assert arrays(alone)[0][2] == -np.inf                   # too close
    assert got.range_min == np.float32(0.1) and got.range_max == 2.0


def test_intensity_field_options(rng: np.random.Generator) -> None:
    xyz = random_points(rng, 100)
    layout = XYZI + [("reflectivity", 4, 16)]
    cloud = make_cloud(xyz, layout=layout, step=20)
    none = cloud_to_laserscan(cloud, min_height=-1, max_height=2, intensity_field=None)
    assert len(none.intensities) == 0
    no_field = cloud_to_laserscan(make_cloud(xyz, layout=XYZI[:3]), min_height=-1, max_height=2)
    assert len(no_field.intensities) == 0                   # IfPresent("intensity")
    with pytest.raises(ConversionError) as err:
        cloud_to_laserscan(cloud, min_height=-1, max_height=2, intensity_field="colour")
    assert err.value.field == "intensity_field"
    refl = cloud_to_laserscan(cloud, min_height=-1, max_height=2,
                              intensity_field="reflectivity")
    assert len(refl.intensities) == 720


# ------------------------------------------------------------------------------ errors

@pytest.mark.parametrize("kwargs, field", [
    ({"min_height": 1.0, "max_height": 0.0}, "slices['slice'].max_height"),
    ({"min_height": math.nan, "max_height": 0.0}, "slices['slice'].min_height"),
    ({"min_height": 0.0, "max_height": 1.0, "angle_increment": 0.0}, "angle_increment"),
    ({"min_height": 0.0, "max_height": 1.0, "angle_min": 1.0, "angle_max": 0.0}, "angle_max"),
    ({"min_height": 0.0, "max_height": 1.0, "range_min": 2.0, "range_max": 1.0}, "range_max"),
    ({"min_height": 0.0, "max_height": 1.0, "range_min": -1.0}, "range_min"),
    ({"min_height": 0.0, "max_height": 1.0, "use_inf": "yes"}, "use_inf"),
    ({"min_height": 0.0, "max_height": 1.0, "extrinsics": np.eye(4)}, "frame_id"),
    ({"min_height": 0.0, "max_height": 1.0, "extrinsics": np.eye(4) * 2, "frame_id": "b"},
     "extrinsics"),
    ({"min_height": 0.0, "max_height": 1.0, "backend": "gpu"}, "backend"),
    ({"min_height": 0.0, "max_height": 1.0, "intensity_field": ""}, "intensity_field"),
])
def test_bad_configurations_name_the_parameter(kwargs: dict[str, Any], field: str) -> None:
    with pytest.raises(ConfigError) as err:
        cloud_to_laserscan(make_cloud([(1.0, 0.0, 0.0)]), **kwargs)
    assert err.value.field == field
    assert isinstance(err.value, LidarScanError)


def test_bad_slice_sets() -> None:
    for slices, field in [({}, "slices"), ({"a": {"min_height": 0.0}}, "slices['a']"),
                          ({"a": {"min_height": 0, "max_height": 1, "colour": 1}},
                           "slices['a']"), ([1, 2], "slices")]:
        with pytest.raises(ConfigError) as err:
            CloudSliceConverter(slices)  # type: ignore[arg-type]
        assert err.value.field == field


@pytest.mark.parametrize("layout, field", [
    ([("x", 7, 0), ("y", 7, 4)], "PointCloud2.fields"),
    ([("x", 7, 0), ("y", 7, 4), ("z", 5, 8)], "PointCloud2 field 'z'"),
])
def test_bad_clouds_are_conversion_errors(layout: Any, field: str) -> None:
    from sensor_msgs.msg import PointField
    cloud = make_cloud([(1.0, 0.0, 0.0)])
    cloud.fields = [PointField(name=f, offset=o, datatype=t, count=1) for f, t, o in layout]
    with pytest.raises(ConversionError) as err:
        cloud_to_laserscan(cloud, min_height=0.0, max_height=1.0)
    assert err.value.field == field
    short = make_cloud([(1.0, 0.0, 0.0)] * 4)
    short.data = bytes(short.data)[:20]
    with pytest.raises(ConversionError):
        cloud_to_laserscan(short, min_height=0.0, max_height=1.0)


# ----------------------------------------------------------------- the compiled binning

def test_atan2_polynomial_is_within_its_bound() -> None:
    from converters._kernels import cloud_slices as k
    t = np.linspace(-math.pi, math.pi, 400_001)
    for radius in (1e-3, 1.0, 1e4):
        x, y = radius * np.cos(t), radius * np.sin(t)
        approx = np.array([k.atan2_approx.py_func(b, a) if hasattr(k.atan2_approx, "py_func")
                           else k.atan2_approx(b, a) for a, b in zip(x[::97], y[::97])])
        assert np.max(np.abs(approx - np.arctan2(y[::97], x[::97]))) < k.EPS / 2
    # the polynomial itself, densely
    u = np.linspace(0.0, 1.0, 2_000_001)
    p = np.zeros_like(u)
    for c in k.ATAN_COEFFS[::-1]:
        p = p * u * u + c
    assert np.max(np.abs(u * p - np.arctan(u))) < k.EPS / 2


@pytest.mark.parametrize("grid", [(-math.pi, math.pi, 2 * math.pi / 1024),
                                  (0.3, 0.3 + 2 * math.pi, 0.01),
                                  (2.5, 3.8, 0.05), (-1.0, 1.0, math.pi / 360)])
def test_kernel_bins_equal_atan2_bins_at_the_edges(grid: tuple[float, float, float]) -> None:
    """Points exactly on, and 1e-12 .. 1e-6 rad around, every bin edge and the wrap point
    get the bin of the exact atan2 (the approximation defers to it near edges)."""
    from converters.slices.spec import AngleGrid
    amin, amax, inc = grid
    g = AngleGrid.create(amin, amax, inc)
    edges = g.angle_min + (np.arange(-1, g.size + 1) + 0.5) * g.increment
    edges = np.r_[edges, g.angle_min - 0.5 * g.increment + 2 * math.pi, math.pi, -math.pi]
    delta = np.array([0.0, 1e-12, -1e-12, 1e-9, -1e-9, 1e-7, -1e-7, 1e-6, -1e-6])
    theta = (edges[:, None] + delta[None, :]).reshape(-1)
    x, y = np.cos(theta) * 3.0, np.sin(theta) * 3.0
    xyz = np.stack([x, y, np.zeros_like(x)], 1)
    cloud = make_cloud(xyz, layout=[("x", 8, 0), ("y", 8, 8), ("z", 8, 16)])
    kw = {"angle_min": amin, "angle_max": amax, "angle_increment": inc, "intensity_field": None}
    exact = ref_cloud_slice(xyz, None, zmin=-1, zmax=1, amin=amin, amax=amax, inc=inc)[0]
    for name in variants():
        with variant(name) as backend:
            got = cloud_to_laserscan(cloud, min_height=-1, max_height=1, backend=backend, **kw)
        np.testing.assert_array_equal(arrays(got)[0], exact)


# ---------------------------------------------------------------------------- property

@st.composite
def cloud_case(draw: Any) -> tuple[np.ndarray, np.ndarray, dict[str, Any], bool, bool]:
    n = draw(st.integers(0, 60))
    coord = st.one_of(st.floats(-6, 6, width=32), st.sampled_from([0.0, math.nan, math.inf]))
    xyz = np.array(draw(st.lists(st.tuples(coord, coord, coord), min_size=n, max_size=n)),
                   np.float32).reshape(-1, 3)
    inten = np.array(draw(st.lists(st.integers(0, 5), min_size=n, max_size=n)), np.float32)
    zmin = draw(st.floats(-2, 2))
    amin = draw(st.floats(-4, 1))
    opts = {"zmin": zmin, "zmax": zmin + draw(st.sampled_from([0.0, 0.5, 2.0, math.inf])),
            "ext": pose(draw(st.floats(-0.5, 0.5)), draw(st.floats(-0.5, 0.5)),
                        draw(st.floats(-1, 1)), draw(st.floats(-4, 4)),
                        draw(st.sampled_from([0.0, 0.3, math.pi])),
                        draw(st.sampled_from([0.0, -0.4]))),
            "amin": amin, "amax": amin + draw(st.sampled_from([2 * math.pi, 0.5, 3.0])),
            "inc": draw(st.floats(0.01, 0.7)), "rmin": draw(st.sampled_from([0.0, 0.5])),
            "rmax": draw(st.sampled_from([math.inf, 4.0]))}
    return xyz, inten, opts, draw(st.booleans()), draw(st.booleans())


@given(cloud_case())
def test_property_matches_the_oracle(case: Any) -> None:
    xyz, inten, o, bigendian, livox = case
    cloud = make_cloud(xyz, inten, layout=LIVOX if livox else XYZI, bigendian=bigendian)
    ref = ref_cloud_slice(xyz, inten, zmin=o["zmin"], zmax=o["zmax"], ext=o["ext"],
                          amin=o["amin"], amax=o["amax"], inc=o["inc"], rmin=o["rmin"],
                          rmax=o["rmax"])
    for name in variants():
        with variant(name) as backend:
            got = cloud_to_laserscan(cloud, min_height=o["zmin"], max_height=o["zmax"],
                                     extrinsics=o["ext"], frame_id="b", angle_min=o["amin"],
                                     angle_max=o["amax"], angle_increment=o["inc"],
                                     range_min=o["rmin"], range_max=o["rmax"], backend=backend)
        assert_same(got, ref)


def test_import_is_cheap() -> None:
    import subprocess
    import sys
    code = ("import sys, converters; converters.CloudSliceConverter; "
            "print('rclpy' in sys.modules, 'numba' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == ["False", "False"]


# ------------------------------------------------------------------- node core and CLI

def test_cloud_slicer_of_the_node_parameters() -> None:
    """The node's parameters -> CloudSlicer (per cloud frame and extrinsics), the same slices
    as the library; a gridless cloud is no error for it."""
    from converters.edge.nodes import cloud_to_scan_node as c2s

    node, per_slice = c2s._specs()
    values = {s.name: s.default for s in node}
    assert c2s.slicer(values) is None                          # no slices configured
    values["slice_names"] = ["low"]
    values.update({t.for_name("low").name: t.default for t in per_slice})
    with pytest.raises(ConfigError, match="slices.low.min_height"):
        c2s.slicer(values)
    values["slices.low.min_height"], values["slices.low.max_height"] = 0.0, 1.0
    values["slices.low.range_min"], values["slices.low.range_max"] = 3.0, 1.0
    with pytest.raises(ConfigError, match="range_max"):         # the library's rule
        c2s.slicer(values)
    values["slices.low.range_min"], values["slices.low.range_max"] = None, None
    values["target_frame"] = "base_link"
    sl = c2s.slicer(values)
    assert sl is not None and sl.slices[0].topic == "slices/low"
    rng = np.random.default_rng(3)
    xyz = random_points(rng, 400)
    cloud = make_cloud(xyz, layout=LIVOX)
    ext = pose(z=0.3, yaw=0.5)
    out = sl.convert(cloud, ext)
    assert out["low"].header.frame_id == "base_link"
    assert_same(out["low"], ref_cloud_slice(xyz, np.arange(len(xyz)), zmin=0.0, zmax=1.0,
                                            ext=ext))


def _livox_mcap(path: Any, demo: Any) -> list[Any]:
    """An MCAP with the demo's organized cloud (/lidar/points), its /tf_static, and a gridless
    Livox cloud (/livox/points, frame os_sensor) per demo cloud. Returns the Livox clouds."""
    from lidarscan.mcap import McapWriter, read_messages

    rng = np.random.default_rng(5)
    clouds = []
    with McapWriter(path) as writer:
        for item in read_messages(demo):
            if item.topic not in ("/lidar/points", "/tf_static"):
                continue
            writer.write(item.topic, item.payload, msgtype=item.msgtype,
                         log_time_ns=item.log_time_ns)
            if item.topic == "/lidar/points":
                cloud = make_cloud(random_points(rng, 2000), layout=LIVOX, frame="os_sensor",
                                   stamp=(item.log_time_ns // 10**9, item.log_time_ns % 10**9))
                writer.write("/livox/points", cloud, log_time_ns=item.log_time_ns)
                clouds.append(cloud)
    return clouds


@pytest.fixture(scope="module")
def demo_mcap(tmp_path_factory: pytest.TempPathFactory) -> Any:
    from converters.edge.demo.run import run_demo

    return run_demo(tmp_path_factory.mktemp("demo"), frames=2, images=False).mcap_path


def test_convert_slices_clouds_without_a_grid(tmp_path: Any, demo_mcap: Any,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    from converters.edge import cli
    from converters.edge.nodes.tf import TransformBuffer
    from lidarscan.mcap import read_messages

    src, dst = tmp_path / "in.mcap", tmp_path / "out.mcap"
    livox = _livox_mcap(src, demo_mcap)
    status = cli.main(["convert", str(src), str(dst), "--slice", "low:0.05:0.5",
                       "--slice", "high:0.5:2.0", "--frame", "base_link"])
    err = capsys.readouterr().err
    assert status == 0, err
    assert err.count("/livox/points: a cloud gave no LidarScan") == 1
    assert "slices are written" in err and "/lidar/points: a cloud" not in err
    out = messages_by_topic(dst)
    tf = TransformBuffer()
    # the organized cloud: LidarScan + info as before, and now its slices too
    assert len(out["/lidar/lidar_scan"]) == 2 and len(out["/lidar/slices/low"]) == 2
    # the gridless cloud: its slices instead of a failure
    assert "/livox/lidar_scan" not in out
    assert len(out["/livox/slices/low"]) == len(out["/livox/slices/high"]) == 2
    tf.add_message(out["/tf_static"][0].decode(), static=True)
    ext = tf.lookup("base_link", "os_sensor")
    expected = CloudSliceConverter({"low": SliceSpec(0.05, 0.5)}, extrinsics=ext,
                                   frame_id="base_link").convert(livox[0])["low"]
    got = out["/livox/slices/low"][0].decode()
    assert got.header.frame_id == "base_link"
    assert_same(got, arrays(expected))
    # without --slice such a cloud is still a bad message (nothing to make of it)
    assert cli.main(["convert", str(src), str(tmp_path / "o2.mcap"), "-q"]) == 1
    # a frame the file's TF does not reach: no slices (bad messages), LidarScans still written
    capsys.readouterr()
    assert cli.main(["convert", str(src), str(tmp_path / "o3.mcap"), "--slice", "low:0:1",
                     "--frame", "nowhere", "-q"]) == 1
    assert "no slices: --frame" in capsys.readouterr().err
    topics = [m.topic for m in read_messages(tmp_path / "o3.mcap")]
    assert topics.count("/lidar/lidar_scan") == 2 and "/lidar/slices/low" not in topics


@pytest.mark.ros
def test_cloud_to_scan_node_publishes_slices_of_a_gridless_cloud(graph: Any) -> None:
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import LaserScan, PointCloud2

    from converters.edge.nodes.cloud_to_scan_node import CloudToScanNode

    node = graph.add(CloudToScanNode(context=graph.context, parameter_overrides=[
        Parameter("slice_names", value=["low"]),
        Parameter("slices.low.min_height", value=0.0),
        Parameter("slices.low.max_height", value=1.0),
        Parameter("target_frame", value="base_link"),
        Parameter("extrinsics", value=[0.0, 0.0, 0.3, 0.0, 0.0, 0.0])]))
    pub = graph.publisher(PointCloud2, "points", "sensor_data")
    got = graph.collect(LaserScan, "slices/low")
    xyz = random_points(np.random.default_rng(9), 1500)
    cloud = make_cloud(xyz, layout=LIVOX)
    assert graph.wait(lambda: bool(got), tick=lambda: pub.publish(cloud))
    assert node.stats["bad"] == 0 and node.stats["no_grid"] >= 1
    assert got[0].header.frame_id == "base_link"
    assert_same(got[0], ref_cloud_slice(xyz, np.arange(len(xyz)), zmin=0.0, zmax=1.0,
                                        ext=pose(z=0.3)))


def test_holes_are_refused_on_clouds_with_the_reason() -> None:
    """Holes need rays (a LidarScan); a cloud slice asking for them is a named config error."""
    with pytest.raises(ConfigError, match=r"slices\['drop'\]\.holes.*LidarScan"):
        CloudSliceConverter({"drop": {"min_height": -0.1, "max_height": 0.1, "holes": True}})
