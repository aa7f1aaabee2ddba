"""from_pointcloud2 on driver point layouts not covered by tests/test_driver_clouds.py.

Every cloud is written from the decoded Nebula recordings (tests/driver_clouds.py: the packet
decoders are checked against Nebula's ground truth elsewhere) in a driver's layout as its source
defines it, then re-imported; the targets are those of tests/test_driver_clouds.py (>= 98 % of
the points kept as valid pixels, nearest decoded point median <= 2 mm, p99 <= 20 mm).

- ``rslidar``: RoboSense rslidar_sdk XYZIRT as its ROS conversion writes it (fields one after
  the other with no alignment: x, y, z, intensity float32, ring uint16 at 16, timestamp float64
  absolute s at 18, point_step 26), and its ``dense_points: false`` form: every pixel a point,
  no return a NaN point, height = the number of lasers but the points in firing order (so a
  "row" of the message is not a ring).
- ``velodyne_organized``: velodyne_pointcloud's ``organize_cloud: true`` output: one message
  row a firing, one column a ring (width = the number of lasers), NaN points for no return,
  fields x, y, z, intensity, ring, time as in its unorganized cloud.
- big-endian and padded copies of the velodyne_pointcloud layout (extra unknown fields).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

pytest.importorskip("rosbags")
pytest.importorskip("sensor_msgs.msg")

import lidarscan  # noqa: E402
from converters.pointcloud2 import converter as pc  # noqa: E402

import driver_clouds as dc  # noqa: E402
from cloud_oracles import make_cloud  # noqa: E402
from test_driver_clouds import KEPT, check_reimport, middle_scan  # noqa: E402

RSLIDAR = np.dtype({"names": ["x", "y", "z", "intensity", "ring", "timestamp"],
                    "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f8"],
                    "offsets": [0, 4, 8, 12, 16, 18], "itemsize": 26})


def rslidar_cloud(scan: Any, info: Any, *, dense: bool) -> tuple[Any, np.ndarray[Any, Any]]:
    """The first return of a decoded scan as rslidar_sdk's XYZIRT cloud (module docstring).

    Returns:
        (cloud, xyz): the PointCloud2 and the (N, 3) float64 finite points it holds.
    """
    proj = lidarscan.make_projector(info)
    stamp = lidarscan.to_ns(scan.header.stamp)
    times = proj.pixel_times(scan) + np.int64(stamp)                 # (H, W) ns
    rng_m, inten = dc._returns(scan, info)[0]
    xyz = proj.xyz(rng_m, tables=proj.tables_for(scan)).astype(np.float64)   # (H, W, 3)
    height, width = rng_m.shape
    ids = np.asarray(info.beam_ids, np.int64)
    fire = np.argsort(ids, kind="stable")                            # rows in laser-id order
    c_idx, u_idx = (a.ravel() for a in np.meshgrid(np.arange(width), fire, indexing="ij"))
    pts_xyz = xyz[u_idx, c_idx]
    good = np.isfinite(rng_m[u_idx, c_idx]) & np.all(np.isfinite(pts_xyz), -1)
    pts_xyz[~good] = np.nan
    if dense:                                                         # no-return points omitted
        c_idx, u_idx, pts_xyz, good = c_idx[good], u_idx[good], pts_xyz[good], good[good]
    pts = np.zeros(c_idx.size, RSLIDAR)
    for j, axis in enumerate("xyz"):
        pts[axis] = pts_xyz[:, j]
    pts["intensity"] = inten[u_idx, c_idx]
    pts["ring"] = ids[u_idx]
    pts["timestamp"] = times[u_idx, c_idx] * 1e-9
    shape = (1, pts.size) if dense else (height, width)
    cloud = make_cloud(pts, height=shape[0], width=shape[1], stamp_ns=int(times.min()),
                       frame_id=scan.header.frame_id)
    return cloud, pts_xyz[good]


@pytest.mark.parametrize("dense", [True, False])
@pytest.mark.parametrize("name", ["velodyne_vlp32", "hesai_xt32", "hesai_pandar64"])
def test_rslidar_xyzirt_cloud(name: str, dense: bool) -> None:
    scan, info = middle_scan(name)
    cloud, truth = rslidar_cloud(scan, info, dense=dense)
    if not dense:
        assert cloud.height == info.height and truth.shape[0] < cloud.width * cloud.height
    back, est = pc.from_pointcloud2(cloud, as_dataclass=True)
    lidarscan.validate(back, est)
    check_reimport(cloud, truth, back, est)
    assert back.height >= 0.95 * info.height
    err = pc.estimation_error(cloud, back, est)
    assert err.matched >= KEPT * err.points and err.max_time_ns is not None \
        and err.max_time_ns < 1000, err


def _padded(pts: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """The points with two unknown fields in between and after (a driver's extras)."""
    names = list(pts.dtype.names) + ["label", "quality"]
    formats = [pts.dtype.fields[n][0].str for n in pts.dtype.names] + ["<u4", "<f8"]
    offsets = [pts.dtype.fields[n][1] for n in pts.dtype.names] + [28, 40]
    out = np.zeros(pts.size, np.dtype({"names": names, "formats": formats, "offsets": offsets,
                                       "itemsize": 56}))
    for n in pts.dtype.names:
        out[n] = pts[n]
    out["label"] = np.arange(pts.size) % 5
    out["quality"] = 0.5
    return out


@pytest.mark.parametrize("variant", ["bigendian", "padded", "row_pad"])
def test_velodyne_cloud_byte_order_padding_and_extra_fields(variant: str) -> None:
    scan, info = middle_scan("velodyne_vls128")
    cloud, truth = dc.driver_cloud(scan, info, "velodyne")
    pts = pc.read_points(cloud).reshape(-1)
    if variant == "padded":
        pts = _padded(pts)
    rows = 4 if variant == "row_pad" else 1
    pts = pts[: pts.size // rows * rows]
    again = make_cloud(pts, height=rows, width=pts.size // rows, stamp_ns=lidarscan.to_ns(
        cloud.header.stamp), bigendian=variant == "bigendian",
        row_pad=3 if variant == "row_pad" else 0)
    back, est = pc.from_pointcloud2(again, as_dataclass=True)
    lidarscan.validate(back, est)
    check_reimport(again, truth[: pts.size], back, est)


def velodyne_organized_cloud(scan: Any, info: Any) -> tuple[Any, np.ndarray[Any, Any]]:
    """The first return of a decoded scan as velodyne_pointcloud's organized cloud."""
    proj = lidarscan.make_projector(info)
    stamp = lidarscan.to_ns(scan.header.stamp)
    times = proj.pixel_times(scan) + np.int64(stamp)
    rng_m, inten = dc._returns(scan, info)[0]
    xyz = proj.xyz(rng_m, tables=proj.tables_for(scan)).astype(np.float64)
    height, width = rng_m.shape
    by_ring = np.argsort(np.asarray(info.vertical_angles), kind="stable")   # ring 0 lowest
    pts = np.zeros((width, height), dc.DTYPES["velodyne"])       # (firings, rings)
    cell = xyz[by_ring].transpose(1, 0, 2)                        # (W, H, 3)
    good = np.isfinite(rng_m[by_ring].T) & np.all(np.isfinite(cell), -1)
    cell = np.where(good[..., None], cell, np.nan)
    for j, axis in enumerate("xyz"):
        pts[axis] = cell[..., j]
    pts["intensity"] = inten[by_ring].T
    pts["ring"] = np.arange(height)[None, :]
    start = int(times.min())
    pts["time"] = (times[by_ring].T - start) * 1e-9
    cloud = make_cloud(pts.reshape(-1), height=width, width=height, stamp_ns=start,
                       frame_id=scan.header.frame_id)
    return cloud, cell[good]


@pytest.mark.parametrize("name", ["velodyne_vlp32", "velodyne_vls128"])
def test_velodyne_organized_cloud(name: str) -> None:
    scan, info = middle_scan(name)
    cloud, truth = velodyne_organized_cloud(scan, info)
    back, est = pc.from_pointcloud2(cloud, as_dataclass=True)
    lidarscan.validate(back, est)
    check_reimport(cloud, truth, back, est)
    assert back.height >= 0.95 * info.height


@pytest.mark.parametrize("bad", ["half", "nan"])
def test_float_ring_field_without_whole_beam_numbers_is_refused(bad: str) -> None:
    """A float ``ring`` holding something else (halves: two beams would share a row; NaN) is
    refused naming the field, never truncated into rows."""
    firings, lasers = 900, 16
    k, c = np.arange(firings * lasers) % lasers, np.arange(firings * lasers) // lasers
    elev, az = np.radians(-15.0 + 2.0 * k), np.radians(-0.4 * c)
    pts = np.zeros(k.size, np.dtype({"names": ["x", "y", "z", "ring"],
                                     "formats": ["<f4", "<f4", "<f4", "<f4"]}))
    pts["x"], pts["y"] = 10 * np.cos(elev) * np.cos(az), 10 * np.cos(elev) * np.sin(az)
    pts["z"] = 10 * np.sin(elev)
    pts["ring"] = k * 0.5 if bad == "half" else k
    if bad == "nan":
        pts["ring"][7] = np.nan
    cloud = make_cloud(pts, height=1, width=pts.size, stamp_ns=10**18)
    with pytest.raises(lidarscan.errors.ConversionError, match="ring.*whole beam numbers"):
        pc.from_pointcloud2(cloud)
    pts["ring"] = k                                               # whole numbers: fine
    scan, _ = pc.from_pointcloud2(make_cloud(pts, height=1, width=pts.size, stamp_ns=10**18),
                                  as_dataclass=True)
    assert scan.height == lasers
