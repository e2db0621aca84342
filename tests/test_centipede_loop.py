"""The sim node serves a centipede (``topology:=centipede:2``) and the policy node drives it, unchanged but for
the 12 global features it builds from odometry for a 12-feature checkpoint: real DDS processes, lockstep."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from nav_msgs.msg import Odometry
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import String

from morph_core.msgs.joint_state import legged_global_features
from morph_core.msgs.stamps import to_ns
from morph_core.policy.actor_critic import GraphActorCritic, PolicyConfig
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.tree import read_urdf
from morph_core.policy.weights import load_checkpoint

pytestmark = pytest.mark.slow  # every test here starts processes (nodes, bring-ups, installs)

STARTUP = 60.0
DEEP = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _ns(msg) -> int:
    return to_ns(msg.header.stamp.sec, msg.header.stamp.nanosec)


@pytest.mark.timeout(300)
def test_the_policy_node_drives_a_served_centipede_on_its_twelve_globals(
    probe, launch, namespace, diagnostics, tmp_path
):
    torch.manual_seed(0)
    ckpt = tmp_path / "centipede.safetensors"  # an untrained 12-feature policy: what it answers is checked
    GraphActorCritic(PolicyConfig(global_features=12)).save(ckpt)
    states = probe.collect(JointState, "joint_states", DEEP)
    odoms = probe.collect(Odometry, "odom", DEEP)
    descriptions = probe.collect(String, "robot_description", LATCHED)
    sim_diag, policy_diag = diagnostics(f"{namespace}/swimmer_sim"), diagnostics(f"{namespace}/morph_policy")
    launch("swimmer_sim_node", topology="centipede:2", lockstep=True, real_time_factor=0.0, effort_timeout=0.5)
    launch("morph_policy_node", checkpoint=str(ckpt))
    stamps = lambda: {_ns(s) for s in states}  # noqa: E731
    probe.spin_until(lambda: len(stamps()) >= 12 and sim_diag.latest and policy_diag.latest, STARTUP + 60, "12 states")
    probe.spin_until(lambda: descriptions, 10.0, "the robot description")

    tree = read_urdf(descriptions[-1].data).tree
    assert tree.root_link == "torso_0" and tree.num_joints == 8 and list(states[-1].name) == list(tree.names)
    policy = NumpyPolicy(load_checkpoint(str(ckpt)))
    odom_at = {_ns(o): o for o in odoms}
    by_stamp = {}
    for s in states:
        by_stamp.setdefault(_ns(s), s)
    ordered = sorted(by_stamp)
    checked = 0
    for now, nxt in zip(ordered, ordered[1:], strict=False):
        o = odom_at[now]
        p, q, lin, ang = o.pose.pose.position, o.pose.pose.orientation, o.twist.twist.linear, o.twist.twist.angular
        assert o.child_frame_id.endswith("torso_0") and p.z > 0.2  # the root in 3-D, standing
        glob = legged_global_features(
            (q.x, q.y, q.z, q.w), (p.x, p.y, p.z), (lin.x, lin.y, lin.z), (ang.x, ang.y, ang.z)
        )
        s = by_stamp[now]
        expected = np.clip(policy.mean(np.array(s.position), np.array(s.velocity), glob, tree.parents), -1, 1)
        assert np.abs(expected - np.array(by_stamp[nxt].effort)).max() < 1e-6, f"state {now}: not the policy's answer"
        checked += 1
    assert checked >= 10
    assert all(c.rejected_total == 0 for c in policy_diag.latest.values()), policy_diag.latest  # odometry taken
    # The sim refuses nothing but, at most once, an answer computed before robot_description reached the policy
    # node (its fallback chain is not the centipede's tree: wrong_tree, the documented start-up race; lockstep
    # publishes the state again and it is answered on the right tree).
    counts = sim_diag.latest
    assert all(set(c.rejected) <= {"wrong_tree"} and c.rejected_total <= 1 for c in counts.values()), counts


def test_the_demo_walks_a_centipede_with_the_shipped_policy_or_a_given_one(tmp_path):
    import re
    import subprocess
    import sys

    # The shipped centipede policy (trained on 2..4 leg pairs) walks a 6-pair centipede it never saw.
    bringup = [sys.executable, "-m", "morph_policy_node.bringup", "--seconds", "20"]
    out = subprocess.run([*bringup, "--bodies", "centipede:6"], capture_output=True, text=True, timeout=240)
    line = next((x for x in out.stdout.splitlines() if x.startswith("walk speed:")), None)
    assert out.returncode == 0 and line is not None, out.stdout[-3000:] + out.stderr[-3000:]
    assert "bodies centipede:6, 24 joints" in line
    forward = float(re.search(r"\(([-+][0-9.]+) m forward", line).group(1))
    assert forward > 5.0, line  # it walks (standing still moves the root well under a metre)
    assert re.search(r"fell \d+ times?", line), line  # a walker's falls are counted
    # --checkpoint: any 12-feature policy drives it (an untrained one here).
    torch.manual_seed(0)
    ckpt = tmp_path / "centipede.safetensors"
    GraphActorCritic(PolicyConfig(global_features=12)).save(ckpt)
    out = subprocess.run([*bringup[:-2], "--bodies", "centipede:2", "--checkpoint", str(ckpt), "--seconds", "2"],
                         capture_output=True, text=True, timeout=240)  # fmt: skip
    line = next((x for x in out.stdout.splitlines() if x.startswith("walk speed:")), None)
    assert out.returncode == 0 and line is not None, out.stdout[-3000:] + out.stderr[-3000:]
    assert "bodies centipede:2, 8 joints" in line


def _ant() -> str:
    import os

    import gymnasium

    return os.path.join(os.path.dirname(gymnasium.__file__), "envs", "mujoco", "assets", "ant.xml")


@pytest.mark.timeout(300)
@pytest.mark.parametrize("given", [True, False], ids=["untrained_given", "shipped_legged"])
def test_the_demo_runs_gymnasiums_ant_with_a_policy_that_reads_joint_descriptions(tmp_path, given):
    """``scripts/demo.sh --model-file <ant.xml> [--checkpoint <joint_features 11>]``: without a checkpoint a
    free-rooted robot gets the shipped legged generalist (models/legged_gnn.safetensors); either way the policy
    node builds the joint descriptions from the sim's robot_description and drives the ant, and the speed is
    printed (neither policy walks it yet: results.md)."""
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "morph_policy_node.bringup", "--model-file", _ant(), "--seconds", "2"]
    if given:
        torch.manual_seed(0)
        ckpt = tmp_path / "described.safetensors"
        GraphActorCritic(PolicyConfig(global_features=12, joint_features=11)).save(ckpt)
        cmd += ["--checkpoint", str(ckpt)]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=240)
    line = next((x for x in out.stdout.splitlines() if x.startswith("walk speed:")), None)
    assert out.returncode == 0 and line is not None, out.stdout[-3000:] + out.stderr[-3000:]
    assert "ant.xml, 8 joints" in line and "over 2.00 s of sim time" in line, line
    log = out.stdout + out.stderr
    assert ("described.safetensors" if given else "models/legged_gnn.safetensors") in log, log[-3000:]


def test_the_demo_picks_the_shipped_model_by_what_it_drives(tmp_path):
    """Chains and planar robots: the chain model; swimmer trees: the trees'; centipedes alone: theirs; any other
    walker (legged bodies, a mix, a free-rooted MJCF): the legged generalist. What the sim would refuse reads as
    chains (the sim says why)."""
    import gymnasium

    from morph_policy_node.bringup import FAMILY_MODELS, _family

    swimmer = str(Path(gymnasium.__file__).parent / "envs" / "mujoco" / "assets" / "swimmer.xml")
    assert _family(None) == _family("2-10") == _family(None, swimmer) == "chains"
    assert _family("y:2x2") == _family("2-10,random:3-10") == "trees"
    assert _family("centipede:2-4") == _family("centipede:2,centipede:5") == "centipedes"
    assert _family("legged:4x2") == _family("centipede:2,legged:6x3") == _family(None, _ant()) == "legged"
    assert _family("not a spec") == _family(None, str(tmp_path / "missing.xml")) == "chains"
    assert {FAMILY_MODELS[f] for f in ("trees", "centipedes", "legged")} == {
        "swimmer_trees_gnn.safetensors", "centipede_gnn.safetensors", "legged_gnn.safetensors"}  # fmt: skip
