"""ROS 2 nodes (rclpy): the thin edge around the converters.

Console scripts (see ``pyproject.toml``):

* ``lidarscan-converter`` (:mod:`converters.nodes.converter_node`): LidarScan + LidarInfo ->
  PointCloud2 and any number of LaserScan height slices;
* ``lidarscan-merger`` (:mod:`converters.nodes.merger_node`): N LaserScans (+ odometry) -> one
  merged LaserScan;
* ``lidarscan-cloud-to-scan`` (:mod:`converters.nodes.cloud_to_scan_node`): an organized
  PointCloud2 from a driver -> LidarScan + latched LidarInfo.

Importing this package does not import rclpy (only the node modules' ``main``/classes do, when
used); :mod:`converters.nodes.tf` and :mod:`converters.nodes.params` hold the pure parts.
"""

__all__ = ["cloud_to_scan_node", "converter_node", "merger_node", "params", "tf"]
