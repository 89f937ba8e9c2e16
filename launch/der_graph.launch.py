"""Launch the der_ros graph on a full ROS 2 install: SUMO bridge, DER agent, safety node and MCAP recorder.

    ros2 launch der_ros der_graph.launch.py steps:=3000 scenario:=ring replay:=der safety:=rss

The agent's command is remapped to ``agent/lane_change_cmd``; the safety node forwards it to the
bridge or replaces an unsafe change by keep lane (``safety:=none`` makes it a plain relay;
docs/safety.md).

Parameters come from ``config/graph.params.yaml`` of the package share directory (override
with ``params_file:=...``); the launch arguments below replace single values of it. Without
a ROS 2 install (PyPI rclpy only), ``der graph`` runs the same three nodes with the same file.
"""

from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare

from launch import LaunchDescription


def generate_launch_description() -> LaunchDescription:
    params_file = LaunchConfiguration("params_file")
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                "params_file",
                default_value=PathJoinSubstitution([FindPackageShare("der_ros"), "config", "graph.params.yaml"]),
                description="ROS params YAML with bridge_node, agent_node and recorder_node sections",
            ),
            DeclareLaunchArgument("steps", default_value="0", description="bridge max_steps (0 = run until stopped)"),
            DeclareLaunchArgument("scenario", default_value="ring", description="SUMO network: ring or urban"),
            DeclareLaunchArgument("replay", default_value="der", description="replay kind: uniform, per or der"),
            DeclareLaunchArgument("lam", default_value="0.5", description="DER lambda (replay.lam)"),
            DeclareLaunchArgument("safety", default_value="rss",
                                  description="the shield: rss (default) or none (the safety node relays every command)"),
            # recorder first in the list: it should be subscribed before data flows
            Node(
                package="der_ros",
                executable="recorder_node",
                name="recorder_node",
                parameters=[params_file],
                output="screen",
            ),
            Node(
                package="der_ros",
                executable="agent_node",
                name="agent_node",
                parameters=[
                    params_file,
                    {
                        "replay.kind": LaunchConfiguration("replay"),
                        "replay.lam": ParameterValue(LaunchConfiguration("lam"), value_type=float),
                    },
                ],
                remappings=[("lane_change_cmd", "agent/lane_change_cmd")],
                output="screen",
            ),
            Node(
                package="der_ros",
                executable="safety_node",
                name="safety_node",
                parameters=[params_file, {"safety.kind": LaunchConfiguration("safety")}],
                output="screen",
            ),
            Node(
                package="der_ros",
                executable="bridge_node",
                name="bridge_node",
                parameters=[
                    params_file,
                    {
                        "max_steps": ParameterValue(LaunchConfiguration("steps"), value_type=int),
                        "scenario.network": LaunchConfiguration("scenario"),
                    },
                ],
                output="screen",
            ),
        ]
    )
