"""Frames shared by the slice converter and the merger: extrinsics, rays, frame agreement.

Conventions: an *extrinsics* matrix is the 4x4 float64 homogeneous pose of an input's frame in
the output (target) frame, ``p_out = M @ p_in`` (REP 103 axes, metres); None means identity,
which is only right when the input's frame *is* the output frame (:func:`check_frame`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from lidarscan.errors import ConfigError, ValidationError

__all__ = ["check_extrinsics", "check_frame", "check_poses", "transform_rays"]


def check_extrinsics(extrinsics: Any, field: str = "extrinsics") -> np.ndarray[Any, Any]:
    """A 4x4 float64 rigid transform (None -> identity).

    Raises:
        ConfigError: wrong shape, non-finite values, a rotation that is not orthonormal with
            determinant +1, or a last row other than 0 0 0 1.
    """
    if extrinsics is None:
        return np.eye(4)
    if isinstance(extrinsics, (str, bytes)):
        raise ConfigError(field, extrinsics, "a 4x4 homogeneous transform")
    try:
        matrix = np.array(extrinsics, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ConfigError(field, extrinsics, "a 4x4 homogeneous transform") from err
    if matrix.size != 16:
        raise ConfigError(field, matrix.shape, "a 4x4 matrix (or 16 values, row-major)")
    matrix = matrix.reshape(4, 4)
    if not _rigid(matrix[None]):
        raise ConfigError(field, matrix.round(6).tolist(), _RIGID)
    return matrix


_RIGID = "a rigid transform (orthonormal rotation with det +1, last row 0 0 0 1)"


def _rigid(stack: np.ndarray[Any, Any]) -> bool:
    """Whether every (N, 4, 4) matrix is a finite rigid transform."""
    rot = stack[:, :3, :3]
    return bool(np.all(np.isfinite(stack))
                and np.allclose(stack[:, 3], [0, 0, 0, 1], atol=1e-9)
                and np.allclose(rot @ rot.transpose(0, 2, 1), np.eye(3), atol=1e-6)
                and np.all(np.linalg.det(rot) > 0))


def check_poses(poses: Any, field: str) -> np.ndarray[Any, Any]:
    """(N, 4, 4) float64 rigid transforms (e.g. what a moving mount's callable returned).

    Raises:
        ValidationError: wrong shape, or a matrix that is not a finite rigid transform (the
            first one is named by its index).
    """
    try:
        stack = np.asarray(poses, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValidationError(field, poses, "4x4 homogeneous transforms") from err
    if stack.ndim != 3 or stack.shape[1:] != (4, 4):
        raise ValidationError(field, stack.shape, "4x4 homogeneous transforms")
    if not _rigid(stack):
        bad = next(i for i in range(len(stack)) if not _rigid(stack[i:i + 1]))
        raise ValidationError(f"{field}[{bad}]", stack[bad].round(6).tolist(), _RIGID)
    return stack


def check_frame(field: str, frame: str, output_frame: str, has_extrinsics: bool,
                error: type[Exception] = ValidationError) -> None:
    """Refuse data in ``frame`` fused into ``output_frame`` without extrinsics.

    Identity is only right when both frames are the same; anything else would put every point
    of that input in the wrong place.

    Raises:
        ``error`` (a LidarScanError class; ValidationError for data, ConfigError for settings)
        naming ``field``, the input's frame and the output frame.
    """
    if not has_extrinsics and frame != output_frame:
        raise error(field, frame, f"{output_frame!r} (the output frame), or extrinsics giving "
                                  f"the pose of {frame!r} in {output_frame!r}")


def transform_rays(d: np.ndarray[Any, Any], o: np.ndarray[Any, Any],
                   matrix: np.ndarray[Any, Any], index: np.ndarray[Any, Any] | None = None
                   ) -> tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]:
    """Directions and origins (n, 3) moved into the target frame and rounded to float32 (like
    the projector's own tables). Written out per component, left to right, in float64 from the
    float32 projector tables, so that a plain loop reproduces them bit for bit.

    ``matrix``: one (4, 4) transform for every ray, or (P, 4, 4) transforms with ``index``
    (n,) int, the transform of each ray (a moving mount: one pose per distinct ray time).
    """
    if index is None:
        m: Any = matrix                                      # m[i, j]: float64 scalars
    else:
        rows = np.asarray(matrix, np.float64)[:, :3, :].reshape(-1, 12)
        m = np.take(np.ascontiguousarray(rows.T), index, axis=1).reshape(3, 4, -1)  # (3, 4, n)
    dx, dy, dz = (d[:, k].astype(np.float64) for k in range(3))
    ox, oy, oz = (o[:, k].astype(np.float64) for k in range(3))
    dt = np.empty(d.shape, np.float32)
    ot = np.empty(o.shape, np.float32)
    for i in range(3):
        dt[:, i] = m[i, 0] * dx + m[i, 1] * dy + m[i, 2] * dz
        ot[:, i] = m[i, 0] * ox + m[i, 1] * oy + m[i, 2] * oz + m[i, 3]
    return dt, ot
