"""Cut height slices out of a 3D scan and merge one with a plain 2D lidar.

Run: python examples/04_slices_and_merger.py
"""

import math

import numpy as np

from converters.demo import (
    METADATA_PATH,
    SimulatedLaser2D,
    SimulatedLidar3D,
    pose_matrix,
    room_scene,
)
from converters.laserscan import SliceConverter
from converters.merger import LaserScanMerger, MergerInput
from converters.ouster import info_from_metadata

scene = room_scene()
robot = pose_matrix(-2.0, 0.2, 0.0)                  # base_link in the room
lidar_mount = pose_matrix(0.0, 0.0, 0.40)            # base_link <- os_sensor
laser_mount = pose_matrix(0.25, 0.0, 0.20)           # base_link <- laser (2D lidar)

info = info_from_metadata(METADATA_PATH, stamp_ns=1_000_000_000, frame_id="os_sensor")
scan = SimulatedLidar3D(info, scene).scan(robot @ lidar_mount, 2_000_000_000)
laser = SimulatedLaser2D(scene).scan(robot @ laser_mount, 2_000_000_000)

# Several height bands in base_link, computed in one pass; tables are built once per info.
slicer = SliceConverter(info, {"floor_to_knee": {"min_height": 0.05, "max_height": 0.5},
                               "table": {"min_height": 0.5, "max_height": 1.0}},
                        extrinsics=lidar_mount, frame_id="base_link",
                        angle_increment=math.radians(0.5), range_max=20.0)
slices = slicer.convert(scan)
for name, s in slices.items():
    r = np.asarray(s.ranges)
    print(f"slice {name!r}: {r.size} bins, {np.isfinite(r).sum()} with an obstacle, "
          f"nearest {np.nanmin(np.where(np.isfinite(r), r, np.nan)):.2f} m")

# Merge the 'table' slice with the 2D lidar: the table top (0.7 m) joins the walls and legs.
merger = LaserScanMerger({"table": MergerInput(),                        # already in base_link
                          "laser": MergerInput(extrinsics=laser_mount)},
                         frame_id="base_link", angle_increment=math.radians(0.5),
                         range_max=20.0)
merged = np.asarray(merger.merge({"table": slices["table"], "laser": laser}).ranges)
alone = np.asarray(merger.merge({"laser": laser}).ranges)   # same grid, 2D lidar only
seen = np.isfinite(alone)                                   # inside the 2D lidar's 270 deg
nearer = seen & (merged < alone - 0.05)
print(f"merged scan: {merged.size} bins in base_link; the 2D lidar alone fills {int(seen.sum())};"
      f" in {int(nearer.sum())} of those the merged scan has a nearer obstacle "
      f"(the table top, 0.7 m high, that the 2D lidar at 0.2 m cannot see)")
