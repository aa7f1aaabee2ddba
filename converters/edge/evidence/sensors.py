"""Question 4b: on real sensors, is the LidarScan + LidarInfo geometry exact?

Per real recording in ``tests/data`` (see their NOTICE files), the scan and info the project's
decoders make are projected with the project's projector (:func:`lidarscan.make_projector`) and
compared with the points of someone else's decoder:

- Ouster (``tests/data/ouster``, frames decoded by ouster-sdk): the vendor's "range to XYZ"
  formula (the one ouster-sdk's ``XYZLut`` implements, written here from the metadata JSON in
  float64, ``tests/test_ouster.py`` has the same oracle) on the same pixels: the error is per
  pixel, every return of every channel (``range``, ``range2``).
- Velodyne VLP-32C, VLS-128, Hesai PandarXT32, Pandar64, PandarQT64 (``tests/data/nebula``):
  the point cloud Nebula (tier4/nebula, the Autoware driver) published for one rotation. The
  points do not correspond one to one, so the distance is the nearest-neighbour distance both
  ways (Nebula -> ours, ours -> Nebula), inside Nebula's range (and, VLP-32C, azimuth) limits.
  Velodyne: the default decoder (Nebula's per-pixel azimuths in the scan's ``azimuth``
  channel, ``converters/sources/velodyne/``) and, beside it, ``azimuth_model="manual"`` (the manuals'
  firing times as per-beam offsets: the same ranges and elevations, other azimuths). Hesai:
  Nebula cuts rotations by corrected azimuth, the decoder by firing, so Nebula's points are
  looked up in the matched rotation and its two neighbours (``tests/test_hesai.py``).

Sizes: the LidarScan CDR of that rotation (every pixel, both returns when sent) against the
driver's PointCloud2 for the same points: Nebula's ``PointXYZIRCAEDT`` (32-byte points), the
velodyne_pointcloud XYZIRT cloud (22 bytes, packed), HesaiLidar_ROS_2.0 (26 bytes, packed),
ouster-ros ``original`` (48 bytes, organized H x W).

Every recording is read once (with :mod:`converters.sources.bags`, the project's rosbag2 reader) and
decoded once per process (:func:`measure` is cached).
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from converters.edge.evidence._common import (
    ROOT,
    Block,
    fmt_int,
    load_frame,
    ouster_files,
    ouster_info,
    pointcloud2_bytes,
    short_name,
    table,
)

__all__ = ["NEBULA", "RECORDINGS", "blocks", "info_fields", "measure", "nearest"]

NEBULA = ROOT / "tests" / "data" / "nebula"

#: folder -> (model label, calibration, Nebula's decoder settings for the ground truth:
#: distance limits in m, block azimuth window in degrees (clockwise) or None, cut angle)
RECORDINGS: dict[str, tuple[str, str, tuple[float, float], tuple[float, float] | None, float]] = {
    "velodyne_vlp32": ("Velodyne VLP-32C", "VLP32.yaml", (0.4, 50.0), (270.0, 90.0), 180.0),
    "velodyne_vls128": ("Velodyne VLS-128", "VLS128.yaml", (0.3, 300.0), None, 0.0),
    "hesai_xt32": ("Hesai PandarXT32", "PandarXT32.csv", (0.05, 120.0), None, 0.0),
    "hesai_pandar64": ("Hesai Pandar64", "Pandar64.csv", (0.3, 200.0), None, 0.0),
    "hesai_qt64": ("Hesai PandarQT64", "PandarQT64.csv", (0.1, 60.0), None, 0.0),
}

TOL = 0.002   # m: "within 2 mm"

#: Nebula's point (nebula_common point_types.hpp, PointXYZIRCAEDT): (name, offset, datatype)
NEBULA_FIELDS = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 2),
                 ("return_type", 13, 2), ("channel", 14, 4), ("azimuth", 16, 7),
                 ("elevation", 20, 7), ("distance", 24, 7), ("time_stamp", 28, 6)]
NEBULA_STEP = 32


# --------------------------------------------------------------------------- nearest points

def nearest(query: np.ndarray[Any, Any], ref: np.ndarray[Any, Any], within: float | None = None
            ) -> np.ndarray[Any, Any]:
    """Exact distance (m) from each query point to its nearest ``ref`` point.

    Args:
        query: (N, 3) points, m.
        ref: (M, 3) points, m, M > 0.
        within: only distances up to this (m) are wanted: larger ones come back as +inf.

    Returns:
        (N,) float64 distances. Grid hashes of growing cell size c: the 2 x 2 x 2 cells nearest
        to a query point hold every point within c / 2 of it, so a neighbour found within c / 2
        is the exact nearest; the others go to the next, coarser grid and finally (unless
        ``within``) to brute force.
    """
    query = np.asarray(query, np.float64).reshape(-1, 3)
    ref = np.asarray(ref, np.float64).reshape(-1, 3)
    best = np.full(len(query), np.inf)
    todo = np.arange(len(query))
    cells = (2 * within,) if within is not None else (0.008, 0.08, 0.8, 8.0)
    for cell in cells:
        if todo.size == 0:
            break
        grid = np.floor(ref / cell).astype(np.int64)
        lo = grid.min(0) - 1
        dims = grid.max(0) - lo + 2

        def key(c: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
            c = np.clip(c - lo, 0, dims - 1)            # outside the box: an empty border cell
            return (c[:, 0] * dims[1] + c[:, 1]) * dims[2] + c[:, 2]

        keys = key(grid)
        order = np.argsort(keys, kind="stable")
        keys, pts = keys[order], ref[order]
        q = query[todo]
        upper = np.floor(q / cell + 0.5).astype(np.int64)    # the 2 cells nearest on each axis
        found = np.full(len(todo), np.inf)
        for dx in (-1, 0):
            for dy in (-1, 0):
                for dz in (-1, 0):
                    k = key(upper + np.array([dx, dy, dz]))
                    j = np.searchsorted(keys, k, "left")
                    stop = np.searchsorted(keys, k, "right")
                    live = np.flatnonzero(j < stop)
                    while live.size:
                        d = np.linalg.norm(pts[j[live]] - q[live], axis=1)
                        found[live] = np.minimum(found[live], d)
                        j[live] += 1
                        live = live[j[live] < stop[live]]
        done = found <= cell / 2
        best[todo[done]] = found[done]
        todo = todo[~done]
    if within is not None:
        return np.where(best <= within, best, np.inf)
    for chunk in np.array_split(todo, max(1, todo.size // 16)):
        if chunk.size:
            d2 = ((query[chunk, None, :] - ref[None, :, :]) ** 2).sum(-1)
            best[chunk] = np.sqrt(d2.min(axis=1))
    return best


# ------------------------------------------------------------------------------ recordings

def _packets(folder: str) -> tuple[list[tuple[int, bytes]], dict[int, int]]:
    """((packet stamp ns, payload) of every packet, receive stamp -> first packet stamp)."""
    from converters.sources.bags import PACKET_TYPES, open_bag
    from lidarscan.mcap import McapMessage

    packets: list[tuple[int, bytes]] = []
    first: dict[int, int] = {}
    for item in open_bag(NEBULA / folder / "bag").messages():
        if isinstance(item, McapMessage) and item.msgtype in PACKET_TYPES:
            scan = PACKET_TYPES[item.msgtype][1](item.payload)
            if scan.packets:
                first.setdefault(item.log_time_ns, scan.packets[0][0])
            packets += [(stamp, bytes(data)) for stamp, data in scan.packets]
    return packets, first


def _truth(folder: str) -> tuple[int, np.ndarray[Any, Any]]:
    """(stamp in the file name, (N, 3) float64 points) of Nebula's binary x y z PCD."""
    path = next((NEBULA / folder).glob("ground_truth_*.pcd"))
    raw = path.read_bytes()
    end = raw.index(b"DATA binary\n") + len(b"DATA binary\n")
    head = raw[:end].decode("ascii")
    if "FIELDS x y z\n" not in head or "SIZE 4 4 4\n" not in head:
        from lidarscan.errors import DecodeError
        raise DecodeError(f"{path.name} header", head[:200], "a binary PCD of float32 x y z")
    count = int(head.split("POINTS ")[1].split()[0])
    points = np.frombuffer(raw, "<f4", count * 3, end).reshape(-1, 3)
    return int(path.stem.rsplit("_", 1)[1]), points.astype(np.float64)


def _cloud_bytes(fields: list[tuple[str, int, int]], step: int, points: int) -> int:
    """CDR bytes of an unorganized PointCloud2 with this field table and ``points`` points."""
    from lidarscan import encode
    from lidarscan.types import Header, Time, message_class
    cloud = message_class("sensor_msgs/msg/PointCloud2")
    field = message_class("sensor_msgs/msg/PointField")
    empty = cloud(header=Header(Time(0, 0), "lidar"), height=1, width=points,
                  fields=[field(name=n, offset=o, datatype=t, count=1) for n, o, t in fields],
                  is_bigendian=False, point_step=step, row_step=step * points, data=b"",
                  is_dense=True)
    return len(encode(empty)) + step * points


def _both_ways(truth: np.ndarray[Any, Any], ours: np.ndarray[Any, Any],
               ours_wide: np.ndarray[Any, Any] | None = None) -> dict[str, float]:
    to_ours = nearest(truth, ours if ours_wide is None else ours_wide)
    to_truth = nearest(ours, truth)
    return {"t_within": float(np.mean(to_ours <= TOL)), "t_median": float(np.median(to_ours)),
            "t_max": float(to_ours.max()), "o_within": float(np.mean(to_truth <= TOL)),
            "o_median": float(np.median(to_truth)), "o_max": float(to_truth.max()),
            "n_truth": len(truth), "n_ours": len(ours)}


def _velodyne_points(scan: Any, info: Any, lo: float, hi: float,
                     window: tuple[float, float] | None) -> np.ndarray[Any, Any]:
    """(N, 3) float64 points of every return inside Nebula's limits: distance (with
    dist_correction) in (lo, hi), block azimuth in the clockwise ``window``."""
    import lidarscan
    projector = lidarscan.make_projector(info)
    clouds = []
    for name in [n for n in ("range", "range2") if n in lidarscan.scan.channel_names(scan)]:
        points = projector.project(scan, info, name)
        rng = lidarscan.scan.range_m(scan, info, name).astype(np.float64) + np.asarray(
            info.beam_range_offsets)[:, None]
        keep = (rng > lo) & (rng < hi) & np.isfinite(points).all(-1)
        if window is not None:
            az = np.mod(-np.degrees(np.asarray(scan.column_azimuth_angles)), 360.0)
            keep &= ((az >= window[0] - 1e-9) | (az <= window[1] + 1e-9))[None]
        clouds.append(points[keep].astype(np.float64))
    return np.concatenate(clouds)


def _velodyne(folder: str) -> list[dict[str, Any]]:
    import lidarscan
    import lidarscan.stamps
    from converters.sources import velodyne
    label, calib_name, (lo, hi), window, cut = RECORDINGS[folder]
    packets, first = _packets(folder)
    stamp, truth = _truth(folder)
    calib = velodyne.load_calibration(NEBULA / folder / calib_name)
    records = []
    index = None
    for variant, model in (("default: Nebula's azimuths (`azimuth` channel)", "nebula"),
                           ("`azimuth_model=\"manual\"`: the manuals' firing times", "manual")):
        results = list(velodyne.decode_packets(packets, calib, cut_angle_deg=cut,
                                               azimuth_model=model, as_dataclass=True))
        if index is None:
            index = min(range(len(results)), key=lambda i: abs(
                lidarscan.stamps.to_ns(results[i][0].header.stamp) - first[stamp]))
        scan, info = results[index]
        lidarscan.validate(scan, info)
        records.append({"sensor": label, "scan": scan, "info": info, "reference": "Nebula",
                        "variant": variant,
                        **_both_ways(truth, _velodyne_points(scan, info, lo, hi, window))})
    return records


def _hesai_points(scan: Any, info: Any, lo: float, hi: float) -> np.ndarray[Any, Any]:
    """(N, 3) float64 points of every return whose range is inside [lo, hi] m."""
    import lidarscan
    projector = lidarscan.make_projector(info)
    names = [n for n in ("range", "range2") if n in lidarscan.scan.channel_names(scan)]
    clouds = []
    for name in names:
        metres = lidarscan.scan.range_m(scan, info, name)
        xyz = projector.project(scan, info, name)
        clouds.append(xyz[(metres >= lo) & (metres <= hi) & np.isfinite(xyz).all(-1)])
    return np.concatenate(clouds).astype(np.float64)


def _hesai(folder: str) -> list[dict[str, Any]]:
    from converters.sources.hesai import decoder as hesai
    label, calib_name, (lo, hi), _, _ = RECORDINGS[folder]
    packets, _ = _packets(folder)
    _, truth = _truth(folder)
    results = list(hesai.decode_packets(packets, NEBULA / folder / calib_name,
                                        as_dataclass=True))
    clouds = [_hesai_points(scan, info, lo, hi) for scan, info in results]
    sample = truth[::50]
    hits = [int(np.sum(nearest(sample, c, TOL) <= TOL)) if len(c) else 0 for c in clouds]
    best = int(np.argmax(hits))
    wide = np.concatenate(clouds[max(0, best - 1):best + 2])
    scan, info = results[best]
    return [{"sensor": label, "scan": scan, "info": info, "reference": "Nebula",
             "variant": "exact", **_both_ways(truth, clouds[best], wide)}]


def _vendor_xyz(meta: dict[str, Any], range_mm: np.ndarray[Any, Any]) -> np.ndarray[Any, Any]:
    """Ouster's range-to-XYZ formula (float64, m) from the metadata JSON (either layout)."""
    if "beam_intrinsics" in meta:
        beams = meta["beam_intrinsics"]
        alt, azi = beams["beam_altitude_angles"], beams["beam_azimuth_angles"]
        b = np.asarray(beams["beam_to_lidar_transform"], float).reshape(4, 4)
        t = np.asarray(meta["lidar_intrinsics"]["lidar_to_sensor_transform"], float)
    else:
        alt, azi = meta["beam_altitude_angles"], meta["beam_azimuth_angles"]
        b = np.eye(4)
        b[0, 3] = meta["lidar_origin_to_beam_origin_mm"]
        t = np.asarray(meta["lidar_to_sensor_transform"], float)
    t = t.reshape(4, 4)
    width = range_mm.shape[1]
    n = b[0, 3] if b[2, 3] == 0 else np.hypot(b[0, 3], b[2, 3])
    encoder = 2 * np.pi - np.arange(width) * 2 * np.pi / width
    theta = encoder[None, :] - np.radians(np.asarray(azi, float))[:, None]
    phi = np.radians(np.asarray(alt, float))[:, None]
    d = np.stack([np.cos(theta) * np.cos(phi), np.sin(theta) * np.cos(phi),
                  np.broadcast_to(np.sin(phi), theta.shape)], -1)
    o = np.stack([b[0, 3] * np.cos(encoder)[None, :] - n * d[..., 0],
                  b[0, 3] * np.sin(encoder)[None, :] - n * d[..., 1], b[2, 3] - n * d[..., 2]],
                 -1)
    r = range_mm.astype(np.float64)[..., None]
    return 0.001 * (r * (d @ t[:3, :3].T) + o @ t[:3, :3].T + t[:3, 3])


def _ouster() -> list[dict[str, Any]]:
    import lidarscan
    from converters.sources.ouster.metadata import scan_from_frame
    out = []
    for meta_path, frame_path in ouster_files():
        if frame_path is None:
            continue
        meta = json.loads(Path(meta_path).read_text())
        frame = load_frame(frame_path)
        info = ouster_info(meta_path)
        scan = scan_from_frame(frame, info, as_dataclass=True)
        projector = lidarscan.make_projector(info)
        errors = []
        for channel, field in (("range", "range_mm"), ("range2", "range2_mm")):
            if field in frame:
                valid = frame[field] > 0
                ours = projector.project(scan, info, channel)
                errors.append(np.linalg.norm(ours[valid] - _vendor_xyz(meta, frame[field])[valid],
                                             axis=1))
        err = np.concatenate(errors)
        stats = {"t_within": float(np.mean(err <= TOL)), "t_median": float(np.median(err)),
                 "t_max": float(err.max()), "n_truth": len(err), "n_ours": len(err)}
        stats.update(o_within=stats["t_within"], o_median=stats["t_median"], o_max=stats["t_max"])
        out.append({"sensor": f"Ouster {short_name(meta_path)}", "scan": scan, "info": info,
                    "reference": "ouster-sdk XYZLut formula, per pixel",
                    "variant": "exact", **stats})
    return out


@lru_cache(maxsize=1)
def measure() -> tuple[dict[str, Any], ...]:
    """One record per (recording, decoder variant); every recording decoded once."""
    records = _ouster()
    for folder in RECORDINGS:
        records += _velodyne(folder) if folder.startswith("velodyne") else _hesai(folder)
    return tuple(records)


# ------------------------------------------------------------------------------ the tables

#: LidarInfo fields that carry the geometry, the timing or the range encoding
GEOMETRY_FIELDS = ("vertical_angles", "horizontal_angles", "beam_azimuth_offsets",
                   "pixel_azimuth_angles", "pixel_altitude_angles", "beam_origins",
                   "beam_range_offsets", "lidar_to_sensor_transform", "pixel_shift_by_row",
                   "beam_time_offsets", "column_time_increment", "beam_ids", "range_multiplier",
                   "range_offset", "range_min", "range_max")


def info_fields(info: Any) -> list[str]:
    """The :data:`GEOMETRY_FIELDS` of ``info`` that differ from their default (empty, zero,
    identity transform, ``range_multiplier`` 1)."""
    used = []
    for name in GEOMETRY_FIELDS:
        value = np.asarray(getattr(info, name), np.float64)
        if name == "lidar_to_sensor_transform":
            flag = value.size == 16 and not (np.array_equal(value, np.eye(4).ravel())
                                             or not value.any())
        elif name == "range_multiplier":
            flag = value.size > 0 and float(value) not in (0.0, 1.0)
        else:
            flag = value.size > 0 and bool(np.any(value != 0))
        if flag:
            used.append(name)
    return used


def _mm(metres: float) -> str:
    mm = metres * 1e3
    if mm >= 100:
        return f"{mm:.0f}"
    if mm >= 1:
        return f"{mm:.1f}"
    return f"{mm:.3f}"


def _pct(x: float) -> str:
    return f"{100 * x:.2f} %"


def _sizes(record: dict[str, Any]) -> tuple[int, list[str]]:
    """(LidarScan CDR bytes, ['driver: bytes'])."""
    from lidarscan import encode
    scan = record["scan"]
    ours = len(encode(scan))
    n = record["n_truth"]
    if record["reference"] == "Nebula":
        vendor = ("velodyne_pointcloud XYZIRT", pointcloud2_bytes("velodyne XYZIRT", 1, n)) \
            if "Velodyne" in record["sensor"] else \
            ("HesaiLidar_ROS_2.0", pointcloud2_bytes("hesai", 1, n))
        drivers = [("Nebula PointXYZIRCAEDT", _cloud_bytes(NEBULA_FIELDS, NEBULA_STEP, n)), vendor]
    else:
        drivers = [("ouster-ros original",
                    pointcloud2_bytes("ouster-ros original", int(scan.height), int(scan.width)))]
    return ours, [f"{name}: {fmt_int(size)} ({size / ours:.1f}×)" for name, size in drivers]


def _label(record: dict[str, Any]) -> str:
    """Sensor name, "(dual return)" when the scan has a second return."""
    import lidarscan
    dual = "range2" in lidarscan.scan.channel_names(record["scan"])
    return record["sensor"] + (" (dual return)" if dual else "")


def blocks(records: tuple[dict[str, Any], ...] | None = None) -> list[Block]:
    """The ``sensors-error`` table, its ``sensors-claims`` sentence, the ``sensors-fields``
    and ``sensors-size`` tables."""
    records = measure() if records is None else records
    rows = []
    for r in records:
        rows.append([_label(r), r["reference"], r["variant"],
                     f"{fmt_int(r['n_truth'])} / {fmt_int(r['n_ours'])}",
                     _pct(r["t_within"]), _mm(r["t_median"]), _mm(r["t_max"]),
                     _pct(r["o_within"]), _mm(r["o_median"]), _mm(r["o_max"])])
    error = table(["sensor", "reference points", "our decoder", "points (ref / ours)",
                   "ref→ours ≤ 2 mm", "median (mm)", "max (mm)", "ours→ref ≤ 2 mm",
                   "median (mm)", "max (mm)"], rows,
                  ["l", "l", "l", "r", "r", "r", "r", "r", "r", "r"])
    seen: dict[str, dict[str, Any]] = {}
    for r in records:
        seen.setdefault(_label(r), r)
    fields = table(["sensor", "LidarScan (H × W, channels)", "LidarInfo fields set"],
                   [[name, f"{r['scan'].height} × {r['scan'].width}, "
                     + ", ".join(c.name for c in r["scan"].channels),
                     ", ".join(f"`{f}`" for f in info_fields(r["info"]))]
                    for name, r in seen.items()], ["l", "l", "l"])
    size_rows = []
    for name, r in seen.items():
        ours, drivers = _sizes(r)
        organized = r["reference"] != "Nebula"
        points = int(r["scan"].height) * int(r["scan"].width) if organized else r["n_truth"]
        size_rows.append([name, fmt_int(points) + (" (H × W)" if organized else ""),
                          fmt_int(ours), "; ".join(drivers)])
    sizes = table(["sensor", "points in the driver's cloud", "LidarScan CDR (bytes)",
                   "driver's PointCloud2 CDR (bytes, × LidarScan)"], size_rows,
                  ["l", "r", "r", "l"])
    return [Block("sensors-error", error), Block("sensors-claims", claims(records)),
            Block("sensors-fields", fields), Block("sensors-size", sizes)]


def claims(records: tuple[dict[str, Any], ...]) -> str:
    """The sentence of numbers the section's reading relies on, from the error table."""
    def pick(vendor: str, variant: str | None = None) -> list[dict[str, Any]]:
        return [r for r in records if r["sensor"].startswith(vendor)
                and (variant is None or r["variant"].startswith(variant))]

    ouster, hesai = pick("Ouster"), pick("Hesai")
    default, manual = pick("Velodyne", "default"), pick("Velodyne", "`azimuth_model")

    def span(rs: list[dict[str, Any]]) -> str:
        values = [100 * r[k] for r in rs for k in ("t_within", "o_within")]
        return f"{min(values):.1f}–{max(values):.1f} %"

    return (f"Measured: every Ouster return within "
            f"{_mm(max(r['t_max'] for r in ouster))} mm of the vendor formula; every Nebula "
            f"point of the {len(hesai)} Hesai models within "
            f"{_mm(max(r['t_max'] for r in hesai))} mm of one of ours, and "
            f"{span(hesai)} of ours within 2 mm of Nebula's; Velodyne: {span(default)} of the "
            f"points within 2 mm (both ways) as decoded by default, {span(manual)} with the "
            "manuals' firing times.")
