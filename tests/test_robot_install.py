"""A robot's install: the two nodes into a fresh venv, without the training stack, and running there over DDS.

The venv is made with ``python -m venv`` and gets what a robot has: ROS (here the PyPI wheels that
requirements-dev.txt names, as scripts/setup.sh installs them; a robot's would be apt's Jazzy), then the nodes
through ``scripts/install_nodes.sh`` (built from the source, not editable, every version pinned by
constraints.txt): first the policy node alone (``--policy-only``), then the sim node beside it. No registry
is reachable inside the tests' network namespace, so pip reads the wheels from ``.venv/robot-wheels``, which
scripts/setup.sh fills with what ``install_nodes.sh --wheels`` resolves for the same packages (torch lies in
pip's find-links on this machine too: a node that required it would get it). The installed distributions are
read with ``importlib.metadata`` in the venv after each step: torch, torch-geometric, TensorBoard and
Matplotlib are never there, MuJoCo and Gymnasium only with the sim node. Then the venv's own console scripts
run: its policy node (with the shipped model, installed as package data) answers a state this test publishes
with the efforts the shipped policy computes here, and its sim node and policy node drive a swimmer together.

Slow: building the venv takes two to four minutes on a loaded 2-core machine (most of it the installs).
Run inside ``scripts/in_netns.sh``.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.weights import load_checkpoint
from morph_policy_node.policy_node import SHIPPED_MODEL

ROOT = Path(__file__).resolve().parents[1]
INSTALL_NODES = ROOT / "scripts" / "install_nodes.sh"
WHEELS = Path(sys.prefix) / "robot-wheels"
OFFLINE = ["--no-index", "--find-links", str(WHEELS)]
TRAINING_STACK = ("torch", "torch-geometric", "tensorboard", "matplotlib")
ENV_STACK = ("mujoco", "gymnasium")
STARTUP = 60.0  # seconds for a node to start and match on a loaded 2-core machine

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]  # installs into fresh venvs


def _normal(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _run(cmd: list[str]) -> None:
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=800)
    assert out.returncode == 0, f"{' '.join(cmd)} failed:\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}"


def _distributions(python: Path) -> set[str]:
    """The (normalised) names of every distribution installed in ``python``'s environment."""
    code = "import importlib.metadata as m, json; print(json.dumps([d.metadata['Name'] for d in m.distributions()]))"
    out = subprocess.run([str(python), "-c", code], capture_output=True, text=True, timeout=120, check=True)
    return {_normal(name) for name in json.loads(out.stdout)}


@dataclass(frozen=True)
class RobotVenv:
    bin: Path
    policy_only: set[str]
    """distributions after ROS and the policy node"""
    both: set[str]
    """... and after the sim node beside it"""


@pytest.fixture(scope="module")
def robot(tmp_path_factory) -> RobotVenv:
    if not WHEELS.is_dir():
        pytest.fail(f"no {WHEELS}: bash scripts/setup.sh")
    venv = tmp_path_factory.mktemp("robot") / "venv"
    _run([sys.executable, "-m", "venv", str(venv)])
    python = venv / "bin" / "python"
    ros = [r for r in (ROOT / "requirements-dev.txt").read_text().splitlines() if r.startswith("ros-")]
    assert any(r.startswith("ros-jazzy-rclpy") for r in ros), ros
    _run([str(python), "-m", "pip", "install", "--quiet", "-c", str(ROOT / "constraints.txt"), *OFFLINE, *ros])
    _run(["bash", str(INSTALL_NODES), str(python), "--policy-only", "--", *OFFLINE])
    policy_only = _distributions(python)
    _run(["bash", str(INSTALL_NODES), str(python), "--", *OFFLINE])
    return RobotVenv(venv / "bin", policy_only, _distributions(python))


def test_the_policy_node_installs_without_the_training_stack_or_mujoco(robot):
    assert {"rclpy", "morph-core", "morph-ros-util", "morph-policy-node"} <= robot.policy_only
    assert "swimmer-sim-node" not in robot.policy_only
    assert not set(TRAINING_STACK + ENV_STACK) & robot.policy_only


def test_the_two_nodes_install_without_the_training_stack(robot):
    assert {"morph-policy-node", "swimmer-sim-node", *ENV_STACK} <= robot.both
    assert not set(TRAINING_STACK) & robot.both
    assert "trainer" not in robot.both


@pytest.mark.skipif(not SHIPPED_MODEL.is_file(), reason="no shipped model")
def test_the_installed_policy_node_answers_a_published_state(robot, probe, launch):
    efforts = probe.collect(Float64MultiArray, "effort_commands")
    pub = probe.node.create_publisher(JointState, "joint_states", 10)
    node = launch(str(robot.bin / "morph_policy_node"))  # the default checkpoint: the shipped model, installed
    probe.spin_until(
        lambda: pub.get_subscription_count() > 0 and probe.node.count_publishers("effort_commands") > 0,
        STARTUP,
        lambda: f"the installed policy node's endpoints; its log:\n{node.log()}",
    )
    pos, vel = np.array([0.3, -0.2, 0.1, 0.0, 0.2]), np.array([0.1, 0.0, -0.1, 0.2, 0.0])
    msg = JointState(name=[f"j{k}" for k in range(5)], position=list(pos), velocity=list(vel))
    for _ in range(5):  # the policy's input is best effort: publish until an answer comes
        pub.publish(msg)
        try:
            probe.spin_until(lambda: efforts, 2.0, "an answer")
            break
        except AssertionError:
            continue
    assert efforts, f"no answer; the node's log:\n{node.log()}"
    # no odometry published: the node's global features are those of a torso at rest (zeros)
    want = np.clip(NumpyPolicy(load_checkpoint(SHIPPED_MODEL)).mean(pos, vel, np.zeros(4)), -1, 1)
    np.testing.assert_allclose(efforts[0].data, want, atol=1e-6)
    assert np.abs(want).max() > 1e-3  # not what a node that ignored its input would send
    assert node.alive()
    assert node.stop() == 0, node.log()
    assert f"policy loaded from {robot.bin.parent}" in node.log(), node.log()  # the venv's copy of the model


def test_the_installed_sim_and_policy_nodes_drive_a_swimmer(robot, probe, launch, untrained_checkpoint):
    states = probe.collect(JointState, "joint_states")
    efforts = probe.collect(Float64MultiArray, "effort_commands")
    nodes = [
        launch(str(robot.bin / "swimmer_sim_node"), num_joints=3),
        launch(str(robot.bin / "morph_policy_node"), checkpoint=str(untrained_checkpoint)),
    ]
    probe.spin_until(
        lambda: len(efforts) >= 10 and len(states) >= 3,
        STARTUP,
        lambda: "joint states and 10 effort commands; the logs:\n" + "\n".join(n.log() for n in nodes),
    )
    assert all(len(e.data) == 3 for e in efforts)
    assert all(n.alive() for n in nodes)
    assert [n.stop() for n in nodes] == [0, 0], "\n".join(n.log() for n in nodes)
