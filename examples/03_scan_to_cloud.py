"""Turn a LidarScan of a real sensor geometry (Ouster OS-1-128) into a PointCloud2.

Run: python examples/03_scan_to_cloud.py
"""

import numpy as np

import lidarscan
from converters.demo import METADATA_PATH, SimulatedLidar3D, pose_matrix, room_scene
from converters.ouster import info_from_metadata
from converters.pointcloud2 import PRESETS, PointCloud2Converter, read_points

# The LidarInfo of a real OS-1-128 (2048 x 10) from its metadata JSON (shipped in the package).
info = info_from_metadata(METADATA_PATH, stamp_ns=1_000_000_000, frame_id="os_sensor")
print(f"{info.vendor} {info.model}: {info.height} beams x {info.width} columns")

# One scan of the demo room, the sensor 0.4 m above the floor (exact ray casting).
lidar = SimulatedLidar3D(info, room_scene())
scan = lidar.scan(pose_matrix(-2.0, 0.0, 0.4), stamp_ns=2_000_000_000, as_dataclass=False)

# A converter holds the per-sensor tables: build it once, call convert() for every scan.
xyzi = PointCloud2Converter(info)                      # x, y, z, intensity; organized H x W
cloud = xyzi.convert(scan)
points = read_points(cloud)                            # zero-copy structured (H, W) view
print(f"PointCloud2 {cloud.height}x{cloud.width}, fields "
      f"{[f.name for f in cloud.fields]}, {len(cloud.data)} bytes "
      f"(LidarScan: {len(lidarscan.encode(scan))} bytes)")
valid = np.isfinite(points["x"])
print(f"{valid.sum()} points, z from {points['z'][valid].min():.2f} "
      f"to {points['z'][valid].max():.2f} m (os_sensor frame)")

# Driver-compatible layouts, e.g. what ouster-ros publishes (48-byte points with t and ring).
ouster = PointCloud2Converter(info, preset="ouster").convert(scan)
print(f"preset 'ouster': point_step {ouster.point_step}, fields "
      f"{[f.name for f in ouster.fields]}; presets available: {sorted(PRESETS)}")
