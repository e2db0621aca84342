"""The sim node beyond chains, over real DDS: branched swimmers drawn per episode (``topology``), joints
listed in a shuffled order (``shuffle_joints``) with efforts applied by name, and your own robot
(``model_file``: Gymnasium's ant.xml).

Runs inside a private network namespace (``scripts/test.sh``). The test's own node plays the controller
where the efforts must be known exactly; the policy node where the point is that a real controller drives
the robot with no configuration.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import gymnasium
import mujoco
import numpy as np
import pytest
from nav_msgs.msg import Odometry
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, Int64MultiArray, MultiArrayDimension, String

from morph_core.env.bodies import parse_bodies
from morph_core.env.mjcf_robot import load_robot
from morph_core.env.swimmer_env import MorphSwimmerEnv
from morph_core.msgs.effort_names import effort_tree, names_label, tree_label
from morph_core.msgs.episode_start import unpack_episode_start
from morph_core.msgs.stamps import answer_tag, to_ns
from morph_core.policy.tree import KinematicTree, read_urdf
from morph_core.protocol.sim_wire import make_sim

pytestmark = pytest.mark.slow  # every test here starts processes (nodes, bring-ups, installs)

STARTUP = 60.0
DEEP = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
ANT_XML = Path(gymnasium.__file__).parent / "envs" / "mujoco" / "assets" / "ant.xml"
YOUR_ROBOT_DOC = Path(__file__).resolve().parents[1] / "docs" / "your_robot.md"
BIN = Path(sys.executable).parent
LOCKSTEP = {"lockstep": True, "real_time_factor": 0.0, "effort_timeout": 2.0}


def _ns(msg) -> int:
    return to_ns(msg.header.stamp.sec, msg.header.stamp.nanosec)


def _unique(states) -> list:
    """The states in stamp order, each once (a lockstep sim re-sends a state that waits too long)."""
    by_stamp = {}
    for s in states:
        by_stamp.setdefault(_ns(s), s)
    return [by_stamp[k] for k in sorted(by_stamp)]


def _starts(announcements) -> dict:
    records = [unpack_episode_start(0, m.layout.dim[0].label, m.data) for m in announcements]
    return {r.stamp_ns: r for r in records}


def _command(values, tag: str | None = None, names=None, layout: KinematicTree | None = None) -> Float64MultiArray:
    msg = Float64MultiArray(data=[float(v) for v in values])
    n = len(values)
    if tag is not None or names is not None:  # the names come after dim[0], the answer tag ('' for none)
        msg.layout.dim.append(MultiArrayDimension(label=tag or "", size=n, stride=n))
    if names is not None:
        msg.layout.dim.append(MultiArrayDimension(label=names_label(tuple(names)), size=1, stride=1))
    if layout is not None:  # the joint layout the efforts were computed on
        msg.layout.dim.append(MultiArrayDimension(label=tree_label(layout.layout_hash), size=1, stride=1))
    return msg


class _Controller:
    """Answers every joint state with seeded random efforts (the same again for a re-sent state), tagged with
    its stamp; ``by_name`` sends them under a names dimension in an order of its own (reversed), else in the
    state's order. Remembers each answer by joint name."""

    def __init__(self, probe, seed: int, by_name: bool = False, gain: float = 1.0):
        self.rng = np.random.default_rng(seed)
        self.by_name, self.gain = by_name, gain
        self.pub = probe.node.create_publisher(Float64MultiArray, "effort_commands", 10)
        self.answers: dict[int, dict[str, float]] = {}
        self.states: list[JointState] = []
        probe.node.create_subscription(JointState, "joint_states", self._on_state, DEEP)

    def _on_state(self, msg: JointState) -> None:
        self.states.append(msg)
        stamp = _ns(msg)
        if stamp not in self.answers:
            values = self.gain * self.rng.uniform(-1, 1, len(msg.name))
            self.answers[stamp] = dict(zip(msg.name, values, strict=True))
        answer = self.answers[stamp]
        tag = answer_tag(msg.header.stamp.sec, msg.header.stamp.nanosec)
        if self.by_name:
            names = list(reversed(msg.name))
            self.pub.publish(_command([answer[n] for n in names], tag, names))
        else:
            self.pub.publish(_command([answer[n] for n in msg.name], tag))


# -- topology -----------------------------------------------------------------------------------------------
@pytest.mark.timeout(240)
def test_topology_draws_a_tree_per_episode_publishes_its_urdf_and_replays_in_the_env(probe, launch):
    spec, steps, seed, wanted = "y:1-2x1-2,star:2-3x1,comb:3", 5, 7, 48
    descriptions = probe.collect(String, "robot_description", LATCHED)
    announcements = probe.collect(Int64MultiArray, "episode_start", LATCHED)
    controller = _Controller(probe, seed=0)
    launch("swimmer_sim_node", topology=spec, episode_steps=steps, seed=seed, joint_prefix="t/", **LOCKSTEP)
    probe.spin_until(lambda: len({_ns(s) for s in controller.states}) >= wanted, STARTUP + 90, f"{wanted} states")
    episodes = -(-wanted // (steps + 1))
    probe.spin_until(lambda: len(_starts(announcements)) >= episodes, 20.0, f"{episodes} announcements")
    states = _unique(controller.states)[:wanted]
    starts = _starts(announcements)

    # Each episode's body: the announcement counts its joints, the latest URDF before its first state is its
    # tree (read back with read_urdf), and its states name exactly that tree's joints, in tree order.
    urdfs = [read_urdf(d.data).tree for d in descriptions]
    assert all(a != b for a, b in zip(urdfs, urdfs[1:], strict=False))  # published when the body changes only
    env = MorphSwimmerEnv(bodies=spec)
    env.reset(seed=seed)
    shapes, prefixed = set(), lambda tree: tuple(f"t/{n}" for n in tree.names)
    for k, s in enumerate(states):
        if k > 0:
            if _ns(s) in starts:
                env.reset()
            else:
                env.step(np.array([controller.answers[_ns(states[k - 1])][n] for n in states[k - 1].name]))
        if _ns(s) in starts:
            assert starts[_ns(s)].num_joints == env.num_joints
            shapes.add(env.tree.parents.tobytes())
        assert tuple(s.name) == prefixed(env.tree)
        assert any(t.names == prefixed(env.tree) and np.array_equal(t.parents, env.parents) for t in urdfs)
        np.testing.assert_array_equal(s.position, env.data.qpos[3:])
        np.testing.assert_array_equal(s.velocity, env.data.qvel[3:])
    assert len(shapes) >= 3  # several bodies were drawn, and each replayed
    assert urdfs[-1].names == prefixed(env.tree) and urdfs[-1].root_link == "t/torso"


@pytest.mark.timeout(180)
def test_num_joints_cannot_be_set_under_a_topology(probe, launch, namespace):
    states = probe.collect(JointState, "joint_states")
    launch("swimmer_sim_node", topology="y:2x2")
    probe.spin_until(lambda: states, STARTUP, "joint states")
    refused = probe.set_parameter(f"{namespace}/swimmer_sim", "num_joints", 4)
    assert not refused.successful and "topology" in refused.reason and "6 joints" in refused.reason
    same = probe.set_parameter(f"{namespace}/swimmer_sim", "num_joints", 6)
    assert same.successful  # the body's own count: nothing to do
    n = len(states)
    probe.spin_until(lambda: len(states) > n + 3, 20.0, "joint states after the refusal")
    assert {len(s.name) for s in states} == {6}


# -- shuffled joint order -------------------------------------------------------------------------------------
@pytest.mark.timeout(240)
@pytest.mark.parametrize("by_name", [False, True], ids=["state_order", "names_dimension"])
def test_shuffled_joints_change_the_order_not_the_physics(probe, launch, by_name):
    """Every state lists the joints in an order of its own; answered per joint name (in the state's order, or
    under a names dimension in reversed order), each joint gets its own effort (the next state's effort field
    says so) and the run, read by name, is the unshuffled one: the in-process replay in tree order."""
    spec, seed, wanted = "y:2x2", 11, 40
    controller = _Controller(probe, seed=3, by_name=by_name)
    launch("swimmer_sim_node", topology=spec, seed=seed, shuffle_joints=True, **LOCKSTEP)
    probe.spin_until(lambda: len({_ns(s) for s in controller.states}) >= wanted, STARTUP + 60, f"{wanted} states")
    states = _unique(controller.states)[:wanted]

    tree = parse_bodies(spec).first()
    orders = [tuple(s.name) for s in states]
    assert all(sorted(o) == sorted(tree.names) for o in orders)
    assert len(set(orders)) >= wanted // 2  # a fresh order per state (720 to draw from)
    env = MorphSwimmerEnv(bodies=spec)
    env.reset(seed=seed)
    for k, s in enumerate(states):
        if k > 0:
            answer = controller.answers[_ns(states[k - 1])]
            env.step(np.array([answer[n] for n in tree.names]))
            assert dict(zip(s.name, s.effort, strict=True)) == answer  # each joint its own
        at = [tree.names.index(n) for n in s.name]
        np.testing.assert_array_equal(s.position, env.data.qpos[3:][at])
        np.testing.assert_array_equal(s.velocity, env.data.qvel[3:][at])
    assert max(abs(e) for s in states[1:] for e in s.effort) > 0.1  # efforts were applied, not zeros


@pytest.mark.timeout(120)
def test_a_state_sent_again_after_a_prefix_change_is_shuffled_under_the_new_names(probe, launch, namespace):
    """Lockstep with no controller: the first state goes out again and again (same stamp, same order); once
    the prefix changes it goes out under the new names, in an order of their own."""
    states = probe.collect(JointState, "joint_states")
    proc = launch("swimmer_sim_node", num_joints=4, shuffle_joints=True, lockstep=True, effort_timeout=0.05)
    probe.spin_until(lambda: len(states) >= 3, STARTUP, "the first state sent three times")
    assert len({_ns(s) for s in states}) == 1 and len({tuple(s.name) for s in states}) == 1
    assert probe.set_parameter(f"{namespace}/swimmer_sim", "joint_prefix", "p/").successful
    n = len(states)
    probe.spin_until(lambda: any(s.name[0].startswith("p/") for s in states[n:]), 20.0, "the new names")
    renamed = [s for s in states[n:] if s.name[0].startswith("p/")]
    assert {_ns(s) for s in renamed} == {_ns(states[0])}  # still the first state, never stepped
    assert sorted(renamed[0].name) == [f"p/motor{k}_rot" for k in range(1, 5)]
    assert proc.alive()


@pytest.mark.timeout(180)
def test_efforts_naming_joints_the_body_lacks_are_rejected_and_counted(probe, launch, namespace, diagnostics):
    states = probe.collect(JointState, "joint_states")
    diag = diagnostics(f"{namespace}/swimmer_sim")
    pub = probe.node.create_publisher(Float64MultiArray, "effort_commands", 10)
    proc = launch("swimmer_sim_node", num_joints=3, shuffle_joints=True, real_time_factor=1.0, effort_timeout=600.0)
    probe.spin_until(lambda: states and pub.get_subscription_count() > 0 and diag.latest, STARTUP, "the sim")
    names = ["motor1_rot", "motor2_rot", "motor3_rot"]
    bad = {
        "unknown_joint": _command([0.1, 0.2, 0.3], names=["motor1_rot", "motor2_rot", "fin"]),
        "missing_joint": _command([0.1, 0.2], names=["motor1_rot", "motor3_rot"]),
        "names": _command([0.1, 0.2, 0.3], names=["motor1_rot", "motor1_rot", "motor2_rot"]),
        # computed on a star of these three joints, not on this chain
        "wrong_tree": _command([0.1, 0.2, 0.3], names=names, layout=KinematicTree.from_parents([-1, -1, -1], names)),
    }
    for msg in bad.values():
        pub.publish(msg)
    good = dict(zip(names, [0.5, -0.25, 0.75], strict=True))
    chain = KinematicTree.chain(3)  # the body's own layout: taken
    pub.publish(_command(list(good.values())[::-1], names=names[::-1], layout=chain))
    probe.spin_until(
        lambda: dict(zip(states[-1].name, states[-1].effort, strict=True)) == good, 20.0, "the good command applied"
    )
    probe.spin_until(lambda: diag.latest["effort_commands"].rejected_total >= len(bad), 20.0, "the rejections counted")
    counts = diag.latest["effort_commands"]
    assert dict(counts.rejected) == dict.fromkeys(bad, 1), counts
    assert "rejected effort command" in proc.log() and "fin" in proc.log()
    assert proc.alive()


# -- your own robot ---------------------------------------------------------------------------------------------
@pytest.mark.timeout(180)
def test_the_sim_runs_the_ant_model(probe, launch):
    states = probe.collect(JointState, "joint_states")
    odoms = probe.collect(Odometry, "odom")
    clocks = probe.collect(Clock, "/clock")
    pub = probe.node.create_publisher(Float64MultiArray, "effort_commands", 10)
    launch("swimmer_sim_node", model_file=str(ANT_XML), real_time_factor=2.0, effort_timeout=600.0)
    probe.spin_until(lambda: len(states) > 5 and odoms and clocks, STARTUP, "the ant's states")
    robot = load_robot(ANT_XML)
    assert all(tuple(s.name) == robot.tree.names for s in states)  # the MJCF's names, tree order

    descriptions = probe.collect(String, "robot_description", LATCHED)  # latched: a late subscriber gets it
    probe.spin_until(lambda: descriptions, 20.0, "the ant's robot_description")
    assert read_urdf(descriptions[-1].data).tree == robot.tree

    # Efforts by name reach their joints: the state after reports them applied.
    want = {name: 0.1 * (k + 1) * (-1) ** k for k, name in enumerate(robot.tree.names)}
    names = sorted(want)
    pub.publish(_command([want[n] for n in names], names=names))
    probe.spin_until(
        lambda: dict(zip(states[-1].name, states[-1].effort, strict=True)) == want,
        20.0,
        "the efforts applied",
    )

    # Odometry: frame odom -> torso, a 3-D pose (it stands about 0.75 m up at first), a unit quaternion,
    # stamped as the joint states.
    first = odoms[0]
    assert (first.header.frame_id, first.child_frame_id) == ("odom", "torso")
    assert 0.4 < first.pose.pose.position.z < 1.0
    q = first.pose.pose.orientation
    assert abs(np.linalg.norm([q.x, q.y, q.z, q.w]) - 1) < 1e-9
    assert len({_ns(o) for o in odoms} & {_ns(s) for s in states}) > len(states) // 2
    twists = np.array([[o.twist.twist.linear.x, o.twist.twist.angular.y] for o in odoms])
    assert np.abs(twists).max() > 1e-3  # a full twist, not a planar one left at zero


def _doc_commands(block: int) -> list[str]:
    """The command lines of the ``block``-th bash block of docs/your_robot.md (comments left out)."""
    blocks = re.findall(r"```bash\n(.*?)```", YOUR_ROBOT_DOC.read_text(), re.S)
    return [line for line in blocks[block].splitlines() if line.strip() and not line.lstrip().startswith("#")]


def _doc_ant(assignment: str) -> str:
    """Run the doc's ``ANT=...`` line as a shell would (``python`` is this environment's), return ``$ANT``."""
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}"}
    out = subprocess.run(["bash", "-c", f'{assignment}\necho "$ANT"'], env=env, capture_output=True, text=True,
                         cwd=YOUR_ROBOT_DOC.parents[1])  # from the checkout, as the page says  # fmt: skip
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


@pytest.mark.timeout(120)
def test_your_robot_doc_commands_run(probe, launch):
    """docs/your_robot.md's first commands, as written: the sim on ant.xml and the policy node with no
    configuration (the shipped model). The robot's states come, the policy node reads the ant's tree off its
    robot_description, and its efforts, eight per state computed on that tree, are applied."""
    states = probe.collect(JointState, "joint_states")
    efforts = probe.collect(Float64MultiArray, "effort_commands")
    assignment, *node_lines = _doc_commands(0)
    ant = _doc_ant(assignment)
    assert Path(ant) == ANT_XML
    procs = []
    for line in node_lines:  # "executable [--ros-args -p name:=value ...]"
        executable, *rest = shlex.split(line.replace("$ANT", ant))
        assert executable.startswith(".venv/bin/"), line  # runs in a fresh shell: the venv named
        executable = Path(executable).name
        assert rest[:1] in ([], ["--ros-args"]) and rest[1::2] == ["-p"] * (len(rest) // 2), line
        params = dict(arg.split(":=", 1) for arg in rest[2::2])
        procs.append(launch(executable, **params))
    assert [p.log_path.name.split("_")[0] for p in procs] == ["swimmer", "morph"]
    probe.spin_until(lambda: len(efforts) >= 20 and len(states) >= 20, STARTUP, "the ant's closed loop running")
    assert "robot 'ant'" in procs[0].log() and "(8 joints, root 'torso')" in procs[0].log()
    assert {len(e.data) for e in efforts} == {8} and {tuple(s.name) for s in states} == {load_robot(ANT_XML).tree.names}
    values = np.array([e.data for e in efforts])
    assert np.isfinite(values).all() and np.abs(values).max() <= 1.0 and np.abs(values).max() > 0
    assert "robot_description: 8 actuated joints, a tree" in procs[1].log()
    assert effort_tree([d.label for d in efforts[-1].layout.dim]) == load_robot(ANT_XML).tree.layout_hash
    probe.spin_until(
        lambda: any(tuple(e.data) in {tuple(s.effort) for s in states} for e in efforts),
        STARTUP,
        "a state reporting one of the policy's efforts as applied",
    )


@pytest.mark.timeout(320)
def test_your_robot_doc_bringup_runs(tmp_path):
    """docs/your_robot.md's bring-up line, as written (its sim seconds as given)."""
    assignment = _doc_commands(0)[0]
    (line,) = _doc_commands(1)
    args = shlex.split(line.replace('"$ANT"', _doc_ant(assignment)))
    assert args[:3] == [".venv/bin/python", "-m", "morph_policy_node.bringup"]
    code, log = _bringup(tmp_path, *args[3:])
    assert code == 0 and f"robot {ANT_XML}, 8 joints" in log, log[-3000:]


@pytest.mark.timeout(120)
def test_the_ant_cannot_be_rebuilt(probe, launch, namespace):
    states = probe.collect(JointState, "joint_states")
    launch("swimmer_sim_node", model_file=str(ANT_XML))
    probe.spin_until(lambda: states, STARTUP, "the ant's states")
    refused = probe.set_parameter(f"{namespace}/swimmer_sim", "num_joints", 3)
    assert not refused.successful and "model_file" in refused.reason


def _slide_mjcf(tmp_path: Path) -> Path:
    path = tmp_path / "slider.xml"
    path.write_text(
        "<mujoco><worldbody><body name='cart'><joint name='rail' type='slide'/><geom size='.1'/>"
        "<body name='pole'><joint name='hinge' type='hinge'/><geom size='.1'/></body></body></worldbody>"
        "<actuator><motor joint='rail'/><motor joint='hinge'/></actuator></mujoco>"
    )
    return path


@pytest.mark.timeout(120)
@pytest.mark.parametrize(
    "params, words",
    [
        ({"model_file": "/nonexistent/robot.xml"}, "no such file"),
        ({"model_file": "slide"}, "'rail', a slide joint: only hinges can be actuated"),
        ({"model_file": str(ANT_XML), "topology": "y:2x2"}, "topology and model_file are both set"),
        ({"topology": "y:2x2", "min_joints": 2, "max_joints": 5}, "min_joints and max_joints must stay 0"),
        ({"topology": "tentacle:8"}, "unknown body family"),
        ({"num_joints": 100}, "num_joints"),  # out of its declared range: rclpy's refusal, no traceback
    ],
    ids=["missing", "slide_actuator", "both", "topology_and_range", "bad_spec", "joints_out_of_range"],
)
def test_a_body_that_cannot_run_stops_the_node_with_one_line(launch, tmp_path, params, words):
    if params.get("model_file") == "slide":
        params = {**params, "model_file": str(_slide_mjcf(tmp_path))}
    proc = launch("swimmer_sim_node", **params)
    assert proc.proc.wait(timeout=STARTUP) == 1
    lines = [line for line in proc.log().splitlines() if "cannot start" in line]
    assert len(lines) == 1 and words in lines[0], proc.log()
    assert "Traceback" not in proc.log()


@pytest.mark.parametrize(
    "args, kind",
    [
        ((6, 0, 0, "", ""), "chain"),
        ((6, 2, 9, "", ""), "range"),
        ((6, 0, 0, "star:3x2", ""), "spec"),
        ((6, 0, 0, "", str(ANT_XML)), "robot"),
        ((6, 0, 0, "centipede:5", ""), "centipede"),
    ],
)
def test_make_sim_builds_the_body_the_parameters_ask_for(args, kind):
    sim, described = make_sim(*args, seed=0)
    if kind == "chain":
        assert sim.num_joints == 6 and sim.joint_range == (6, 6) and described == "swimmer with 6 joints"
    elif kind == "range":
        assert sim.joint_range == (2, 9) and "2..9" in described
    elif kind == "spec":
        assert sim.bodies == parse_bodies("star:3x2") and sim.tree.parents.tolist() == [-1, 0, -1, 2, -1, 4]
        assert described.startswith("swimmers of 'star:3x2'")
    elif kind == "centipede":  # named by what it is: no "swimmers of 'centipede:5'"
        assert described.startswith("centipedes of 'centipede:5'") and sim.num_joints == 20
    else:
        assert sim.robot is not None and sim.tree == KinematicTree.from_mujoco(
            mujoco.MjModel.from_xml_path(str(ANT_XML))
        )
        assert "'ant'" in described


# -- the demo's bring-up ------------------------------------------------------------------------------------
def _bringup(tmp_path: Path, *args: str) -> tuple[int, str]:
    """Run the bring-up (2 s of sim time unless ``args`` say otherwise); its exit code and output."""
    log = tmp_path / "bringup.log"
    with open(log, "wb") as out:
        proc = subprocess.run(
            [sys.executable, "-m", "morph_policy_node.bringup", "--seconds", "2", *args],
            stdout=out,
            stderr=subprocess.STDOUT,
            timeout=300,
        )
    return proc.returncode, log.read_text(errors="replace")


@pytest.mark.timeout(320)
@pytest.mark.parametrize(
    "args, gait, words",
    [
        (["--bodies", "y:1x1"], "swim speed:", "bodies y:1x1, 3 joints"),
        (["--model-file", str(ANT_XML)], "walk speed:", f"robot {ANT_XML}, 8 joints"),
    ],
    ids=["bodies", "model_file"],
)
def test_the_bringup_runs_a_tree_or_a_robot_and_prints_its_speed(tmp_path, untrained_checkpoint, args, gait, words):
    """A swimmer swims; Gymnasium's ant, a robot on a floor, walks, and the line counts its falls."""
    code, log = _bringup(tmp_path, *args, "--checkpoint", str(untrained_checkpoint))
    lines = [line for line in log.splitlines() if line.startswith(gait)]
    assert code == 0 and len(lines) == 1 and words in lines[0], log[-3000:]
    assert ("fell " in lines[0]) == (gait == "walk speed:")


@pytest.mark.parametrize("args", [["--joints", "100"], ["--joints", "0"], ["--seconds", "0"]])
def test_the_bringup_refuses_what_the_sim_cannot_run_in_one_line_before_any_node(tmp_path, args):
    code, log = _bringup(tmp_path, *args)
    assert code == 2 and len(log.strip().splitlines()) == 1 and "cannot start:" in log, log
    assert "Traceback" not in log and "swimmer_sim" not in log


def test_the_bringup_posture_counts_each_fall_once():
    from types import SimpleNamespace as Q

    from morph_policy_node.bringup import Posture

    posture = Posture()
    for q in [Q(x=0.0, y=0.0, z=0.3, w=0.95)] * 3:  # a swimmer: planar, upright
        posture.see(0.0, q)
    assert not posture.in_3d and posture.falls == 0
    upright, over = Q(x=0.0, y=0.1, z=0.0, w=0.99), Q(x=0.0, y=0.99, z=0.0, w=0.1)  # tipped past the horizon
    for q in [upright, over, over, upright, over]:
        posture.see(0.5, q)
    assert posture.in_3d and posture.falls == 2


@pytest.mark.timeout(320)
def test_the_bringup_stops_with_one_line_when_the_model_file_cannot_run(tmp_path):
    code, log = _bringup(tmp_path, "--model-file", str(tmp_path / "missing.xml"), "--startup-timeout", "60")
    assert code == 1 and "no such file" in log and "bringup: the sim node did not come up" in log, log[-3000:]
    assert "Traceback" not in log
