"""Sim + policy on a Jazzy install.

ros2 launch morph_policy_node swimmer_policy.launch.py [num_joints:=10] [lockstep:=true] [real_time_factor:=0.0]
    [episode_steps:=1000]
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, SetEnvironmentVariable
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

import morph_policy_node


def generate_launch_description():
    params = os.path.join(get_package_share_directory("morph_policy_node"), "config", "swimmer_policy.yaml")
    num_joints = LaunchConfiguration("num_joints")
    lockstep = LaunchConfiguration("lockstep")
    real_time_factor = LaunchConfiguration("real_time_factor")
    episode_steps = LaunchConfiguration("episode_steps")
    # The nodes' Fast DDS profile (quick discovery, UDP only: docs/design.md), unless the user set their own.
    profile = os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE", str(morph_policy_node.FASTDDS_PROFILE))
    return LaunchDescription(
        [
            SetEnvironmentVariable("FASTRTPS_DEFAULT_PROFILES_FILE", profile),
            DeclareLaunchArgument("num_joints", default_value="6", description="chain length (1..64)"),
            DeclareLaunchArgument("lockstep", default_value="false", description="deterministic closed loop"),
            DeclareLaunchArgument("real_time_factor", default_value="1.0", description="0 = as fast as possible"),
            DeclareLaunchArgument("episode_steps", default_value="0", description="steps per episode; 0 = no resets"),
            Node(
                package="swimmer_sim_node",
                executable="swimmer_sim_node",
                name="swimmer_sim",
                parameters=[
                    params,
                    {
                        "num_joints": num_joints,
                        "lockstep": lockstep,
                        "real_time_factor": real_time_factor,
                        "episode_steps": episode_steps,
                    },
                ],
                output="screen",
            ),
            Node(
                package="morph_policy_node",
                executable="morph_policy_node",
                name="morph_policy",
                parameters=[params],
                output="screen",
            ),
        ]
    )
