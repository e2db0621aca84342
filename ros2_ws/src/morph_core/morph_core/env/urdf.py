"""URDF of the swimmer, read off the compiled MuJoCo model, for ``robot_description``.

One link per MuJoCo body (``torso``, then the segments under their MJCF
names), one revolute joint per actuated hinge under its MJCF name
(``motor{k}_rot``, as ``joint_states`` names them), with the same frames:
a joint's origin is its child body's position and rest rotation in the parent
body, its axis z. Chains and trees alike: links and joints are written in
MuJoCo's (pre-)order, so ``KinematicTree.from_urdf`` reads back the tree
``KinematicTree.from_mujoco`` reads off the model.
Limits are the hinges' ranges in radians and the motors' peak torque (gear x
ctrl range). Each link carries its capsule as a cylinder of the capsule's
straight length (the segment length; URDF has no capsule) and radius, and
MuJoCo's mass and inertia, expressed in the link frame.

What URDF cannot say is left out: the torso's three unactuated planar DoFs
(the root link floats; ``odom`` gives its pose), the joints' armature, and a
velocity limit (the MJCF has none; URDF requires the attribute, so it holds
``NO_VELOCITY_LIMIT``).

Built from the model rather than from the MJCF's parameters so the two cannot
drift apart; ``test_urdf`` checks it against MuJoCo's own kinematics through a
real URDF parser.
"""

from __future__ import annotations

from xml.sax.saxutils import quoteattr

import mujoco
import numpy as np

from morph_core.env.model import body_parents, swimmer_model

NO_VELOCITY_LIMIT = 1000.0
"""rad/s written as every joint's velocity limit: the MJCF sets none"""

_INERTIA_ENTRIES = {"ixx": (0, 0), "ixy": (0, 1), "ixz": (0, 2), "iyy": (1, 1), "iyz": (1, 2), "izz": (2, 2)}

_INERTIA_ENTRIES = {"ixx": (0, 0), "ixy": (0, 1), "ixz": (0, 2), "iyy": (1, 1), "iyz": (1, 2), "izz": (2, 2)}

_BODY, _JOINT = mujoco.mjtObj.mjOBJ_BODY, mujoco.mjtObj.mjOBJ_JOINT


def _num(x: float) -> str:
    # repr of a float is the shortest text that reads back to the same double
    return repr(float(x)) if x != 0 else "0"


def _vec(v) -> str:
    return " ".join(_num(x) for x in v)


def _quat_to_matrix(q) -> np.ndarray:
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _rpy(q) -> np.ndarray:
    """URDF's roll-pitch-yaw (fixed axes x, y, z) of a MuJoCo quaternion (w, x, y, z)."""
    r = _quat_to_matrix(q)
    pitch = np.arcsin(-np.clip(r[2, 0], -1.0, 1.0))
    if abs(r[2, 0]) < 1 - 1e-12:
        roll = np.arctan2(r[2, 1], r[2, 2])
        yaw = np.arctan2(r[1, 0], r[0, 0])
    else:  # gimbal lock: roll and yaw share one angle; put it all in yaw
        roll = 0.0
        yaw = np.arctan2(-r[0, 1], r[1, 1])
    # Exact zeros instead of 1e-17 noise keep the text stable and readable.
    return np.where(np.abs([roll, pitch, yaw]) < 1e-12, 0.0, [roll, pitch, yaw])


def _name(model: mujoco.MjModel, kind: mujoco.mjtObj, index: int) -> str:
    return mujoco.mj_id2name(model, kind, int(index))


def swimmer_urdf(body, prefix: str = "") -> str:
    """URDF text of a swimmer: ``body`` a chain length (``num_joints``), a ``KinematicTree`` or a parent
    array (``model.swimmer_model``'s); ``prefix`` goes in front of every link and joint name (the sim
    node's ``joint_prefix``)."""
    parents = body_parents(body)
    m = swimmer_model(parents)
    n, chain = len(parents), parents == tuple(range(-1, len(parents) - 1))
    rgba = " ".join(f"{c:.6g}" for c in m.geom_rgba[m.geom_bodyid == 1][0])  # float32: 6 digits
    parts = [f'<?xml version="1.0"?>\n<robot name={quoteattr(f"swimmer{n}" if chain else f"swimmer{n}_tree")}>\n']
    parts.append(f'  <material name="segment"><color rgba="{rgba}"/></material>\n')
    for body in range(1, m.nbody):
        parts.append(_link(m, body, prefix))
    for j in range(m.njnt):
        if m.jnt_bodyid[j] != 1:  # the torso's slides and yaw are the floating base, not URDF joints
            parts.append(_joint(m, j, prefix))
    parts.append("</robot>\n")
    return "".join(parts)


def _link(m, body: int, prefix: str) -> str:
    name = quoteattr(prefix + _name(m, _BODY, body))
    # Inertia about the centre of mass in the link's axes: MuJoCo stores principal moments and
    # their frame (body_iquat); URDF wants the full tensor.
    rot = _quat_to_matrix(m.body_iquat[body])
    tensor = rot @ np.diag(m.body_inertia[body]) @ rot.T
    tensor[np.abs(tensor) < 1e-12 * max(1.0, np.abs(tensor).max())] = 0.0
    inertia = " ".join(f"{key}={quoteattr(_num(tensor[a, b]))}" for key, (a, b) in _INERTIA_ENTRIES.items())
    out = [f"  <link name={name}>\n"]
    out.append(
        f'    <inertial><origin xyz="{_vec(m.body_ipos[body])}" rpy="0 0 0"/>'
        f'<mass value="{_num(m.body_mass[body])}"/><inertia {inertia}/></inertial>\n'
    )
    for g in np.flatnonzero(m.geom_bodyid == body):
        if m.geom_type[g] != mujoco.mjtGeom.mjGEOM_CAPSULE:
            raise ValueError(f"geom {g} of body {body} is not a capsule; swimmer_urdf only knows capsules")
        # A capsule's axis is its local z, as a URDF cylinder's; size = (radius, half the straight length).
        origin = f'<origin xyz="{_vec(m.geom_pos[g])}" rpy="{_vec(_rpy(m.geom_quat[g]))}"/>'
        radius, half_length = m.geom_size[g][:2]
        shape = f'<geometry><cylinder radius="{_num(radius)}" length="{_num(2 * half_length)}"/></geometry>'
        out.append(f'    <visual>{origin}{shape}<material name="segment"/></visual>\n')
        out.append(f"    <collision>{origin}{shape}</collision>\n")
    out.append("  </link>\n")
    return "".join(out)


def _joint(m, j: int, prefix: str) -> str:
    child = m.jnt_bodyid[j]
    if m.jnt_type[j] != mujoco.mjtJoint.mjJNT_HINGE or not np.allclose(m.jnt_pos[j], 0) or not m.jnt_limited[j]:
        raise ValueError(f"joint {j} is not a limited hinge at its body's origin; swimmer_urdf cannot write it")
    actuators = np.flatnonzero(m.actuator_trnid[:, 0] == j)
    peak = max(abs(m.actuator_gear[a, 0]) * np.abs(m.actuator_ctrlrange[a]).max() for a in actuators)
    lo, hi = m.jnt_range[j]
    return (
        f'  <joint name={quoteattr(prefix + _name(m, _JOINT, j))} type="revolute">\n'
        f"    <parent link={quoteattr(prefix + _name(m, _BODY, m.body_parentid[child]))}/>"
        f"<child link={quoteattr(prefix + _name(m, _BODY, child))}/>\n"
        f'    <origin xyz="{_vec(m.body_pos[child])}" rpy="{_vec(_rpy(m.body_quat[child]))}"/>'
        f'<axis xyz="{_vec(m.jnt_axis[j])}"/>\n'
        f'    <limit lower="{_num(lo)}" upper="{_num(hi)}" effort="{_num(peak)}" '
        f'velocity="{_num(NO_VELOCITY_LIMIT)}"/>\n'
        "  </joint>\n"
    )
