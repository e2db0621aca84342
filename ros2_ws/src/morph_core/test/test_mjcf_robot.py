"""Your own robot in the sim: any MJCF of actuated hinges (Gymnasium's ant.xml here, and a made-up gadget with
every case the tree rule has), its joints, efforts to ctrl, root odometry, episodes, and the refusals."""

from __future__ import annotations

from pathlib import Path

import gymnasium
import mujoco
import numpy as np
import pytest

from morph_core.env.mjcf_robot import MjcfRobot, RobotModelError, load_robot
from morph_core.env.sim import SwimmerSim
from morph_core.msgs.episode_start import EpisodeCause
from morph_core.policy.tree import KinematicTree

ANT_XML = Path(gymnasium.__file__).parent / "envs" / "mujoco" / "assets" / "ant.xml"

GADGET_PATH = Path(__file__).parent / "data" / "gadget.xml"
"""a made-up robot with each case the tree rule has: a free root, a hinge off its body's origin with a ref, an
unlimited hinge and a second on one body, an unnamed body without joints, an unactuated hinge, motors out of
order, an asymmetric, an unlimited and a doubled actuator, a position servo; boxes, spheres, an ellipsoid"""
GADGET_XML = GADGET_PATH.read_text()
GADGET_JOINTS = ("shoulder", "elbow_a", "elbow_b", "wrist", "tail_yaw")


def _write(tmp_path: Path, text: str | bytes, name: str = "robot.xml") -> Path:
    path = tmp_path / name
    path.write_bytes(text.encode() if isinstance(text, str) else text)
    return path


@pytest.fixture
def gadget() -> Path:
    return GADGET_PATH


def test_the_ants_joints_are_its_actuated_hinges_in_tree_order():
    robot = load_robot(ANT_XML)
    model = mujoco.MjModel.from_xml_path(str(ANT_XML))
    assert robot.tree == KinematicTree.from_mujoco(model)
    assert robot.tree.names == tuple(f"{part}_{k}" for k in range(1, 5) for part in ("hip", "ankle"))
    assert robot.tree.parents.tolist() == [-1, 0, -1, 2, -1, 4, -1, 6]  # four legs of two joints
    assert robot.tree.root_link == "torso" and robot.name == "ant"
    sim = SwimmerSim(robot=robot, seed=0)
    assert sim.joint_names("a/") == [f"a/{n}" for n in robot.tree.names]
    assert sim.num_joints == 8 and sim.joint_range == (8, 8) and sim.dt == pytest.approx(0.04)
    # Positions and velocities are the named joints' own entries of qpos and qvel.
    for k, name in enumerate(robot.tree.names):
        j = mujoco.mj_name2id(robot.model, mujoco.mjtObj.mjOBJ_JOINT, name)
        assert sim.joint_positions[k] == robot.data.qpos[robot.model.jnt_qposadr[j]]
        assert sim.joint_velocities[k] == robot.data.qvel[robot.model.jnt_dofadr[j]]


def test_efforts_reach_each_actuators_ctrl_scaled_to_its_range(gadget):
    """The ant lists its motors in another order than its joints; the gadget has asymmetric, unlimited and
    doubled actuators: ctrl = effort x the far end of the ctrl range (1 when unlimited)."""
    ant = SwimmerSim(robot=load_robot(ANT_XML), seed=0, effort_timeout=None)
    efforts = np.linspace(-0.8, 0.9, 8)
    ant.command(efforts, now=0)
    ant.step(now=0)
    by_actuator = ["hip_4", "ankle_4", "hip_1", "ankle_1", "hip_2", "ankle_2", "hip_3", "ankle_3"]
    want = [efforts[ant.tree.names.index(name)] for name in by_actuator]
    np.testing.assert_array_equal(ant.robot.data.ctrl, want)
    np.testing.assert_array_equal(ant.applied, efforts)

    sim = SwimmerSim(robot=load_robot(gadget), seed=0, effort_timeout=None)
    assert sim.tree.names == GADGET_JOINTS
    e = np.array([0.5, -0.4, 0.7, -0.3, 0.2])  # shoulder, elbow_a, elbow_b, wrist, tail_yaw
    sim.command(e, now=0)
    sim.step(now=0)
    # wrist x 2, shoulder x 1, elbow_a x max(0.5, 1), elbow_b unlimited x 1, tail_yaw x 1, shoulder again x 1
    np.testing.assert_allclose(sim.robot.data.ctrl, [-0.6, 0.5, -0.4, 0.7, 0.2, 0.5], rtol=0, atol=0)
    sim.command([2.0, -3.0, 0, 0, 0], now=1)  # clipped to [-1, 1] first
    sim.step(now=1)
    assert sim.robot.data.ctrl[1] == 1.0 and sim.robot.data.ctrl[2] == -1.0


def test_zero_effort_is_zero_ctrl_and_a_timeout_zeroes_it():
    sim = SwimmerSim(robot=load_robot(ANT_XML), seed=0, effort_timeout=0.25)
    sim.command(np.ones(8), now=0.0)
    sim.step(now=0.1)
    assert (sim.robot.data.ctrl == 1).all()
    sim.step(now=1.0)
    assert sim.timed_out and (sim.robot.data.ctrl == 0).all()


def _quat_matrix(x, y, z, w) -> np.ndarray:
    mat = np.empty(9)
    mujoco.mju_quat2Mat(mat, np.array([w, x, y, z]))
    return mat.reshape(3, 3)


def test_odometry_of_a_free_root_is_its_pose_and_body_frame_twist():
    sim = SwimmerSim(robot=load_robot(ANT_XML), seed=3, effort_timeout=None)
    rng = np.random.default_rng(0)
    for k in range(30):
        sim.command(rng.uniform(-1, 1, 8), now=k)
        sim.step(now=k)
    odom = sim.odometry()
    qpos, qvel = sim.robot.data.qpos, sim.robot.data.qvel
    assert odom.frame == "torso"
    np.testing.assert_allclose(odom.position, qpos[:3], atol=1e-12)
    w, x, y, z = qpos[3:7] / np.linalg.norm(qpos[3:7])
    np.testing.assert_allclose(odom.orientation, [x, y, z, w], atol=1e-12)
    # The free joint's qvel: linear velocity in the world frame, angular in the body's.
    rot = _quat_matrix(*odom.orientation)
    np.testing.assert_allclose(odom.linear, rot.T @ qvel[:3], atol=1e-9)
    np.testing.assert_allclose(odom.angular, qvel[3:6], atol=1e-9)
    assert np.abs(odom.linear).max() > 1e-3  # it moved: the check compared a real twist
    assert abs(np.linalg.norm(odom.orientation) - 1) < 1e-12


def test_a_root_fixed_to_the_world_stands_still(tmp_path):
    text = GADGET_XML.replace('<freejoint name="float"/>', "")
    sim = SwimmerSim(robot=load_robot(_write(tmp_path, text)), seed=0, effort_timeout=None)
    sim.command(np.full(5, 0.8), now=0)
    for k in range(10):
        sim.step(now=k)
    odom = sim.odometry()
    assert odom.frame == "base"
    np.testing.assert_allclose(odom.position, [0.1, 0.2, 0.5], atol=1e-12)
    np.testing.assert_allclose(odom.linear + odom.angular, 0, atol=1e-12)
    assert np.abs(sim.joint_velocities).max() > 1e-3  # the arm moved; its base did not


def _run(sim: SwimmerSim, steps: int, seed: int):
    rng = np.random.default_rng(seed)
    out = [sim.robot.data.qpos.copy()]
    for k in range(steps):
        sim.command(rng.uniform(-1, 1, sim.num_joints), now=k)
        sim.advance(now=k)
        out.append(sim.robot.data.qpos.copy())
    return np.array(out)


def test_episodes_reset_with_fresh_noise_and_replay_from_the_seed():
    a = SwimmerSim(robot=load_robot(ANT_XML), seed=5, effort_timeout=None, episode_steps=10)
    b = SwimmerSim(robot=load_robot(ANT_XML), seed=5, effort_timeout=None, episode_steps=10)
    c = SwimmerSim(robot=load_robot(ANT_XML), seed=6, effort_timeout=None, episode_steps=10)
    qa, qb, qc = _run(a, 35, 0), _run(b, 35, 0), _run(c, 35, 0)
    np.testing.assert_array_equal(qa, qb)
    assert np.abs(qa - qc).max() > 1e-3
    assert a.episode == 3 and a.episode_cause is EpisodeCause.STEPS
    # Each episode starts at qpos0 plus noise of at most the scale, each with its own noise.
    model = a.robot.model
    starts = [qa[0], qa[11], qa[22], qa[33]]
    for q in starts:
        assert np.abs(q[:3] - model.qpos0[:3]).max() <= 0.1 + 1e-12
        assert np.abs(q[7:] - model.qpos0[7:]).max() <= 0.1 + 1e-12
        assert abs(np.linalg.norm(q[3:7]) - 1) < 1e-12  # the free joint's quaternion stays a rotation
    assert len({q.tobytes() for q in starts}) == 4
    # A fresh robot reset the same way from the same seed is the same run (the replay rule).
    robot = load_robot(ANT_XML)
    robot.reset(seed=5)
    np.testing.assert_array_equal(robot.data.qpos, qa[0])
    robot.reset()
    np.testing.assert_array_equal(robot.data.qpos, qa[11])


def test_the_models_keyframe_is_where_an_episode_starts(tmp_path):
    text = GADGET_XML.replace(
        "</actuator>", '</actuator>\n  <keyframe><key qpos="0 0 2 1 0 0 0 0.5 0.1 0.2 0 0.3 -0.4"/></keyframe>'
    )
    sim = SwimmerSim(robot=load_robot(_write(tmp_path, text)), seed=0)
    assert 1.8 < sim.odometry().position[2] < 2.2
    np.testing.assert_allclose(sim.joint_positions, [0.5, 0.1, 0.2, 0.3, -0.4], atol=0.1 + 1e-12)


def test_a_robot_model_cannot_be_rebuilt():
    sim = SwimmerSim(robot=load_robot(ANT_XML))
    with pytest.raises(ValueError, match="ant.*cannot be rebuilt"):
        sim.rebuild(4)
    with pytest.raises(TypeError, match="odometry"):
        sim.torso()
    with pytest.raises(ValueError, match="not both"):
        SwimmerSim(robot=load_robot(ANT_XML), bodies="y:1x1")


def test_divergence_starts_a_new_episode(tmp_path):
    """A motor far too strong for its link: MuJoCo's acceleration check resets the state; the sim begins
    the next episode in its place, as it does for a swimmer."""
    text = GADGET_XML.replace('gear="3" ctrlrange="-2 2"', 'gear="1e16" ctrlrange="-2 2"')
    sim = SwimmerSim(robot=load_robot(_write(tmp_path, text)), seed=0, effort_timeout=None)
    sim.command([0, 0, 0, 1.0, 0], now=0)
    assert not sim.step(now=0)
    assert sim.episode == 1 and sim.episode_cause is EpisodeCause.DIVERGED and sim.unstable_resets == 1
    assert np.isfinite(sim.joint_positions).all() and not sim.applied.any()


# -- refusals ------------------------------------------------------------------------------------------------
def _refusal(path) -> str:
    with pytest.raises(RobotModelError) as err:
        load_robot(path)
    reason = str(err.value)
    assert "\n" not in reason and str(path) in reason
    return reason


def test_missing_and_unreadable_paths_are_refused(tmp_path):
    assert "no such file" in _refusal(tmp_path / "nope.xml")
    assert "not a regular file" in _refusal(tmp_path)
    with pytest.raises(RobotModelError, match="empty"):
        load_robot("")


@pytest.mark.parametrize(
    "content, words",
    [
        (b"", "malformed XML"),
        (b"\x00\xff\xfe garbage \x89PNG", "malformed XML"),
        (ANT_XML.read_bytes()[: len(ANT_XML.read_bytes()) // 2], "malformed XML"),
        (b'<robot name="r"><link name="a"/></robot>', "<robot>"),
        (b"<html><body>hi</body></html>", "root element is <html>"),
        (b"<mujoco><worldbody><frobnicate/></worldbody></mujoco>", "does not compile: XML Error"),
        (b'<mujoco><worldbody><body><geom size="-1"/></body></worldbody></mujoco>', "does not compile"),
        (b'<mujoco><include file="elsewhere.xml"/></mujoco>', "does not compile"),
    ],
    ids=["empty", "binary", "truncated", "urdf", "html", "unknown_element", "bad_geom", "missing_include"],
)
def test_files_that_are_not_mjcf_or_do_not_compile_are_refused(tmp_path, content, words):
    assert words in _refusal(_write(tmp_path, content))


def _arm(joints: int, actuated: str = "hinge") -> str:
    bodies = "".join(
        f'<body name="b{k}" pos="0.1 0 0"><joint name="j{k}" type="{actuated if k == 0 else "hinge"}"/>'
        '<geom size="0.01"/>'
        for k in range(joints)
    )
    motors = "".join(f'<motor joint="j{k}"/>' for k in range(joints))
    return f"<mujoco><worldbody>{bodies}{'</body>' * joints}</worldbody><actuator>{motors}</actuator></mujoco>"


@pytest.mark.parametrize(
    "text, words",
    [
        (_arm(2, "slide"), "a slide joint: only hinges can be actuated"),
        (_arm(2, "ball"), "a ball joint"),
        (_arm(65), "65 actuated joints, more than the maximum of 64"),
        (_arm(2).replace("<actuator>", "<actuator>").replace('<motor joint="j0"/><motor joint="j1"/>', ""), "empty"),
        (_arm(1).replace("j0", "j\u00e9"), "not printable ASCII"),
        (
            _arm(1)
            .replace('name="b0" ', "")
            .replace("<worldbody>", '<worldbody><body name="x">', 1)
            .replace("</worldbody>", "</body></worldbody>"),
            "",
        ),  # fmt: skip
        (
            "<mujoco><worldbody><body><body name='a'><joint name='j' type='hinge'/><geom size='.1'/></body></body>"
            "</worldbody><actuator><motor joint='j'/></actuator></mujoco>",
            "root body",
        ),
        (
            "<mujoco><worldbody><body name='a'><joint name='j' type='hinge'/><geom size='.1'/><site name='s'/>"
            "</body></worldbody><actuator><motor site='s'/></actuator></mujoco>",
            "drives a site",
        ),
    ],
    ids=["slide", "ball", "too_many", "no_actuator", "non_ascii_name", "named_root_ok", "unnamed_root", "site"],
)
def test_models_that_are_not_a_tree_of_actuated_hinges_are_refused(tmp_path, text, words):
    path = _write(tmp_path, text)
    if not words:  # the control case: a named root above an unnamed hinge body is fine
        assert load_robot(path).tree.root_link == "x"
        return
    assert words in _refusal(path)


def test_fuzzed_model_files_load_or_are_refused_with_one_line(tmp_path):
    """Random damage to ant.xml (bytes flipped, cut out, doubled): each file either runs or is refused with a
    one-line RobotModelError, never another exception."""
    good = ANT_XML.read_bytes()
    rng = np.random.default_rng(38)
    outcomes = {"loaded": 0, "refused": 0}
    for case in range(60):
        data = bytearray(good)
        for _ in range(int(rng.integers(1, 4))):
            at = int(rng.integers(len(data)))
            kind = rng.integers(3)
            if kind == 0:
                data[at] = int(rng.integers(256))
            elif kind == 1:
                del data[at : at + int(rng.integers(1, 40))]
            else:
                data[at:at] = data[at : at + int(rng.integers(1, 40))]
        path = _write(tmp_path, bytes(data), f"fuzz{case}.xml")
        try:
            robot = load_robot(path)
        except RobotModelError as err:
            assert "\n" not in str(err)
            outcomes["refused"] += 1
            continue
        sim = SwimmerSim(robot=robot, seed=case, effort_timeout=None)
        sim.command(np.ones(sim.num_joints), now=0)
        sim.advance(now=0)
        assert np.isfinite(sim.joint_positions).all()
        outcomes["loaded"] += 1
    assert outcomes["loaded"] > 0 and outcomes["refused"] > 0, outcomes


def test_a_robot_hung_off_the_world_has_the_world_as_root():
    robot = MjcfRobot(mujoco.MjModel.from_xml_string(_arm(3)))
    assert robot.tree.root_link == "world" and robot.tree.parents.tolist() == [-1, 0, 1]
    robot.reset(seed=0)
    odom = robot.root_state()
    assert odom.frame == "world" and odom.position == (0.0, 0.0, 0.0) and odom.orientation == (0.0, 0.0, 0.0, 1.0)
