"""Real lidar clouds in the point layouts of the ROS drivers, built from decoded Nebula recordings.

The packet decoders (converters.sources.velodyne, converters.sources.hesai.decoder; checked against Nebula's ground-truth
PCDs in tests/test_velodyne_packets.py and tests/test_hesai.py) turn the bags of
tests/data/nebula into (LidarScan, LidarInfo); :func:`driver_cloud` writes one decoded scan as the
unorganized PointCloud2 a driver publishes:

- ``velodyne``: velodyne_pointcloud (x, y, z, intensity float32, ring uint16 = 0 for the lowest
  beam, time float32 s relative to the cloud stamp); ``velodyne_notime`` the same without time.
  Order: firing by firing, each return's block in turn, lasers in firing order.
- ``hesai_ros``: the Hesai ROS driver (x, y, z, intensity float32, ring uint16 = laser id,
  timestamp float64 absolute s). Same order.
- ``nebula``: Nebula's point type (x, y, z float32, intensity uint8, return_type uint8, channel
  uint16 = laser id, azimuth, elevation, distance float32, time_stamp uint32 ns relative to the
  stamp). Order: firing by firing, laser by laser, its returns; an identical second return is
  dropped (as Nebula does).

No-return pixels are omitted; dual return gives two points per firing. The points are the
scan's rays (``geometry_reference.checked_tables``: the project's tables after a check against
the plain-loop beam model) times its ranges, so a projector bug cannot hide in the ground truth.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import numpy as np

import lidarscan
from lidarscan.scan import channel_names, range_m

DATA = Path(__file__).parent / "data" / "nebula"
KINDS = ("velodyne", "velodyne_notime", "hesai_ros", "nebula")

_F4, _U2 = "<f4", "<u2"
DTYPES = {
    "velodyne": np.dtype({"names": ["x", "y", "z", "intensity", "ring", "time"],
                          "formats": [_F4, _F4, _F4, _F4, _U2, _F4],
                          "offsets": [0, 4, 8, 16, 20, 24], "itemsize": 32}),
    "velodyne_notime": np.dtype({"names": ["x", "y", "z", "intensity", "ring"],
                                 "formats": [_F4, _F4, _F4, _F4, _U2],
                                 "offsets": [0, 4, 8, 16, 20], "itemsize": 32}),
    "hesai_ros": np.dtype({"names": ["x", "y", "z", "intensity", "ring", "timestamp"],
                           "formats": [_F4, _F4, _F4, _F4, _U2, "<f8"],
                           "offsets": [0, 4, 8, 16, 20, 24], "itemsize": 32}),
    "nebula": np.dtype({"names": ["x", "y", "z", "intensity", "return_type", "channel",
                                  "azimuth", "elevation", "distance", "time_stamp"],
                        "formats": [_F4, _F4, _F4, "u1", "u1", _U2, _F4, _F4, _F4, "<u4"],
                        "offsets": [0, 4, 8, 12, 13, 14, 16, 20, 24, 28], "itemsize": 32}),
}


@functools.lru_cache(maxsize=None)
def decoded(name: str) -> tuple[tuple[Any, Any], ...]:
    """(scan, info) of every rotation of a Nebula recording, decoded by our packet decoders."""
    if name.startswith("velodyne"):
        import tempfile

        from test_velodyne_packets import RECORDINGS, _read_bag

        from converters.sources import velodyne
        calib_name, _, settings = RECORDINGS[name]
        with tempfile.TemporaryDirectory() as tmp:
            messages = _read_bag(DATA / name, Path(tmp))
        packets = [p for _, pk in messages for p in pk]
        calib = velodyne.load_calibration(DATA / name / calib_name)
        # the manuals' per-beam geometry (velodyne_pointcloud's): the estimator fits column
        # azimuths + beam offsets, which Nebula's per-pixel azimuths (the default) are not
        return tuple(velodyne.decode_packets(packets, calib, cut_angle_deg=settings["cut"],
                                             azimuth_model="manual", as_dataclass=True))
    from test_hesai import _decode_recording
    return tuple(_decode_recording(name))


def full_scans(name: str) -> list[tuple[Any, Any]]:
    """The decoded rotations that are complete (not the partial first and last)."""
    scans = list(decoded(name))
    return scans[1:-1] if len(scans) > 2 else scans


def _returns(scan: Any, info: Any) -> list[tuple[np.ndarray[Any, Any], np.ndarray[Any, Any]]]:
    """[(range m (H, W) with inf for no return, intensity (H, W))] per return."""
    names = channel_names(scan)
    out = []
    for rng, inten in (("range", "intensity"), ("range2", "intensity2")):
        if rng not in names:
            continue
        r = np.asarray(range_m(scan, info, rng), np.float64)
        r = np.where(np.isfinite(r) & (r > 0), r, np.inf)
        i = (lidarscan.scan.channel(scan, inten).astype(np.float64) if inten in names
             else np.zeros(r.shape))
        out.append((r, i))
    return out


def driver_cloud(scan: Any, info: Any, kind: str) -> tuple[Any, np.ndarray[Any, Any]]:
    """One decoded scan as the unorganized cloud of a driver (see the module docstring).

    Returns:
        (cloud, xyz): the sensor_msgs/PointCloud2 and the (N, 3) float64 decoded points it holds,
        in cloud order (the ground truth of the re-import).
    """
    from cloud_oracles import make_cloud
    from geometry_reference import checked_tables

    proj = lidarscan.make_projector(info)
    tables = checked_tables(scan, info)          # held to the plain-loop beam model
    stamp = lidarscan.to_ns(scan.header.stamp)
    times = proj.pixel_times(scan) + np.int64(stamp)             # (H, W) absolute ns
    height, width = times.shape
    ids = np.asarray(info.beam_ids, np.int64)
    fire = np.argsort(ids, kind="stable")                        # rows in laser-id order
    elev_rank = np.empty(height, np.int64)
    elev_rank[np.argsort(np.asarray(info.vertical_angles), kind="stable")] = np.arange(height)
    rets = _returns(scan, info)
    xyz = [proj.xyz(r, tables=tables).astype(np.float64) for r, _ in rets]
    ncomp = len(rets)
    # per-point (return, row, column) in driver order
    c_idx, k_idx, u_idx = np.meshgrid(np.arange(width), np.arange(ncomp), fire, indexing="ij")
    if kind == "nebula":
        c_idx, u_idx, k_idx = np.meshgrid(np.arange(width), fire, np.arange(ncomp),
                                          indexing="ij")
    c_idx, k_idx, u_idx = c_idx.ravel(), k_idx.ravel(), u_idx.ravel()
    rng = np.stack([r for r, _ in rets])[k_idx, u_idx, c_idx]
    keep = np.isfinite(rng)
    if kind == "nebula" and ncomp == 2:
        first = np.stack([r for r, _ in rets])[0, u_idx, c_idx]
        keep &= ~((k_idx == 1) & (rng == first))
    c_idx, k_idx, u_idx, rng = c_idx[keep], k_idx[keep], u_idx[keep], rng[keep]
    pts_xyz = np.stack(xyz)[k_idx, u_idx, c_idx]
    keep = np.all(np.isfinite(pts_xyz), -1)
    c_idx, k_idx, u_idx, rng, pts_xyz = (a[keep] for a in (c_idx, k_idx, u_idx, rng, pts_xyz))
    inten = np.stack([i for _, i in rets])[k_idx, u_idx, c_idx]
    t = times[u_idx, c_idx]
    base = kind.split("_notime")[0]
    pts = np.zeros(c_idx.size, DTYPES[kind])
    for j, axis in enumerate("xyz"):
        pts[axis] = pts_xyz[:, j]
    cloud_stamp = int(t.min()) if t.size else stamp
    if base in ("velodyne", "hesai_ros"):
        pts["intensity"] = inten
        pts["ring"] = elev_rank[u_idx] if base == "velodyne" else ids[u_idx]
    if kind == "velodyne":
        pts["time"] = (t - cloud_stamp) * 1e-9
    elif kind == "hesai_ros":
        pts["timestamp"] = t * 1e-9
    elif kind == "nebula":
        pts["intensity"] = np.clip(inten, 0, 255)
        pts["return_type"] = k_idx + 1
        pts["channel"] = ids[u_idx]
        pts["azimuth"] = np.mod(np.arctan2(pts_xyz[:, 1], pts_xyz[:, 0]), 2 * np.pi)
        pts["elevation"] = np.arcsin(np.clip(pts_xyz[:, 2] / np.maximum(
            np.linalg.norm(pts_xyz, axis=1), 1e-9), -1, 1))
        delta = np.asarray(info.beam_range_offsets, np.float64)
        pts["distance"] = rng + (delta[u_idx] if delta.size else 0.0)
        pts["time_stamp"] = t - cloud_stamp
    cloud = make_cloud(pts, height=1, width=pts.size, stamp_ns=cloud_stamp,
                       frame_id=scan.header.frame_id)
    return cloud, pts_xyz
