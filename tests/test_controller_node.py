"""The policy node is the loopback's controller, and its efforts in the robot's units: real process, real DDS.

Runs inside a private network namespace (``scripts/test.sh``). The probe replays a loopback recording
(``protocol.loopback``: a sampling policy on a chain, then on trees described by robot_description with their joints
listed in shuffled orders) to a policy node running the same checkpoint with the same seed, one state at a time as a
lockstep sim sends them, and compares every effort command and policy_info the node sends with the recorded ones,
bit for bit: the node and the loopback are one ``protocol.controller.Controller``.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import numpy as np
import pytest
from nav_msgs.msg import Odometry
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, Int64MultiArray, MultiArrayDimension, String
from trajectory_msgs.msg import JointTrajectory

from morph_core.env.bodies import swimmer_tree, y_parents
from morph_core.env.centipede_model import centipede_model
from morph_core.env.sim import SwimmerSim
from morph_core.env.urdf import robot_urdf, swimmer_urdf
from morph_core.msgs.effort_names import effort_names, effort_tree
from morph_core.msgs.episode_start import LABEL
from morph_core.msgs.records import (
    DescriptionRecord,
    EffortRecord,
    EpisodeStartRecord,
    JointStateRecord,
    OdometryRecord,
    PolicyInfoRecord,
)
from morph_core.msgs.stamps import answer_tag, from_ns
from morph_core.policy.joint_description import NUM_DESCRIPTION_FEATURES
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.tree import KinematicTree
from morph_core.policy.weights import load_checkpoint
from morph_core.protocol.controller import Controller
from morph_core.protocol.loopback import LoopbackRecording, SamplingController

pytestmark = pytest.mark.slow  # every test here starts processes (nodes, bring-ups, installs)

STARTUP = 60.0
Y = swimmer_tree(y_parents(1, 2))
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
DEEP = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


class Peer:
    """The probe's endpoints to one policy node: what a sim publishes, and the node's answers by stamp."""

    def __init__(self, probe, diagnostics, ns: str):
        self.probe, node = probe, probe.node
        self.efforts: dict[str, Float64MultiArray] = {}
        self.infos: dict[tuple[int, int], JointTrajectory] = {}
        node.create_subscription(Float64MultiArray, f"{ns}/effort_commands", self._on_efforts, DEEP)
        node.create_subscription(JointTrajectory, f"{ns}/policy_info", self._on_info, DEEP)
        self.pub = {
            "joint_states": node.create_publisher(JointState, f"{ns}/joint_states", 10),
            "odom": node.create_publisher(Odometry, f"{ns}/odom", 10),
            "episode_start": node.create_publisher(Int64MultiArray, f"{ns}/episode_start", 10),
            "robot_description": node.create_publisher(String, f"{ns}/robot_description", LATCHED),
        }
        self.diag = diagnostics(f"{ns}/morph_policy")

    def _on_efforts(self, msg):
        if msg.layout.dim:
            self.efforts[msg.layout.dim[0].label] = msg

    def _on_info(self, msg):
        self.infos[(msg.header.stamp.sec, msg.header.stamp.nanosec)] = msg

    def wait_up(self, proc) -> None:
        self.probe.spin_until(
            lambda: self.pub["joint_states"].get_subscription_count() > 0 and self.diag.latest is not None,
            STARTUP,
            lambda: f"the policy node (log: {proc.log()[-2000:]})",
        )

    def count(self, what: str, kind: str = "received", reason: str | None = None) -> int:
        c = self.diag.latest[what] if self.diag.latest else None
        if c is None:
            return 0
        return c.received if kind == "received" else getattr(c, kind)[reason]

    def wait_count(self, what: str, at_least: int, kind: str = "received", reason: str | None = None) -> None:
        self.probe.spin_until(
            lambda: self.count(what, kind, reason) >= at_least,
            20.0,
            lambda: f"{what} {kind} {reason or ''} >= {at_least} (now {self.diag.latest})",
        )

    def describe(self, text: str) -> None:
        n = self.count("robot_description")
        self.pub["robot_description"].publish(String(data=text))
        self.wait_count("robot_description", n + 1)

    def answer(self, state: JointState, sampling: bool) -> tuple[Float64MultiArray, JointTrajectory | None]:
        """The answer to one state (re-sent until answered: the node reads states best effort)."""
        stamp = state.header.stamp
        tag, key = answer_tag(stamp.sec, stamp.nanosec), (stamp.sec, stamp.nanosec)
        for _ in range(5):
            self.pub["joint_states"].publish(state)
            try:
                self.probe.spin_until(lambda: tag in self.efforts and (key in self.infos or not sampling), 3.0, tag)
                return self.efforts[tag], self.infos.get(key)
            except AssertionError:
                continue
        raise AssertionError(f"no answer to the state {tag}")


def _header(msg, stamp_ns: int):
    msg.header.stamp.sec, msg.header.stamp.nanosec = from_ns(stamp_ns)
    return msg


def _odometry(r: OdometryRecord) -> Odometry:
    msg = _header(Odometry(), r.stamp_ns)
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    p.x, p.y, p.z = r.position
    q.x, q.y, q.z, q.w = (float(v) for v in r.orientation_xyzw)
    lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
    lin.x, lin.y, lin.z = (float(v) for v in r.body_linear)
    ang.x, ang.y, ang.z = (float(v) for v in r.body_angular)
    return msg


def _state(r: JointStateRecord) -> JointState:
    msg = _header(JointState(name=list(r.names)), r.stamp_ns)
    msg.position, msg.velocity = [float(x) for x in r.position], [float(x) for x in r.velocity]
    msg.effort = [float(x) for x in r.effort]
    return msg


def _bits(values) -> bytes:
    return np.asarray(values, dtype=np.float64).tobytes()


def described_checkpoint(tmp_path) -> Path:
    """A fresh legged policy that reads joint descriptions (joint_features 11), saved as a checkpoint."""
    import torch

    from morph_core.policy.actor_critic import GraphActorCritic
    from morph_core.policy.config import PolicyConfig

    torch.manual_seed(5)
    path = tmp_path / "described.safetensors"
    GraphActorCritic(PolicyConfig(global_features=12, joint_features=NUM_DESCRIPTION_FEATURES)).save(path)
    return path


@pytest.mark.timeout(300)
@pytest.mark.parametrize("case", ["swimmers", "legged, described"])
def test_the_node_answers_recorded_messages_as_the_loopback_recorded_them(
    probe, launch, diagnostics, namespace, untrained_checkpoint, tmp_path, case
):
    """Swimmers (a chain, then trees), and generated legged bodies under a policy that reads joint descriptions,
    which the node builds from each robot_description as the loopback's controller did."""
    if case == "swimmers":
        checkpoint, sim, bodies = untrained_checkpoint, SwimmerSim(3, seed=4, effort_timeout=None), (None, Y, 4)
    else:
        checkpoint = described_checkpoint(tmp_path)
        sim, bodies = SwimmerSim(bodies="legged:4-6x2-3", seed=4, effort_timeout=None), (None, None, None)
    weights = load_checkpoint(checkpoint)
    loop = LoopbackRecording(
        sim, SamplingController(weights, seed=11), describe=True, shuffle_seed=2, name_efforts=True
    )
    for i, body in enumerate(bodies):
        if i:
            loop.new_episode(body)
        loop.run(12)
    loop.finish()

    peer = Peer(probe, diagnostics, namespace)
    proc = launch("morph_policy_node", checkpoint=str(checkpoint), deterministic=False, seed=11)
    peer.wait_up(proc)
    recorded_efforts = {r.answers_ns: r for r in loop.records if isinstance(r, EffortRecord)}
    recorded_infos = {r.stamp_ns: r for r in loop.records if isinstance(r, PolicyInfoRecord)}
    answered = 0
    for r in loop.records:  # in the order a recorder received them, as a lockstep sim sends them
        if isinstance(r, DescriptionRecord):
            peer.describe(r.text)
        elif isinstance(r, EpisodeStartRecord):
            announcement = Int64MultiArray(data=[r.episode, r.stamp_ns, r.num_joints, 0])
            announcement.layout.dim = [MultiArrayDimension(label=LABEL, size=4, stride=4)]
            peer.pub["episode_start"].publish(announcement)
        elif isinstance(r, OdometryRecord):
            peer.pub["odom"].publish(_odometry(r))
        elif isinstance(r, JointStateRecord):
            efforts, info = peer.answer(_state(r), sampling=True)
            want, want_info = recorded_efforts[r.stamp_ns], recorded_infos[r.stamp_ns]
            labels = [d.label for d in efforts.layout.dim]
            assert _bits(efforts.data) == _bits(want.effort), r.stamp_ns
            assert effort_names(labels, len(efforts.data)) == want.names and effort_tree(labels) == want.layout
            assert tuple(info.joint_names) == want_info.names
            point = info.points[0]
            assert _bits(point.positions) == _bits(want_info.action)
            assert _bits(point.velocities) == _bits(want_info.mean)
            assert _bits(point.effort) == _bits(want_info.log_prob_per_joint)
            answered += 1
    assert answered == len(loop.truth) > 35
    assert "no robot_description yet" not in proc.log()
    if case != "swimmers":  # each body's own descriptions reached the policy: they differ between bodies
        assert len({t.observation["joint_desc"].tobytes() for t in loop.truth}) > 1


def limited_urdf(limits) -> str:
    """A three-joint swimmer whose joints' ``<limit effort>`` are ``limits`` (None: left out)."""
    text, out, start = swimmer_urdf(3), [], 0
    for limit in limits:
        at = text.index("effort=", start)
        end = text.index('"', text.index('"', at) + 1) + 1
        out += [text[start:at], "" if limit is None else f'effort="{limit}"']
        start = end
    return "".join(out) + text[start:]


@pytest.mark.timeout(240)
def test_effort_units_urdf_scale_by_the_limits_and_refuse_without_them(
    probe, launch, diagnostics, namespace, untrained_checkpoint
):
    peer = Peer(probe, diagnostics, namespace)
    proc = launch("morph_policy_node", checkpoint=str(untrained_checkpoint), effort_units="urdf")
    peer.wait_up(proc)
    policy = NumpyPolicy(load_checkpoint(untrained_checkpoint))
    names = ["motor1_rot", "motor2_rot", "motor3_rot"]
    pos, vel = np.array([0.4, -0.3, 0.2]), np.array([1.0, -0.5, 0.25])
    stamps = iter(range(1, 10**6))

    def state(order) -> JointState:
        msg = JointState(name=[names[j] for j in order], position=list(pos[order]), velocity=list(vel[order]))
        msg.header.stamp.sec = next(stamps)
        return msg

    def refused(reason: str) -> None:
        n = peer.count("joint_states", "rejected", reason)
        for _ in range(5):
            msg = state([0, 1, 2])
            peer.pub["joint_states"].publish(msg)
            try:
                peer.wait_count("joint_states", n + 1, "rejected", reason)
                break
            except AssertionError:
                continue
        assert peer.count("joint_states", "rejected", reason) > n, f"no state refused for {reason}"
        assert answer_tag(msg.header.stamp.sec, 0) not in peer.efforts

    refused("no_effort_limits")  # no description yet: no unit to scale into
    peer.describe(limited_urdf([2.5, 0, 40]))  # a zero limit: refused, counted
    assert peer.count("robot_description", "rejected", "effort_limit") == 1
    refused("no_effort_limits")
    assert "rejected robot_description" in proc.log() and "'motor2_rot' has <limit effort> 0.0" in proc.log()

    peer.describe(limited_urdf([2.5, 0.5, 40]))
    mean = np.clip(policy.mean(pos, vel, np.zeros(4)).astype(np.float64), -1, 1)  # no odometry: globals zero
    want = mean * [2.5, 0.5, 40.0]
    for order in ([0, 1, 2], [2, 0, 1]):
        efforts, _ = peer.answer(state(order), sampling=False)
        np.testing.assert_allclose(efforts.data, want[order], rtol=0, atol=1e-12)
    assert not np.allclose(want, mean, rtol=0.1, atol=0)  # scaled, each joint by its own limit
    peer.describe(limited_urdf([2.5, None, 40]))  # a limit left out: refused, the limits before kept
    assert peer.count("robot_description", "rejected", "effort_limit") == 2
    efforts, _ = peer.answer(state([0, 1, 2]), sampling=False)
    np.testing.assert_allclose(efforts.data, want, rtol=0, atol=1e-12)


def _refused_at_start(proc) -> tuple[list[str], str]:
    """The node ends 1 at start without a traceback: its "cannot start" lines, and its log."""
    try:
        code = proc.proc.wait(timeout=STARTUP)
    except subprocess.TimeoutExpired:
        raise AssertionError(f"still running:\n{proc.log()}") from None
    log = proc.log()
    lines = [line for line in log.splitlines() if "cannot start" in line]
    assert code == 1 and "Traceback" not in log, log
    return lines, log


@pytest.mark.timeout(120)
def test_an_unknown_effort_units_stops_the_node_with_one_line(launch, untrained_checkpoint):
    proc = launch("morph_policy_node", checkpoint=str(untrained_checkpoint), effort_units="newton_metres")
    lines, log = _refused_at_start(proc)
    assert len(lines) == 1 and "effort_units must be one of normalized, urdf; got 'newton_metres'" in lines[0], log


@pytest.mark.timeout(240)
def test_a_policy_reading_joint_descriptions_waits_for_robot_description_and_says_so_once(
    probe, launch, diagnostics, namespace, tmp_path
):
    """No chain fallback: states before a description are counted (ignored, ``no_description``) and not answered,
    the wait is logged once; a description whose joint descriptions cannot be built (a body of 0.1 mm) is a
    counted rejection (``joint_description``) and the wait goes on; a good one is answered on, as the in-process
    controller answers."""
    checkpoint = described_checkpoint(tmp_path)
    peer = Peer(probe, diagnostics, namespace)
    proc = launch("morph_policy_node", checkpoint=str(checkpoint))
    peer.wait_up(proc)
    text = robot_urdf(centipede_model(2))
    names = KinematicTree.from_urdf(text).names
    pos, vel = np.linspace(-0.3, 0.3, len(names)), np.full(len(names), 0.2)

    def state(sec: int) -> JointState:
        msg = JointState(name=list(names), position=list(pos), velocity=list(vel))
        msg.header.stamp.sec = sec
        return msg

    def waited(sec: int, at_least: int) -> None:
        for _ in range(20):
            peer.pub["joint_states"].publish(state(sec))
            try:
                peer.wait_count("joint_states", at_least, "ignored", "no_description")
                return
            except AssertionError:
                continue
        raise AssertionError("no state counted as waiting for a description")

    for sec in (1, 2, 3):
        waited(sec, sec)
    tiny = text
    for xyz in {m for m in re.findall(r'xyz="([^"]*)"', text)}:
        tiny = tiny.replace(f'xyz="{xyz}"', 'xyz="{}"'.format(" ".join(repr(float(v) * 1e-4) for v in xyz.split())))
    peer.describe(tiny)
    assert peer.count("robot_description", "rejected", "joint_description") == 1
    waited(4, 4)
    assert not peer.efforts  # nothing answered, no chain fallback
    log = proc.log()
    assert log.count("waiting for robot_description") == 1 and "still waiting for one" in log, log
    assert "no robot_description yet" not in log

    peer.describe(text)
    efforts, _ = peer.answer(state(5), sampling=False)
    c = Controller(NumpyPolicy(load_checkpoint(checkpoint)))
    assert c.description(text).outcome == "adopted"
    want = c.answer(*c.state(JointStateRecord(0, 5, names, pos, vel, np.empty(0)), 0.0))  # no odometry: at rest
    assert _bits(efforts.data) == _bits(want.efforts)
