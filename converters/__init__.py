"""converters: algorithms and importers built on the lidarscan core.

* LidarScan -> PointCloud2: :func:`to_pointcloud2` (driver presets, deskew);
* PointCloud2 -> LidarScan + estimated LidarInfo: :func:`from_pointcloud2`;
* LidarScan -> height-filtered LaserScan slices: :func:`to_laserscan`, :class:`SliceConverter`;
* any PointCloud2 (no grid needed) -> slices: :func:`cloud_to_laserscan`,
  :class:`CloudSliceConverter` (:mod:`converters.slices.cloud`);
* N LaserScans -> one: :class:`LaserScanMerger` configured with :class:`MergerInput`; moving
  mounts as :class:`TransformTrack` (:mod:`converters.shared.transforms`);
* importers: :mod:`converters.sources.ouster.metadata` (metadata JSON, frames), :mod:`converters.sources.velodyne`
  (calibration YAML, raw packets), :mod:`converters.sources.hesai.decoder` (raw packets -> scans per rotation),
  :func:`from_laserscan_sweep` (tilting 2D lasers), :func:`from_depth_image` (depth cameras,
  :mod:`converters.sources.depth`).

Names are resolved lazily (importing this package imports neither rclpy nor the submodules);
the rclpy nodes live in :mod:`converters.edge.nodes` and the CLI in :mod:`converters.edge.cli`.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
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
    "to_pointcloud2": "converters.pointcloud2.converter",
    "PointCloud2Converter": "converters.pointcloud2.converter",
    "from_pointcloud2": "converters.pointcloud2.converter",
    "to_laserscan": "converters.slices.converter",
    "SliceConverter": "converters.slices.converter",
    "cloud_to_laserscan": "converters.slices.cloud",
    "CloudSliceConverter": "converters.slices.cloud",
    "LaserScanMerger": "converters.merger",
    "MergerInput": "converters.merger",
    "TransformTrack": "converters.shared.transforms",
    "from_laserscan_sweep": "converters.sources.sweep",
    "from_depth_image": "converters.sources.depth",
}
_SUBMODULES = {"ouster", "velodyne", "hesai", "pointcloud2", "laserscan", "merger", "sweep",
               "depth", "transforms", "cloud_slices"}


#: Short public module paths -> the module (or package) that holds them. A key also covers its
#: submodules (``converters.velodyne.calibration`` -> ``converters.sources.velodyne.calibration``).
MOVED = {
    "converters.options": "converters.shared.options",
    "converters.frames": "converters.shared.frames",
    "converters.transforms": "converters.shared.transforms",
    "converters.deskew": "converters.shared.deskew",
    "converters.cloud_layout": "converters.shared.cloud_layout",
    "converters.laserscan": "converters.slices.converter",
    "converters.cloud_slices": "converters.slices.cloud",
    "converters._grid": "converters.slices.spec",
    "converters.ouster": "converters.sources.ouster",
    "converters.velodyne": "converters.sources.velodyne",
    "converters.hesai": "converters.sources.hesai",
    "converters.cloud_import": "converters.sources.clouds.importer",
    "converters.cloud_grid": "converters.sources.clouds.grid",
    "converters.depth": "converters.sources.depth",
    "converters.sweep": "converters.sources.sweep",
    "converters.bags": "converters.sources.bags",
    "converters.cli": "converters.edge.cli",
    "converters.nodes": "converters.edge.nodes",
    "converters.evidence": "converters.edge.evidence",
    "converters.demo": "converters.edge.demo.run",
    "converters.viz": "converters.edge.demo.viz",
}


def _moved_target(name: str) -> str | None:
    """The real module of the short path ``name`` (``converters.velodyne.calibration`` ->
    ``converters.sources.velodyne.calibration``), or None when ``name`` is not a moved path."""
    for short, real in MOVED.items():
        if name == short or name.startswith(short + "."):
            return real + name[len(short):]
    return None


class _MovedModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Import hook for :data:`MOVED`: the short path is bound to the real module object."""

    def find_spec(self, fullname: str, path: Any, target: Any = None) -> Any:
        real = _moved_target(fullname) if fullname.startswith("converters.") else None
        return None if real is None else importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec: Any) -> Any:
        module = importlib.import_module(_moved_target(spec.name))  # type: ignore[arg-type]
        _REAL_SPECS[spec.name] = module.__spec__  # importlib overwrites it: exec_module restores
        return module

    def exec_module(self, module: Any) -> None:
        module.__spec__ = _REAL_SPECS[module.__spec__.name]


_REAL_SPECS: dict[str, Any] = {}


if not any(isinstance(finder, _MovedModules) for finder in sys.meta_path):
    sys.meta_path.insert(0, _MovedModules())  # before the path finder: a moved package's
    # submodules must resolve to the real ones, not load a second copy from its __path__


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
