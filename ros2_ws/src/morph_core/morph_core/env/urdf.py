"""URDF of a compiled MuJoCo model (a swimmer, or your own robot), for ``robot_description``.

``robot_urdf(model)`` writes any model whose actuated hinges form a tree
(``KinematicTree.from_mujoco``); ``swimmer_urdf(body)`` is it for a swimmer.
The rule is the tree's: the root link is the tree's root body (its free
joint, or the swimmer's three planar DoFs, left out: the root link floats,
``odom`` gives its pose); every body below it is a link under its MJCF name
(``body<id>`` for an unnamed one); a body moved by actuated hinges hangs off
its parent by revolute joints under the hinges' MJCF names (``continuous``
for an unlimited hinge; several hinges on one body are joined by massless
links, as ``from_mujoco`` reads them), every other body by a fixed joint
(``<link>_fixed``), its unactuated joints left out. So ``read_urdf`` reads
back the tree ``KinematicTree.from_mujoco`` reads off the model, in the same
order (links and joints are written in MuJoCo's pre-order). Frames are
MuJoCo's: a joint's origin is its anchor in the parent link (turned back by
the hinge's ``ref``, so that the URDF's joint angle is MuJoCo's qpos, as
``joint_states`` publishes it), its axis the hinge's; a link's frame is its
body's moved to its last hinge's anchor (the body's origin for the swimmer's
hinges).
Limits are the hinges' ranges in radians and the motors' peak torque
(sum over the joint's actuators of gear x the ctrl range's far end, capped by
a force range; ``joint_description.NO_EFFORT_LIMIT`` when neither bounds it). Each link carries
its spheres, boxes, cylinders and capsules (a capsule as a cylinder of its
straight length: URDF has no capsule; ellipsoids, meshes, planes and height
fields are left out, a URDF would need files or shapes it does not have),
one material per colour, and MuJoCo's mass and inertia in the link frame.

What URDF cannot say is left out: the root's unactuated DoFs, unactuated
joints below it, the joints' armature, and a velocity limit (an MJCF has none;
URDF requires the attribute, so it holds ``NO_VELOCITY_LIMIT``).

Built from the model rather than from the MJCF's parameters so the two cannot
drift apart; ``test_urdf`` checks it against MuJoCo's own kinematics through a
real URDF parser.
"""

from __future__ import annotations

from xml.sax.saxutils import quoteattr

import mujoco
import numpy as np

from morph_core.env.model import body_parents, swimmer_model
from morph_core.policy.joint_description import peak_effort
from morph_core.policy.tree import KinematicTree, TreeError

NO_VELOCITY_LIMIT = 1000.0
"""rad/s written as every joint's velocity limit: the MJCF sets none"""

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


def model_name(m: mujoco.MjModel) -> str:
    """The MJCF's ``<mujoco model=...>`` (``robot`` when it has none): the URDF's robot name."""
    return m.names[: m.names.index(b"\0")].decode(errors="replace") or "robot"


def swimmer_urdf(body, prefix: str = "") -> str:
    """URDF text of a swimmer: ``body`` a chain length (``num_joints``), a ``KinematicTree`` or a parent
    array (``model.swimmer_model``'s); ``prefix`` goes in front of every link and joint name (the sim
    node's ``joint_prefix``)."""
    m = swimmer_model(body_parents(body))
    return _urdf(m, KinematicTree.from_mujoco(m), prefix, materials=("segment",))


def robot_urdf(model: mujoco.MjModel, prefix: str = "") -> str:
    """URDF text of a compiled model whose actuated hinges form a tree (``KinematicTree.from_mujoco``, whose
    ``TreeError`` says why one does not; so does a root body without a name)."""
    tree = KinematicTree.from_mujoco(model)
    if tree.root_link is None:
        raise TreeError("the root body (the deepest body every actuated hinge hangs below) has no name")
    return _urdf(model, tree, prefix, materials=())


def _unique(name: str, taken: set[str]) -> str:
    while name in taken:
        name += "_"
    taken.add(name)
    return name


def _urdf(m: mujoco.MjModel, tree: KinematicTree, prefix: str, materials: tuple[str, ...]) -> str:
    """The URDF of ``m`` with ``tree`` its actuated hinges; colours named ``materials`` in order of first
    use, then ``color<k>``."""
    root = mujoco.mj_name2id(m, _BODY, tree.root_link)
    hinges: dict[int, list[int]] = {}  # body -> its actuated hinges, MuJoCo's order
    for name in tree.names:
        j = mujoco.mj_name2id(m, _JOINT, name)
        hinges.setdefault(int(m.jnt_bodyid[j]), []).append(j)
    inside = {root}
    bodies = [root]
    for b in range(root + 1, m.nbody):  # MuJoCo numbers bodies in pre-order: a parent comes first
        if m.body_parentid[b] in inside:
            inside.add(b)
            bodies.append(b)
    taken_links = {_name(m, _BODY, b) for b in range(m.nbody)} - {None}
    link = {b: prefix + (_name(m, _BODY, b) or _unique(f"body{b}", taken_links)) for b in bodies}
    # A link's frame is its body's moved to the anchor of its last actuated hinge.
    offset = {b: m.jnt_pos[hinges[b][-1]] if b in hinges and m.jnt_pos[hinges[b][-1]].any() else None for b in bodies}

    colours: dict[str, str] = {}
    links, joints = [], []
    taken_joints = set(tree.names)
    for b in bodies:
        chain = hinges.get(b, [])
        between = [prefix + _unique(f"{link[b][len(prefix) :]}_{_name(m, _JOINT, j)}", taken_links) for j in chain[:-1]]
        links += [f"  <link name={quoteattr(name)}/>\n" for name in between]  # massless, between two hinges
        links.append(_link(m, b, link[b], offset[b], colours, materials))
        if b == root:
            continue
        parent = m.body_parentid[b]
        xyz = m.body_pos[b] - offset[parent] if offset[parent] is not None else m.body_pos[b]
        quat = m.body_quat[b]
        if not chain:
            name = prefix + _unique(f"{link[b][len(prefix) :]}_fixed", taken_joints)
            joints.append(_fixed(name, link[parent], link[b], xyz, _rpy(quat)))
            continue
        ends = [link[parent], *between, link[b]]
        anchor = np.zeros(3)
        for i, j in enumerate(chain):
            if i == 0 and m.jnt_pos[j].any():
                xyz = xyz + _quat_to_matrix(quat) @ m.jnt_pos[j]
            elif i > 0:
                xyz, quat = m.jnt_pos[j] - anchor, np.array([1.0, 0.0, 0.0, 0.0])
            anchor = m.jnt_pos[j]
            # MuJoCo turns a hinge by qpos - ref from the MJCF's pose; URDF by its angle from the origin's:
            # turning the origin back by ref makes the URDF angle the published qpos.
            ref = m.qpos0[m.jnt_qposadr[j]]
            if ref != 0:
                back, turned = np.empty(4), np.empty(4)
                mujoco.mju_axisAngle2Quat(back, m.jnt_axis[j], -ref)
                mujoco.mju_mulQuat(turned, quat, back)
                quat = turned
            joints.append(_joint(m, j, prefix, ends[i], ends[i + 1], xyz, _rpy(quat)))
    parts = [f'<?xml version="1.0"?>\n<robot name={quoteattr(model_name(m))}>\n']
    parts += [f"  <material name={quoteattr(n)}><color rgba={quoteattr(c)}/></material>\n" for c, n in colours.items()]
    parts += links + joints
    parts.append("</robot>\n")
    return "".join(parts)


def _link(m, body: int, name: str, offset, colours: dict[str, str], materials: tuple[str, ...]) -> str:
    def local(pos):
        return pos if offset is None else pos - offset

    out = [f"  <link name={quoteattr(name)}>\n"]
    if m.body_mass[body] > 0:
        # Inertia about the centre of mass in the link's axes: MuJoCo stores principal moments and
        # their frame (body_iquat); URDF wants the full tensor.
        rot = _quat_to_matrix(m.body_iquat[body])
        tensor = rot @ np.diag(m.body_inertia[body]) @ rot.T
        tensor[np.abs(tensor) < 1e-12 * max(1.0, np.abs(tensor).max())] = 0.0
        inertia = " ".join(f"{key}={quoteattr(_num(tensor[a, b]))}" for key, (a, b) in _INERTIA_ENTRIES.items())
        out.append(
            f'    <inertial><origin xyz="{_vec(local(m.body_ipos[body]))}" rpy="0 0 0"/>'
            f'<mass value="{_num(m.body_mass[body])}"/><inertia {inertia}/></inertial>\n'
        )
    for g in np.flatnonzero(m.geom_bodyid == body):
        shape = _shape(m, g)
        if shape is None:
            continue
        rgba = " ".join(f"{c:.6g}" for c in m.geom_rgba[g])  # float32: 6 digits
        if rgba not in colours:
            k = len(colours)
            colours[rgba] = materials[k] if k < len(materials) else f"color{k}"
        origin = f'<origin xyz="{_vec(local(m.geom_pos[g]))}" rpy="{_vec(_rpy(m.geom_quat[g]))}"/>'
        out.append(f"    <visual>{origin}{shape}<material name={quoteattr(colours[rgba])}/></visual>\n")
        out.append(f"    <collision>{origin}{shape}</collision>\n")
    out.append("  </link>\n")
    return "".join(out)


def _shape(m, g: int) -> str | None:
    """A geom as URDF geometry (its local z the axis of a cylinder, as MuJoCo's), or None if URDF cannot draw it."""
    kind, size = int(m.geom_type[g]), m.geom_size[g]
    if kind in (mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_CYLINDER):  # size: radius, half length
        shape = f'<cylinder radius="{_num(size[0])}" length="{_num(2 * size[1])}"/>'
    elif kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        shape = f'<sphere radius="{_num(size[0])}"/>'
    elif kind == mujoco.mjtGeom.mjGEOM_BOX:
        shape = f'<box size="{_vec(2 * size)}"/>'
    else:
        return None
    return f"<geometry>{shape}</geometry>"


def _fixed(name: str, parent: str, child: str, xyz, rpy) -> str:
    return (
        f'  <joint name={quoteattr(name)} type="fixed">\n'
        f"    <parent link={quoteattr(parent)}/><child link={quoteattr(child)}/>\n"
        f'    <origin xyz="{_vec(xyz)}" rpy="{_vec(rpy)}"/>\n'
        "  </joint>\n"
    )


def _joint(m, j: int, prefix: str, parent: str, child: str, xyz, rpy) -> str:
    limited = bool(m.jnt_limited[j])
    lo, hi = m.jnt_range[j]
    bounds = f'lower="{_num(lo)}" upper="{_num(hi)}" ' if limited else ""
    return (
        f'  <joint name={quoteattr(prefix + _name(m, _JOINT, j))} type="{"revolute" if limited else "continuous"}">\n'
        f"    <parent link={quoteattr(parent)}/>"
        f"<child link={quoteattr(child)}/>\n"
        f'    <origin xyz="{_vec(xyz)}" rpy="{_vec(rpy)}"/>'
        f'<axis xyz="{_vec(m.jnt_axis[j])}"/>\n'
        f'    <limit {bounds}effort="{_num(peak_effort(m, j))}" '
        f'velocity="{_num(NO_VELOCITY_LIMIT)}"/>\n'
        "  </joint>\n"
    )
