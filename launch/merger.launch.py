"""Launch ``lidarscan-merger``: N LaserScan topics (+ optional odometry) -> one merged LaserScan.

    ros2 launch lidarscan merger.launch.py params_file:=my_merger.yaml

The inputs, output grid and synchronisation are parameters (default file: the installed
``config/merger.yaml``, which merges the converter's ``slices/full`` with ``/laser/scan``).
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
        DeclareLaunchArgument("params_file", default_value=os.path.join(config, "merger.yaml"),
                              description="parameters of lidarscan_merger"),
        DeclareLaunchArgument("output_topic", default_value="scan_merged",
                              description="output sensor_msgs/LaserScan topic"),
        Node(package="lidarscan", executable="lidarscan-merger", name="lidarscan_merger",
             namespace=LaunchConfiguration("namespace"), output="screen",
             parameters=[LaunchConfiguration("params_file"),
                         {"output_topic": LaunchConfiguration("output_topic")}]),
    ])
