"""converters.sources.ouster.metadata on real Ouster metadata and frames (tests/data/ouster, see NOTICE.md).

The oracle is the vendor's "lidar range to XYZ" formula (prior-art.md section (b)), written here
directly from the metadata JSON (degrees, millimetres) without any project code::

    theta_e = 2*pi - v*2*pi/W, theta_a = -az_u (rad), phi = alt_u (rad)
    n = B03 if B23 == 0 else hypot(B03, B23)
    dir = (cos(theta_e + theta_a) cos phi, sin(theta_e + theta_a) cos phi, sin phi)
    off = (B03 cos theta_e - n dir_x, B03 sin theta_e - n dir_y, B23 - n dir_z)
    xyz = 0.001 * (r * R_T dir + R_T off + t_T)     for r != 0 (mm)
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import lidarscan
from converters.sources.ouster import metadata as ouster
from lidarscan import geometry
from lidarscan.errors import DecodeError, LidarScanError, ValidationError

DATA = Path(__file__).parent / "data" / "ouster"
OS2 = "OS-2-128-U1_v2.3.0_1024x10"
OS0 = "OS-0-32-U1_v2.2.0_1024x10"
OS1 = "2_0_0_os1-992008000494-128_col_win_legacy"
NESTED = "OS-2-128-U1_v2.3.0_1024x10_nested"
FRAMES = {OS2: "frame1259", OS0: "frame1453"}

# expected identification per metadata file: (model, serial, firmware, H, W, shift pattern head,
# beam origin mm, lidar_to_sensor z mm, fps)
EXPECTED = {
    OS2: ("OS-2-128", "992210000957", "v2.3.0", 128, 1024, [12, 8, 4, 0], 13.762, 78.296, 10),
    OS0: ("OS-0-32-U1", "992137000142", "v2.2.0-rc.2-17-gbc0879e", 32, 1024, [26, 26], 27.67,
          36.18, 10),
    OS1: ("OS-1-128", "992008000494", "v2.0.0", 128, 2048, [48, 32, 16, 0], 15.806, 36.18, 10),
    NESTED: ("OS-2-128", "992210000957", "v2.3.0", 128, 1024, [12, 8, 4, 0], 13.762, 78.296,
             10),
}


def _json(name: str) -> dict[str, Any]:
    return json.loads((DATA / f"{name}.json").read_text())


def _frame(name: str) -> dict[str, np.ndarray]:
    with np.load(DATA / f"{name}_{FRAMES[name]}.npz", allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _flat(meta: dict[str, Any]) -> dict[str, Any]:
    """The few values the oracle needs, from either layout (read by hand, not by the importer)."""
    if "beam_intrinsics" in meta:
        b = meta["beam_intrinsics"]
        return {"alt": b["beam_altitude_angles"], "az": b["beam_azimuth_angles"],
                "B": b["beam_to_lidar_transform"],
                "T": meta["lidar_intrinsics"]["lidar_to_sensor_transform"],
                "W": meta["lidar_data_format"]["columns_per_frame"]}
    origin = meta["lidar_origin_to_beam_origin_mm"]
    return {"alt": meta["beam_altitude_angles"], "az": meta["beam_azimuth_angles"],
            "B": [1, 0, 0, origin, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1],
            "T": meta["lidar_to_sensor_transform"],
            "W": meta["data_format"]["columns_per_frame"]}


def _vendor_xyz(meta: dict[str, Any], range_mm: np.ndarray, use_transform: bool = True
                ) -> np.ndarray:
    """Vectorised vendor formula in float64 (m); (0, 0, 0) where r == 0, as the SDK does."""
    m = _flat(meta)
    width = range_mm.shape[1]
    b = np.asarray(m["B"], float).reshape(4, 4)
    b03, b23 = b[0, 3], b[2, 3]
    n = b03 if b23 == 0 else math.hypot(b03, b23)
    theta_e = 2 * np.pi - np.arange(width) * 2 * np.pi / width
    theta_a = -np.deg2rad(np.asarray(m["az"], float))
    phi = np.deg2rad(np.asarray(m["alt"], float))
    theta = theta_e[None, :] + theta_a[:, None]
    cphi = np.cos(phi)[:, None]
    dx, dy = np.cos(theta) * cphi, np.sin(theta) * cphi
    dz = np.broadcast_to(np.sin(phi)[:, None], theta.shape)
    ox = b03 * np.cos(theta_e)[None, :] - n * dx
    oy = b03 * np.sin(theta_e)[None, :] - n * dy
    oz = b23 - n * dz
    t = np.asarray(m["T"], float).reshape(4, 4) if use_transform else np.eye(4)
    r = range_mm.astype(np.float64)
    d = np.stack([dx, dy, dz], -1)
    o = np.stack([ox, oy, oz], -1)
    xyz = 0.001 * (r[..., None] * (d @ t[:3, :3].T) + o @ t[:3, :3].T + t[:3, 3])
    xyz[range_mm == 0] = 0.0
    return xyz


def _loop_vendor_point(meta: dict[str, Any], u: int, v: int, r_mm: float) -> list[float]:
    """The same formula for one pixel with math only (guards the vectorised oracle)."""
    m = _flat(meta)
    w = m["W"]
    b03, b23 = float(m["B"][3]), float(m["B"][11])
    n = b03 if b23 == 0 else math.hypot(b03, b23)
    te = 2 * math.pi - v * 2 * math.pi / w
    ta = -m["az"][u] * math.pi / 180
    ph = m["alt"][u] * math.pi / 180
    d = [math.cos(te + ta) * math.cos(ph), math.sin(te + ta) * math.cos(ph), math.sin(ph)]
    off = [b03 * math.cos(te) - n * d[0], b03 * math.sin(te) - n * d[1], b23 - n * d[2]]
    t = m["T"]
    return [0.001 * sum(t[4 * i + j] * (r_mm * d[j] + off[j]) for j in range(3))
            + 0.001 * t[4 * i + 3] for i in range(3)]


# ------------------------------------------------------------------------------ metadata

@pytest.mark.parametrize("name", [OS2, OS0, OS1, NESTED])
def test_info_fields(name: str) -> None:
    model, serial, firmware, height, width, shifts, origin_mm, z_mm, fps = EXPECTED[name]
    meta = _json(name)
    m = _flat(meta)
    info = ouster.info_from_metadata(DATA / f"{name}.json", stamp_ns=5, as_dataclass=True)
    lidarscan.validate_info(info)
    assert (info.vendor, info.model, info.serial_number, info.firmware_version) == (
        "Ouster", model, serial, firmware)
    assert (info.height, info.width) == (height, width)
    assert info.header.frame_id == "os_sensor" and lidarscan.to_ns(info.header.stamp) == 5
    np.testing.assert_allclose(info.vertical_angles, np.deg2rad(m["alt"]), rtol=0, atol=1e-15)
    assert np.all(np.diff(info.vertical_angles) <= 0)  # row 0 = top
    np.testing.assert_allclose(info.horizontal_angles,
                               2 * np.pi * (1 - np.arange(width) / width), rtol=0, atol=1e-15)
    np.testing.assert_allclose(info.beam_azimuth_offsets, -np.deg2rad(m["az"]), atol=1e-15)
    assert list(info.pixel_shift_by_row[: len(shifts)]) == shifts
    np.testing.assert_allclose(info.beam_range_offsets, -origin_mm / 1000, rtol=1e-12)
    origins = np.asarray(info.beam_origins).reshape(height, 3)
    beta = -np.deg2rad(m["az"])
    np.testing.assert_allclose(origins[:, 0], origin_mm / 1000 * np.cos(beta), atol=1e-15)
    np.testing.assert_allclose(origins[:, 1], -origin_mm / 1000 * np.sin(beta), atol=1e-15)
    np.testing.assert_array_equal(origins[:, 2], 0.0)
    matrix = np.asarray(info.lidar_to_sensor_transform).reshape(4, 4)
    np.testing.assert_allclose(matrix[:3, :3], np.diag([-1.0, -1.0, 1.0]))
    np.testing.assert_allclose(matrix[:3, 3], [0, 0, z_mm / 1000], atol=1e-15)
    assert info.column_time_increment == round(1e9 / (fps * width))
    assert info.range_multiplier == 0.001 and info.range_offset == 0.0
    assert 0 < info.range_min < info.range_max
    np.testing.assert_array_equal(info.beam_ids, np.arange(height))
    assert len(info.beam_time_offsets) == 0
    assert info.vendor_metadata == (DATA / f"{name}.json").read_text()


def test_nested_layout_gives_the_same_geometry_as_the_flat_one() -> None:
    flat = ouster.info_from_metadata(DATA / f"{OS2}.json", as_dataclass=True)
    nested = ouster.info_from_metadata(DATA / f"{NESTED}.json", as_dataclass=True)
    assert geometry.info_key(flat) == geometry.info_key(nested)
    for field in ("vertical_angles", "beam_origins", "beam_range_offsets", "pixel_shift_by_row",
                  "lidar_to_sensor_transform", "beam_ids"):
        np.testing.assert_array_equal(getattr(flat, field), getattr(nested, field))
    assert (flat.range_min, flat.range_max) == (nested.range_min, nested.range_max)


def test_sources_path_text_dict_and_rclpy_message() -> None:
    path = DATA / f"{OS0}.json"
    text = path.read_text()
    by_path = ouster.info_from_metadata(str(path), as_dataclass=True)
    by_text = ouster.info_from_metadata(text, as_dataclass=True)
    by_dict = ouster.info_from_metadata(json.loads(text), as_dataclass=True)
    message = ouster.info_from_metadata(path)
    assert type(message).__module__.startswith("lidarscan_msgs")
    assert geometry.info_key(by_path) == geometry.info_key(by_text) == geometry.info_key(
        by_dict) == geometry.info_key(message)
    assert json.loads(by_dict.vendor_metadata) == json.loads(text)


def test_identity_transform_option() -> None:
    info = ouster.info_from_metadata(DATA / f"{OS2}.json", use_lidar_to_sensor=False,
                                     as_dataclass=True)
    assert info.header.frame_id == "os_lidar"
    np.testing.assert_array_equal(np.asarray(info.lidar_to_sensor_transform), np.eye(4).ravel())
    named = ouster.info_from_metadata(DATA / f"{OS2}.json", frame_id="lidar", as_dataclass=True)
    assert named.header.frame_id == "lidar"


def test_beam_to_lidar_transform_with_z_offset() -> None:
    """Nested layout with B23 != 0: n = hypot(B03, B23), origin z = B23 (newer sensors)."""
    meta = _json(NESTED)
    meta["beam_intrinsics"]["beam_to_lidar_transform"][3] = 15.0
    meta["beam_intrinsics"]["beam_to_lidar_transform"][11] = 4.0
    info = ouster.info_from_metadata(meta, as_dataclass=True)
    np.testing.assert_allclose(info.beam_range_offsets, -math.hypot(15.0, 4.0) / 1000)
    np.testing.assert_allclose(np.asarray(info.beam_origins).reshape(-1, 3)[:, 2], 0.004)
    frame = _frame(OS2)
    scan = ouster.scan_from_frame(frame, info, as_dataclass=True)
    points = lidarscan.make_projector(info).project(scan)
    expected = _vendor_xyz(meta, frame["range_mm"])
    valid = frame["range_mm"] > 0
    assert np.abs(points[valid] - expected[valid]).max() < 1e-4


def test_missing_legacy_beam_origin_uses_product_default() -> None:
    meta = _json(OS0)
    del meta["lidar_origin_to_beam_origin_mm"]
    info = ouster.info_from_metadata(meta, as_dataclass=True)
    np.testing.assert_allclose(info.beam_range_offsets, -0.02767)
    assert ouster.default_beam_origin_mm("OS-1-64") == 15.806
    assert ouster.default_beam_origin_mm("OS2-128") == 13.762
    assert ouster.default_beam_origin_mm("OS-DOME-128") == 12.163


@pytest.mark.parametrize("mutate, error, field", [
    (lambda m: m.pop("beam_altitude_angles"), DecodeError, "beam_altitude_angles"),
    (lambda m: m.pop("lidar_to_sensor_transform"), DecodeError, "lidar_to_sensor_transform"),
    (lambda m: m["beam_azimuth_angles"].pop(), ValidationError, "beam_azimuth_angles"),
    (lambda m: m["data_format"]["pixel_shift_by_row"].pop(), ValidationError,
     "pixel_shift_by_row"),
    (lambda m: m.update(lidar_mode="fast"), DecodeError, "lidar_mode"),
    (lambda m: m.update(lidar_mode="2048x10"), ValidationError, "columns_per_frame"),
    (lambda m: m["data_format"].update(pixels_per_column=64), ValidationError,
     "pixels_per_column"),
    (lambda m: m["beam_altitude_angles"].__setitem__(0, "x"), DecodeError,
     "beam_altitude_angles"),
])
def test_bad_metadata_names_the_key(mutate: Any, error: type, field: str) -> None:
    meta = _json(OS0)
    mutate(meta)
    with pytest.raises(error) as info:
        ouster.info_from_metadata(meta)
    assert field in info.value.field


def test_bad_json_sources() -> None:
    with pytest.raises(DecodeError):
        ouster.info_from_metadata("{not json")
    with pytest.raises(DecodeError):
        ouster.info_from_metadata("[1, 2]")
    with pytest.raises(DecodeError):
        ouster.info_from_metadata(DATA / "does_not_exist.json")
    nested = _json(NESTED)
    del nested["beam_intrinsics"]["beam_azimuth_angles"]
    with pytest.raises(DecodeError) as err:
        ouster.info_from_metadata(nested)
    assert err.value.field == "metadata.beam_intrinsics.beam_azimuth_angles"


# -------------------------------------------------------------------------- real frames

@pytest.mark.parametrize("name", [OS2, OS0])
@pytest.mark.parametrize("use_transform", [True, False])
@pytest.mark.parametrize("destagger", [False, True])
def test_projection_matches_vendor_formula(name: str, use_transform: bool,
                                           destagger: bool) -> None:
    meta = _json(name)
    frame = _frame(name)
    info = ouster.info_from_metadata(DATA / f"{name}.json", use_lidar_to_sensor=use_transform,
                                     as_dataclass=True)
    scan = ouster.scan_from_frame(frame, info, destagger=destagger, as_dataclass=True)
    projector = lidarscan.make_projector(info)
    points = projector.project(scan)
    if destagger:
        points = projector.restagger(points)
    expected = _vendor_xyz(meta, frame["range_mm"], use_transform)
    valid = frame["range_mm"] != 0
    assert valid.sum() > 0.5 * valid.size
    error = np.abs(points[valid].astype(np.float64) - expected[valid]).max()
    assert error < 1e-4, f"max error {error * 1000:.4f} mm"
    assert np.isnan(points[~valid]).all()          # zero range = no point
    # the float64 path (float64 metres, not the float32 channel) agrees to round-off
    metres = np.where(valid, frame["range_mm"] * 0.001, np.inf)
    exact = geometry.exact_xyz(info, projector.destagger(metres) if destagger else metres,
                               destaggered=destagger)
    if destagger:
        exact = projector.restagger(exact)
    assert np.abs(exact[valid] - expected[valid]).max() < 1e-9
    # spot check the vectorised oracle against a per-pixel loop
    rng = np.random.default_rng(0)
    for u, v in zip(rng.integers(0, info.height, 50), rng.integers(0, info.width, 50)):
        r = float(frame["range_mm"][u, v])
        if r:
            m = meta if use_transform else _with_identity(meta)
            np.testing.assert_allclose(_loop_vendor_point(m, int(u), int(v), r),
                                       expected[u, v], atol=1e-12)


def _with_identity(meta: dict[str, Any]) -> dict[str, Any]:
    meta = json.loads(json.dumps(meta))
    identity = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]
    if "lidar_intrinsics" in meta:
        meta["lidar_intrinsics"]["lidar_to_sensor_transform"] = identity
    else:
        meta["lidar_to_sensor_transform"] = identity
    return meta


def test_matches_ouster_sdk_xyzlut() -> None:
    """Cross-check with the vendor's own C++ lookup table when ouster-sdk is installed."""
    core = pytest.importorskip("ouster.sdk.core")
    for name in (OS2, OS0):
        text = (DATA / f"{name}.json").read_text()
        frame = _frame(name)
        info = ouster.info_from_metadata(text, as_dataclass=True)
        points = lidarscan.make_projector(info).project(
            ouster.scan_from_frame(frame, info, as_dataclass=True))
        sdk = core.XYZLut(core.SensorInfo(text))(frame["range_mm"].astype(np.uint32))
        valid = frame["range_mm"] != 0
        assert np.abs(points[valid] - sdk[valid]).max() < 1e-4


def test_scan_channels_and_times_single_return() -> None:
    frame = _frame(OS2)
    before = {k: v.copy() for k, v in frame.items()}
    info = ouster.info_from_metadata(DATA / f"{OS2}.json", stamp_ns=77)
    scan = ouster.scan_from_frame(frame, info)
    lidarscan.validate(scan, info)
    assert lidarscan.channel_names(scan) == ["range", "intensity", "reflectivity", "ambient",
                                             "flags"]
    rng = lidarscan.channel(scan, "range")
    assert rng.dtype == np.float32
    mm = frame["range_mm"]
    np.testing.assert_array_equal(rng[mm == 0], np.inf)
    np.testing.assert_array_equal(rng[mm != 0], (mm[mm != 0] * 0.001).astype(np.float32))
    for name, key, dtype in (("intensity", "signal", np.uint16),
                             ("reflectivity", "reflectivity", np.uint8),
                             ("ambient", "near_ir", np.uint16), ("flags", "flags", np.uint8)):
        arr = lidarscan.channel(scan, name)
        assert arr.dtype == dtype
        np.testing.assert_array_equal(arr, frame[key])
    ts = frame["timestamps_ns"].astype(np.int64)
    assert lidarscan.to_ns(scan.header.stamp) == ts[0]
    np.testing.assert_array_equal(np.asarray(scan.column_time_offsets), ts - ts[0])
    assert lidarscan.to_ns(scan.lidar_info_time) == 77
    assert not scan.is_destaggered
    for key, value in before.items():                     # caller's arrays untouched
        np.testing.assert_array_equal(frame[key], value)


def test_dual_return_frame() -> None:
    frame = _frame(OS0)
    info = ouster.info_from_metadata(DATA / f"{OS0}.json", as_dataclass=True)
    scan = ouster.scan_from_frame(frame, info, as_dataclass=True)
    names = lidarscan.channel_names(scan)
    assert names == ["range", "intensity", "reflectivity", "ambient", "flags", "range2",
                     "intensity2", "reflectivity2", "flags2"]
    range2 = lidarscan.range_m(scan, info, "range2")
    assert np.isfinite(range2).sum() == (frame["range2_mm"] != 0).sum() == 172
    np.testing.assert_array_equal(lidarscan.channel(scan, "flags2"), frame["flags2"])
    points2 = lidarscan.make_projector(info).project(scan, channel="range2")
    expected = _vendor_xyz(_json(OS0), frame["range2_mm"])
    valid = frame["range2_mm"] != 0
    assert np.abs(points2[valid] - expected[valid]).max() < 1e-4
    assert np.isnan(points2[~valid]).all()


@pytest.mark.parametrize("destagger", [False, True])
def test_uint32_mm_lossless_round_trip(destagger: bool) -> None:
    frame = _frame(OS0)
    info = ouster.info_from_metadata(DATA / f"{OS0}.json", stamp_ns=123)
    scan = ouster.scan_from_frame(frame, info, range_encoding="uint32_mm", destagger=destagger)
    decoded = lidarscan.decode_scan(lidarscan.encode(scan))
    decoded_info = lidarscan.decode_info(lidarscan.encode(info))
    lidarscan.validate(decoded, decoded_info)
    projector = lidarscan.make_projector(decoded_info)
    raw = lidarscan.channel(decoded, "range")
    raw2 = lidarscan.channel(decoded, "range2")
    assert raw.dtype == np.dtype("<u4")
    if destagger:
        raw, raw2 = projector.restagger(raw), projector.restagger(raw2)
    np.testing.assert_array_equal(raw, frame["range_mm"])
    np.testing.assert_array_equal(raw2, frame["range2_mm"])
    as_float = ouster.scan_from_frame(frame, info, destagger=destagger, as_dataclass=True)
    np.testing.assert_array_equal(lidarscan.range_m(decoded, decoded_info),
                                  lidarscan.range_m(as_float))
    np.testing.assert_array_equal(projector.project(decoded, decoded_info),
                                  projector.project(as_float))


def test_invalid_columns_have_no_return_and_interpolated_times() -> None:
    frame = _frame(OS2)
    frame["status"] = frame["status"].copy()
    frame["timestamps_ns"] = frame["timestamps_ns"].copy()
    bad = [0, 1, 500, 1023]
    frame["status"][bad] = 0
    frame["timestamps_ns"][bad] = 0
    info = ouster.info_from_metadata(DATA / f"{OS2}.json", as_dataclass=True)
    scan = ouster.scan_from_frame(frame, info, as_dataclass=True)
    rng = lidarscan.channel(scan, "range")
    assert np.isinf(rng[:, bad]).all()
    assert np.isfinite(rng[:, 2]).sum() == (frame["range_mm"][:, 2] != 0).sum()
    ts = _frame(OS2)["timestamps_ns"].astype(np.int64)
    inc = info.column_time_increment
    stamp = lidarscan.to_ns(scan.header.stamp)
    assert stamp == ts[2] - 2 * inc                         # extrapolated column 0
    times = stamp + np.asarray(scan.column_time_offsets)
    np.testing.assert_array_equal(times[2:500], ts[2:500])
    assert times[500] == round((ts[499] + ts[501]) / 2)
    assert times[1023] == ts[1022] + inc
    raw = ouster.scan_from_frame(frame, info, range_encoding="uint32_mm", as_dataclass=True)
    assert (lidarscan.channel(raw, "range")[:, bad] == 0).all()


def test_sdk_field_names_and_explicit_stamp() -> None:
    frame = _frame(OS2)
    sdk_names = {"RANGE": frame["range_mm"], "SIGNAL": frame["signal"],
                 "NEAR_IR": frame["near_ir"], "timestamp": frame["timestamps_ns"]}
    info = ouster.info_from_metadata(DATA / f"{OS2}.json", as_dataclass=True)
    scan = ouster.scan_from_frame(sdk_names, info, stamp_ns=42, as_dataclass=True)
    assert lidarscan.channel_names(scan) == ["range", "intensity", "ambient"]
    assert lidarscan.to_ns(scan.header.stamp) == 42
    ts = frame["timestamps_ns"].astype(np.int64)
    np.testing.assert_array_equal(scan.column_time_offsets, ts - ts[0])


def test_scan_from_frame_errors() -> None:
    frame = _frame(OS2)
    info = ouster.info_from_metadata(DATA / f"{OS2}.json", as_dataclass=True)
    with pytest.raises(ValidationError):
        ouster.scan_from_frame({"signal": frame["signal"]}, info, stamp_ns=0)
    with pytest.raises(ValidationError):
        ouster.scan_from_frame({"range_mm": frame["range_mm"][:, :10]}, info, stamp_ns=0)
    with pytest.raises(ValidationError):
        ouster.scan_from_frame(frame, info, range_encoding="mm")
    with pytest.raises(ValidationError):   # no timestamps and no stamp
        ouster.scan_from_frame({"range_mm": frame["range_mm"]}, info)
    other = lidarscan.make_info(stamp_ns=0, frame_id="x", vertical_angles=info.vertical_angles,
                                horizontal_angles=info.horizontal_angles, range_multiplier=0.002,
                                as_dataclass=True)
    with pytest.raises(LidarScanError):
        ouster.scan_from_frame(frame, other, range_encoding="uint32_mm")


def test_column_window_metadata() -> None:
    info = ouster.info_from_metadata(DATA / f"{OS1}.json", as_dataclass=True)
    assert info.width == 2048 and info.column_time_increment == 48828
    assert json.loads(info.vendor_metadata)["data_format"]["column_window"] == [2014, 2036]


def test_scans_from_osf_recording(tmp_path: Path) -> None:
    """Optional ouster-sdk path: write the real frame to an OSF file with the SDK, read it back."""
    pytest.importorskip("ouster.sdk")
    from ouster.sdk import core, osf
    text = (DATA / f"{OS0}.json").read_text()
    frame = _frame(OS0)
    sensor = core.SensorInfo(text)
    lidar_frame = core.LidarFrame(sensor)
    names = {"RANGE": "range_mm", "RANGE2": "range2_mm", "SIGNAL": "signal",
             "SIGNAL2": "signal2", "REFLECTIVITY": "reflectivity",
             "REFLECTIVITY2": "reflectivity2", "NEAR_IR": "near_ir", "FLAGS": "flags",
             "FLAGS2": "flags2"}
    for field in lidar_frame.fields:
        lidar_frame.field(field)[:] = frame[names[field]]
    lidar_frame.timestamp[:] = frame["timestamps_ns"]
    lidar_frame.status[:] = frame["status"]
    lidar_frame.measurement_id[:] = frame["measurement_id"]
    path = tmp_path / "one_frame.osf"
    writer = osf.Writer(str(path), sensor)
    writer.save(0, lidar_frame)
    writer.close()
    results = list(ouster.scans_from_recording(path, stamp_ns=3, as_dataclass=True))
    assert len(results) == 1
    scan, info = results[0]
    direct_info = ouster.info_from_metadata(text, stamp_ns=3, as_dataclass=True)
    assert geometry.info_key(info) == geometry.info_key(direct_info)
    direct = ouster.scan_from_frame(frame, direct_info, as_dataclass=True)
    assert lidarscan.channel_names(scan) == lidarscan.channel_names(direct)
    np.testing.assert_array_equal(np.asarray(scan.data), np.asarray(direct.data))
    np.testing.assert_array_equal(scan.column_time_offsets, direct.column_time_offsets)
    assert scan.header.stamp == direct.header.stamp
