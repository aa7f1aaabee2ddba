"""LidarScan -> sensor_msgs/PointCloud2.

:mod:`.converter` holds :class:`PointCloud2Converter` and :func:`to_pointcloud2`; its numpy
reference path is :mod:`.fields`, its compiled path's plan :mod:`.kernel` (the kernel itself is
bound in :mod:`converters._kernels.cloud`). Field layouts (presets, ``read_points``) are shared
with the cloud importer and live in :mod:`converters.shared.cloud_layout`.
"""

from converters.pointcloud2.converter import *  # noqa: F401,F403  (the public names)
from converters.pointcloud2.converter import __all__  # noqa: F401
