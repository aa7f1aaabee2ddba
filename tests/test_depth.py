"""converters.sources.depth: depth images -> LidarScan, against a plain per-pixel loop reference.

Reference (written from the CameraInfo / OpenCV model definitions with ``math`` only): pixel
(u, v) of the published image is full-sensor pixel (u*bx + roi_x, v*by + roi_y); rectified:
pinhole of P, ray R^T (x, y, 1); raw: pinhole of K, then the distortion inverted by fixed-point
iteration (OpenCV's undistortPoints scheme, run to convergence) or, for the fisheye model, by
bisection on theta; point = depth * ray / ray_z. OpenCV (``cv2.projectPoints``, the forward model)
is a second, independent oracle where installed.
"""

from __future__ import annotations

import array
import dataclasses
import json
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import converters
from converters.sources.depth import DepthImageConverter, from_depth_image, pixel_rays
from lidarscan import channel, geometry, types
from lidarscan.stamps import to_ns
from lidarscan.errors import ConfigError, ConversionError, LidarScanError

from grid_reference import pose, ref_bin, ref_grid

CameraInfo = types.message_class("sensor_msgs/msg/CameraInfo")
Image = types.message_class("sensor_msgs/msg/Image")
Roi = types.message_class("sensor_msgs/msg/RegionOfInterest")

PLUMB_BOB = [-0.21, 0.05, 0.0012, -0.0008, -0.004]
RATIONAL = [0.35, -0.12, 0.0007, 0.0011, 0.02, 0.6, -0.08, 0.03]
EQUIDISTANT = [0.08, -0.02, 0.004, -0.001]
# a small rotation (rectification of a stereo camera)
R_RECT = pose(roll=0.01, pitch=-0.02, yaw=0.015)[:3, :3]


def camera_info(*, height: int = 48, width: int = 64, model: str = "plumb_bob",
                d: Any = (), k: Any = None, r: Any = None, p: Any = None, bx: int = 0,
                by: int = 0, roi: tuple[int, int, int, int] = (0, 0, 0, 0),
                stamp: int = 10, frame: str = "cam_optical") -> Any:
    """A CameraInfo dataclass; K default: fx 0.9 W, fy 0.95 W, principal point off-centre."""
    if k is None:
        k = [0.9 * width, 0.0, 0.52 * width, 0.0, 0.95 * width, 0.47 * height, 0.0, 0.0, 1.0]
    if p is None:
        p = [k[0], k[1], k[2], 0.0, 0.0, k[4], k[5], 0.0, 0.0, 0.0, 1.0, 0.0]
    return CameraInfo(
        header=types.Header(types.Time(stamp, 0), frame), height=height, width=width,
        distortion_model=model, d=np.asarray(d, float), k=np.asarray(k, float),
        r=np.asarray(np.eye(3) if r is None else r, float).reshape(-1), p=np.asarray(p, float),
        binning_x=bx, binning_y=by, roi=Roi(*roi, False))


def image_msg(depth: np.ndarray, encoding: str, *, bigendian: bool = False, pad: int = 0,
              stamp: int = 20, frame: str = "cam_optical") -> Any:
    """An Image dataclass with ``pad`` garbage bytes at the end of every row."""
    h, w = depth.shape
    dtype = depth.dtype.newbyteorder(">" if bigendian else "<")
    rows = depth.astype(dtype).view(np.uint8).reshape(h, -1)
    garbage = np.full((h, pad), 0xAB, np.uint8)
    data = np.ascontiguousarray(np.concatenate([rows, garbage], axis=1)).reshape(-1)
    return Image(header=types.Header(types.Time(stamp, 0), frame), height=h, width=w,
                 encoding=encoding, is_bigendian=int(bigendian),
                 step=w * depth.dtype.itemsize + pad, data=data.tobytes())


# ------------------------------------------------------------------------ the loop reference

def ref_distort(x: float, y: float, model: str, d: list[float]) -> tuple[float, float]:
    if model == "equidistant":
        k = list(d) + [0.0] * (4 - len(d))
        r = math.hypot(x, y)
        if r == 0:
            return x, y
        t = math.atan(r)
        td = t * (1 + k[0] * t**2 + k[1] * t**4 + k[2] * t**6 + k[3] * t**8)
        return x * td / r, y * td / r
    k1, k2, p1, p2, k3, k4, k5, k6 = list(d) + [0.0] * (8 - len(d))
    r2 = x * x + y * y
    g = (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
    return (x * g + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * g + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


def ref_undistort(xd: float, yd: float, model: str, d: list[float]) -> tuple[float, float, float]:
    """Unit ray (optical axes) of a distorted normalised point."""
    if model == "equidistant":
        k = list(d) + [0.0] * (4 - len(d))
        td = math.hypot(xd, yd)
        lo, hi = 0.0, math.pi / 2
        for _ in range(64):                        # bisection: theta_d(theta) is increasing
            mid = 0.5 * (lo + hi)
            if mid * (1 + k[0] * mid**2 + k[1] * mid**4 + k[2] * mid**6 + k[3] * mid**8) < td:
                lo = mid
            else:
                hi = mid
        t = 0.5 * (lo + hi)
        s = math.sin(t) / td if td > 0 else 0.0
        return xd * s, yd * s, math.cos(t)
    k1, k2, p1, p2, k3, k4, k5, k6 = list(d) + [0.0] * (8 - len(d))
    x, y = xd, yd
    for _ in range(2000):                          # OpenCV's fixed-point scheme, to convergence
        r2 = x * x + y * y
        g = (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        nx, ny = (xd - dx) / g, (yd - dy) / g
        done = abs(nx - x) <= 1e-15 and abs(ny - y) <= 1e-15
        x, y = nx, ny
        if done:
            break
    n = math.sqrt(x * x + y * y + 1)
    return x / n, y / n, 1 / n


def ref_ray(ci: Any, u: int, v: int, rectified: bool) -> tuple[float, float, float]:
    """Unit ray of pixel (u, v) in the camera's frame, and the model frame's z component."""
    bx, by = max(ci.binning_x, 1), max(ci.binning_y, 1)
    uf, vf = u * bx + ci.roi.x_offset, v * by + ci.roi.y_offset
    m = list(ci.p) if rectified else list(ci.k)
    s = 4 if rectified else 3
    fx, skew, cx, fy, cy = m[0], m[1], m[2], m[s + 1], m[s + 2]
    y = (vf - cy) / fy
    x = (uf - cx - skew * y) / fx
    if rectified:
        n = math.sqrt(x * x + y * y + 1)
        ray = (x / n, y / n, 1 / n)
        r = list(ci.r)
        return tuple(sum(r[3 * j + i] * ray[j] for j in range(3)) for i in range(3))  # R^T ray
    if not any(ci.d):
        n = math.sqrt(x * x + y * y + 1)
        return x / n, y / n, 1 / n
    return ref_undistort(x, y, ci.distortion_model, list(ci.d))


def ref_point(ci: Any, u: int, v: int, depth: float, rectified: bool,
              ray: tuple[float, ...] | None = None) -> tuple[float, ...]:
    """depth * ray / (the ray's z in the model's frame); ``ray``: ref_ray's, if known."""
    ray = ref_ray(ci, u, v, rectified) if ray is None else ray
    if rectified:   # depth is z in the rectified frame: the model-frame ray's z
        r = list(ci.r)
        z_model = sum(r[6 + j] * ray[j] for j in range(3))
    else:
        z_model = ray[2]
    return tuple(depth * c / z_model for c in ray)


def random_depth(rng: np.random.Generator, shape: tuple[int, int], encoding: str
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(image values, depth in metres)."""
    if encoding == "32FC1":
        z = rng.uniform(0.2, 12.0, shape).astype(np.float32)
        return z, z.astype(np.float64)
    z = rng.integers(200, 65535, shape).astype(np.uint16)
    return z, z * 0.001


CASES = {
    "rect": dict(rectified=True),
    "rect_R": dict(rectified=True, r=R_RECT, p_scale=0.97),
    "raw_plumb_bob": dict(rectified=False, model="plumb_bob", d=PLUMB_BOB),
    "raw_rational": dict(rectified=False, model="rational_polynomial", d=RATIONAL),
    "raw_equidistant": dict(rectified=False, model="equidistant", d=EQUIDISTANT),
    "raw_binning_roi": dict(rectified=False, model="plumb_bob", d=PLUMB_BOB, bx=2, by=2,
                            roi=(8, 6, 32, 48)),
    "rect_binning_roi": dict(rectified=True, bx=2, by=1, roi=(4, 2, 40, 56)),
}


def make_case(name: str) -> tuple[Any, bool]:
    case = dict(CASES[name])
    rectified = case.pop("rectified")
    p_scale = case.pop("p_scale", None)
    ci = camera_info(**case)
    if p_scale is not None:
        p = np.array(ci.p)
        p[[0, 5]] *= p_scale
        ci = camera_info(**case, p=p)
    return ci, rectified


@pytest.mark.parametrize("encoding", ["16UC1", "32FC1"])
@pytest.mark.parametrize("case", sorted(CASES))
def test_points_and_rays_match_the_loop_reference(case: str, encoding: str) -> None:
    ci, rectified = make_case(case)
    rng = np.random.default_rng(len(case))
    conv = DepthImageConverter(ci, rectified=rectified, as_dataclass=True)
    h, w = conv.scale.shape
    values, z = random_depth(rng, (h, w), encoding)
    scan, info = conv.convert(image_msg(values, encoding))
    assert (info.height, info.width) == (h, w) and info.header.frame_id == "cam_optical"
    assert scan.header.frame_id == "cam_optical"
    points = geometry.make_projector(info).project(scan, info)       # float32 tables
    d64, o64 = geometry.beam_tables(info)                            # the beam model in float64
    assert np.all(o64 == 0)
    worst_point = worst_ray = 0.0
    for v in range(h):
        for u in range(w):
            ray = ref_ray(ci, u, v, rectified)
            ref = ref_point(ci, u, v, float(z[v, u]), rectified, ray)
            worst_point = max(worst_point, max(abs(points[v, u, i] - ref[i]) for i in range(3)))
            worst_ray = max(worst_ray, max(abs(d64[v, u, i] - ray[i]) for i in range(3)))
    assert worst_point <= 1e-4          # 0.1 mm (float32 tables and ranges: ~1 um measured)
    assert worst_ray <= 1e-12


@pytest.mark.parametrize("case", sorted(CASES))
def test_range_is_depth_over_cosine_rounded_once(case: str) -> None:
    ci, rectified = make_case(case)
    conv = DepthImageConverter(ci, rectified=rectified, as_dataclass=True)
    values, z = random_depth(np.random.default_rng(3), conv.scale.shape, "16UC1")
    scan, _ = conv.convert(values, encoding="16UC1", stamp_ns=5)
    r = channel(scan, "range")
    h, w = r.shape
    for v in range(0, h, 5):
        for u in range(0, w, 3):
            ref = math.sqrt(sum(c * c for c in ref_point(ci, u, v, float(z[v, u]), rectified)))
            # float32 of the exact range: within half an ulp (+ the reference's float64 error)
            assert abs(float(r[v, u]) - ref) <= 0.5 * float(np.spacing(np.float32(ref))) + 1e-12
    # a 16UC1 depth is recovered exactly from the float32 range
    assert np.array_equal(np.rint(r / conv.scale * 1000).astype(np.uint16), values)


def test_opencv_forward_model_reproduces_the_pixels() -> None:
    cv2 = pytest.importorskip("cv2")
    for model, d in (("plumb_bob", PLUMB_BOB), ("rational_polynomial", RATIONAL),
                     ("equidistant", EQUIDISTANT)):
        ci = camera_info(model=model, d=d, bx=2, by=2, roi=(8, 6, 32, 48))
        rays, ok, _, _ = pixel_rays(ci, rectified=False)
        assert ok.all()
        h, w = ok.shape
        obj = (rays / rays[..., 2:3]).reshape(-1, 1, 3)
        kmat = np.array(ci.k).reshape(3, 3)
        if model == "equidistant":
            px, _ = cv2.fisheye.projectPoints(obj, np.zeros(3), np.zeros(3), kmat, np.array(d))
        else:
            px, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), kmat, np.array(d))
        uu, vv = np.meshgrid(np.arange(w) * 2 + 8.0, np.arange(h) * 2 + 6.0)
        expected = np.stack([uu, vv], -1).reshape(-1, 1, 2)
        assert np.max(np.abs(px - expected)) < 1e-6, model      # pixels (OpenCV: float64)


def test_opencv_undistort_points_agrees() -> None:
    cv2 = pytest.importorskip("cv2")
    ci = camera_info(model="rational_polynomial", d=RATIONAL)
    rays, _, _, _ = pixel_rays(ci, rectified=False)
    h, w = rays.shape[:2]
    uu, vv = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    src = np.stack([uu, vv], -1).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 1000, 1e-15)
    und = cv2.undistortPoints(src, np.array(ci.k).reshape(3, 3), np.array(RATIONAL),
                              criteria=criteria).reshape(h, w, 2)
    assert np.max(np.abs(und - rays[..., :2] / rays[..., 2:3])) < 1e-9


# --------------------------------------------------------------------- image encodings, REP 118

def test_big_endian_and_row_padding_give_the_same_scan() -> None:
    ci = camera_info()
    conv = DepthImageConverter(ci, as_dataclass=True)
    rng = np.random.default_rng(1)
    for encoding in ("16UC1", "32FC1"):
        values, _ = random_depth(rng, conv.scale.shape, encoding)
        plain = conv.convert(image_msg(values, encoding))[0]
        for big, pad in ((True, 0), (False, 6), (True, 3)):
            other = conv.convert(image_msg(values, encoding, bigendian=big, pad=pad))[0]
            assert other.data.tobytes() == plain.data.tobytes()
        swapped = values.astype(values.dtype.newbyteorder(">"))
        assert conv.convert(swapped, encoding=encoding, stamp_ns=20)[0].data.tobytes() == \
            plain.data.tobytes()


def test_rep118_values_have_no_point() -> None:
    ci = camera_info(height=2, width=4, k=[3, 0, 1.5, 0, 3, 0.5, 0, 0, 1])
    conv = DepthImageConverter(ci, as_dataclass=True)
    f = np.array([[np.nan, np.inf, -np.inf, 0.0], [-1.5, 2.0, np.float32(1e-30), -0.0]],
                 np.float32)
    scan, info = conv.convert(image_msg(f, "32FC1"))
    r = channel(scan, "range")
    assert np.isnan(r[0, 0]) and r[0, 1] == np.inf and r[0, 2] == -np.inf
    assert np.isnan(r[0, 3]) and np.isnan(r[1, 0]) and np.isnan(r[1, 3])
    assert np.isfinite(r[1, 1]) and r[1, 2] > 0
    pts = geometry.make_projector(info).project(scan, info)
    assert np.isnan(pts[0]).all() and np.isnan(pts[1, 0]).all() and np.isnan(pts[1, 3]).all()
    u16 = np.array([[0, 1, 65535, 0], [7, 0, 0, 2]], np.uint16)
    r16 = channel(conv.convert(image_msg(u16, "16UC1"))[0], "range")
    assert np.array_equal(np.isnan(r16), u16 == 0)
    inf_conv = DepthImageConverter(ci, invalid=math.inf, as_dataclass=True)
    r_inf = channel(inf_conv.convert(image_msg(f, "32FC1"))[0], "range")
    assert r_inf[0, 0] == np.inf and r_inf[1, 0] == np.inf and r_inf[0, 2] == -np.inf
    with pytest.raises(ConfigError):
        DepthImageConverter(ci, invalid=-1.0)


def test_caller_buffers_are_never_modified() -> None:
    ci = camera_info()
    conv = DepthImageConverter(ci, as_dataclass=True)
    values, _ = random_depth(np.random.default_rng(2), conv.scale.shape, "32FC1")
    values[0, :5] = [np.nan, 0, -1, np.inf, -np.inf]
    before = values.copy()
    buffer = bytearray(image_msg(values, "32FC1", pad=4).data)
    msg = image_msg(values, "32FC1", pad=4)
    msg = Image(header=msg.header, height=msg.height, width=msg.width, encoding=msg.encoding,
                is_bigendian=0, step=msg.step, data=buffer)
    snapshot = bytes(buffer)
    conv.convert(msg)
    conv.convert(values, encoding="32FC1", stamp_ns=1)
    assert bytes(buffer) == snapshot
    assert np.array_equal(values, before, equal_nan=True)


def test_keep_depth_channel_is_bit_exact() -> None:
    ci = camera_info()
    conv = DepthImageConverter(ci, keep_depth=True, as_dataclass=True)
    for encoding in ("16UC1", "32FC1"):
        values, _ = random_depth(np.random.default_rng(4), conv.scale.shape, encoding)
        scan = conv.convert(image_msg(values, encoding, bigendian=True))[0]
        assert np.array_equal(channel(scan, "depth"), values)


def test_bad_inputs_raise_project_errors() -> None:
    ci = camera_info()
    conv = DepthImageConverter(ci, as_dataclass=True)
    good = np.ones(conv.scale.shape, np.float32)
    msg = image_msg(good, "32FC1")
    cases = [
        lambda: conv.convert(good),                                    # no encoding
        lambda: conv.convert(good, encoding="32FC1"),                  # no stamp
        lambda: conv.convert(good, encoding="16UC1", stamp_ns=1),      # dtype mismatch
        lambda: conv.convert(np.ones((3, 3), np.float32), encoding="32FC1", stamp_ns=1),
        lambda: conv.convert(Image(**{**_fields(msg), "encoding": "rgb8"})),
        lambda: conv.convert(Image(**{**_fields(msg), "step": 4})),
        lambda: conv.convert(Image(**{**_fields(msg), "data": msg.data[:-5]})),
        lambda: conv.convert(image_msg(good, "32FC1", frame="other")),
        lambda: DepthImageConverter(camera_info(k=[0] * 9, p=[0] * 12), rectified=False),
        lambda: DepthImageConverter(camera_info(model="kannala", d=[0.1]), rectified=False),
        lambda: DepthImageConverter(camera_info(d=[0.1] * 6), rectified=False),
        lambda: DepthImageConverter(camera_info(d=PLUMB_BOB + [0, 0, 1e-3]), rectified=False),
        lambda: DepthImageConverter(camera_info(k=[1, 0, 0, 0, np.nan, 0, 0, 0, 1])),
    ]
    for i, case in enumerate(cases):
        with pytest.raises(LidarScanError):
            case()
            pytest.fail(f"case {i} did not raise")


def _fields(msg: Any) -> dict[str, Any]:
    return {name: getattr(msg, name) for name in msg.__dataclass_fields__}


# ---------------------------------------------------------------------- model choice, versions

def test_trailing_zero_coefficients_are_accepted() -> None:
    eight = DepthImageConverter(camera_info(d=PLUMB_BOB + [0.0, 0.0, 0.0]), rectified=False)
    five = DepthImageConverter(camera_info(d=PLUMB_BOB), rectified=False)
    assert np.array_equal(eight.rays, five.rays)


def test_default_model_comes_from_the_data() -> None:
    ci = camera_info(d=[0.0] * 5)                       # D zero, P == K: both the same
    assert DepthImageConverter(ci).rectified is False
    with pytest.raises(ConfigError):                    # distortion: only the topic can tell
        DepthImageConverter(camera_info(d=PLUMB_BOB))
    with pytest.raises(ConfigError):                    # D zero but P differs from K
        DepthImageConverter(camera_info(p=[50, 0, 30, 0, 0, 50, 20, 0, 0, 0, 1, 0]))
    rect = DepthImageConverter(camera_info(d=PLUMB_BOB), rectified=True)
    assert rect.rectified is True and json.loads(rect.info.vendor_metadata)["rectified"]


@pytest.mark.parametrize(("model", "d"), [("plumb_bob", PLUMB_BOB),
                                          ("rational_polynomial", RATIONAL),
                                          ("equidistant", EQUIDISTANT)])
def test_no_projection_matrix_means_the_raw_model(model: str, d: list[float]) -> None:
    """A CameraInfo with distortion and P all zero (a driver that fills K and D only) has one
    model, the raw one: the default uses it instead of asking for ``rectified``; and asking for
    the rectified one names P."""
    ci = camera_info(model=model, d=d, p=[0.0] * 12)
    conv = DepthImageConverter(ci)
    assert conv.rectified is False
    assert np.array_equal(conv.rays, DepthImageConverter(ci, rectified=False).rays)
    with pytest.raises(ConversionError, match="CameraInfo.p"):
        DepthImageConverter(ci, rectified=True)
    with pytest.raises(ConversionError, match="CameraInfo.k"):      # and K all zero: K named
        DepthImageConverter(camera_info(model=model, d=d, k=[0.0] * 9, p=[0.0] * 12))


def test_info_is_built_once_per_camera_info_content() -> None:
    ci = camera_info(d=PLUMB_BOB, stamp=100)
    conv = DepthImageConverter(ci, rectified=False, as_dataclass=True)
    first = conv.info
    values = np.ones(conv.scale.shape, np.float32)
    _, info = conv.convert(image_msg(values, "32FC1"), camera_info=camera_info(d=PLUMB_BOB,
                                                                               stamp=105))
    assert info is first and to_ns(info.header.stamp) == 100 * 10**9
    changed = camera_info(d=[-0.2, 0.05, 0.0012, -0.0008, -0.004], stamp=50)   # older stamp
    scan, info2 = conv.convert(image_msg(values, "32FC1"), camera_info=changed)
    assert info2 is not first
    assert to_ns(info2.header.stamp) == 100 * 10**9 + 1           # still a new key
    assert scan.lidar_info_time == info2.header.stamp
    # the function: cached per content, same info object every frame
    a = from_depth_image(image_msg(values, "32FC1"), ci, rectified=False, as_dataclass=True)
    b = from_depth_image(image_msg(values, "32FC1", stamp=21), camera_info(d=PLUMB_BOB, stamp=9),
                         rectified=False, as_dataclass=True)
    assert a[1] is b[1] and to_ns(b[0].header.stamp) == 21 * 10**9
    # a previous info keeps its version key (same content) or is outdated by the new one
    again = from_depth_image(values, ci, rectified=False, info=a[1], stamp_ns=1,
                             encoding="32FC1", as_dataclass=True)[1]
    assert again.header.stamp == a[1].header.stamp
    newer = from_depth_image(values, changed, rectified=False, info=a[1], stamp_ns=1,
                             encoding="32FC1", as_dataclass=True)[1]
    assert to_ns(newer.header.stamp) == to_ns(a[1].header.stamp) + 1


def test_plain_python_inputs_without_ros_types() -> None:
    """A mapping for the CameraInfo and a numpy array for the image (non-ROS users)."""
    ci = camera_info(d=RATIONAL, model="rational_polynomial", bx=2, by=2, roi=(8, 6, 32, 48))
    mapping = {"height": 48, "width": 64, "distortion_model": "rational_polynomial",
               "d": list(ci.d), "k": list(ci.k), "r": list(ci.r), "p": list(ci.p),
               "binning_x": 2, "binning_y": 2,
               "roi": {"x_offset": 8, "y_offset": 6, "height": 32, "width": 48},
               "header": {"frame_id": "cam_optical", "stamp": types.Time(10, 0)}}
    values, _ = random_depth(np.random.default_rng(6), (16, 24), "16UC1")
    scan, info = from_depth_image(values, mapping, encoding="16UC1", stamp_ns=20 * 10**9,
                                  rectified=False, as_dataclass=True)
    ref, ref_info = DepthImageConverter(ci, rectified=False, as_dataclass=True).convert(
        image_msg(values, "16UC1"))
    assert scan.data.tobytes() == ref.data.tobytes() and scan.header == ref.header
    assert np.array_equal(info.pixel_azimuth_angles, ref_info.pixel_azimuth_angles)
    with pytest.raises(LidarScanError):          # no K
        from_depth_image(values, {"height": 48, "width": 64}, encoding="16UC1", stamp_ns=0,
                         rectified=False)
    # all plain: the header's stamp a mapping too (e.g. a message converted to a dict)
    mapping["header"] = {"frame_id": "cam_optical", "stamp": {"sec": 10, "nanosec": 0}}
    again, again_info = from_depth_image(values, mapping, encoding="16UC1", stamp_ns=20 * 10**9,
                                         rectified=False, as_dataclass=True)
    assert again.data.tobytes() == scan.data.tobytes() and again_info.header == info.header
    mapping["header"]["stamp"] = {"seconds": 10}
    with pytest.raises(LidarScanError, match="CameraInfo.header.stamp"):
        from_depth_image(values, mapping, encoding="16UC1", stamp_ns=0, rectified=False)
    # a mapping stamp gets the Time message's nanosec range check (it used to skip it:
    # {sec: 10, nanosec: 2e9} silently became 12 s)
    for nanosec in (2 * 10**9, -1):
        mapping["header"]["stamp"] = {"sec": 10, "nanosec": nanosec}
        with pytest.raises(LidarScanError, match=r"CameraInfo.header.stamp.nanosec"):
            from_depth_image(values, mapping, encoding="16UC1", stamp_ns=0, rectified=False)
    image = dataclasses.replace(image_msg(values, "16UC1"),      # an image's stamp names it
                                header=types.Header(types.Time(20, 2 * 10**9), "cam_optical"))
    with pytest.raises(LidarScanError, match=r"Image.header.stamp.nanosec"):
        DepthImageConverter(ci, rectified=False).convert(image)


def test_lazy_registration() -> None:
    assert converters.from_depth_image is from_depth_image
    assert converters.sources.depth.DepthImageConverter is DepthImageConverter


def test_lidar_info_fields() -> None:
    ci = camera_info(d=PLUMB_BOB)
    info = DepthImageConverter(ci, rectified=False, as_dataclass=True).info
    assert (info.height, info.width) == (48, 64)
    alt = np.asarray(info.pixel_altitude_angles).reshape(48, 64)
    az = np.asarray(info.pixel_azimuth_angles).reshape(48, 64)
    assert np.all(np.diff(alt, axis=0) < 0)          # row 0 = top row = highest
    assert np.all(np.diff(az, axis=1) < 0)           # columns sweep right = clockwise
    assert np.array_equal(info.vertical_angles, alt[:, 32])
    assert np.array_equal(info.horizontal_angles, az[24])
    meta = json.loads(info.vendor_metadata)
    assert meta["camera_info"]["d"] == PLUMB_BOB and meta["rectified"] is False


@pytest.mark.ros
def test_rclpy_messages() -> None:
    pytest.importorskip("rclpy")
    from sensor_msgs.msg import CameraInfo as RosInfo
    from sensor_msgs.msg import Image as RosImage
    ci = camera_info(d=PLUMB_BOB)
    ros_ci = RosInfo(height=ci.height, width=ci.width, distortion_model=ci.distortion_model,
                     d=list(ci.d), k=list(ci.k), r=list(ci.r), p=list(ci.p))
    ros_ci.header.frame_id = "cam_optical"
    ros_ci.header.stamp.sec = 10
    values, z = random_depth(np.random.default_rng(9), (48, 64), "16UC1")
    img = RosImage(height=48, width=64, encoding="16UC1", is_bigendian=0, step=128)
    img.data = array.array("B", values.tobytes())
    img.header.frame_id = "cam_optical"
    scan, info = from_depth_image(img, ros_ci, rectified=False)
    ref, _ = from_depth_image(image_msg(values, "16UC1", stamp=0), ci, rectified=False,
                              as_dataclass=True)
    assert bytes(scan.data) == ref.data.tobytes()
    assert type(info).__module__.startswith("lidarscan_msgs")


# -------------------------------------------------------------------------- property: random

@settings(max_examples=40)
@given(fx=st.floats(20.0, 200.0), aspect=st.floats(0.8, 1.25), cx=st.floats(0.3, 0.7),
       cy=st.floats(0.3, 0.7), skew=st.floats(-0.5, 0.5), k1=st.floats(-0.2, 0.2),
       k2=st.floats(-0.05, 0.05), p1=st.floats(-0.005, 0.005), p2=st.floats(-0.005, 0.005),
       k3=st.floats(-0.01, 0.01), rational=st.booleans(), seed=st.integers(0, 2**16))
def test_random_intrinsics_round_trip(fx: float, aspect: float, cx: float, cy: float,
                                      skew: float, k1: float, k2: float, p1: float, p2: float,
                                      k3: float, rational: bool, seed: int) -> None:
    h, w = 12, 16
    fx = max(fx, 1.6 * w)                 # keep the field of view where the model is monotonic
    d = [k1, k2, p1, p2, k3] + ([0.1 * k1, 0.0, 0.0] if rational else [])
    model = "rational_polynomial" if rational else "plumb_bob"
    k = [fx, skew, cx * w, 0, fx * aspect, cy * h, 0, 0, 1]
    ci = camera_info(height=h, width=w, model=model, d=d, k=k)
    conv = DepthImageConverter(ci, rectified=False, as_dataclass=True)
    rays = conv.rays
    assert np.isfinite(conv.scale).all()
    values, z = random_depth(np.random.default_rng(seed), (h, w), "32FC1")
    scan, info = conv.convert(values, encoding="32FC1", stamp_ns=0)
    pts = geometry.exact_xyz(info, channel(scan, "range"))
    for v in range(h):
        for u in range(w):
            xd, yd = ref_distort(rays[v, u, 0] / rays[v, u, 2], rays[v, u, 1] / rays[v, u, 2],
                                 model, d)
            assert abs(fx * xd + skew * yd + cx * w - u) < 1e-8
            assert abs(fx * aspect * yd + cy * h - v) < 1e-8
            assert abs(pts[v, u, 2] - z[v, u]) <= 2e-6 * z[v, u]


def test_strong_distortion_marks_unreachable_pixels_invalid() -> None:
    # k1 strongly negative: the forward model folds over beyond r ~ 1 (wide corners)
    ci = camera_info(height=30, width=40, d=[-0.9, 0.0, 0.0, 0.0, 0.0],
                     k=[12.0, 0, 20, 0, 12.0, 15, 0, 0, 1])
    conv = DepthImageConverter(ci, rectified=False, as_dataclass=True)
    ok = np.isfinite(conv.scale)
    assert ok[15, 20] and not ok.all()
    r = channel(conv.convert(np.ones((30, 40), np.float32), encoding="32FC1",
                             stamp_ns=0)[0], "range")
    assert np.array_equal(np.isnan(r), ~ok)
    # where the inverse exists, it is right
    for v, u in zip(*np.nonzero(ok)):
        ray = conv.rays[v, u]
        xd, yd = ref_distort(ray[0] / ray[2], ray[1] / ray[2], "plumb_bob", [-0.9])
        assert abs(12 * xd + 20 - u) < 1e-8 and abs(12 * yd + 15 - v) < 1e-8


# ----------------------------------------------------------------------- slicer: floor and box

def _cast(origin: np.ndarray, ray: np.ndarray, box: tuple[tuple[float, float], ...]) -> float:
    """Parameter t >= 0 of the first hit of origin + t*ray with the floor z=0 or the box."""
    best = -origin[2] / ray[2] if ray[2] < 0 else math.inf
    lo_t, hi_t = 0.0, math.inf
    for axis in range(3):
        lo, hi = box[axis]
        if ray[axis] == 0:
            if not lo <= origin[axis] <= hi:
                return best
            continue
        a, b = (lo - origin[axis]) / ray[axis], (hi - origin[axis]) / ray[axis]
        lo_t, hi_t = max(lo_t, min(a, b)), min(hi_t, max(a, b))
    if lo_t <= hi_t:
        best = min(best, lo_t)
    return best


@pytest.mark.parametrize("encoding", ["32FC1", "16UC1"])
def test_tilted_camera_slice_sees_the_box_not_the_floor(encoding: str) -> None:
    h, w = 60, 80
    ci = camera_info(height=h, width=w, d=PLUMB_BOB,
                     k=[65.0, 0, 40.5, 0, 65.0, 29.5, 0, 0, 1])
    body_from_optical = np.eye(4)
    body_from_optical[:3, :3] = converters.sources.depth.OPTICAL_FROM_BODY.T
    base_from_optical = pose(x=0.1, z=0.6, pitch=math.radians(35)) @ body_from_optical
    box = ((1.0, 1.4), (-0.2, 0.3), (0.0, 0.4))
    rot, origin = base_from_optical[:3, :3], base_from_optical[:3, 3]
    rays = {(u, v): ref_ray(ci, u, v, False) for v in range(h) for u in range(w)}
    depth = np.zeros((h, w))
    for (u, v), ray in rays.items():
        t = _cast(origin, rot @ (np.array(ray) / ray[2]), box)    # ray scaled to z = 1: t = depth
        depth[v, u] = t
    assert np.isfinite(depth).all()
    values = (depth.astype(np.float32) if encoding == "32FC1"
              else np.rint(depth * 1000).astype(np.uint16))
    z = values.astype(np.float64) * (1.0 if encoding == "32FC1" else 0.001)
    scan, info = from_depth_image(image_msg(values, encoding), ci, rectified=False,
                                  as_dataclass=True)
    band = (0.05, 0.5)
    amin, amax, inc = -0.8, 0.8, 0.01
    # intensity_channel=None: a depth scan has no intensity channel (the slicer's default
    # "intensity" would raise UnknownChannelError)
    slicer = converters.SliceConverter(
        info, {"low": {"min_height": band[0], "max_height": band[1]}},
        extrinsics=base_from_optical, frame_id="base_link", angle_min=amin, angle_max=amax,
        angle_increment=inc, intensity_channel=None)
    out = slicer.convert(scan)["low"]
    got = np.asarray(out.ranges)
    assert out.header.frame_id == "base_link"
    # per-pixel loop: point -> base_link -> band -> bin -> minimum planar range
    grid = ref_grid(amin, amax, inc)
    expected = np.full(grid[2], np.inf)
    hits_floor = hits_box = 0
    for v in range(h):
        for u in range(w):
            p = ref_point(ci, u, v, float(z[v, u]), False, rays[u, v])
            q = rot @ np.array(p) + origin
            on_box = q[2] > 1e-6
            hits_box += on_box
            hits_floor += not on_box
            if band[0] <= q[2] <= band[1]:
                k = ref_bin(math.atan2(q[1], q[0]), grid)
                if k is not None:
                    expected[k] = min(expected[k], math.hypot(q[0], q[1]))
    assert hits_box > 100 and hits_floor > 1000
    finite = np.isfinite(expected)
    assert finite.sum() > 20
    assert np.array_equal(np.isfinite(got), finite)
    assert np.max(np.abs(got[finite] - expected[finite])) < 2e-3   # 16UC1: 1 mm steps
    # the box front face is at x = 1.0: the bins around straight ahead see it at about 1.0 m
    # (pixels are 1.3 deg apart here, bins 0.57 deg: some bins get no pixel)
    ahead = ref_bin(0.0, grid)
    near = got[ahead - 5:ahead + 6]
    assert np.isfinite(near).sum() >= 8 and np.all(np.abs(near[np.isfinite(near)] - 1.0) < 0.01)
    bearings = amin + inc * np.flatnonzero(finite)
    assert bearings.min() > math.atan2(-0.2, 1.0) - 0.02
    assert bearings.max() < math.atan2(0.3, 1.0) + 0.02


def test_an_roi_with_offsets_but_no_size_is_named() -> None:
    """An ROI with an offset but zero height or width describes no image: the error names the
    ROI (it used to be an image shape mismatch against (0, 0))."""
    values, _ = random_depth(np.random.default_rng(8), (48, 64), "16UC1")
    for roi in ((8, 6, 0, 0), (8, 6, 32, 0), (0, 0, 32, 0)):
        with pytest.raises(LidarScanError, match=r"CameraInfo.roi.*height and width > 0"):
            from_depth_image(image_msg(values, "16UC1"), camera_info(d=PLUMB_BOB, roi=roi),
                             rectified=False)
    # all zero: the full image
    scan, _ = from_depth_image(image_msg(values, "16UC1"), camera_info(d=PLUMB_BOB, roi=(0,) * 4),
                               rectified=False, as_dataclass=True)
    assert (scan.height, scan.width) == (48, 64)
