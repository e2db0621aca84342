"""The swimmer's (and any robot model's) URDF and planar segment poses against the compiled MuJoCo model.

The URDF goes through a real URDF parser (urdf_parser_py, ROS's own); its
forward kinematics, written here from the URDF's joint origins, axes and
visual origins, must put every capsule where ``mj_kinematics`` does for
random bends, and its names, limits and lengths must be the MJCF's.
"""

from __future__ import annotations

import math
from pathlib import Path

import gymnasium
import mujoco
import numpy as np
import pytest
from urdf_parser_py.urdf import URDF

from morph_core.env.bodies import parse_bodies
from morph_core.env.model import GEAR, HINGE_RANGE_DEG, SEGMENT_LENGTH, SEGMENT_RADIUS, swimmer_model
from morph_core.env.segments import segment_poses
from morph_core.env.sim import SwimmerSim
from morph_core.env.urdf import robot_urdf, swimmer_urdf
from morph_core.policy.joint_description import NO_EFFORT_LIMIT
from morph_core.policy.tree import KinematicTree, TreeError, read_urdf

LENGTHS = [1, 6, 64]
TREES = [
    *(parse_bodies(spec).first() for spec in ("star:3x2", "y:2x3", "comb:5", "star:4x8")),
    *(parse_bodies(f"random:8-32:b{b}").draw(np.random.default_rng(b)) for b in (2, 3)),
]
BODIES = [*LENGTHS, *TREES]


def _body_id(body) -> str:
    return str(body) if isinstance(body, int) else f"tree{body.num_joints}-{body.topology_hash[:6]}"


def _rpy_matrix(rpy) -> np.ndarray:
    r, p, y = rpy
    rx = np.array([[1, 0, 0], [0, math.cos(r), -math.sin(r)], [0, math.sin(r), math.cos(r)]])
    ry = np.array([[math.cos(p), 0, math.sin(p)], [0, 1, 0], [-math.sin(p), 0, math.cos(p)]])
    rz = np.array([[math.cos(y), -math.sin(y), 0], [math.sin(y), math.cos(y), 0], [0, 0, 1]])
    return rz @ ry @ rx


def _transform(xyz, rpy) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = _rpy_matrix(rpy or (0, 0, 0))
    t[:3, 3] = xyz or (0, 0, 0)
    return t


def _axis_rotation(axis, angle) -> np.ndarray:
    mat = np.empty(9)
    quat = np.empty(4)
    mujoco.mju_axisAngle2Quat(quat, np.asarray(axis, dtype=float), angle)
    mujoco.mju_quat2Mat(mat, quat)
    t = np.eye(4)
    t[:3, :3] = mat.reshape(3, 3)
    return t


def _urdf_capsules(robot: URDF, root_pose: np.ndarray, angles: dict[str, float]) -> dict[str, np.ndarray]:
    """Link name -> world transform of its visual cylinder, by the URDF's own kinematics."""
    link_pose = {robot.get_root(): root_pose}
    pending = list(robot.joints)
    while pending:  # parents before children, whatever order the file lists joints in
        joint = next(j for j in pending if j.parent in link_pose)
        pending.remove(joint)
        t = link_pose[joint.parent] @ _transform(joint.origin.xyz, joint.origin.rpy)
        link_pose[joint.child] = t @ _axis_rotation(joint.axis, angles[joint.name])
    return {
        link.name: link_pose[link.name] @ _transform(link.visual.origin.xyz, link.visual.origin.rpy)
        for link in robot.links
    }


@pytest.mark.parametrize("body", BODIES, ids=_body_id)
def test_urdf_matches_the_mujoco_model(body):
    m = swimmer_model(body)
    text = swimmer_urdf(body)
    robot = URDF.from_xml_string(text)
    revolute = [j for j in robot.joints if j.type == "revolute"]
    joints = m.nu
    assert KinematicTree.from_urdf(text) == KinematicTree.from_mujoco(m)  # the same tree, in the same order

    assert [j.name for j in revolute] == SwimmerSim(num_joints=joints).joint_names()
    assert [link.name for link in robot.links] == [
        mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) for b in range(1, m.nbody)
    ]
    assert robot.get_root() == "torso"
    assert len(robot.joints) == len(revolute) == joints
    for joint in revolute:
        j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, joint.name)
        assert (joint.limit.lower, joint.limit.upper) == pytest.approx(tuple(m.jnt_range[j]), abs=1e-15)
        assert joint.limit.upper == pytest.approx(math.radians(HINGE_RANGE_DEG))
        assert joint.limit.effort == pytest.approx(GEAR)
        assert joint.parent == mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, m.body_parentid[m.jnt_bodyid[j]])
    for link in robot.links:
        b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, link.name)
        assert link.visual.geometry.length == pytest.approx(SEGMENT_LENGTH)
        assert link.visual.geometry.radius == pytest.approx(SEGMENT_RADIUS)
        assert link.inertial.mass == pytest.approx(m.body_mass[b])

    # Random bends and torso poses: every capsule where MuJoCo puts it, pointing the same way.
    rng = np.random.default_rng(joints + len(robot.links))
    d = mujoco.MjData(m)
    for _ in range(5):
        d.qpos[:2] = rng.uniform(-5, 5, 2)
        d.qpos[2] = rng.uniform(-math.pi, math.pi)
        d.qpos[3:] = rng.uniform(*m.jnt_range[3], joints)
        mujoco.mj_kinematics(m, d)
        root = _transform([d.qpos[0], d.qpos[1], 0.0], [0.0, 0.0, d.qpos[2]])
        capsules = _urdf_capsules(robot, root, dict(zip([j.name for j in revolute], d.qpos[3:], strict=True)))
        for name, t in capsules.items():
            g = np.flatnonzero(m.geom_bodyid == mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name))[0]
            np.testing.assert_allclose(t[:3, 3], d.geom_xpos[g], atol=1e-9)
            np.testing.assert_allclose(t[:3, :3], d.geom_xmat[g].reshape(3, 3), atol=1e-9)


def test_urdf_prefix_names_every_link_and_joint():
    robot = URDF.from_xml_string(swimmer_urdf(2, prefix="left/"))
    assert [link.name for link in robot.links] == ["left/torso", "left/mid", "left/back"]
    assert [j.name for j in robot.joints] == SwimmerSim(num_joints=2).joint_names("left/")
    assert [(j.parent, j.child) for j in robot.joints] == [("left/torso", "left/mid"), ("left/mid", "left/back")]


@pytest.mark.parametrize("bad", [0, 65, 2.0, "6"])
def test_urdf_refuses_a_bad_length(bad):
    with pytest.raises((ValueError, TypeError), match="num_joints"):
        swimmer_urdf(bad)


@pytest.mark.parametrize("body", BODIES, ids=_body_id)
def test_segment_poses_are_mujoco_kinematics(body):
    m = swimmer_model(body)
    joints = m.nu
    parents = None if isinstance(body, int) else body  # a chain needs no parents
    d = mujoco.MjData(m)
    rng = np.random.default_rng(100 + joints)
    for _ in range(5):
        d.qpos[:2] = rng.uniform(-5, 5, 2)
        d.qpos[2] = rng.uniform(-10, 10)  # continuous yaw, many turns
        d.qpos[3:] = rng.uniform(*m.jnt_range[3], joints)
        mujoco.mj_kinematics(m, d)
        poses = segment_poses(d.qpos[0], d.qpos[1], d.qpos[2], d.qpos[3:], parents)
        np.testing.assert_allclose(poses.centers, d.geom_xpos[1:, :2], atol=1e-9)
        axes = d.geom_xmat[1:].reshape(-1, 3, 3)[:, :, 2]  # a capsule's axis is its local z
        heading = np.stack([np.cos(poses.headings), np.sin(poses.headings), np.zeros(joints + 1)], axis=1)
        np.testing.assert_allclose(np.abs(np.sum(axes * heading, axis=1)), 1.0, atol=1e-9)
        np.testing.assert_allclose(poses.lengths, 2 * m.geom_size[1:, 1])
        np.testing.assert_allclose(poses.radii, m.geom_size[1:, 0])


def test_segment_poses_refuse_positions_of_another_body():
    with pytest.raises(ValueError, match="joint positions"):
        segment_poses(0, 0, 0, np.zeros(3), [-1, 0, 0, 0])


# -- your own robot: any compiled model ----------------------------------------------------------------------
ANT_XML = Path(gymnasium.__file__).parent / "envs" / "mujoco" / "assets" / "ant.xml"
GADGET_XML = (Path(__file__).parent / "data" / "gadget.xml").read_text()  # test_mjcf_robot says what it has


def _robot_models() -> dict[str, mujoco.MjModel]:
    return {
        "ant": mujoco.MjModel.from_xml_path(str(ANT_XML)),
        "gadget": mujoco.MjModel.from_xml_string(GADGET_XML),
        "gadget_on_world": mujoco.MjModel.from_xml_string(GADGET_XML.replace('<freejoint name="float"/>', "")),
    }


def _urdf_link_poses(robot: URDF, root_pose: np.ndarray, angles: dict[str, float]) -> dict[str, np.ndarray]:
    """Link name -> world transform of the link frame, by the URDF's own kinematics (fixed joints at 0)."""
    link_pose = {robot.get_root(): root_pose}
    pending = list(robot.joints)
    while pending:
        joint = next(j for j in pending if j.parent in link_pose)
        pending.remove(joint)
        t = link_pose[joint.parent] @ _transform(joint.origin.xyz, joint.origin.rpy)
        link_pose[joint.child] = t @ _axis_rotation(joint.axis or (1, 0, 0), angles.get(joint.name, 0.0))
    return link_pose


@pytest.mark.parametrize("which", ["ant", "gadget", "gadget_on_world"])
def test_robot_urdf_is_the_models_tree_and_kinematics(which):
    m = _robot_models()[which]
    text = robot_urdf(m)
    tree = KinematicTree.from_mujoco(m)
    assert read_urdf(text).tree == tree  # the same tree, order and root as the policy reads off the model
    robot = URDF.from_xml_string(text)
    hinges = [j for j in robot.joints if j.type in ("revolute", "continuous")]
    assert [j.name for j in hinges] == list(tree.names)
    assert robot.get_root() == tree.root_link

    # Random hinge angles (qpos, as joint_states publishes them) and root poses: every drawn geom where
    # MuJoCo puts it, turned the same way.
    rng = np.random.default_rng(len(text))
    d = mujoco.MjData(m)
    root = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, tree.root_link)
    checked = 0
    for _ in range(5):
        d.qpos[:] = m.qpos0
        mujoco.mj_integratePos(m, d.qpos, rng.uniform(-1, 1, m.nv), 1.0)  # moves the free root too
        for name in tree.names:
            j = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)
            d.qpos[m.jnt_qposadr[j]] = rng.uniform(-1.5, 1.5)
        for j in range(m.njnt):  # joints the URDF leaves out (unactuated) stay at the MJCF's pose
            if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE and _name(m, j) not in tree.names:
                d.qpos[m.jnt_qposadr[j]] = m.qpos0[m.jnt_qposadr[j]]
        mujoco.mj_kinematics(m, d)
        root_pose = np.eye(4)
        root_pose[:3, :3], root_pose[:3, 3] = d.xmat[root].reshape(3, 3), d.xpos[root]
        angles = {
            name: d.qpos[m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)]] for name in tree.names
        }
        poses = _urdf_link_poses(robot, root_pose, angles)
        for link in robot.links:
            b = _body_of_link(m, link.name)
            if b is None:
                assert not link.visuals and link.inertial is None  # a massless link between two hinges
                continue
            geoms = [g for g in np.flatnonzero(m.geom_bodyid == b) if m.geom_type[g] != mujoco.mjtGeom.mjGEOM_ELLIPSOID]
            assert len(link.visuals) == len(geoms)
            for visual, g in zip(link.visuals, geoms, strict=True):
                t = poses[link.name] @ _transform(visual.origin.xyz, visual.origin.rpy)
                np.testing.assert_allclose(t[:3, 3], d.geom_xpos[g], atol=1e-9)
                np.testing.assert_allclose(t[:3, :3], d.geom_xmat[g].reshape(3, 3), atol=1e-9)
                checked += 1
    assert checked >= 5 * 6  # the gadget draws 6 geoms, the ant 13


def _body_of_link(m, name: str) -> int | None:
    """The body a link is: by its MJCF name, or ``body<id>`` for an unnamed body; None for a link between hinges."""
    b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name)
    if b >= 0:
        return b
    if (
        name.startswith("body")
        and name[4:].isdigit()
        and mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, int(name[4:])) is None
    ):
        return int(name[4:])
    return None


def _name(m, j: int) -> str | None:
    return mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, j)


def test_robot_urdf_names_links_joints_shapes_and_limits():
    m = _robot_models()["gadget"]
    robot = URDF.from_xml_string(robot_urdf(m, prefix="g/"))
    joints = {j.name: j for j in robot.joints}
    links = {link.name: link for link in robot.links}
    assert joints["g/elbow_a"].type == "continuous"  # no range
    assert joints["g/shoulder"].type == joints["g/elbow_b"].type == joints["g/wrist"].type == "revolute"
    assert (joints["g/wrist"].limit.lower, joints["g/wrist"].limit.upper) == (-1.0, 1.0)
    assert joints["g/shoulder"].limit.effort == pytest.approx(12.0)  # two motors: 10 x 1 + 2 x 1
    assert joints["g/wrist"].limit.effort == pytest.approx(6.0)  # gear 3 x ctrl range's far end 2
    assert joints["g/elbow_b"].limit.effort == NO_EFFORT_LIMIT  # no ctrl range: unbounded
    # elbow_a and elbow_b share a body: a massless link between them; the unnamed body is named by its id.
    assert (joints["g/elbow_a"].parent, joints["g/elbow_a"].child) == ("g/upper", "g/fore_elbow_a")
    assert (joints["g/elbow_b"].parent, joints["g/elbow_b"].child) == ("g/fore_elbow_a", "g/fore")
    unnamed = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "tip") - 1
    assert joints[f"g/body{unnamed}_fixed"].type == "fixed" and f"g/body{unnamed}" in links
    assert "g/passive" not in joints  # unactuated: its body hangs on the wrist alone
    assert [type(v.geometry).__name__ for v in links["g/base"].visuals] == ["Box"]
    assert [type(v.geometry).__name__ for v in links["g/tip"].visuals] == ["Sphere"]  # the ellipsoid left out
    assert {v.material.name for link in robot.links for v in link.visuals} == {"color0", "color1"}
    assert read_urdf(robot_urdf(m, prefix="g/")).tree.names == tuple(
        f"g/{n}" for n in KinematicTree.from_mujoco(m).names
    )


def test_robot_urdf_refuses_what_is_not_a_tree_of_actuated_hinges():
    slide = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body name='a'><joint name='s' type='slide'/><geom size='.1'/></body></worldbody>"
        "<actuator><motor joint='s'/></actuator></mujoco>"
    )
    with pytest.raises(TreeError, match="slide"):
        robot_urdf(slide)
