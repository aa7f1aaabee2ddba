"""ROS 2 nodes (rclpy): the thin edge around the converters.

Console scripts (see ``pyproject.toml``):

* ``lidarscan-converter`` (:mod:`converters.edge.nodes.converter_node`): LidarScan + LidarInfo ->
  PointCloud2 and any number of LaserScan height slices;
* ``lidarscan-merger`` (:mod:`converters.edge.nodes.merger_node`): N LaserScans (+ odometry) -> one
  merged LaserScan;
* ``lidarscan-cloud-to-scan`` (:mod:`converters.edge.nodes.cloud_to_scan_node`): an organized
  PointCloud2 from a driver -> LidarScan + latched LidarInfo.

Importing this package does not import rclpy (only the node modules' ``main``/classes do, when
used); :mod:`converters.edge.nodes.tf` and :mod:`converters.edge.nodes.params` hold the pure parts.
"""

__all__ = ["cloud_to_scan_node", "converter_node", "merger_node", "params", "tf"]
