"""The policy node builds its graph from robot_description and reads joint states by name: real processes, real DDS.

Runs inside a private network namespace (``scripts/test.sh``). The probe is the robot: it publishes the
latched URDF (reliable, transient local, as ``robot_state_publisher`` does) and the joint states itself, and
each answer is checked against the NumPy policy run here on the same checkpoint (no odometry is sent, so
the node's global features are zero), to 1e-9: the node's efforts are the policy's on the description's tree.
"""

from __future__ import annotations

import subprocess

import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String
from trajectory_msgs.msg import JointTrajectory

from morph_core.env.bodies import star_parents, y_parents
from morph_core.env.urdf import swimmer_urdf
from morph_core.msgs.effort_names import effort_names
from morph_core.msgs.stamps import answer_tag
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.tree import read_urdf
from morph_core.policy.weights import load_checkpoint

pytestmark = pytest.mark.slow  # every test here starts processes (nodes, bring-ups, installs)

STARTUP = 60.0
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
DEEP = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
RSS_GROWTH_LIMIT_KB = 20_000
"""RSS growth allowed over a flood (allocator slack); a leak per message is far more"""


def urdf(parents, names, fixed=(), uncommanded=()) -> str:
    """A URDF of revolute joints ``names`` with ``parents`` (-1: off the base link), fixed joints ``fixed`` off
    the base, and, when ``uncommanded`` is given, a ``<ros2_control>`` block leaving those hinges without a
    command interface."""
    links = ["base", *(f"{n}_link" for n in names), *(f"{n}_link" for n in fixed)]
    parts = [f'<link name="{name}"/>' for name in links]
    for name, p in zip(names, parents, strict=True):
        parent = "base" if p < 0 else f"{names[p]}_link"
        parts.append(f'<joint name="{name}" type="revolute"><parent link="{parent}"/><child link="{name}_link"/>'
                     '<axis xyz="0 0 1"/></joint>')  # fmt: skip
    parts += [f'<joint name="{n}" type="fixed"><parent link="base"/><child link="{n}_link"/></joint>' for n in fixed]
    if uncommanded:
        command = '<command_interface name="effort"/>'
        rows = "".join(f'<joint name="{n}">{"" if n in uncommanded else command}</joint>' for n in names)
        parts.append(f'<ros2_control name="hw" type="system">{rows}</ros2_control>')
    return '<?xml version="1.0"?>\n<robot name="r">' + "".join(parts) + "</robot>\n"


def chain(names) -> str:
    return urdf(list(range(-1, len(names) - 1)), list(names))


class Policy:
    """One policy node process and the probe's endpoints to it: latched description, states, answers by stamp."""

    _stamps = iter(range(100, 10**9))

    def __init__(self, probe, diagnostics, ns: str, sampling: bool = False):
        self.probe, self.ns = probe, ns
        self.proc = None  # the NodeProcess, once started
        node = probe.node
        self.answers: dict[str, Float64MultiArray] = {}  # answer tag -> efforts
        self.infos: dict[tuple[int, int], JointTrajectory] = {}
        node.create_subscription(Float64MultiArray, f"{ns}/effort_commands", self._on_efforts, DEEP)
        if sampling:
            node.create_subscription(JointTrajectory, f"{ns}/policy_info", self._on_info, DEEP)
        self.states = node.create_publisher(JointState, f"{ns}/joint_states", 10)
        self.description = node.create_publisher(String, f"{ns}/robot_description", LATCHED)
        self.diag = diagnostics(f"{ns}/morph_policy")

    def _on_efforts(self, msg):
        if msg.layout.dim:
            self.answers[msg.layout.dim[0].label] = msg

    def _on_info(self, msg):
        self.infos[(msg.header.stamp.sec, msg.header.stamp.nanosec)] = msg

    def wait_up(self) -> None:
        self.probe.spin_until(
            lambda: self.states.get_subscription_count() > 0 and self.diag.latest is not None,
            STARTUP,
            lambda: f"{self.ns}'s policy node (log: {self.proc.log()[-2000:]})",
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
            lambda: f"{what} {kind} {reason or ''} >= {at_least} on {self.ns} (now {self.diag.latest})",
        )

    def describe(self, text: str) -> None:
        """Publish a description and wait until the node has counted it."""
        n = self.count("robot_description")
        self.description.publish(String(data=text))
        self.wait_count("robot_description", n + 1)

    def state(self, names, pos, vel) -> JointState:
        msg = JointState(name=list(names), position=[float(x) for x in pos], velocity=[float(x) for x in vel])
        msg.header.stamp.sec = next(self._stamps)
        return msg

    def ask(self, names, pos, vel) -> Float64MultiArray:
        """The answer to one state (re-sent until answered: the node reads states best effort)."""
        msg = self.state(names, pos, vel)
        tag = answer_tag(msg.header.stamp.sec, 0)
        for _ in range(5):
            self.states.publish(msg)
            try:
                self.probe.spin_until(lambda: tag in self.answers, 3.0, "an answer")
                return self.answers[tag]
            except AssertionError:
                continue
        raise AssertionError(f"no answer from {self.ns} to {list(names)[:5]}...: {self.proc.log()[-2000:]}")

    def refused(self, names, pos, vel, kind: str, reason: str) -> JointState:
        """Send a state the node must not answer; returns once it counted it under ``kind``/``reason``."""
        msg = self.state(names, pos, vel)
        n = self.count("joint_states", kind, reason)
        for _ in range(5):
            self.states.publish(msg)
            try:
                self.wait_count("joint_states", n + 1, kind, reason)
                break
            except AssertionError:
                continue
        else:
            raise AssertionError(f"the state was never counted as {kind} {reason}: {self.diag.latest}")
        assert answer_tag(msg.header.stamp.sec, 0) not in self.answers
        return msg


@pytest.fixture
def policies(probe, namespace, diagnostics, launch, tmp_path, untrained_checkpoint):
    """policies(suffix, description=None, **params) -> Policy: a policy node in namespace ``namespace + suffix``
    running the untrained checkpoint; a description given is published (latched) before the node starts. The
    first has suffix '' (the test's namespace, through ``launch``); the others are started the same way."""
    started: list[Policy] = []

    def start(suffix: str, description: str | None = None, sampling: bool = False, **params) -> Policy:
        policy = Policy(probe, diagnostics, namespace + suffix, sampling)
        if description is not None:
            policy.description.publish(String(data=description))
        params = {"checkpoint": str(untrained_checkpoint), "deterministic": not sampling, **params}
        if not suffix:
            policy.proc = launch("morph_policy_node", **params)
        else:
            assert started and not started[0].ns.removeprefix(namespace), "start the test's namespace's node first"
            node_process = type(started[0].proc)  # conftest's NodeProcess (its module is not importable by name)
            policy.proc = node_process("morph_policy_node", policy.ns, params, tmp_path / f"policy{suffix}.log")
        started.append(policy)
        return policy

    yield start
    for policy in started[1:]:  # the first is launch's to stop
        policy.proc.stop()


@pytest.fixture
def expected(untrained_checkpoint):
    """expected(pos, vel, parents=None) -> the clipped mean efforts the node's policy gives, tree order."""
    policy = NumpyPolicy(load_checkpoint(untrained_checkpoint))

    def mean(pos, vel, parents=None) -> np.ndarray:
        out = policy.mean(np.asarray(pos, float), np.asarray(vel, float), np.zeros(4), parents)
        return np.clip(out.astype(np.float64), -1.0, 1.0)

    return mean


def names_of(msg: Float64MultiArray) -> tuple[str, ...] | None:
    return effort_names([d.label for d in msg.layout.dim], len(msg.data))


def _random_state(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    return rng.uniform(-0.8, 0.8, n), rng.uniform(-2.0, 2.0, n)


# -- trees by name ------------------------------------------------------------------------------------------
@pytest.mark.timeout(240)
def test_a_tree_description_published_before_the_start_is_read_by_name(policies, expected):
    """The y tree's efforts follow its joints whatever order the state lists them in; effort_order:=description
    keeps the tree's order. Both nodes got the URDF published before they started (transient local)."""
    text = swimmer_urdf(y_parents(2, 2))
    tree = read_urdf(text).tree
    by_state = policies("", description=text)
    by_tree = policies("_d", description=text, effort_order="description")
    for node in (by_state, by_tree):
        node.wait_up()
        node.wait_count("robot_description", 1)  # the latched sample, sent when the node matched
    rng = np.random.default_rng(1)
    pos, vel = _random_state(rng, tree.num_joints)
    want = expected(pos, vel, tree.parents)
    assert not np.allclose(want, expected(pos, vel)), "the tree must answer otherwise than a chain would"

    answer = by_state.ask(tree.names, pos, vel)
    np.testing.assert_allclose(answer.data, want, rtol=0, atol=1e-9)
    assert names_of(answer) == tree.names
    assert [d.label for d in answer.layout.dim][0].startswith("joints@") and answer.layout.dim[1].size == 1
    for k in range(5):
        perm = rng.permutation(tree.num_joints) if k else np.arange(tree.num_joints)[::-1]
        names = [tree.names[j] for j in perm]
        shuffled = by_state.ask(names, pos[perm], vel[perm])
        np.testing.assert_allclose(shuffled.data, want[perm], rtol=0, atol=1e-9)  # the same permutation
        assert names_of(shuffled) == tuple(names)
        in_tree_order = by_tree.ask(names, pos[perm], vel[perm])
        np.testing.assert_allclose(in_tree_order.data, want, rtol=0, atol=1e-9)
        assert names_of(in_tree_order) == tree.names
    for node in (by_state, by_tree):
        assert node.diag.latest["robot_description"].rejected_total == 0
        assert node.diag.latest["joint_states"].rejected_total == 0
        assert "robot_description: 6 actuated joints, a tree" in node.proc.log()
        assert "no robot_description yet" not in node.proc.log()


@pytest.mark.timeout(240)
def test_a_chain_description_answers_as_the_fallback_and_leaves_unactuated_joints_out(policies, expected):
    names = [f"j{k}" for k in range(5)]
    # A hinge with no command interface: the sixth revolute joint hangs off j4 and is not driven.
    text = urdf([-1, 0, 1, 2, 3, 4], [*names, "passive"], fixed=["camera_mount"], uncommanded=["passive"])
    fallback = policies("")
    described = policies("_c", description=text)
    for node in (fallback, described):
        node.wait_up()
    described.wait_count("robot_description", 1)
    rng = np.random.default_rng(2)
    pos, vel = _random_state(rng, 5)
    want = expected(pos, vel)

    # States in the chain's order: the same arrays from both, and the policy's.
    a, b = fallback.ask(names, pos, vel), described.ask(names, pos, vel)
    np.testing.assert_allclose(a.data, want, rtol=0, atol=1e-9)
    np.testing.assert_allclose(b.data, a.data, rtol=0, atol=1e-9)
    assert names_of(a) == names_of(b) == tuple(names)

    # Out of order, with the fixed joint and the uncommanded hinge in the state: they are left out.
    perm = np.array([3, 0, 4, 1, 2])
    extra = ["passive", *[names[j] for j in perm[:2]], "camera_mount", *[names[j] for j in perm[2:]]]
    extra_pos = np.concatenate([[0.5], pos[perm[:2]], [0.0], pos[perm[2:]]])
    extra_vel = np.concatenate([[-1.0], vel[perm[:2]], [0.0], vel[perm[2:]]])
    mixed = described.ask(extra, extra_pos, extra_vel)
    assert names_of(mixed) == tuple(names[j] for j in perm)
    np.testing.assert_allclose(mixed.data, want[perm], rtol=0, atol=1e-9)
    # The fallback takes an out-of-order state as the chain it lists.
    listed = fallback.ask([names[j] for j in perm], pos[perm], vel[perm])
    np.testing.assert_allclose(listed.data, expected(pos[perm], vel[perm]), rtol=0, atol=1e-9)
    assert fallback.proc.log().count("no robot_description yet: joints taken as a chain in message order") == 1

    # What does not fit the description is rejected with the reason, nothing answered.
    described.refused([*names, "wheel"], [0.0] * 6, [0.0] * 6, "rejected", "unknown_joint")
    assert "'wheel'" in described.diag.latest["joint_states"].last_rejection
    described.refused(names[:4], pos[:4], vel[:4], "rejected", "missing_joint")
    assert "'j4'" in described.diag.latest["joint_states"].last_rejection
    assert "rejected joint_states" in described.proc.log()
    np.testing.assert_allclose(described.ask(names, pos, vel).data, want, rtol=0, atol=1e-9)  # still answering


@pytest.mark.timeout(240)
def test_a_robot_swapped_at_runtime(policies, expected):
    """A chain, then a star tree, then a longer chain: each rebuilds the graph between two messages; states of
    the robot before the swap are ignored as previous_description, counted apart from rejections. Sampling:
    policy_info's names and arrays are in the efforts' order."""
    node = policies("", description=chain(["a0", "a1", "a2"]), sampling=True)
    node.wait_up()
    node.wait_count("robot_description", 1)
    rng = np.random.default_rng(3)
    pos3, vel3 = _random_state(rng, 3)
    assert len(node.ask(["a0", "a1", "a2"], pos3, vel3).data) == 3

    star = swimmer_urdf(star_parents(3, 2))
    tree = read_urdf(star).tree
    node.describe(star)
    node.refused(["a0", "a1", "a2"], pos3, vel3, "ignored", "previous_description")  # the chain's, in flight
    pos, vel = _random_state(rng, 6)
    perm = rng.permutation(6)
    names = [tree.names[j] for j in perm]
    answer = node.ask(names, pos[perm], vel[perm])
    assert names_of(answer) == tuple(names)
    node.probe.spin_until(lambda: any(answer_tag(*k) == answer.layout.dim[0].label for k in node.infos), 10.0,
                          "the answer's policy_info")  # fmt: skip
    stamp = next(k for k in node.infos if answer_tag(*k) == answer.layout.dim[0].label)
    info = node.infos[stamp].points[0]
    assert list(node.infos[stamp].joint_names) == names
    np.testing.assert_allclose(info.velocities, expected(pos, vel, tree.parents)[perm], rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.clip(info.positions, -1, 1), answer.data, rtol=0, atol=1e-12)

    longer = [f"a{k}" for k in range(5)]
    node.describe(chain(longer))
    node.refused(names, pos[perm], vel[perm], "ignored", "previous_description")  # the star's
    # Only the description just before is remembered: the first chain's states are now plain rejections.
    node.refused(["a0", "a1", "a2"], pos3, vel3, "rejected", "missing_joint")
    assert len(node.ask(longer, *_random_state(rng, 5)).data) == 5
    counts = node.diag.latest
    assert counts["robot_description"].received == 3 and counts["robot_description"].rejected_total == 0
    assert counts["joint_states"].rejected == {"missing_joint": 1}
    assert "previous robot_description" in node.proc.log()
    assert node.proc.alive()


@pytest.mark.timeout(240)
def test_a_new_bodys_state_ahead_of_its_description_is_answered_when_the_description_comes(policies):
    """At a body swap the sim publishes the new robot_description, then the new body's first state, on two topics:
    the state may come first, fitting no description. The node answers it as soon as the description is adopted
    (nothing re-sent here), not only when a lockstep sim re-sends it after its effort timeout."""
    node = policies("", description=chain(["a0", "a1", "a2"]))
    node.wait_up()
    node.wait_count("robot_description", 1)
    rng = np.random.default_rng(5)
    assert len(node.ask(["a0", "a1", "a2"], *_random_state(rng, 3)).data) == 3
    longer = [f"a{k}" for k in range(5)]
    pos, vel = _random_state(rng, 5)
    msg = node.refused(longer, pos, vel, "rejected", "unknown_joint")  # ahead of its description
    tag = answer_tag(msg.header.stamp.sec, 0)
    node.describe(chain(longer))
    node.probe.spin_until(lambda: tag in node.answers, 20.0, "the answer to the state that came before its robot")
    assert len(node.answers[tag].data) == 5
    assert node.proc.alive()


# -- bad descriptions and floods ----------------------------------------------------------------------------
def _bad_descriptions() -> list[tuple[str, str, str]]:
    """(case, description, words its rejection must contain)."""
    big = "<robot>" + " " * (10 * 2**20) + "</robot>"
    cycle = urdf([-1, 0], ["c0", "c1"]).replace('<child link="c0_link"/>', '<child link="base"/>')
    return [
        ("not_xml", "this is not a robot {", "malformed XML"),
        ("over_10MB", big, "more than 10000000 bytes"),
        ("cycle", cycle, "cycle"),
        ("two_roots", '<robot name="r"><link name="a"/><link name="b"/></robot>', "more than one root"),
        ("duplicate_names", urdf([-1, 0], ["d", "e"]).replace('joint name="e"', 'joint name="d"'), "duplicate joint"),
        ("65_joints", chain([f"m{k}" for k in range(65)]), "65 actuated joints"),
    ]


@pytest.mark.timeout(300)
def test_bad_descriptions_are_rejected_and_the_last_good_graph_kept(policies, expected):
    good = ["g0", "g1", "g2"]
    node = policies("", description=chain(good))
    node.wait_up()
    node.wait_count("robot_description", 1)
    rng = np.random.default_rng(4)
    pos, vel = _random_state(rng, 3)
    perm = [2, 0, 1]
    want = expected(pos, vel)[perm]

    for k, (case, text, words) in enumerate(_bad_descriptions(), start=1):
        # Each waits until counted before the next goes out: a large sample replaced before the reader has it
        # all is the Fast DDS wedge's trigger (docs/design.md).
        node.describe(text)
        node.wait_count("robot_description", k, "rejected", "description")
        assert words in node.diag.latest["robot_description"].last_rejection, (case, node.diag.latest)
        answer = node.ask([good[j] for j in perm], pos[perm], vel[perm])  # the last good graph, still
        np.testing.assert_allclose(answer.data, want, rtol=0, atol=1e-9, err_msg=case)
    log = node.proc.log()
    assert "rejected robot_description" in log and "the current graph kept" in log

    # A valid description whose joints never match the states: the states it replaced are the previous
    # robot's (ignored), others rejected; its own are answered; the good one again takes over.
    node.describe(chain(["x0", "x1", "x2"]))
    node.refused(good, pos, vel, "ignored", "previous_description")
    node.refused(["y0", "y1", "y2"], pos, vel, "rejected", "unknown_joint")
    assert len(node.ask(["x0", "x1", "x2"], pos, vel).data) == 3
    node.describe(chain(good))
    np.testing.assert_allclose(node.ask([good[j] for j in perm], pos[perm], vel[perm]).data, want, atol=1e-9)
    assert node.proc.alive() and "Traceback" not in node.proc.log()


@pytest.mark.timeout(300)
def test_descriptions_at_100_hz_while_states_flow(policies, expected):
    """Two robots alternating 100 times a second for 3 s while the first one's states flow: each state is
    answered (its robot current) or ignored as the previous robot's, never rejected; memory stays flat."""
    a_names = ["a0", "a1", "a2"]
    a, b = chain(a_names), swimmer_urdf(y_parents(2, 2))
    node = policies("", description=a)
    node.wait_up()
    node.wait_count("robot_description", 1)
    rng = np.random.default_rng(5)
    pos, vel = _random_state(rng, 3)
    node.ask(a_names, pos, vel)
    sent_states = []

    def flood(seconds: float) -> None:
        for k in range(int(seconds * 100)):
            node.description.publish(String(data=b if k % 2 == 0 else a))
            if k % 4 == 0:
                msg = node.state(a_names, pos, vel)
                sent_states.append(answer_tag(msg.header.stamp.sec, 0))
                node.states.publish(msg)
            node.probe.spin_for(0.01)

    flood(1.0)  # warm-up: every path taken, allocator pools grown
    node.probe.spin_for(1.0)
    rss_before = node.proc.rss_kb()
    flood(3.0)
    node.probe.spin_for(1.0)
    rss_after = node.proc.rss_kb()
    node.describe(a)  # a again after b: the chain's states are answered once more
    answer = node.ask(a_names, pos, vel)
    np.testing.assert_allclose(answer.data, expected(pos, vel), rtol=0, atol=1e-9)

    probe = node.probe
    probe.spin_until(lambda: node.count("joint_states") >= len(sent_states) * 0.5, 20.0, "the states counted")
    probe.spin_for(2.5)  # two more reports: nothing in flight
    counts = node.diag.latest
    states, descriptions = counts["joint_states"], counts["robot_description"]
    answered = sum(tag in node.answers for tag in sent_states)
    print(
        f"\n{len(sent_states)} states sent during the flood: {answered} answered, "
        f"{states.ignored.get('previous_description', 0)} ignored as the previous robot's; "
        f"{descriptions.received} descriptions received; RSS {rss_before} -> {rss_after} kB"
    )
    assert states.rejected_total == 0, states
    assert descriptions.rejected_total == 0 and descriptions.received > 100
    # Every state the node received was answered or ignored (the ask()s before and after were answered).
    assert states.received - answered - 2 == states.ignored["previous_description"] > 0
    assert answered > 0
    assert rss_after - rss_before < RSS_GROWTH_LIMIT_KB, f"RSS grew by {rss_after - rss_before} kB"
    assert node.proc.alive() and "Traceback" not in node.proc.log()


@pytest.mark.timeout(240)
def test_64_joints_in_random_order(policies, expected):
    text = swimmer_urdf(64)
    tree = read_urdf(text).tree
    node = policies("", description=text)
    node.wait_up()
    node.wait_count("robot_description", 1)
    rng = np.random.default_rng(6)

    def shuffled_rounds(count: int) -> None:
        for _ in range(count):
            pos, vel = _random_state(rng, 64)
            perm = rng.permutation(64)
            names = [tree.names[j] for j in perm]
            answer = node.ask(names, pos[perm], vel[perm])
            assert names_of(answer) == tuple(names)
            np.testing.assert_allclose(answer.data, expected(pos, vel)[perm], rtol=0, atol=1e-9)

    shuffled_rounds(20)  # warm-up
    rss_before = node.proc.rss_kb()
    shuffled_rounds(150)
    rss_after = node.proc.rss_kb()
    assert node.diag.latest["joint_states"].rejected_total == 0
    assert rss_after - rss_before < RSS_GROWTH_LIMIT_KB, f"RSS grew by {rss_after - rss_before} kB"
    print(f"\n64 joints, 170 random orders: RSS {rss_before} -> {rss_after} kB")


def test_urdf_helper_writes_what_the_reader_reads():
    # The test's own URDF writer, checked once so the node tests above test the node.
    robot = read_urdf(urdf([-1, 0, 0], ["p", "q", "r"], fixed=["f"], uncommanded=["r"]))
    assert robot.tree.names == ("p", "q") and robot.tree.parents.tolist() == [-1, 0]
    assert robot.unactuated == {"f", "r"}


@pytest.mark.timeout(120)
def test_an_unknown_effort_order_stops_the_node_at_start_up_with_one_line(launch, untrained_checkpoint):
    proc = launch("morph_policy_node", checkpoint=str(untrained_checkpoint), effort_order="alphabetical")
    try:
        code = proc.proc.wait(timeout=STARTUP)
    except subprocess.TimeoutExpired:
        raise AssertionError(f"still running:\n{proc.log()}") from None
    log = proc.log()
    lines = [line for line in log.splitlines() if "cannot start" in line]
    assert code == 1 and "Traceback" not in log, log
    assert len(lines) == 1 and "effort_order must be one of state, description" in lines[0], log
    assert "'alphabetical'" in lines[0]
