"""Mapping to vendor messages: LidarScan/LidarInfo field by field against what vendors publish.

Two tables for ``docs/proposal.md`` ("Mapping to vendor messages"):

* ``vendor-draft``: against Ouster's April 2026 draft (``lidar_msgs`` as filled by ouster-ros
  PR #536, commit b158e4d, and read by ``lidar-conversions``): what maps, what is lost in each
  direction;
* ``vendor-clouds``: against the point clouds and images drivers publish today (ouster-ros
  ``original`` point and image topics, velodyne_pointcloud XYZIRT, Nebula ``PointXYZIRCAEDT``):
  where each of their per-point fields comes from in a LidarScan + LidarInfo, and what a
  LidarScan cannot give them.

The tables are facts read from the sources listed in :data:`SOURCES` (each cell that could not
be confirmed says so); the numbers in them are computed here (bytes per point from the field
lists, the float32 angle error on the real Ouster metadata), so a change of either makes
``--check`` fail until the document is regenerated.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from converters.edge.evidence._common import Block, table

__all__ = ["POINT_TYPES", "SOURCES", "blocks", "float32_angle_error", "point_bytes"]

#: short name -> URL (and the revision read) of every source the tables cite
SOURCES: dict[str, str] = {
    "draft-driver": "https://github.com/ouster-lidar/ouster-ros/pull/536 (commit b158e4d, "
                    "`ouster-ros/src/ouster_lidar_ros_msgs.cpp`, `os_driver_node.cpp`)",
    "draft-msgs": "https://github.com/ouster-lidar/lidar-msgs (README; the `.msg` files "
                  "themselves were not retrieved)",
    "draft-conv": "https://github.com/ouster-lidar/lidar-conversions "
                  "(`src/lidar_scan_conversions.cpp`)",
    "ouster-ros": "https://github.com/ouster-lidar/ouster-ros (rolling-devel eaaf35d: "
                  "`include/ouster_ros/os_point.h`, `src/image_processor.h`, "
                  "`src/os_image_node.cpp`, `src/os_ros.cpp`)",
    "velodyne": "https://github.com/ros-drivers/velodyne "
                "(`velodyne_pointcloud/src/lib/organized_cloudXYZIRT.cpp`, "
                "`pointcloudXYZIRT.cpp`)",
    "nebula": "https://github.com/tier4/nebula (`docs/point_types.md`)",
}

#: PointField sizes in bytes (datatype name -> size)
_SIZE = {"int8": 1, "uint8": 1, "int16": 2, "uint16": 2, "int32": 4, "uint32": 4,
         "float32": 4, "float64": 8}

#: point type -> (fields (name, type), point_step as published or None if not confirmed)
POINT_TYPES: dict[str, tuple[list[tuple[str, str]], int | None]] = {
    "ouster-ros `original`": ([("x", "float32"), ("y", "float32"), ("z", "float32"),
                               ("intensity", "float32"), ("t", "uint32"),
                               ("reflectivity", "uint16"), ("ring", "uint16"),
                               ("ambient", "uint16"), ("range", "uint32")], 48),
    "velodyne XYZIRT": ([("x", "float32"), ("y", "float32"), ("z", "float32"),
                         ("intensity", "float32"), ("ring", "uint16"), ("time", "float32")], 22),
    "Nebula PointXYZIRCAEDT": ([("x", "float32"), ("y", "float32"), ("z", "float32"),
                                ("intensity", "uint8"), ("return_type", "uint8"),
                                ("channel", "uint16"), ("azimuth", "float32"),
                                ("elevation", "float32"), ("distance", "float32"),
                                ("time_stamp", "uint32")], None),
}


def point_bytes(name: str) -> tuple[int, int | None]:
    """(sum of the field sizes, published point_step or None) of a point type, bytes."""
    fields, step = POINT_TYPES[name]
    return sum(_SIZE[t] for _, t in fields), step


def float32_angle_error(metadata: Any = None, at_m: float = 100.0) -> float:
    """Largest point displacement (mm at ``at_m``) from storing the angle tables as float32.

    The draft's driver casts ``horizontal_angles``, ``vertical_angles`` and
    ``beam_azimuth_angles`` to float (``static_cast<float>``); this projects every pixel of the
    real Ouster metadata at ``at_m`` metres with float64 tables and with the same tables rounded
    to float32 (everything else equal) and returns the largest distance between the two.

    Args:
        metadata: one Ouster metadata JSON path (default: every fixture, the worst is returned).
        at_m: range of every pixel, metres.
    """
    import dataclasses

    from converters.edge.evidence._common import ouster_files, ouster_info
    from lidarscan.geometry import exact_xyz
    metas = [metadata] if metadata is not None else [m for m, _ in ouster_files()]
    worst = 0.0
    for meta in metas:
        info = ouster_info(meta)
        rounded = dataclasses.replace(info, **{
            f: np.asarray(getattr(info, f), np.float64).astype(np.float32).astype(np.float64)
            for f in ("horizontal_angles", "vertical_angles", "beam_azimuth_offsets")})
        ranges = np.full((int(info.height), int(info.width)), at_m, np.float32)
        diff = np.linalg.norm(exact_xyz(info, ranges) - exact_xyz(rounded, ranges), axis=-1)
        worst = max(worst, float(diff.max()) * 1000.0)
    return worst


def _draft_table() -> str:
    f32 = float32_angle_error()
    rows = [
        ("`header.stamp` (scan)", "time of measurement column 0",
         "set to the driver's scan time", "maps"),
        ("`header.stamp` (info)", "version key", "not set (zero)",
         "the draft's info has no version: lost"),
        ("`header.frame_id`", "frame of the projected points",
         "the driver's lidar frame (`os_lidar`)", "maps, with `lidar_to_sensor_transform` = "
         "identity; here the frame can also be `os_sensor` (transform in the info)"),
        ("`lidar_info_time`", "link to the info version", "✖ (no link)",
         "draft → here: the receiver must assume the latest info (§5: misprojections)"),
        ("`height`, `width`", "grid", "same", "maps"),
        ("`is_bigendian`", "byte order", "same (always false)", "maps"),
        ("`is_destaggered`", "column order flag", "✖; published staggered (the destagger call "
         "is commented out)", "draft → here: `false` (correct for the draft's data)"),
        ("`column_time_offsets`", "ns per measurement column", "✖",
         "here → draft: lost (no deskew); draft → here: empty, nominal "
         "`column_time_increment` only"),
        ("`column_azimuth_angles`", "measured azimuth per firing (Velodyne/Hesai)", "✖",
         "here → draft: lost for sensors that measure it"),
        ("`channels[].name`", "`range`, `intensity`, `reflectivity`, `ambient`, `flags`, "
         "`range2`…", "lowercased SDK names sorted alphabetically, e.g. `flags`, `near_ir`, `range`, "
         "`reflectivity`, `signal` (+`…2` for the second return)",
         "renames only: `signal` → `intensity`, `near_ir` → `ambient`"),
        ("`channels[].datatype`, `offset`, `count`", "PointField ids, planar blocks",
         "same ids and layout; SDK UINT64/INT64 fields dropped, CHAR → UINT8", "maps"),
        ("`range` channel", "FLOAT32 m (or integer × `range_multiplier`)",
         "UINT32 mm, `range_multiplier` 0.001 (a TODO says SI metres were agreed)",
         "maps losslessly either way (§3: every native value is recovered from float32)"),
        ("`vertical_angles`", "φ per row, float64", "same meaning, float32 in the driver",
         f"float32 angles move points by at most {f32:.3f} mm at 100 m (all fixtures): "
         "negligible"),
        ("`horizontal_angles`", "α per measurement column, float64",
         "2π − c·2π/W, float32; or `horizontal_fov_min/max` interpolated inclusively",
         "explicit table maps; the FOV fallback duplicates the end column (§4)"),
        ("`beam_azimuth_offsets`", "β per row", "`beam_azimuth_angles` (same sign convention)",
         "maps"),
        ("`vertical_fov_min/max`, `horizontal_fov_min/max`", "✖ (explicit tables only)",
         "float32 fallbacks, interpolated inclusively (the vertical one puts row 0 at the bottom)",
         "here → draft: computed from the tables"),
        ("`pixel_azimuth_angles`, `pixel_altitude_angles`", "per-pixel directions (DF, tilting "
         "lasers)", "✖; DF per-pixel tables row-averaged", "draft loses per-pixel geometry"),
        ("`beam_origins`, `beam_range_offsets`", "beam-origin offset", "✖",
         "draft loses mm (OS-1/OS-2) to cm (OS-0) (§4)"),
        ("`lidar_to_sensor_transform`", "lidar → frame_id", "✖ (frame = lidar frame; TF "
         "published separately)", "here → draft: published as TF instead"),
        ("`pixel_shift_by_row`", "stagger", "✖", "draft → here: needed to destagger; "
         "must come from the vendor metadata"),
        ("`beam_time_offsets`, `column_time_increment`", "per-beam and nominal column time",
         "\"timing fields\" in the README, not filled by the driver; names not confirmed",
         "not confirmed"),
        ("`range_multiplier`, `range_offset`", "integer range decoding", "same", "maps"),
        ("`range_min`, `range_max`", "REP 117 limits", "✖", "draft → here: 0 = unknown"),
        ("`vendor`, `model`, `serial_number`, `firmware_version`, `vendor_metadata`",
         "identification, verbatim metadata", "✖ (ouster-ros keeps the JSON on its latched "
         "`metadata` topic)", "draft → here: filled from that JSON"),
        ("`beam_ids`", "vendor ring number per row", "✖ (row index)", "maps (empty = row index)"),
    ]
    return table(["field (here)", "meaning here", "Ouster draft (PR #536 / lidar_msgs)",
                  "mapping, and what is lost"], rows, ["l", "l", "l", "l"])


#: per-point field -> (ouster-ros original, velodyne XYZIRT, Nebula, source in LidarScan/Info)
_CLOUD_ROWS = [
    ("x, y, z", "float32, in `point_cloud_frame` (`os_lidar` in the shipped configs, or "
     "`os_sensor`)", "float32", "float32",
     "projected from `range` with the LidarInfo geometry (`lidarscan.geometry`)"),
    ("range / distance", "`range` uint32 mm", "✖", "`distance` float32 m",
     "`range` channel (float32 m, or native integer × `range_multiplier`)"),
    ("intensity", "`intensity` float32 (= SIGNAL)", "`intensity` float32", "`intensity` uint8",
     "`intensity` channel in its native type (uint16 Ouster, uint8 Velodyne/Hesai)"),
    ("reflectivity, ambient", "`reflectivity` uint16, `ambient` uint16 (= NEAR_IR)", "✖", "✖",
     "`reflectivity`, `ambient` channels"),
    ("ring / channel", "`ring` uint16, 0 = top", "`ring` uint16, 0 = lowest",
     "`channel` uint16", "the row; vendor numbering in `LidarInfo.beam_ids`"),
    ("per-point time", "`t` uint32 ns from column 0", "`time` float32 s, relative to the "
     "stamp (≤ 0: stamp = last packet)", "`time_stamp` uint32 ns, relative to the cloud stamp",
     "`column_time_offsets[c]` + `beam_time_offsets[u]` (int64 ns from `header.stamp`)"),
    ("azimuth, elevation", "✖ (in x, y)", "✖ (in x, y)", "`azimuth`, `elevation` float32 rad "
     "per point", "`horizontal_angles`/`column_azimuth_angles` + `beam_azimuth_offsets`; "
     "`vertical_angles`"),
    ("return", "second return → second cloud `points2`", "dual returns as separate points "
     "(not confirmed)", "`return_type` uint8 per point (which echo: first, last, strongest…)",
     "`range2`… channels (or `count` 2) number the returns; the echo kind only as an extra "
     "uint8 channel (no canonical name)"),
    ("no return", "pixel kept (organized H×W, destaggered), `range` 0", "NaN point (organized: "
     "one row per firing, width = lasers, the transpose of the grid)", "dropped (not "
     "confirmed for every sensor)", "`range` +Inf (REP 117); the grid position is kept"),
    ("geometry, stagger, link", "`metadata` topic (std_msgs/String JSON, latched), no link",
     "calibration file, not published", "calibration file, not published (not confirmed)",
     "LidarInfo (latched) + `lidar_info_time`"),
]


def _clouds_table() -> str:
    rows = [list(r) for r in _CLOUD_ROWS]
    sizes = ["ouster-ros `original`", "velodyne XYZIRT", "Nebula PointXYZIRCAEDT"]
    cells = []
    for name in sizes:
        total, step = point_bytes(name)
        if step is None:
            cells.append(f"{total} B of fields (point_step not confirmed)")
        else:
            pad = ", the rest padding" if step > total else ""
            cells.append(f"{step} B/point ({total} B of fields{pad})")
    rows.append(["bytes per point"] + cells + ["10 B/pixel for the five Ouster channels "
                                               "(sizes of whole messages: §1)"])
    return table(["per-point field", "ouster-ros `original`", "velodyne_pointcloud XYZIRT",
                  "Nebula `PointXYZIRCAEDT` (Hesai, Velodyne, …)",
                  "from a LidarScan + LidarInfo"], rows, ["l", "l", "l", "l", "l"])


def _images_text() -> str:
    return ("ouster-ros images (`os_image` node): `range_image`, `signal_image`, `reflec_image`, "
            "`nearir_image` (+ `rgb_image` on RGB profiles; `…2` topics for the second return), "
            "all `sensor_msgs/Image` MONO16 H×W destaggered; `range_image` is range in 4 mm "
            "steps with returns beyond 65 535 × 4 mm (≈ 262 m) zeroed, the other three are "
            "auto-exposed (scaled per frame, lossy). Each is one channel block of a LidarScan "
            "with a lossy encoding; a LidarScan carries the same channels losslessly in one "
            "message, and each image is computable from it (e.g. `compression.png_image` "
            "reproduces the 4 mm range image).")


def sources_text() -> str:
    """The sources list (markdown bullets)."""
    return "\n".join(f"- {name}: {url}" for name, url in SOURCES.items())


def blocks() -> list[Block]:
    """The ``vendor-draft`` and ``vendor-clouds`` blocks (deterministic)."""
    return [Block("vendor-draft", _draft_table()),
            Block("vendor-clouds", _clouds_table() + "\n\n" + _images_text()
                  + "\n\nSources:\n\n" + sources_text())]
