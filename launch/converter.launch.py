"""Launch ``lidarscan-converter``: LidarScan + latched LidarInfo -> PointCloud2 + LaserScan slices.

    ros2 launch lidarscan converter.launch.py scan_topic:=/ouster/lidar_scan \
        info_topic:=/ouster/lidar_info

Parameters come from ``params_file`` (default: the installed ``config/converter.yaml``, every
parameter with its default); the launch arguments below override the input topics.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    config = os.path.join(get_package_share_directory("lidarscan"), "config")
    return LaunchDescription([
        DeclareLaunchArgument("namespace", default_value="",
                              description="namespace of the node and its relative topics"),
        DeclareLaunchArgument("params_file", default_value=os.path.join(config, "converter.yaml"),
                              description="parameters of lidarscan_converter"),
        DeclareLaunchArgument("scan_topic", default_value="lidar_scan",
                              description="input lidarscan_msgs/LidarScan topic"),
        DeclareLaunchArgument("info_topic", default_value="lidar_info",
                              description="input lidarscan_msgs/LidarInfo topic (latched)"),
        Node(package="lidarscan", executable="lidarscan-converter", name="lidarscan_converter",
             namespace=LaunchConfiguration("namespace"), output="screen",
             parameters=[LaunchConfiguration("params_file"),
                         {"scan_topic": LaunchConfiguration("scan_topic"),
                          "info_topic": LaunchConfiguration("info_topic")}]),
    ])
