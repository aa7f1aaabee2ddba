"""converters: algorithms and importers built on the lidarscan core.

* LidarScan -> PointCloud2: :func:`to_pointcloud2` (driver presets, deskew);
* PointCloud2 -> LidarScan + estimated LidarInfo: :func:`from_pointcloud2`;
* LidarScan -> height-filtered LaserScan slices: :func:`to_laserscan`, :class:`SliceConverter`;
* any PointCloud2 (no grid needed) -> slices: :func:`cloud_to_laserscan`,
  :class:`CloudSliceConverter` (:mod:`converters.cloud_slices`);
* N LaserScans -> one: :class:`LaserScanMerger` configured with :class:`MergerInput`; moving
  mounts as :class:`TransformTrack` (:mod:`converters.transforms`);
* importers: :mod:`converters.ouster` (metadata JSON, frames), :mod:`converters.velodyne`
  (calibration YAML, raw packets), :mod:`converters.hesai` (raw packets -> scans per rotation),
  :func:`from_laserscan_sweep` (tilting 2D lasers), :func:`from_depth_image` (depth cameras,
  :mod:`converters.depth`).

Names are resolved lazily (importing this package imports neither rclpy nor the submodules);
the rclpy nodes live in :mod:`converters.nodes` and the CLI in :mod:`converters.cli`.
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = [
    "to_pointcloud2",
    "PointCloud2Converter",
    "from_pointcloud2",
    "to_laserscan",
    "SliceConverter",
    "cloud_to_laserscan",
    "CloudSliceConverter",
    "LaserScanMerger",
    "MergerInput",
    "TransformTrack",
    "from_laserscan_sweep",
    "from_depth_image",
    "ouster",
    "velodyne",
    "hesai",
    "depth",
]

_LAZY = {
    "to_pointcloud2": "converters.pointcloud2",
    "PointCloud2Converter": "converters.pointcloud2",
    "from_pointcloud2": "converters.pointcloud2",
    "to_laserscan": "converters.laserscan",
    "SliceConverter": "converters.laserscan",
    "cloud_to_laserscan": "converters.cloud_slices",
    "CloudSliceConverter": "converters.cloud_slices",
    "LaserScanMerger": "converters.merger",
    "MergerInput": "converters.merger",
    "TransformTrack": "converters.transforms",
    "from_laserscan_sweep": "converters.sweep",
    "from_depth_image": "converters.depth",
}
_SUBMODULES = {"ouster", "velodyne", "hesai", "pointcloud2", "laserscan", "merger", "sweep",
               "depth", "transforms", "cloud_slices"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
    elif name in _SUBMODULES:
        value = importlib.import_module(f"converters.{name}")
    else:
        raise AttributeError(f"module 'converters' has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
