"""Trees closed loop over DDS: the sim swapping bodies, the policy node reading each body's robot_description.

Runs inside a private network namespace (``scripts/test.sh``). Real sim node, real policy node (the shipped
tree-trained model), lockstep. What is checked is what the sim applied (each state reports the efforts applied
over the period that ended at it), against the NumPy policy run here on the previous state and the tree that
state's body really had: never an effort computed on another tree, even when two bodies have the same joint
names and the description of a new body reaches the policy after its first state.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Int64MultiArray, String

from morph_core.env.swimmer_env import MorphSwimmerEnv
from morph_core.msgs.joint_state import global_features
from morph_core.msgs.stamps import to_ns
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.tree import read_urdf
from morph_core.policy.weights import load_checkpoint
from morph_policy_node.bringup import TREE_MODEL
from morph_policy_node.policy_node import SHIPPED_MODEL

pytestmark = pytest.mark.slow  # every test here starts processes (nodes, bring-ups, installs)

STARTUP = 60.0
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
DEEP = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
TREES = SHIPPED_MODEL.with_name(TREE_MODEL)


def _ns(msg) -> int:
    return to_ns(msg.header.stamp.sec, msg.header.stamp.nanosec)


@pytest.mark.timeout(300)
def test_bodies_with_equal_joint_names_are_each_driven_on_their_own_tree(probe, launch):
    # A Y and a star of six joints: both name their joints motor1_rot..motor6_rot, in different places.
    spec, steps, wanted = "y:2x2,star:3x2", 2, 8
    states = probe.collect(JointState, "joint_states", DEEP)
    odoms = probe.collect(Odometry, "odom", DEEP)
    starts = probe.collect(Int64MultiArray, "episode_start", LATCHED)
    descriptions = probe.collect(String, "robot_description", DEEP)
    launch("swimmer_sim_node", topology=spec, episode_steps=steps, seed=5, lockstep=True, real_time_factor=0.0,
           effort_timeout=0.5)  # fmt: skip
    launch("morph_policy_node", checkpoint=str(TREES))
    episodes = lambda: {int(m.data[1]) for m in starts}  # noqa: E731 - first-state stamps
    probe.spin_until(lambda: len(episodes()) >= wanted, STARTUP + 120, f"{wanted} episodes")

    policy = NumpyPolicy(load_checkpoint(str(TREES)))
    trees = {read_urdf(m.data).tree.parents.tobytes(): read_urdf(m.data).tree for m in descriptions}
    assert len(trees) == 2  # both bodies were drawn
    first = sorted(episodes())
    # Each episode's body, as the sim drew it: the env reset the same way draws the same (test_sim_trees).
    env = MorphSwimmerEnv(bodies=spec)
    env.reset(seed=5)
    body_of = {first[0]: env.tree}
    for start in first[1:]:
        env.reset()
        body_of[start] = env.tree
    odom_at = {_ns(o): o for o in odoms}
    by_stamp = {}
    for s in states:
        by_stamp.setdefault(_ns(s), s)  # a re-sent state is the same state
    checked = differs = 0
    for start in first[1:-1]:
        s, later = by_stamp.get(start), [t for t in by_stamp if t > start]
        if s is None or not later:
            continue
        nxt = by_stamp[min(later)]
        if min(later) in episodes():
            continue  # the episode ended before a step was taken
        body = body_of[start]
        o = odom_at[start]
        q, lin = o.pose.pose.orientation, o.twist.twist.linear
        glob = global_features((q.x, q.y, q.z, q.w), (lin.x, lin.y), o.twist.twist.angular.z)  # unwrapping restarts
        pos = dict(zip(s.name, s.position, strict=True))
        vel = dict(zip(s.name, s.velocity, strict=True))
        for tree in trees.values():
            args = (np.array([pos[n] for n in tree.names]), np.array([vel[n] for n in tree.names]), glob)
            expected = np.clip(policy.mean(*args, tree.parents), -1, 1)
            applied = dict(zip(nxt.name, nxt.effort, strict=True))
            gap = np.abs(expected - np.array([applied[n] for n in tree.names])).max()
            if tree.parents.tobytes() == body.parents.tobytes():
                assert gap < 1e-9, f"episode at {start}: efforts applied are not the policy's on its own tree"
                checked += 1
            else:
                differs += gap > 1e-6  # the other tree's answer would have been told apart
    assert checked >= 3 and differs == checked


@pytest.mark.timeout(300)
def test_the_demo_drives_a_branched_swimmer_with_the_tree_policy_and_it_swims(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "morph_policy_node.bringup", "--bodies", "y:2x2", "--seconds", "20"],
        capture_output=True, text=True, timeout=280,
    )  # fmt: skip
    line = next((x for x in out.stdout.splitlines() if x.startswith("swim speed:")), None)
    assert out.returncode == 0 and line is not None, out.stdout[-3000:] + out.stderr[-3000:]
    assert "bodies y:2x2, 6 joints" in line
    speed = float(line.split()[2])
    assert speed > 0.02, line  # forward: the tree policy swims (zero efforts drift at ~0)
