"""Launch genreg_ros register_node with the shipped parameters (ROS 2 launch, needs launch_ros).

    ros2 launch genreg_ros genreg.launch.py source:=/lidar/points target:=/map/points
    ros2 launch genreg_ros genreg.launch.py params_file:=/path/to/my.yaml large_clouds:=true

The default params file is config/genreg.yaml (depth-camera scenes, model 7scenes); for object models pass
params_file:=$(ros2 pkg prefix genreg_ros)/share/genreg_ros/config/genreg_objects.yaml. The node is a
lifecycle node that configures and activates itself (autostart true in both files).

Set ROS_AUTOMATIC_DISCOVERY_RANGE and ROS_DOMAIN_ID in the shell that launches (see docs/ros_node.md).
`large_clouds:=true` points Fast DDS at the shipped shared-memory profile for multi-MB best-effort clouds;
the processes on the other end of the topics need the same FASTDDS_DEFAULT_PROFILES_FILE.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch.actions import DeclareLaunchArgument, SetEnvironmentVariable
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from launch import LaunchDescription


def generate_launch_description() -> LaunchDescription:
    share = get_package_share_directory("genreg_ros")
    params_file = LaunchConfiguration("params_file")
    return LaunchDescription([
        DeclareLaunchArgument("params_file", default_value=os.path.join(share, "config", "genreg.yaml"),
                              description="Parameters of register_node"),
        DeclareLaunchArgument("source", default_value="source_cloud", description="Source PointCloud2 topic"),
        DeclareLaunchArgument("target", default_value="target_cloud", description="Target PointCloud2 topic"),
        DeclareLaunchArgument("namespace", default_value="", description="Namespace of the node"),
        DeclareLaunchArgument("large_clouds", default_value="false",
                              description="Use the Fast DDS shared-memory profile for large clouds"),
        SetEnvironmentVariable(
            "FASTDDS_DEFAULT_PROFILES_FILE", os.path.join(share, "config", "fastdds_large_clouds.xml"),
            condition=IfCondition(LaunchConfiguration("large_clouds"))),
        Node(
            package="genreg_ros",
            executable="register_node",
            namespace=LaunchConfiguration("namespace"),
            parameters=[params_file],
            remappings=[("source_cloud", LaunchConfiguration("source")),
                        ("target_cloud", LaunchConfiguration("target"))],
            output="screen",
        ),
    ])
