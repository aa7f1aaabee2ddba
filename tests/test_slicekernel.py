"""The compiled slicing kernel (converters/_kernels/_slicekernel.c, driven by
converters/_kernels/slices.py).

It must give the row-ordered numba kernel's slices bit for bit (and so the numpy backend's and
the plain-loop oracle's), in both of its implementations: the AVX-512 one (eight pixels per
step, lanes reversed for rows whose bins descend) and the scalar one (any CPU, and the last
W % 8 columns of every row), here forced with ``_slicec.SIMD = 0``.
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
from converters.slices import spec as _grid
from converters._kernels import slices as _slicec
from converters.slices.converter import SliceConverter, SliceSpec
from grid_reference import pose
from test_laserscan import (MOUNTS, SPECIALS, TWO_PI, arrays, draw_image, make_sensor,
                            ref_slice, room_scan)

HAVE_C = _slicec.available()
HAVE_NUMBA = importlib.util.find_spec("numba") is not None
pytestmark = pytest.mark.skipif(not HAVE_C, reason="compiled slicing kernel not built")


@pytest.fixture(params=[1, 0], ids=["simd", "scalar"])
def simd(request: Any, monkeypatch: pytest.MonkeyPatch) -> int:
    monkeypatch.setattr(_slicec, "SIMD", request.param)
    return int(request.param)


def bits(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    """Ranges as int32 bit patterns (NaN payloads and -0 count) and intensities."""
    ranges, ints = arrays(msg)
    return ranges.view(np.int32), ints


def assert_bits(a: Any, b: Any) -> None:
    (ra, ia), (rb, ib) = bits(a), bits(b)
    np.testing.assert_array_equal(ra, rb)
    np.testing.assert_array_equal(ia, ib)


def kernel_converter(*args: Any, **kw: Any) -> SliceConverter:
    """A converter on the kernel, even where "auto" would prefer numba (no AVX-512)."""
    conv = SliceConverter(*args, **kw)
    conv._c_kernel = True
    return conv


def c_plan(conv: SliceConverter, scan: Any) -> Any:
    tables = conv._tables_for(scan)
    rows = None if tables.sorted is None else tables.sorted.rows
    return None if rows is None else rows.c_plan(tables, conv.slices)


def others(sensor: Any, specs: Any, **kw: Any) -> list[SliceConverter]:
    """The same converter on the numba kernel (when installed) and on numpy."""
    return [SliceConverter(sensor, specs, backend=b, **kw)
            for b in (["numba"] if HAVE_NUMBA else []) + ["numpy"]]


@pytest.mark.parametrize(("mount", "n_slices", "destagger"), [
    ("level", 1, False), ("level", 3, True), ("level", 5, False), ("level", 9, True),
    ("offset", 3, False), ("offset", 6, True), ("upside_down", 2, False),
    ("upside_down", 5, True)])
def test_kernel_equals_numba_numpy_and_oracle(mount: str, n_slices: int, destagger: bool,
                                              simd: int) -> None:
    """Room scenes: 1-9 slices (live-slice blocks of four, and a remainder), staggered and
    destaggered scans (tie keys then differ from pixel indices), an off-axis mount (points
    closer than their far-field threshold take the atan2 path) and an upside-down one (each
    row's bins run the other way)."""
    sensor = make_sensor(shifts=True)
    ext = MOUNTS[mount]
    scan = room_scan(sensor, ext, destagger=destagger)
    bands = {f"s{i}": (-0.2 + 0.3 * i, 0.35 + 0.3 * i) for i in range(n_slices)}
    specs = {k: SliceSpec(*v) for k, v in bands.items()}
    kw = {"extrinsics": ext, "frame_id": "b"}
    conv = kernel_converter(sensor, specs, **kw)
    assert c_plan(conv, scan) is not None
    out = conv.convert(scan)
    if mount == "offset":
        flat = lidarscan.range_m(scan, sensor).reshape(-1).astype(np.float64)
        assert conv._tables_for(scan).near_fraction(flat) > 0.1
    for other in others(sensor, specs, **kw):
        alt = other.convert(scan)
        for name in bands:
            assert_bits(out[name], alt[name])
    for name, (zmin, zmax) in bands.items():
        ref = ref_slice(scan, sensor, zmin=zmin, zmax=zmax, ext=ext)
        np.testing.assert_array_equal(arrays(out[name])[0], ref[0])
        np.testing.assert_array_equal(arrays(out[name])[1], ref[1])


@st.composite
def row_case(draw: Any) -> tuple[Any, Any, dict[str, Any], dict[str, Any]]:
    """A small sensor on the row-ordered path: any width (vector groups plus a scalar tail),
    columns sweeping either way, optional pixel shifts, beam offsets; ranges with every class;
    1-6 bands, range limits, an upright or upside-down mount."""
    height = draw(st.integers(1, 6))
    width = draw(st.integers(3, 40))
    sweep = draw(st.sampled_from([1.0, -1.0]))
    vert = sorted(draw(st.lists(st.floats(-0.6, 0.6), min_size=height, max_size=height)),
                  reverse=True)
    fields: dict[str, Any] = {"range_min": draw(st.sampled_from([0.0, 0.2]))}
    if draw(st.booleans()):
        inc = TWO_PI / width
        beta = np.array(draw(st.lists(st.floats(-0.45, 0.45), min_size=height,
                                      max_size=height))) * inc
        fields["beam_azimuth_offsets"] = beta
        fields["beam_origins"] = np.stack([0.015 * np.cos(beta), -0.015 * np.sin(beta),
                                           np.zeros(height)], 1).reshape(-1)
    if draw(st.booleans()):
        fields["pixel_shift_by_row"] = np.array(
            draw(st.lists(st.integers(-width, width), min_size=height, max_size=height)),
            np.int32)
    info = lidarscan.make_info(
        stamp_ns=3, frame_id="l", vertical_angles=vert,
        horizontal_angles=sweep * TWO_PI * (np.arange(width) / width) + draw(st.floats(-1, 1)),
        as_dataclass=True, **fields)
    r = draw_image(draw, height, width, st.one_of(st.floats(0.015625, 12, width=32),
                                                  st.sampled_from(SPECIALS)), np.float32)
    inten = draw_image(draw, height, width, st.integers(0, 60000), np.uint16)
    destagger = "pixel_shift_by_row" in fields and draw(st.booleans())
    channels = {"range": r, "intensity": inten}
    if destagger:
        proj = lidarscan.make_projector(info)
        channels = {k: proj.destagger(v) for k, v in channels.items()}
    scan = lidarscan.make_scan(info, channels, 0, is_destaggered=destagger, as_dataclass=True)
    n = draw(st.integers(1, 6))
    specs = {}
    for i in range(n):
        zmin = draw(st.floats(-1.5, 1.5))
        specs[f"s{i}"] = SliceSpec(zmin, zmin + draw(st.sampled_from([0.0, 0.2, 1.0, math.inf])))
    ext = pose(draw(st.floats(-0.5, 0.5)), draw(st.floats(-0.5, 0.5)), draw(st.floats(-1, 1)),
               draw(st.floats(-4, 4)), draw(st.sampled_from([0.0, math.pi])), 0.0)
    kw = {"extrinsics": ext, "frame_id": "b", "range_min": draw(st.sampled_from([0.0, 0.5])),
          "range_max": draw(st.sampled_from([math.inf, 5.0]))}
    return info, scan, specs, kw


@settings(max_examples=150, deadline=None)
@given(row_case())
def test_property_kernel_equals_numba_and_numpy(case: Any) -> None:
    info, scan, specs, kw = case
    conv = kernel_converter(info, specs, **kw)
    expect = [o.convert(scan) for o in others(info, specs, **kw)]
    for mode in (1, 0):
        _slicec.SIMD = mode
        try:
            out = conv.convert(scan)
        finally:
            _slicec.SIMD = 1
        for alt in expect:
            for name in specs:
                assert_bits(out[name], alt[name])


def test_the_row_path_is_taken_by_the_property_cases() -> None:
    """(The property test above must exercise the kernel, not only fall back.)"""
    info = make_sensor(height=3, width=21, shifts=True)
    scan = room_scan(info, MOUNTS["level"])
    conv = SliceConverter(info, {"a": SliceSpec(0.0, 1.0)}, extrinsics=MOUNTS["level"],
                          frame_id="b")
    assert c_plan(conv, scan) is not None


def test_per_pixel_qualifiers(simd: int) -> None:
    """+Inf/NaN/-Inf qualifiers per pixel (when they differ along a row) give the same slices
    as per row; forced here on tables where they do not differ."""
    sensor = make_sensor()
    ext = MOUNTS["level"]
    scan = room_scan(sensor, ext)
    specs = {"a": SliceSpec(0.05, 0.5), "b": SliceSpec(0.3, 1.5), "c": SliceSpec(-1.0, 0.2)}
    kw = {"extrinsics": ext, "frame_id": "b", "range_min": 0.5, "range_max": 3.0}
    conv = kernel_converter(sensor, specs, **kw)
    per_row = conv.convert(scan)
    tables = conv._tables_for(scan)
    rows = tables.sorted.rows
    assert rows.c_plan(tables, conv.slices).q_per_pixel is False
    rows.q_rows = False                      # rebuild the plan with per-pixel qualifiers
    rows._c_plan, rows._c_plan_tried = None, False
    assert rows.c_plan(tables, conv.slices).q_per_pixel is True
    per_pixel = conv.convert(scan)
    for name in specs:
        assert_bits(per_row[name], per_pixel[name])
    assert any(np.isnan(arrays(per_row[n])[0]).any() or np.isinf(arrays(per_row[n])[0]).any()
               for n in specs)


@pytest.mark.parametrize("dtype", ["f4", "f8", "u1", "u2", "u4", "i1", "i2", "i4", ">u2", ">f4"])
def test_intensity_types(dtype: str) -> None:
    """Every PointField type is read by the kernel (cast like numpy); a big-endian channel is
    cast to float32 first."""
    sensor = make_sensor()
    ext = MOUNTS["level"]
    scan = room_scan(sensor, ext, intensity_dtype=np.dtype(dtype))
    specs = {"a": SliceSpec(0.05, 0.5)}
    conv = kernel_converter(sensor, specs, extrinsics=ext, frame_id="b")
    assert c_plan(conv, scan) is not None
    out = conv.convert(scan)["a"]
    ref = SliceConverter(sensor, specs, extrinsics=ext, frame_id="b",
                         backend="numpy").convert(scan)["a"]
    assert_bits(out, ref)
    assert np.count_nonzero(arrays(out)[1]) > 10


def test_aligned_rows() -> None:
    """(Also the kernel's test of its tie-key columns.)"""
    w = 6
    fwd = (np.array([[2], [5]]) + np.arange(w)) % w
    start, step = _grid.aligned_rows(fwd, w, w)
    assert start.tolist() == [2, 5] and step.tolist() == [1, 1]
    back = (np.array([[0], [3]]) - np.arange(w)) % w
    start, step = _grid.aligned_rows(np.vstack([fwd[:1], back[1:]]), w, w)
    assert start.tolist() == [2, 3] and step.tolist() == [1, -1]
    swapped = fwd.copy()
    swapped[1, [2, 3]] = swapped[1, [3, 2]]
    assert _grid.aligned_rows(swapped, w, w) is None
    assert _grid.aligned_rows(fwd + w, w, w) is None           # out of range
    assert _grid.aligned_rows(fwd[:, :4], w, w) is None        # wrong width
    assert _grid.aligned_rows(np.zeros((2, 1), np.int64), 1, 1) is None


def test_backend_choice_and_kill_switch(monkeypatch: pytest.MonkeyPatch) -> None:
    """"auto" uses the kernel, "numba" and "numpy" do not; LIDARSCAN_NO_KERNEL, a stale build
    (ABI) or a different plan layout disable it."""
    sensor = make_sensor()
    specs = {"a": SliceSpec(0.05, 0.5)}
    assert SliceConverter(sensor, specs)._c_kernel == (_slicec.vectorised() or not HAVE_NUMBA)
    monkeypatch.setattr(_slicec, "vectorised", lambda: False)   # a CPU without AVX-512
    assert SliceConverter(sensor, specs)._c_kernel == (not HAVE_NUMBA)
    monkeypatch.undo()
    assert not SliceConverter(sensor, specs, backend="numpy")._c_kernel
    if HAVE_NUMBA:
        assert not SliceConverter(sensor, specs, backend="numba")._c_kernel
    assert _slicec._load() is not None
    monkeypatch.setenv("LIDARSCAN_NO_KERNEL", "1")
    assert _slicec._load() is None
    monkeypatch.setenv("LIDARSCAN_NO_KERNEL", "0")
    monkeypatch.setattr(_slicec, "ABI", _slicec.ABI + 1)
    assert _slicec._load() is None
    monkeypatch.setattr(_slicec, "ABI", _slicec.ABI - 1)

    class Longer(_slicec._Plan):
        _fields_ = [("extra", _slicec._i64)]
    monkeypatch.setattr(_slicec, "_Plan", Longer)
    assert _slicec._load() is None


def test_run_checks_its_inputs() -> None:
    sensor = make_sensor()
    scan = room_scan(sensor, MOUNTS["level"])
    conv = SliceConverter(sensor, {"a": SliceSpec(0.05, 0.5)}, extrinsics=MOUNTS["level"],
                          frame_id="b")
    plan = c_plan(conv, scan)
    r = lidarscan.range_m(scan, sensor).reshape(-1)
    with pytest.raises(ValueError, match="ranges"):
        plan.run(r[:-1], None)
    with pytest.raises(ValueError, match="intensities"):
        plan.run(r, np.zeros(3, np.float32))
    ranges, ints, keys = plan.run(r, None, winners=True)
    assert ints.size == 0 and keys is not None and keys.shape == ranges.shape
    hit = keys >= 0
    assert hit.any() and np.all(np.isfinite(ranges[hit]) | np.isinf(ranges[hit])
                                | np.isnan(ranges[hit]))


@pytest.mark.parametrize("value", [np.inf, -np.inf, np.nan, 0.0, -1.0])
@pytest.mark.parametrize("mount", ["level", "upside_down"])
def test_scans_of_one_class(value: float, mount: str, simd: int) -> None:
    """A scan of one non-point class only: every bin shows that class exactly where the
    class qualifies (no point hides a wrong code). A band ending exactly at the sensor's origin
    height: rays pointing away from it are inside it only at r = 0, so only -Inf (too close)
    qualifies there (an empty range interval that must still be visited)."""
    sensor = make_sensor(shifts=True)
    ext = MOUNTS[mount]
    r = np.full((sensor.height, sensor.width), value, np.float32)
    scan = lidarscan.make_scan(sensor, {"range": r, "intensity": np.ones_like(r)}, 1,
                               as_dataclass=True)
    probe = SliceConverter(sensor, {"x": SliceSpec(0.0, 1.0)}, extrinsics=ext, frame_id="b")
    oz = float(probe._tables_for(scan).oz[0])               # the same for every pixel here
    bands = {"around": (0.0, 1.0), "origin_up": (oz, oz + 2.0), "origin_down": (oz - 2.0, oz),
             "far": (-30.0, -20.0)}
    specs = {k: SliceSpec(*v) for k, v in bands.items()}
    conv = kernel_converter(sensor, specs, extrinsics=ext, frame_id="b")
    assert c_plan(conv, scan) is not None
    out = conv.convert(scan)
    for other in others(sensor, specs, extrinsics=ext, frame_id="b"):
        alt = other.convert(scan)
        for name in bands:
            assert_bits(out[name], alt[name])
    for name, (zmin, zmax) in bands.items():
        np.testing.assert_array_equal(arrays(out[name])[0],
                                      ref_slice(scan, sensor, zmin=zmin, zmax=zmax, ext=ext)[0])
    seen = {name: set(np.unique(arrays(out[name])[0].astype(np.float64)).tolist())
            for name in bands}
    if value == -np.inf:
        assert -np.inf in seen["origin_up"] and -np.inf in seen["origin_down"]
