"""Plain-loop rays of the beam model, for the oracles (slices, merger, holes).

Written from the beam model as ``msgs/msg/LidarInfo.msg`` and ``msgs/README.md`` document it
(per-pixel ``azimuth`` channel included), not from ``lidarscan.geometry``: one pixel at a time,
with ``math`` in float64. :func:`checked_tables` holds the project's float32 tables to these
rays, so an oracle built on them does not inherit a projector bug.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

import lidarscan


def _floats(values: Any) -> list[float]:
    return [float(x) for x in np.asarray(values, dtype=np.float64).reshape(-1)]


def shifts_of(info: Any) -> list[int]:
    """``pixel_shift_by_row`` per row (empty: no stagger)."""
    shifts = [int(x) for x in np.asarray(info.pixel_shift_by_row).reshape(-1)]
    return shifts or [0] * int(info.height)


def _azimuth_channel(scan: Any, range_channel: str) -> np.ndarray | None:
    """The pixel azimuths (radians, scan column order) of ``range_channel``'s ``azimuthN``
    channel, else of ``azimuth``; None without one. Integer channels count 0.01 degree."""
    names = [c.name for c in scan.channels]
    suffix = range_channel[5:] if range_channel.startswith("range") else ""
    for name in (f"azimuth{suffix}", "azimuth"):
        if name in names:
            values = np.asarray(lidarscan.channel(scan, name))
            if values.ndim == 3:
                values = values[..., 0]
            if values.dtype.kind in "iu":
                return values.astype(np.float64) * (math.pi / 18000.0)
            return values.astype(np.float64)
    return None


def ref_tables(scan: Any, info: Any, range_channel: str = "range"
               ) -> tuple[np.ndarray, np.ndarray]:
    """(D, O): (H, W, 3) float64 direction and offset of every pixel of ``scan`` in its own
    column order (stored column v; measurement column c = (v - shift_u) mod W when the scan is
    destaggered), so that its point is ``rho * D + O`` in ``info.header.frame_id``."""
    height, width = int(info.height), int(info.width)
    phi = _floats(info.vertical_angles)
    measured = _floats(scan.column_azimuth_angles)
    alpha = measured if measured else _floats(info.horizontal_angles)
    beta = _floats(info.beam_azimuth_offsets) or [0.0] * height
    pix_az, pix_alt = _floats(info.pixel_azimuth_angles), _floats(info.pixel_altitude_angles)
    origins = _floats(info.beam_origins) or [0.0] * (3 * height)
    delta = _floats(info.beam_range_offsets) or [0.0] * height
    matrix = _floats(info.lidar_to_sensor_transform)
    if not any(matrix):
        matrix = [1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0]
    rot = [[matrix[4 * i + j] for j in range(3)] for i in range(3)]
    trans = [matrix[4 * i + 3] for i in range(3)]
    shifts = shifts_of(info)
    pixel_theta = _azimuth_channel(scan, range_channel)
    dirs, offs = np.zeros((height, width, 3)), np.zeros((height, width, 3))
    for u in range(height):
        ox, oy, oz = origins[3 * u:3 * u + 3]
        for v in range(width):
            c = (v - shifts[u]) % width if scan.is_destaggered else v
            if pixel_theta is not None:
                theta = float(pixel_theta[u, v])
            else:
                theta = alpha[c] + beta[u]
            if pix_az:
                theta_d, phi_d = pix_az[u * width + c], pix_alt[u * width + c]
            else:
                theta_d, phi_d = theta, phi[u]
            d = (math.cos(phi_d) * math.cos(theta_d), math.cos(phi_d) * math.sin(theta_d),
                 math.sin(phi_d))
            ct, st = math.cos(theta), math.sin(theta)
            o = (ct * ox - st * oy + delta[u] * d[0], st * ox + ct * oy + delta[u] * d[1],
                 oz + delta[u] * d[2])
            for i in range(3):
                dirs[u, v, i] = rot[i][0] * d[0] + rot[i][1] * d[1] + rot[i][2] * d[2]
                offs[u, v, i] = rot[i][0] * o[0] + rot[i][1] * o[1] + rot[i][2] * o[2] + trans[i]
    return dirs, offs


def checked_tables(scan: Any, info: Any, range_channel: str = "range"
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The project's float32 tables of ``scan`` (``make_projector(info).tables_for``), after
    checking every value against :func:`ref_tables`: the documented model rounded to float32,
    so within 2 float32 ulps (plus 1e-9 for float64 noise on values near zero). The oracles
    compute with these exact float32 values, as the converters do, so that their outputs can be
    compared bit for bit; a projector that differs from the model fails here."""
    dirs, offs = lidarscan.make_projector(info).tables_for(scan, range_channel)
    ref_dirs, ref_offs = ref_tables(scan, info, range_channel)
    for name, got, want in (("directions", dirs, ref_dirs), ("offsets", offs, ref_offs)):
        got64 = np.asarray(got, np.float64)
        ulp = np.spacing(np.abs(want).astype(np.float32)).astype(np.float64)
        bad = ~(np.abs(got64 - want) <= 2 * ulp + 1e-9)
        if bad.any():
            u, v, i = np.argwhere(bad)[0]
            raise AssertionError(f"projector {name}[{u}, {v}, {i}] = {got64[u, v, i]!r}, the "
                                 f"beam model gives {want[u, v, i]!r} "
                                 f"({int(bad.sum())} values differ)")
    return dirs, offs
