"""Live training on a Jazzy install: K lockstep sim+policy pairs in /swimmer0.. plus the live trainer.

ros2 launch trainer live_training.launch.py pairs:=4 out:=runs/live [updates:=0] [episode_steps:=1000]
    [resume:=false] [min_joints:=2] [max_joints:=10] [real_time_factor:=1.0]
    [train_args:='--num-steps 1024 --seed 1']

The same processes as ``python -m trainer.live.bringup`` (which needs no ``launch``): each pair's sim runs
in lockstep at real_time_factor (1: real time; 0: as fast as it goes) with its chain length redrawn from
min_joints..max_joints at each reset; its policy samples (``deterministic:=false``) and takes the weights
the trainer pushes on ``policy_weights``. A key pair is made for each launch (in a private temporary
directory): the trainer signs with it, and the policy nodes trust its public half and no other key.
"""

import os
import tempfile

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess, OpaqueFunction, SetEnvironmentVariable
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

import morph_policy_node
from morph_core.protocol.trust import public_key_path
from trainer.live.bringup import run_key_pair

# The nodes' Fast DDS profile (quick discovery, UDP only: docs/design.md), unless the user set their own.
PROFILE = os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE", str(morph_policy_node.FASTDDS_PROFILE))


def _nodes(context):
    value = lambda name: LaunchConfiguration(name).perform(context)  # noqa: E731
    pairs = int(value("pairs"))
    namespaces = [f"/swimmer{i}" for i in range(pairs)]
    key = run_key_pair(tempfile.mkdtemp(prefix="morph-live-keys-"))  # mode 0700, this launch's alone
    cmd = ["morph-train", "--live", "--namespaces", *namespaces, "--out", value("out"),
           "--episode-steps", value("episode_steps"), "--max-updates", value("updates"),
           "--signing-key", str(key)]  # fmt: skip
    if value("resume").lower() == "true":
        cmd.append("--resume")
    cmd += value("train_args").split()
    actions = [ExecuteProcess(cmd=cmd, output="screen", name="morph_live_trainer")]
    # The trainer's weights follow, signed by this launch's key.
    policy = {"deterministic": False, "checkpoint": "", "allow_untrained": True,
              "trusted_keys": [str(public_key_path(key))]}  # fmt: skip
    for i, ns in enumerate(namespaces):
        actions.append(Node(package="swimmer_sim_node", executable="swimmer_sim_node", name="swimmer_sim",
                            namespace=ns, output="screen", respawn=True, respawn_delay=1.0,
                            parameters=[{"lockstep": True, "real_time_factor": float(value("real_time_factor")),
                                         "effort_timeout": 2.0,
                                         "min_joints": int(value("min_joints")),
                                         "max_joints": int(value("max_joints")), "seed": i}]))  # fmt: skip
        actions.append(Node(package="morph_policy_node", executable="morph_policy_node", name="morph_policy",
                            namespace=ns, output="screen", respawn=True, respawn_delay=1.0,
                            parameters=[{**policy, "seed": i}]))  # fmt: skip
    return actions


def generate_launch_description():
    args = [
        ("pairs", "2", "sim+policy pairs (K)"),
        ("out", "runs/live", "the trainer's run directory"),
        ("updates", "0", "stop after this many updates (0: total_timesteps)"),
        ("episode_steps", "1000", "control steps per episode, set on each sim by the trainer"),
        ("resume", "false", "continue the run in out"),
        ("min_joints", "2", "shortest chain drawn at a reset"),
        ("max_joints", "10", "longest chain drawn at a reset"),
        ("real_time_factor", "1.0", "the sims' pace (1: real time, as robots run; 0: unpaced)"),
        ("train_args", "", "further morph-train options (TrainConfig fields)"),
    ]
    return LaunchDescription(
        [DeclareLaunchArgument(n, default_value=d, description=h) for n, d, h in args]
        + [SetEnvironmentVariable("FASTRTPS_DEFAULT_PROFILES_FILE", PROFILE), OpaqueFunction(function=_nodes)]
    )
