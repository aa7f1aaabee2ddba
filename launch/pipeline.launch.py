"""Launch the whole pipeline: a driver's PointCloud2 -> LidarScan + LidarInfo -> PointCloud2 and
LaserScan slices -> one merged LaserScan (with a 2D lidar).

    ros2 launch lidarscan pipeline.launch.py driver_points:=/ouster/points laser:=/laser/scan

Nodes (all in ``namespace``; topics relative to it unless absolute):

* ``lidarscan_cloud_to_scan``: ``driver_points`` -> ``lidar_scan`` + ``lidar_info`` (latched);
* ``lidarscan_converter``: ``lidar_scan`` + ``lidar_info`` -> ``points`` and ``slices/<name>``
  (the slices of ``config/converter.yaml``);
* ``lidarscan_merger``: the inputs of ``config/merger.yaml`` (``slices/full`` and, renamed by
  the ``laser`` argument, the 2D lidar) -> ``scan_merged``.

A driver that publishes LidarScan itself needs only the converter and the merger
(``converter.launch.py``, ``merger.launch.py``).
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

SCAN_TOPIC = "lidar_scan"   # between cloud_to_scan and the converter
INFO_TOPIC = "lidar_info"


def generate_launch_description():
    config = os.path.join(get_package_share_directory("lidarscan"), "config")
    namespace = LaunchConfiguration("namespace")
    return LaunchDescription([
        DeclareLaunchArgument("namespace", default_value="",
                              description="namespace of the nodes and their relative topics"),
        DeclareLaunchArgument("driver_points", default_value="/ouster/points",
                              description="the driver's organized sensor_msgs/PointCloud2"),
        DeclareLaunchArgument("laser", default_value="/laser/scan",
                              description="the 2D lidar (input 'laser' of the merger)"),
        DeclareLaunchArgument("cloud_to_scan_params",
                              default_value=os.path.join(config, "cloud_to_scan.yaml")),
        DeclareLaunchArgument("converter_params",
                              default_value=os.path.join(config, "converter.yaml")),
        DeclareLaunchArgument("merger_params", default_value=os.path.join(config, "merger.yaml")),
        Node(package="lidarscan", executable="lidarscan-cloud-to-scan",
             name="lidarscan_cloud_to_scan", namespace=namespace, output="screen",
             parameters=[LaunchConfiguration("cloud_to_scan_params"),
                         {"cloud_topic": LaunchConfiguration("driver_points"),
                          "scan_topic": SCAN_TOPIC, "info_topic": INFO_TOPIC}]),
        Node(package="lidarscan", executable="lidarscan-converter", name="lidarscan_converter",
             namespace=namespace, output="screen",
             parameters=[LaunchConfiguration("converter_params"),
                         {"scan_topic": SCAN_TOPIC, "info_topic": INFO_TOPIC}]),
        Node(package="lidarscan", executable="lidarscan-merger", name="lidarscan_merger",
             namespace=namespace, output="screen",
             parameters=[LaunchConfiguration("merger_params"),
                         {"inputs.laser.topic": LaunchConfiguration("laser")}]),
    ])
