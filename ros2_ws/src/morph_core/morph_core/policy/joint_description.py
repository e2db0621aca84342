"""Joint descriptions: what each actuated hinge of a body is, read off the body at rest, as numbers a policy reads.

One vector of ``NUM_DESCRIPTION_FEATURES`` per joint of a ``KinematicTree``, in the tree's order,
the same from a URDF (``urdf_descriptions``: what ``robot_description`` carries) and from a compiled
MuJoCo model (``mujoco_descriptions``: the env, the sim node, every generated body). The rest pose is
every actuated hinge at angle 0 (the URDF's zero, MuJoCo's qpos 0; other joints as the model is
written), seen from the root link's frame (``KinematicTree.root_link``):

    0..2  anchor / L       the joint's anchor (its position) in the root frame
    3..5  axis             its axis in the root frame, a unit vector
    6     centre / pi      the middle of its range (radians)          \\ a continuous joint, or one whose
    7     half width / pi  half its range, in 0..1                    / range is missing or empty: 0 and 1
    8     effort           log10(effort limit / (M g L)) / 3, clipped to [-1, 1]; 0 when unknown (below)
    9     reach / L        how far its child link reaches from the anchor (below)
    10    mass / M         the mass its child link carries (the link alone, not the subtree)

Normalisation, so that bodies of different sizes and units compare: lengths are divided by the
body's characteristic size L, the radius of the smallest ball about the root frame's origin holding
every joint's reach (``max_j |anchor_j| + reach_j``), so anchors and reaches lie in [-1, 1] and
[0, 1] whatever the unit; masses by the body's mass M (every link's); an effort limit, a torque, by
``M g L`` (g = 9.81 m/s^2: the torque that lifts the whole body by its own size), on a log scale since
it spans decades (Gymnasium's Ant: ~10; a swimmer: ~0.1). Angles are radians over pi.

A link is a graph link (``policy.tree``): a URDF link or MuJoCo body with everything merged into it
that no actuated hinge moves. Its reach: the farthest anchor of the joints hanging off it, or for a
leaf (no joint below), twice the distance from the anchor to its centre of mass (a uniform rod's far
end); a massless leaf reaches 0. Both sources carry anchors and masses, so both compute the same
numbers (``test_joint_description``); geometry is not read (URDF has no capsule).

Effort limits: a MuJoCo joint's is its motors' peak torque (``peak_effort``, the one rule, which the
URDF writer (``env.urdf``) writes as the URDF's ``effort``). Unknown (a documented default, feature 8
= 0, as if the motor lifted the body by its size): a URDF effort of 0 or missing, ``NO_EFFORT_LIMIT``
or more (unbounded), or a body without mass (then feature 10 is 0 as well).

Refused with ``TreeError`` (one line, as every bad robot description): a non-finite number (NaN or
inf origins, axes, limits, masses), a zero axis, a negative mass or effort, a body smaller than
``MIN_SIZE`` or larger than ``MAX_SIZE`` metres (in the URDF's unit: metres by URDF's rule). A URDF
revolute joint without ``<axis>`` turns about x, URDF's default; without ``<limit>`` (or with
lower >= upper) it gets the continuous joint's range. No output ever holds NaN or inf.

NumPy and the standard library only (MuJoCo imported when a model is read), so that the policy node
may read it without loading MuJoCo or torch.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from typing import TYPE_CHECKING

import numpy as np

from morph_core.policy.tree import KinematicTree, TreeError, _parse_robot, read_urdf

if TYPE_CHECKING:
    import mujoco

DESCRIPTION_FEATURES = (
    "anchor_x", "anchor_y", "anchor_z", "axis_x", "axis_y", "axis_z",
    "range_centre", "range_half_width", "effort", "reach", "mass",
)  # fmt: skip
NUM_DESCRIPTION_FEATURES = len(DESCRIPTION_FEATURES)
GRAVITY = 9.81
NO_EFFORT_LIMIT = 1e9
"""an effort limit at least this large is no limit (what ``env.urdf`` writes for a joint nothing bounds)"""
MIN_SIZE = 1e-3
"""smallest body accepted, metres: below it the normalised lengths would amplify rounding noise"""
MAX_SIZE = 1e3
"""largest body accepted, metres (a description in millimetres, say, is refused rather than misread)"""
MAX_MASS = 1e9
"""largest link mass accepted, kg"""
EFFORT_DECADES = 3.0
"""the effort feature spans 1e-3..1e3 times ``M g L``"""


def peak_effort(model: mujoco.MjModel, joint: int) -> float:
    """A MuJoCo joint's peak torque: the sum over its actuators of |gear| x the ctrl range's far end, capped by
    a force range; ``NO_EFFORT_LIMIT`` when neither bounds one (the URDF's ``effort``, ``env.urdf``)."""
    total = 0.0
    for a in np.flatnonzero(model.actuator_trnid[:, 0] == joint):
        peak = np.inf
        if model.actuator_ctrllimited[a]:
            peak = abs(model.actuator_gear[a, 0]) * np.abs(model.actuator_ctrlrange[a]).max()
        if model.actuator_forcelimited[a]:
            peak = min(peak, np.abs(model.actuator_forcerange[a]).max())
        total += peak
    return float(total) if np.isfinite(total) else NO_EFFORT_LIMIT


# -- the vector, from the numbers every source gives ----------------------------------------------------------
def describe(
    anchors: np.ndarray,
    axes: np.ndarray,
    ranges: np.ndarray,
    efforts: np.ndarray,
    com: np.ndarray,
    masses: np.ndarray,
    parents: np.ndarray,
    total_mass: float,
) -> np.ndarray:
    """[J, NUM_DESCRIPTION_FEATURES] float64 from each joint's anchor [J, 3] and axis [J, 3] in the root frame,
    range [J, 2] (NaN: none), effort limit [J] (NaN or <= 0: unknown), its child link's centre of mass [J, 3]
    (root frame) and mass [J], the tree's parents, and the body's mass (every link's). TreeError if any is not
    finite where it must be, or the body's size is out of bounds."""
    anchors, axes, com = (np.asarray(a, dtype=np.float64).reshape(-1, 3) for a in (anchors, axes, com))
    j = anchors.shape[0]
    for name, values in (("anchor", anchors), ("axis", axes), ("centre of mass", com), ("mass", masses)):
        if not np.isfinite(values).all():
            k = int(np.flatnonzero(~np.isfinite(np.asarray(values).reshape(j, -1)).all(axis=1))[0])
            raise TreeError(f"joint {k}: its {name} is not a finite number")
    if not math.isfinite(total_mass) or total_mass < 0 or (np.asarray(masses) < 0).any():
        raise TreeError("a link has a negative or non-finite mass")
    if (masses > MAX_MASS).any():
        raise TreeError(f"a link has a mass of more than {MAX_MASS:g} kg")
    with np.errstate(over="ignore", invalid="ignore"):
        norms = np.linalg.norm(axes, axis=1)
    if not np.isfinite(norms).all():
        raise TreeError("a joint's axis is too large to normalise")
    if (norms < 1e-9).any():
        raise TreeError(f"joint {int(np.flatnonzero(norms < 1e-9)[0])} has a zero axis")
    axes = axes / norms[:, None]
    # reach: the farthest child anchor, or a leaf's rod end (twice its centre of mass, when it has mass)
    reach = np.where(masses > 0, 2.0 * np.linalg.norm(com - anchors, axis=1), 0.0)
    parents = np.asarray(parents)
    reach[parents[parents >= 0]] = 0.0  # not a leaf: the farthest child anchor instead
    for k, p in enumerate(parents):
        if p >= 0:
            reach[p] = max(reach[p], float(np.linalg.norm(anchors[k] - anchors[p])))
    size = float(np.max(np.linalg.norm(anchors, axis=1) + reach))
    if not math.isfinite(size) or not MIN_SIZE <= size <= MAX_SIZE:
        raise TreeError(
            f"the body's size is {size:.3g} m, outside {MIN_SIZE:g}..{MAX_SIZE:g} m (URDF lengths are metres)"
        )
    out = np.zeros((j, NUM_DESCRIPTION_FEATURES))
    out[:, 0:3] = anchors / size
    out[:, 3:6] = axes
    lo, hi = np.asarray(ranges, dtype=np.float64).reshape(j, 2).T
    known = np.isfinite(lo) & np.isfinite(hi) & (lo < hi)
    out[:, 6] = np.where(known, np.clip((lo + hi) / 2 / np.pi, -1.0, 1.0), 0.0)
    out[:, 7] = np.where(known, np.clip((hi - lo) / 2 / np.pi, 0.0, 1.0), 1.0)
    efforts = np.asarray(efforts, dtype=np.float64)
    scale = total_mass * GRAVITY * size
    usable = np.isfinite(efforts) & (efforts > 0) & (efforts < NO_EFFORT_LIMIT) & (scale > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.log10(np.where(usable, efforts, 1.0) / (scale if scale > 0 else 1.0))
    out[:, 8] = np.where(usable, np.clip(ratio / EFFORT_DECADES, -1.0, 1.0), 0.0)
    out[:, 9] = reach / size
    out[:, 10] = masses / total_mass if total_mass > 0 else 0.0
    if not np.isfinite(out).all():  # every step above is bounded; this is the promise, kept whatever happens
        raise TreeError("the joint descriptions are not finite")
    return out


# -- from a compiled MuJoCo model ---------------------------------------------------------------------------
def mujoco_descriptions(model: mujoco.MjModel, tree: KinematicTree | None = None) -> np.ndarray:
    """[J, NUM_DESCRIPTION_FEATURES] descriptions of a compiled model's actuated hinges, in ``tree``'s order
    (default: ``KinematicTree.from_mujoco(model)``)."""
    import mujoco  # MuJoCo (the sim extra) only for a compiled model: a robot's node describes its URDF without it

    tree = KinematicTree.from_mujoco(model) if tree is None else tree
    data = mujoco.MjData(model)
    ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name) for name in tree.names]
    qpos = model.qpos0.copy()
    qpos[model.jnt_qposadr[ids]] = 0.0  # the rest pose: actuated hinges at 0, every other joint as written
    data.qpos[:] = qpos
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)
    root = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, tree.root_link) if tree.root_link else -1
    if root < 0:  # unnamed root: the deepest common ancestor of the hinges' bodies is the first hinge's parent line
        root = _mujoco_root(model, [int(model.jnt_bodyid[i]) for i in ids])
    rot, origin = data.xmat[root].reshape(3, 3), data.xpos[root]

    def to_root(points: np.ndarray) -> np.ndarray:
        return (points - origin) @ rot

    # Which graph link every body belongs to: a body's last actuated hinge's link, else its parent's.
    joint_of_body: dict[int, int] = {}
    for k, i in enumerate(ids):
        joint_of_body[int(model.jnt_bodyid[i])] = k  # several hinges on one body: the last one's link
    link = np.full(model.nbody, -2)  # -2: not in the robot, -1: the root link
    link[root] = -1
    for b in range(root + 1, model.nbody):  # pre-order: a parent before its children
        parent_link = link[model.body_parentid[b]]
        if parent_link != -2:
            link[b] = joint_of_body.get(b, parent_link)
    j = tree.num_joints
    masses, moments = np.zeros(j), np.zeros((j, 3))
    for b in np.flatnonzero(link >= 0):
        masses[link[b]] += model.body_mass[b]
        moments[link[b]] += model.body_mass[b] * data.xipos[b]
    total = float(model.body_mass[link != -2].sum())
    com = np.where(masses[:, None] > 0, moments / np.maximum(masses, 1e-300)[:, None], data.xanchor[ids])
    ranges = np.where(model.jnt_limited[ids][:, None].astype(bool), model.jnt_range[ids], np.nan)
    efforts = np.array([peak_effort(model, i) for i in ids])
    return describe(
        to_root(data.xanchor[ids]), data.xaxis[ids] @ rot, ranges, efforts, to_root(com), masses,
        tree.parents, total,
    )  # fmt: skip


def _mujoco_root(model, bodies: list[int]) -> int:
    def line(b):
        out = []
        while True:
            out.append(b)
            if b == 0:
                return out
            b = int(model.body_parentid[b])

    common = set(line(int(model.body_parentid[bodies[0]])))
    for b in bodies[1:]:
        common &= set(line(int(model.body_parentid[b])))
    return next(b for b in line(int(model.body_parentid[bodies[0]])) if b in common)


# -- from a URDF ------------------------------------------------------------------------------------------------
def _floats(element: ET.Element | None, attribute: str, default: tuple[float, ...], what: str) -> np.ndarray:
    text = None if element is None else element.get(attribute)
    if text is None:
        return np.array(default, dtype=np.float64)
    try:
        values = np.array([float(x) for x in text.split()], dtype=np.float64)
    except ValueError:
        raise TreeError(f"{what}: {attribute}={text[:40]!r} is not numbers") from None
    if values.shape != (len(default),):
        raise TreeError(f"{what}: {attribute} needs {len(default)} numbers, got {values.size}")
    if not np.isfinite(values).all():
        raise TreeError(f"{what}: {attribute} is not finite ({text[:40]!r})")
    return values


def _number(element: ET.Element | None, attribute: str, what: str) -> float:
    """A float attribute, NaN when missing; TreeError when unreadable or not finite."""
    text = None if element is None else element.get(attribute)
    if text is None:
        return math.nan
    try:
        value = float(text)
    except ValueError:
        raise TreeError(f"{what}: {attribute}={text[:40]!r} is not a number") from None
    if not math.isfinite(value):
        raise TreeError(f"{what}: {attribute} is not finite")
    return value


def _rpy_matrix(rpy: np.ndarray) -> np.ndarray:
    """URDF's fixed-axis roll, pitch, yaw: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    (cr, cp, cy), (sr, sp, sy) = np.cos(rpy), np.sin(rpy)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def urdf_descriptions(text: str | bytes) -> np.ndarray:
    """[J, NUM_DESCRIPTION_FEATURES] descriptions of a URDF's actuated hinges, in ``read_urdf``'s tree order;
    ``TreeError`` for what ``read_urdf`` refuses and for the bad numbers the module docstring lists."""
    with np.errstate(over="ignore", invalid="ignore"):  # huge numbers become inf, which ``describe`` refuses
        return _urdf_descriptions(text)


def _urdf_descriptions(text: str | bytes) -> np.ndarray:
    robot_info = read_urdf(text)
    tree, unactuated = robot_info.tree, robot_info.unactuated
    robot = _parse_robot(text)
    link_elements = {e.get("name"): e for e in robot.findall("link")}
    joints = {e.get("name"): e for e in robot.findall("joint")}
    children: dict[str, list[ET.Element]] = {name: [] for name in link_elements}
    child_links = set()
    for element in joints.values():
        children[element.find("parent").get("link")].append(element)
        child_links.add(element.find("child").get("link"))
    root = next(name for name in link_elements if name not in child_links)
    index = {name: k for k, name in enumerate(tree.names)}
    j = tree.num_joints
    anchors, axes, ranges = np.zeros((j, 3)), np.zeros((j, 3)), np.full((j, 2), np.nan)
    efforts, masses, moments = np.full(j, np.nan), np.zeros(j), np.zeros((j, 3))
    total = 0.0
    # (link, its pose in the root frame, the graph link it belongs to: -1 the root's, k joint k's child)
    stack = [(root, np.eye(3), np.zeros(3), -1)]
    while stack:
        name, rot, pos, graph_link = stack.pop()
        inertial = link_elements[name].find("inertial")
        if inertial is not None:
            what = f"link {name[:60]!r}"
            mass = _number(inertial.find("mass"), "value", what)
            mass = 0.0 if math.isnan(mass) else mass
            if mass < 0 or mass > MAX_MASS:
                raise TreeError(f"{what} has mass {mass:g}, outside 0..{MAX_MASS:g} kg")
            centre = pos + rot @ _floats(inertial.find("origin"), "xyz", (0.0, 0.0, 0.0), what)
            total += mass
            if graph_link >= 0:
                masses[graph_link] += mass
                moments[graph_link] += mass * centre
        for element in children[name]:
            jname = element.get("name")
            what = f"joint {jname[:60]!r}"
            origin = element.find("origin")
            xyz = _floats(origin, "xyz", (0.0, 0.0, 0.0), what)
            turn = rot @ _rpy_matrix(_floats(origin, "rpy", (0.0, 0.0, 0.0), what))
            anchor = pos + rot @ xyz
            below = graph_link
            if jname in index and jname not in unactuated:
                k = below = index[jname]
                anchors[k] = anchor
                axes[k] = turn @ _floats(element.find("axis"), "xyz", (1.0, 0.0, 0.0), what)  # URDF's default axis
                limit = element.find("limit")
                lo, hi = _number(limit, "lower", what), _number(limit, "upper", what)
                effort = robot_info.effort_limits.get(jname, math.nan)  # read_urdf's reading; NaN: not a number
                if jname in robot_info.effort_limits and not math.isfinite(effort):
                    raise TreeError(f"{what}: its effort limit is not a finite number")
                if effort < 0:
                    raise TreeError(f"{what} has a negative effort limit {effort:g}")
                if element.get("type") == "revolute":
                    ranges[k] = (lo, hi)
                efforts[k] = effort
            stack.append((element.find("child").get("link"), turn, anchor, below))
    com = np.where(masses[:, None] > 0, moments / np.maximum(masses, 1e-300)[:, None], anchors)
    return describe(anchors, axes, ranges, efforts, com, masses, tree.parents, total)
