"""Launch only the MCAP recorder (e.g. next to a graph started elsewhere).

    ros2 launch der_ros recorder.launch.py all_topics:=true output:=runs/bags/mine
"""

from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare

from launch import LaunchDescription


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                "params_file",
                default_value=PathJoinSubstitution([FindPackageShare("der_ros"), "config", "graph.params.yaml"]),
                description="ROS params YAML with a recorder_node section",
            ),
            DeclareLaunchArgument("all_topics", default_value="false", description="record every discovered topic"),
            DeclareLaunchArgument("output", default_value="runs/bags/recording",
                                  description="bag directory to create (must not exist)"),
            Node(
                package="der_ros",
                executable="recorder_node",
                name="recorder_node",
                parameters=[
                    LaunchConfiguration("params_file"),
                    {
                        "all_topics": ParameterValue(LaunchConfiguration("all_topics"), value_type=bool),
                        "output": ParameterValue(LaunchConfiguration("output"), value_type=str),
                    },
                ],
                output="screen",
            ),
        ]
    )
