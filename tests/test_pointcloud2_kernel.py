"""The compiled PointCloud2 kernel (converters._kernels.cloud, arguments from
converters.pointcloud2.kernel) against the numpy reference: bit-identical clouds for every preset,
field, source dtype and order, the canonical NaN, its C contract against a loop oracle, the
factored beam model against its float32 oracle, the switches (kernel=, LIDARSCAN_NO_KERNEL).
"""

from __future__ import annotations

import importlib.util
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
from lidarscan.errors import ConfigError

pytest.importorskip("sensor_msgs.msg")

from converters.pointcloud2 import converter as pc
from converters._kernels import cloud as kc
from cloud_oracles import (  # noqa: E402  (os2, tiny: fixtures)
    Spy,
    assert_equivalent,
    assert_identical,
    assert_points_close,
    destaggered,
    info_fields,
    kernel_and_numpy,
    needs_kernel,
    os2,  # noqa: F401 (fixture)
    tiny,  # noqa: F401 (fixture)
    with_channels,
    xyz_of,
)


# ------------------------------------------------------------------------- compiled kernel

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
        info2 = lidarscan.make_info(**{**info_fields(info), "range_multiplier": mult,
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
from converters.pointcloud2 import converter as pc
from converters._kernels import cloud as kc
from lidarscan.errors import ConfigError
sys.path.insert(0, sys.argv[1])
from cloud_oracles import destaggered
from test_pointcloud2_kernel import fallback_case
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
    spy = Spy(conv._kfn.project_rc)
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
        spies = Spy(conv._kfn.project), Spy(conv._kfn.project_rc)
        conv._kfn = kc.Kernels(*spies)
        cloud = conv.convert(scan)
        assert (spies[0].calls, spies[1].calls) == (1, 0)
        assert_identical(cloud, pc.PointCloud2Converter(pinfo, kernel=False,
                                                        organized=organized).convert(scan))


def test_vectorised_names_the_path_this_cpu_runs() -> None:
    """kc.vectorised() is true exactly where the CPU has AVX-512 (and the kernel is built): the
    path the test below compares with the portable one."""
    if kc.kernel() is None:
        pytest.skip("the PointCloud2 kernel is not built (or switched off)")
    flags = set()
    cpuinfo = Path("/proc/cpuinfo")
    if not cpuinfo.exists():
        pytest.skip("no /proc/cpuinfo to read the CPU's flags from")
    for line in cpuinfo.read_text().splitlines():
        if line.startswith("flags"):
            flags = set(line.split(":", 1)[1].split())
            break
    assert kc.vectorised() == ("avx512f" in flags)


@needs_kernel
def test_avx512_path_writes_the_portable_paths_bytes(os2: Any,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """The factored kernel's 16-pixel AVX-512 path (organized clouds whose channel field follows
    z, 16 or more pixels per run) and its portable code (``SIMD = 0``,
    ``LIDARSCAN_CLOUD_SIMD=0``) write the same bytes, on the real frame: float and integer
    ranges, both column orders, threads."""
    if not kc.vectorised():
        pytest.skip("no AVX-512 on this CPU: only the portable path runs here")
    _, frame, info, scan = os2
    mm = with_channels(scan, info, range=frame["range_mm"].astype(np.uint32))
    cases = [(scan, {}), (destaggered(scan, info), {}), (scan, {"destagger": False}),
             (scan, {"threads": 2}), (mm, {}), (scan, {"preset": "ouster_xyzi"}),
             (scan, {"fields": ("x", "y", "z", "reflectivity")})]
    for source, options in cases:
        clouds = []
        for simd in (1, 0):
            monkeypatch.setattr(kc, "SIMD", simd)
            clouds.append(pc.PointCloud2Converter(info, kernel=True, **options).convert(source))
        assert_identical(*clouds)
