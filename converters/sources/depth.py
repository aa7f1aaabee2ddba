"""Depth images (REP 118) -> LidarScan + LidarInfo carrying the camera's exact per-pixel rays.

Input: ``sensor_msgs/Image`` with encoding ``16UC1`` (or ``mono16``: millimetres, 0 = no
measurement) or ``32FC1`` (metres; NaN, +Inf, -Inf with their REP 117 meanings), either byte order
(``is_bigendian``), any row padding (``step``); or a 2-D numpy array plus an explicit encoding.
The caller's buffer is only read. Geometry: ``sensor_msgs/CameraInfo`` (rclpy message, decoded
dataclass or a mapping with the same field names).

**Pixels and models.** Pixel (u, v) of the published image (u = column, v = row, centres at
integers) is pixel ``(u * binning_x + roi.x_offset, v * binning_y + roi.y_offset)`` of the full
sensor, the convention of ``image_geometry`` (binning 0 means 1; an all-zero ROI means the full
image). The image size must be ``(roi or full) size // binning``. Two models, chosen by
``rectified``:

* ``rectified=True`` (an ``image_rect`` topic, e.g. depth_image_proc's input): the pinhole model of
  P (its fx', fy', cx', cy' and skew; D and K ignored). The ray is ``R^T (x, y, 1)`` with
  ``x = (u_full - cx' - s' y) / fx'``, ``y = (v_full - cy') / fy'``: the depth is z in the
  rectified frame, and R^T turns that frame back into the camera's (``header.frame_id``).
  depth_image_proc ignores R; both agree when R = I (monocular, registered depth). P's Tx, Ty
  (the position of this camera in a stereo pair's first camera frame) are ignored: the points are
  in this camera's own frame, like the image header says.
* ``rectified=False`` (an ``image_raw`` topic): K and the distortion D of ``distortion_model``
  ``plumb_bob`` (k1 k2 p1 p2 k3), ``rational_polynomial`` (k1 k2 p1 p2 k3 k4 k5 k6) or
  ``equidistant`` (k1 k2 k3 k4, OpenCV's fisheye model); the distorted normalised point
  ``((u_full - cx - s y_d) / fx, y_d = (v_full - cy) / fy)`` is undistorted by Newton's method
  (analytic Jacobian, halved steps when the residual grows) until the residual is below 1e-12
  (about 1e-9 pixel): OpenCV's undistortPoints iterates the same forward model, but with a fixed
  count of fixed-point steps. The depth is z in the camera frame.
* ``rectified=None`` (default): the data decide when they can. If D is empty or all zero and both
  models give the same rays (R = I and P's intrinsics equal K's, within 1e-9 rad), the raw model is
  used (it is then the rectified one too); so is it when P has no focal lengths (all zero: there
  is no rectified model, only K and D). Otherwise :class:`ConfigError`: the CameraInfo of an
  ``image_rect`` topic is the raw camera's (image_proc does not change it), so only the topic tells.

A pixel whose ray cannot be found (outside the domain where the distortion model is invertible:
no convergence, a folded-over Jacobian, or a fisheye ray at or behind 90 degrees) gets range NaN in
every scan; its table entry holds the distorted pixel's pinhole ray so the tables stay finite.

**LidarInfo.** One row per image row (row 0 = top), one column per image column, no stagger.
``pixel_azimuth_angles`` / ``pixel_altitude_angles`` are the exact ray of each pixel in the
camera's *body* axes (x forward along the optical axis, y left, z up; REP 103), and
``lidar_to_sensor_transform`` is the rotation from those axes to the image's optical frame
(x right, y down, z forward), times R^T for a rectified image. So the beam model's point
``T (rho d(azimuth, altitude))`` is exactly ``depth * ray`` in ``header.frame_id``.
``vertical_angles[u]`` is the altitude of row u's ray in the middle column and
``horizontal_angles[c]`` the azimuth of column c's ray in the middle row (origins and range
offsets are zero, so the beam model uses neither). ``vendor_metadata`` holds the CameraInfo (JSON)
and the model used. The info is built once per CameraInfo *content* (its header stamp changes
with every frame and is not part of it); its ``header.stamp`` (the version key) is the stamp of
the first CameraInfo seen with that content, made larger than the previous version's if needed.

**Range channel.** A depth image stores z, not the range along the ray: the channel ``range`` is
``z / cos(angle between ray and optical axis)`` = ``z * |(x, y, 1)|``, computed in float64 from the
exact depth and rounded once to float32 metres (relative error <= 2^-24: 4 micrometres at 65 m).
Integer millimetres with ``range_multiplier`` cannot hold it exactly (the range of an integer
depth is not an integer number of millimetres), while float32 keeps it to well under a
millimetre: a 16UC1 depth is recovered exactly as ``round(1000 * range / |ray|)``. For bit-exact
depths pass ``keep_depth=True``: a channel ``depth`` then carries the image's values unchanged
(uint16 millimetres or float32 metres, native byte order). Values: a depth > 0 -> its range;
+Inf -> +Inf (no return); -Inf -> -Inf (too close); 16UC1 0, NaN, 0.0 and negative float depths
-> ``invalid`` (NaN by default, REP 117 "invalid"; pass ``invalid=math.inf`` to treat them as no
return, which lets costmaps clear through them). None of these has a point.
"""

from __future__ import annotations

import hashlib
import json
import math
import threading
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import numpy as np

from lidarscan.errors import ConfigError, ConversionError, ValidationError
from lidarscan.scan import _as_array, make_info, make_scan
from lidarscan.stamps import to_ns

__all__ = ["DepthImageConverter", "from_depth_image", "distort", "pixel_rays", "undistort",
           "ENCODINGS", "OPTICAL_FROM_BODY"]

#: encoding -> (numpy dtype kind/size, metres per unit).
ENCODINGS: dict[str, tuple[str, float]] = {"16UC1": ("u2", 0.001), "mono16": ("u2", 0.001),
                                           "32FC1": ("f4", 1.0)}

#: Rotation from camera body axes (x forward, y left, z up) to the optical frame (x right,
#: y down, z forward): ``p_optical = OPTICAL_FROM_BODY @ p_body``.
OPTICAL_FROM_BODY = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])

_MODELS = {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}
_TOLERANCE = 1e-12       # undistortion residual, normalised image units
_SAME_RAYS = 1e-9        # rad: raw and rectified models count as the same below this
_MAX_ITER = 50
_CHUNK = 8192          # points per block (numpy temporaries of 64 KiB)
_CACHE_SIZE = 8


# ----------------------------------------------------------------------------- CameraInfo

def _field(msg: Any, name: str, default: Any = None) -> Any:
    if isinstance(msg, Mapping):
        return msg.get(name, default)
    return getattr(msg, name, default)


@dataclass(frozen=True)
class _Camera:
    """The geometry fields of a CameraInfo, normalised (the content key is ``key``)."""

    height: int
    width: int
    model: str
    d: tuple[float, ...]
    k: tuple[float, ...]
    r: tuple[float, ...]
    p: tuple[float, ...]
    binning: tuple[int, int]
    roi: tuple[int, int, int, int]      # x_offset, y_offset, height, width
    frame_id: str

    @property
    def key(self) -> str:
        return hashlib.blake2b(repr(self).encode(), digest_size=16).hexdigest()

    def image_size(self) -> tuple[int, int]:
        """(rows, columns) of the published image."""
        _, _, rh, rw = self.roi
        full_h, full_w = (rh, rw) if any(self.roi) else (self.height, self.width)
        return full_h // self.binning[1], full_w // self.binning[0]

    def as_json(self) -> dict[str, Any]:
        return {"height": self.height, "width": self.width, "distortion_model": self.model,
                "d": list(self.d), "k": list(self.k), "r": list(self.r), "p": list(self.p),
                "binning_x": self.binning[0], "binning_y": self.binning[1],
                "roi": dict(zip(("x_offset", "y_offset", "height", "width"), self.roi)),
                "frame_id": self.frame_id}


def _floats(msg: Any, name: str, size: int | None) -> tuple[float, ...]:
    value = _field(msg, name)
    arr = np.zeros(0) if value is None else np.asarray(_as_array(value, np.float64), np.float64)
    arr = arr.reshape(-1)
    if size is not None and arr.size != size:
        raise ValidationError(f"CameraInfo.{name}", f"length {arr.size}", f"length {size}")
    if not np.all(np.isfinite(arr)):
        raise ValidationError(f"CameraInfo.{name}", arr.tolist(), "finite values")
    return tuple(float(x) for x in arr)


def _camera(camera_info: Any) -> _Camera:
    roi = _field(camera_info, "roi")
    roi_t = (0, 0, 0, 0) if roi is None else tuple(
        int(_field(roi, f, 0)) for f in ("x_offset", "y_offset", "height", "width"))
    if any(roi_t) and not (roi_t[2] > 0 and roi_t[3] > 0):
        raise ValidationError("CameraInfo.roi", dict(zip(("x_offset", "y_offset", "height",
                                                          "width"), roi_t)),
                              "height and width > 0 when an offset is set (an all-zero ROI "
                              "means the full image)")
    header = _field(camera_info, "header")
    return _Camera(
        height=int(_field(camera_info, "height", 0)), width=int(_field(camera_info, "width", 0)),
        model=str(_field(camera_info, "distortion_model", "") or ""),
        d=_floats(camera_info, "d", None), k=_floats(camera_info, "k", 9),
        r=_floats(camera_info, "r", 9), p=_floats(camera_info, "p", 12),
        binning=(max(int(_field(camera_info, "binning_x", 0)), 1),
                 max(int(_field(camera_info, "binning_y", 0)), 1)),
        roi=roi_t,  # type: ignore[arg-type]
        frame_id="" if header is None else str(_field(header, "frame_id", "")))


def _stamp_ns(msg: Any, what: str = "CameraInfo") -> int:
    """int ns of ``msg.header.stamp`` (a Time message or a plain ``{sec, nanosec}`` mapping,
    checked alike by :func:`lidarscan.stamps.to_ns`); 0 without a header."""
    header = _field(msg, "header")
    stamp = None if header is None else _field(header, "stamp")
    field = f"{what}.header.stamp"
    if isinstance(stamp, Mapping):                    # a plain mapping: {"sec", "nanosec"}
        try:
            stamp = SimpleNamespace(sec=int(stamp["sec"]), nanosec=int(stamp.get("nanosec", 0)))
        except (KeyError, TypeError, ValueError) as err:
            raise ValidationError(field, dict(stamp),
                                  "{sec, nanosec} integers or a Time message") from err
    return 0 if stamp is None else to_ns(stamp, field=field)


# ------------------------------------------------------------------------- distortion math

def _coefficients(model: str, d: tuple[float, ...]) -> np.ndarray[Any, Any]:
    """D padded with zeros to the model's length: plumb_bob/rational -> (k1 k2 p1 p2 k3 k4 k5 k6),
    equidistant -> (k1 k2 k3 k4)."""
    if model not in _MODELS:
        raise ConversionError("CameraInfo.distortion_model", model,
                              f"one of {sorted(_MODELS)} (or D empty / all zero)")
    size = _MODELS[model]
    if any(d[size:]):
        raise ConversionError("CameraInfo.d", list(d),
                              f"at most {size} coefficients for {model} (extra ones all zero)")
    d = d[:size]
    return np.array(list(d) + [0.0] * (8 - len(d)) if model != "equidistant"
                    else list(d) + [0.0] * (4 - len(d)))


def distort(x: Any, y: Any, model: str, d: Any) -> tuple[np.ndarray[Any, Any],
                                                          np.ndarray[Any, Any]]:
    """Forward distortion of normalised undistorted points (x = X/Z, y = Y/Z), float64 arrays.

    plumb_bob / rational_polynomial (OpenCV's model, D = k1 k2 p1 p2 k3 k4 k5 k6)::

        r2 = x^2 + y^2,  g = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)
        x_d = x g + 2 p1 x y + p2 (r2 + 2 x^2),   y_d = y g + p1 (r2 + 2 y^2) + 2 p2 x y

    equidistant (D = k1 k2 k3 k4): ``theta = atan(r)``,
    ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``,
    ``(x_d, y_d) = (theta_d / r) (x, y)``.
    """
    c = _coefficients(model, tuple(float(v) for v in np.asarray(d, np.float64).reshape(-1)))
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    if model == "equidistant":
        r = np.hypot(x, y)
        theta = np.arctan(r)
        t2 = theta * theta
        theta_d = theta * (1 + t2 * (c[0] + t2 * (c[1] + t2 * (c[2] + t2 * c[3]))))
        with np.errstate(invalid="ignore", divide="ignore"):
            scale = np.where(r > 0, theta_d / r, 1.0)
        return x * scale, y * scale
    xd, yd, *_ = _rational(x, y, c)
    return xd, yd


def _rational(x: np.ndarray[Any, Any], y: np.ndarray[Any, Any], c: np.ndarray[Any, Any]
              ) -> tuple[np.ndarray[Any, Any], ...]:
    """(x_d, y_d, dxd/dx, dxd/dy, dyd/dx, dyd/dy, denominator) of the rational model."""
    k1, k2, p1, p2, k3, k4, k5, k6 = c
    r2 = x * x + y * y
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        g = num / den
        dg = ((k1 + r2 * (2 * k2 + 3 * k3 * r2)) * den
              - num * (k4 + r2 * (2 * k5 + 3 * k6 * r2))) / (den * den)       # dg/dr2
        xy = x * y
        xd = x * g + 2 * p1 * xy + p2 * (r2 + 2 * x * x)
        yd = y * g + p1 * (r2 + 2 * y * y) + 2 * p2 * xy
        cross = 2 * xy * dg + 2 * p1 * x + 2 * p2 * y
        jxx = g + 2 * x * x * dg + 2 * p1 * y + 6 * p2 * x
        jyy = g + 2 * y * y * dg + 6 * p1 * y + 2 * p2 * x
    return xd, yd, jxx, cross, cross, jyy, den


def undistort(xd: Any, yd: Any, model: str, d: Any
              ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """Unit ray directions of distorted normalised points (inverse of :func:`distort`).

    Args:
        xd, yd: float64 arrays of one shape S: distorted normalised image coordinates.
        model, d: CameraInfo ``distortion_model`` and D.

    Returns:
        (rays, ok): rays (S + (3,)) float64 unit vectors in the camera's optical axes (z forward);
        ok (S) bool, False where the inverse was not found (no convergence to 1e-12, a folded
        Jacobian, a fisheye angle >= 90 deg); there the ray is the pinhole ray of (xd, yd).
    """
    c = _coefficients(model, tuple(float(v) for v in np.asarray(d, np.float64).reshape(-1)))
    xd, yd = np.broadcast_arrays(np.asarray(xd, np.float64), np.asarray(yd, np.float64))
    shape = xd.shape
    flat_x, flat_y = xd.reshape(-1), yd.reshape(-1)
    rays = np.empty((flat_x.size, 3))
    ok = np.empty(flat_x.size, bool)
    # blocks of a few thousand points: the temporaries stay in cache and are not mmapped anew
    for start in range(0, flat_x.size, _CHUNK):
        part = slice(start, start + _CHUNK)
        rays[part], ok[part] = _undistort_block(flat_x[part], flat_y[part], model, c)
    return rays.reshape(shape + (3,)), ok.reshape(shape)


def _undistort_block(xd: np.ndarray[Any, Any], yd: np.ndarray[Any, Any], model: str,
                     c: np.ndarray[Any, Any]) -> tuple[np.ndarray[Any, Any],
                                                       np.ndarray[Any, Any]]:
    if model == "equidistant":
        theta_d = np.hypot(xd, yd)
        theta, ok = _newton_1d(theta_d, c)
        ok &= theta < 0.5 * math.pi
        with np.errstate(invalid="ignore", divide="ignore"):
            s = np.where(theta_d > 0, np.sin(theta) / theta_d, 1.0)
        rays = np.stack([xd * s, yd * s, np.cos(theta)], -1)
    else:
        x, y, ok = _newton_2d(xd, yd, c)
        rays = _unit(x, y)
    return np.where(ok[..., None], rays, _unit(xd, yd)), ok


def _newton_2d(xd: np.ndarray[Any, Any], yd: np.ndarray[Any, Any], c: np.ndarray[Any, Any]
               ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    x, y = xd.copy(), yd.copy()

    def residual(px: Any, py: Any) -> tuple[Any, ...]:
        out = _rational(px, py, c)
        return (out[0] - xd, out[1] - yd) + out[2:]

    ex, ey, jxx, jxy, jyx, jyy, den = residual(x, y)
    err = np.hypot(ex, ey)
    for _ in range(_MAX_ITER):
        active = ~(err <= _TOLERANCE)          # NaN stays active (and fails below)
        if not np.any(active):
            break
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            det = jxx * jyy - jxy * jyx
            dx = np.where(active, (jyy * ex - jxy * ey) / det, 0.0)
            dy = np.where(active, (jxx * ey - jyx * ex) / det, 0.0)
        step = np.ones_like(x)
        for _ in range(30):                    # halve the step where the residual grows
            nx, ny = x - step * dx, y - step * dy
            new = residual(nx, ny)
            new_err = np.hypot(new[0], new[1])
            worse = active & ~(new_err < err) & (step > 2.0 ** -29)
            if not np.any(worse):
                break
            step = np.where(worse, 0.5 * step, step)
        x, y = np.where(active, nx, x), np.where(active, ny, y)
        ex, ey, jxx, jxy, jyx, jyy, den = (np.where(active, a, b)
                                           for a, b in zip(new, (ex, ey, jxx, jxy, jyx, jyy, den)))
        err = np.where(active, new_err, err)
    with np.errstate(invalid="ignore"):
        ok = (err <= _TOLERANCE) & (jxx * jyy - jxy * jyx > 0) & (den > 0)
    return x, y, ok


def _newton_1d(theta_d: np.ndarray[Any, Any], c: np.ndarray[Any, Any]
               ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    k1, k2, k3, k4 = c
    theta = theta_d.copy()
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        for _ in range(_MAX_ITER):
            t2 = theta * theta
            f = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - theta_d
            df = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
            if not np.any(np.abs(f) > _TOLERANCE):
                break
            theta = theta - f / df
        t2 = theta * theta
        f = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - theta_d
        df = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
        ok = (np.abs(f) <= _TOLERANCE) & (df > 0) & (theta >= 0)
    return theta, ok


# ------------------------------------------------------------------------------ pixel rays

def _is_zero(values: tuple[float, ...]) -> bool:
    return not any(values)


def _pinhole(cam: _Camera, matrix: tuple[float, ...], stride: int
             ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """Normalised (x, y), each (H, W) float64, of every published pixel under the pinhole
    intrinsics of ``matrix`` (K with stride 3, P with stride 4), in full-sensor pixels."""
    fx, skew, cx = matrix[0], matrix[1], matrix[2]
    fy, cy = matrix[stride + 1], matrix[stride + 2]
    if not (fx != 0 and fy != 0):
        which = "K" if stride == 3 else "P"
        raise ConversionError(f"CameraInfo.{which.lower()}", list(matrix),
                              f"a calibrated {which} (fx, fy non-zero)")
    rows, cols = cam.image_size()
    u = np.arange(cols, dtype=np.float64) * cam.binning[0] + cam.roi[0]
    v = np.arange(rows, dtype=np.float64) * cam.binning[1] + cam.roi[1]
    y = np.broadcast_to(((v - cy) / fy)[:, None], (rows, cols))
    x = (u[None, :] - cx - skew * y) / fx
    return x, np.array(y)


def _unit(x: np.ndarray[Any, Any], y: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """(..., 3) unit vectors along (x, y, 1)."""
    inv = 1.0 / np.sqrt(x * x + y * y + 1.0)
    rays = np.empty(x.shape + (3,))
    np.multiply(x, inv, out=rays[..., 0])
    np.multiply(y, inv, out=rays[..., 1])
    rays[..., 2] = inv
    return rays


def pixel_rays(camera_info: Any, rectified: bool | None = None
               ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any], np.ndarray[Any, Any], bool]:
    """The ray of every pixel of the images described by ``camera_info`` (module docstring).

    Returns:
        (rays, ok, rotation, rectified): rays (H, W, 3) float64 unit vectors in the model's
        optical frame (rectified frame for P, camera frame for K; z forward), H x W the published
        image size; ok (H, W) bool (False: no ray, see :func:`undistort`); rotation (3, 3) from
        the model's frame to ``header.frame_id`` (R^T, or I); the model used.

    Raises:
        ConfigError: ``rectified=None`` while the raw and rectified models differ.
        ConversionError: uncalibrated K/P, unknown distortion model, too many coefficients.
    """
    cam = camera_info if isinstance(camera_info, _Camera) else _camera(camera_info)
    if rectified is None:
        rectified = _choose_model(cam)
    if rectified:
        x, y = _pinhole(cam, cam.p, 4)
        rays = _unit(x, y)
        r = np.array(cam.r).reshape(3, 3)
        rotation = np.eye(3) if _is_zero(cam.r) else r.T
        if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-6) or \
                np.linalg.det(rotation) <= 0:
            raise ConversionError("CameraInfo.r", list(cam.r), "a rotation matrix")
        return rays, np.ones(x.shape, bool), rotation, True
    xd, yd = _pinhole(cam, cam.k, 3)
    if _is_zero(cam.d):
        rays = _unit(xd, yd)
        ok = np.ones(xd.shape, bool)
    else:
        rays, ok = undistort(xd, yd, cam.model, cam.d)
    return rays, ok, np.eye(3), False


def _choose_model(cam: _Camera) -> bool:
    """The ``rectified=None`` default: False when raw and rectified rays coincide or when there
    is no rectified model (P without focal lengths: K and D are all there is), else error."""
    if not (cam.p[0] != 0 and cam.p[5] != 0):
        return False
    if _is_zero(cam.d):
        raw = pixel_rays(cam, False)[0]
        rect, _, rotation, _ = pixel_rays(cam, True)
        chord = np.abs(raw - rect @ rotation.T)           # |difference| ~ angle (rad)
        if float(np.max(chord, initial=0.0)) <= _SAME_RAYS:
            return False
    raise ConfigError("rectified", None,
                      "True for an image_rect topic (model P, R) or False for image_raw (K, D): "
                      "this CameraInfo's raw and rectified models give different rays")


# ------------------------------------------------------------------------------ the image

def _depth_view(image: Any, encoding: str | None) -> tuple[np.ndarray[Any, Any], str]:
    """Read-only (H, W) view of the depth values (their own byte order) and the encoding."""
    if isinstance(image, np.ndarray):
        if encoding is None:
            raise ConfigError("encoding", None, f"one of {sorted(ENCODINGS)} for a numpy array")
        if encoding not in ENCODINGS:
            raise ConfigError("encoding", encoding, f"one of {sorted(ENCODINGS)}")
        kind = ENCODINGS[encoding][0]
        if image.ndim != 2 or image.dtype.kind + str(image.dtype.itemsize) != kind:
            raise ValidationError("image", f"shape {image.shape} dtype {image.dtype}",
                                  f"a 2-D {np.dtype(kind)} array for {encoding}")
        view = image.view()
        view.flags.writeable = False
        return view, encoding
    enc = str(image.encoding) if encoding is None else encoding
    if enc not in ENCODINGS:
        raise ConversionError("Image.encoding", enc, f"a depth encoding: {sorted(ENCODINGS)}")
    dtype = np.dtype(ENCODINGS[enc][0]).newbyteorder(">" if int(image.is_bigendian) else "<")
    height, width, step = int(image.height), int(image.width), int(image.step)
    data = image.data
    buf = data if isinstance(data, np.ndarray) else np.frombuffer(data, np.uint8)
    buf = buf.reshape(-1).view(np.uint8)
    if step < width * dtype.itemsize:
        raise ValidationError("Image.step", step,
                              f">= width * {dtype.itemsize} = {width * dtype.itemsize} bytes")
    need = (height - 1) * step + width * dtype.itemsize if height and width else 0
    if buf.size < need:
        raise ValidationError("Image.data", f"length {buf.size}",
                              f">= {need} bytes for {height} rows of step {step}")
    if height == 0 or width == 0:
        return np.zeros((height, width), dtype), enc
    view = np.ndarray((height, width), dtype, buffer=buf, strides=(step, dtype.itemsize))
    view.flags.writeable = False
    return view, enc


# ------------------------------------------------------------------------------ converter

class DepthImageConverter:
    """Depth images of one camera -> LidarScans; rays and LidarInfo built once per CameraInfo.

    Args:
        camera_info: the camera's ``sensor_msgs/CameraInfo`` (rclpy, dataclass or mapping).
        rectified: True = image_rect (P, R), False = image_raw (K, D), None = decided from the
            data when unambiguous (module docstring).
        frame_id: frame of scan and info; default the CameraInfo's ``header.frame_id``.
        invalid: range given to pixels without a measurement (16UC1 0; NaN, 0 or negative float
            depths): NaN (default, REP 117 invalid) or +inf (no return).
        keep_depth: also store the image's own values in a channel ``depth``.
        range_min, range_max: the info's range limits in metres along the ray (0 = unknown).
        info_stamp_ns: version key of the first info; default the CameraInfo's stamp.
        as_dataclass: produce :mod:`lidarscan.types` dataclasses instead of rclpy messages.

    Attributes:
        info: the current LidarInfo; rays: (H, W, 3) float64 unit rays in ``frame_id`` (optical
        axes); scale: (H, W) float64 ``|(x, y, 1)|`` = range / depth (NaN where no ray).
    """

    def __init__(self, camera_info: Any, *, rectified: bool | None = None,
                 frame_id: str | None = None, invalid: float = math.nan,
                 keep_depth: bool = False, range_min: float = 0.0, range_max: float = 0.0,
                 info_stamp_ns: int | None = None, as_dataclass: bool = False) -> None:
        if not (math.isnan(invalid) or invalid == math.inf):
            raise ConfigError("invalid", invalid, "nan or inf")
        self._rectified_option = rectified
        self._frame_option = frame_id
        self.invalid = float(invalid)
        self.keep_depth = bool(keep_depth)
        self._limits = (float(range_min), float(range_max))
        self.as_dataclass = as_dataclass
        self._camera: _Camera | None = None
        self._version = -1
        self._set_camera(_camera(camera_info),
                         _stamp_ns(camera_info) if info_stamp_ns is None else int(info_stamp_ns))

    # ---------------------------------------------------------------------------- geometry
    def _set_camera(self, cam: _Camera, stamp_ns: int) -> None:
        rays, ok, rotation, rectified = pixel_rays(cam, self._rectified_option)
        with np.errstate(divide="ignore"):
            scale = np.where(ok, 1.0 / rays[..., 2], np.nan)
        transform = np.eye(4)
        transform[:3, :3] = rotation @ OPTICAL_FROM_BODY
        # body axes (x, y, z) = optical (z, -x, -y)
        azimuth = np.arctan2(-rays[..., 0], rays[..., 2])
        altitude = np.arctan2(-rays[..., 1], np.hypot(rays[..., 2], rays[..., 0]))
        rows, cols = scale.shape
        frame = self._frame_option if self._frame_option is not None else cam.frame_id
        version = stamp_ns if stamp_ns > self._version else self._version + 1
        metadata = {"source": "depth_image", "rectified": rectified,
                    "camera_info_key": cam.key, "camera_info": cam.as_json()}
        self.info = make_info(
            stamp_ns=version, frame_id=frame,
            vertical_angles=altitude[:, cols // 2] if cols else np.zeros(rows),
            horizontal_angles=azimuth[rows // 2] if rows else np.zeros(cols),
            pixel_azimuth_angles=azimuth.reshape(-1), pixel_altitude_angles=altitude.reshape(-1),
            lidar_to_sensor_transform=transform.reshape(-1), model="depth camera",
            range_min=self._limits[0], range_max=self._limits[1],
            vendor_metadata=json.dumps(metadata), as_dataclass=self.as_dataclass)
        self.rays = rays if np.array_equal(rotation, np.eye(3)) else rays @ rotation.T
        self.scale = scale
        self._scales: dict[float, np.ndarray[Any, Any]] = {}
        missing = np.flatnonzero(~ok)
        self._no_ray = missing if missing.size else None
        self.rectified = rectified
        self.frame_id = frame
        self._camera = cam
        self._version = version

    def update(self, camera_info: Any) -> bool:
        """Switch to ``camera_info`` if its content differs (new version); True if it did."""
        cam = _camera(camera_info)
        if cam == self._camera:
            return False
        self._set_camera(cam, _stamp_ns(camera_info))
        return True

    # ---------------------------------------------------------------------------- convert
    def ranges(self, depth: np.ndarray[Any, Any], encoding: str) -> np.ndarray[Any, Any]:
        """(H, W) float32 range along each ray in metres (module docstring for the values)."""
        if depth.shape != self.scale.shape:
            raise ValidationError("image.shape", depth.shape,
                                  f"{self.scale.shape} (CameraInfo size // binning, ROI)")
        unit = ENCODINGS[encoding][1]
        scale = self._scales.get(unit)
        if scale is None:
            scale = self._scales[unit] = self.scale * unit
        height, width = depth.shape
        out = np.empty((height, width), np.float32)
        rows = max(1, _CHUNK // max(width, 1))
        tmp = np.empty((rows, width))
        integer = depth.dtype.kind == "u"
        # row blocks: float64 product rounded once to float32, without image-sized temporaries
        for start in range(0, height, rows):
            z = depth[start:start + rows]
            r64 = tmp[:z.shape[0]]
            np.multiply(z, scale[start:start + rows], out=r64)
            if integer:
                bad = z == 0
            else:
                with np.errstate(invalid="ignore"):
                    bad = ~(z > 0)
                bad &= ~np.isinf(z)
            r64[bad] = self.invalid
            out[start:start + rows] = r64
        if self._no_ray is not None:          # no ray: invalid whatever the depth
            out.reshape(-1)[self._no_ray] = np.nan
        return out

    def convert(self, image: Any, *, camera_info: Any = None, stamp_ns: int | None = None,
                encoding: str | None = None) -> tuple[Any, Any]:
        """One depth image -> (LidarScan, LidarInfo).

        Args:
            image: ``sensor_msgs/Image`` (16UC1, mono16 or 32FC1; any byte order and step), or a
                2-D numpy array (uint16 or float32, any byte order) with ``encoding``.
            camera_info: the CameraInfo received with the image; tables and info are rebuilt
                only when its content changed.
            stamp_ns: the scan's header.stamp; default the image's (required for an array).
            encoding: overrides ``image.encoding``; required for an array.

        Returns:
            (scan, info): H x W scan, channel ``range`` float32 metres (plus ``depth``), in
            ``frame_id``, ``lidar_info_time`` = ``info.header.stamp``.
        """
        if camera_info is not None:
            self.update(camera_info)
        depth, enc = _depth_view(image, encoding)
        if stamp_ns is None:
            if isinstance(image, np.ndarray):
                raise ConfigError("stamp_ns", None, "the image time in ns for a numpy array")
            stamp_ns = _stamp_ns(image, "Image")
        frame = getattr(getattr(image, "header", None), "frame_id", "") or self.frame_id
        if self._frame_option is None and frame != self.frame_id and self.frame_id:
            raise ValidationError("Image.header.frame_id", frame,
                                  f"the CameraInfo's frame {self.frame_id!r} (or pass frame_id)")
        channels: dict[str, Any] = {"range": self.ranges(depth, enc)}
        if self.keep_depth:
            channels["depth"] = depth.astype(depth.dtype.newbyteorder("="), copy=False)
        scan = make_scan(self.info, channels, int(stamp_ns), frame_id=self.frame_id,
                         as_dataclass=self.as_dataclass)
        return scan, self.info


_CONVERTERS: OrderedDict[tuple[Any, ...], DepthImageConverter] = OrderedDict()
_LOCK = threading.Lock()


def from_depth_image(image: Any, camera_info: Any, *, stamp_ns: int | None = None,
                     info: Any = None, encoding: str | None = None,
                     rectified: bool | None = None, frame_id: str | None = None,
                     invalid: float = math.nan, keep_depth: bool = False,
                     range_min: float = 0.0, range_max: float = 0.0,
                     as_dataclass: bool = False) -> tuple[Any, Any]:
    """A depth image -> (LidarScan, LidarInfo); see :class:`DepthImageConverter` for the options.

    Converters are cached per CameraInfo content and options (8 kept), so a stream of images
    builds its rays once and gets the same LidarInfo (same version stamp) every frame.

    Args:
        info: the LidarInfo of a previous call for this camera, or None. If it was built from
            the same CameraInfo content its stamp (version key) is kept, even after the cache
            dropped it or in another process; if not, the new info's stamp is made larger than
            it so the two versions differ.
    """
    cam = _camera(camera_info)
    version = _stamp_ns(camera_info)
    if info is not None:
        previous = to_ns(info.header.stamp, field="info.header.stamp")
        try:
            same = json.loads(str(info.vendor_metadata)).get("camera_info_key") == cam.key
        except (ValueError, AttributeError):
            same = False
        version = previous if same else max(version, previous + 1)
    key = (cam, rectified, frame_id, float(invalid) if not math.isnan(invalid) else "nan",
           bool(keep_depth), float(range_min), float(range_max), bool(as_dataclass))
    with _LOCK:
        converter = _CONVERTERS.get(key)
        if converter is not None:
            _CONVERTERS.move_to_end(key)
    if converter is None or (info is not None and converter._version != version):
        converter = DepthImageConverter(
            camera_info, rectified=rectified, frame_id=frame_id, invalid=invalid,
            keep_depth=keep_depth, range_min=range_min, range_max=range_max,
            info_stamp_ns=version, as_dataclass=as_dataclass)
        with _LOCK:
            _CONVERTERS[key] = converter
            _CONVERTERS.move_to_end(key)
            while len(_CONVERTERS) > _CACHE_SIZE:
                _CONVERTERS.popitem(last=False)
    return converter.convert(image, stamp_ns=stamp_ns, encoding=encoding)
