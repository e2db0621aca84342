"""A robot's morphology as a kinematic tree of actuated hinges: the one type the project describes robots with.

Links are the graph's nodes and actuated joints its edges. Link 0 is the root
body with every body that no actuated hinge moves merged into it (bodies on
fixed joints, on unactuated joints such as a floating base's DoFs, or on
none); link j+1 is joint j's child link. Joint j connects link
``parent_links[j]`` to link j+1, so for a chain joint j connects link j to
link j+1: today's chain graph (``policy.chains``).

The same rule reads a compiled MuJoCo model and a URDF: actuated hinges are
joints, everything else merges into its parent link. Joints are listed in
depth-first pre-order from the root, a link's children in document order.
MuJoCo numbers bodies and joints in that order too, so for an MJCF written
like the URDF the tree's order is MuJoCo's qpos order (the swimmer's is).

Several actuated hinges on one MuJoCo body (a universal joint, say) are
consecutive joints in MuJoCo's order, joined by massless links, as a URDF
writes them with a dummy link between two revolute joints; the body's child
bodies hang off the last one.

A robot description comes off the network (``robot_description``), so bad
input raises ``TreeError`` with a one-line reason, never another exception.
"""

from __future__ import annotations

import functools
import hashlib
import math
import numbers
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from morph_core.constants import MAX_JOINTS, MAX_NAME_CHARS
from morph_core.policy.index_plan import chain_parents

if TYPE_CHECKING:
    import mujoco

MAX_DESCRIPTION_BYTES = 10_000_000
"""largest robot description read; a URDF of a few hundred links is a few hundred kB"""
URDF_HINGE_TYPES = ("revolute", "continuous")
"""URDF joint types taken as actuated hinges; ``fixed`` joints merge, every other type is refused"""
_HASH_PREFIX = b"morph-control kinematic tree v1\0"
_LAYOUT_PREFIX = b"morph-control joint layout v1\0"


class TreeError(ValueError):
    """A description that is not a kinematic tree of 1..MAX_JOINTS actuated hinges; ``str(err)`` is the reason."""


def joint_name_error(names: Sequence[str]) -> str | None:
    """Why the names are not a robot's joint names (each 1..MAX_NAME_CHARS printable ASCII), or None: the one
    rule, which a robot description and a joint state (``msgs.joint_state``) both check."""
    for i, name in enumerate(names):
        if not 0 < len(name) <= MAX_NAME_CHARS:
            return f"joint name {i} has {len(name)} characters, expected 1..{MAX_NAME_CHARS}"
        if not (name.isascii() and name.isprintable()):
            return f"joint name {i} {name[:40]!r} is not printable ASCII"
    return None


def swimmer_joint_names(num_joints: int) -> tuple[str, ...]:
    """The swimmer's hinge names, root to tail, as ``env.model`` writes them (``motor{k}_rot``, k from 1)."""
    return tuple(f"motor{k}_rot" for k in range(1, num_joints + 1))


def _quote(name: object) -> str:
    """A name as it goes into a one-line reason: escaped (no newline gets through) and cut short."""
    text = repr(name)
    return text if len(text) <= 60 else text[:56] + "...'"


def _frozen_int64(values: np.ndarray) -> np.ndarray:
    # Backed by immutable bytes: unlike setflags(write=False) alone, nobody can make it writeable again.
    return np.frombuffer(np.ascontiguousarray(values, dtype=np.int64).tobytes(), dtype=np.int64)


@dataclass(frozen=True, eq=False)
class KinematicTree:
    """J actuated hinges in topological (depth-first) order.

    names: [J] joint names, unique, each 1..256 printable ASCII characters (as ``joint_states`` carries them).
    parents: [J] int64, read-only; parents[j] < j is joint j's parent joint, -1 when it hangs off the root link.
    root_link: name of the deepest link every joint hangs below (the robot's base), None if unnamed.
    parent_links: [J] int64, read-only, parents + 1: the link (graph node) joint j's parent side is.

    Two trees are equal when names, parents and root_link are. Constructing one validates it.
    """

    names: tuple[str, ...]
    parents: np.ndarray
    root_link: str | None = None
    parent_links: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        names, parents = _validated(self.names, self.parents, self.root_link)
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "parents", _frozen_int64(parents))
        object.__setattr__(self, "parent_links", _frozen_int64(parents + 1))

    @property
    def num_joints(self) -> int:
        return len(self.names)

    @property
    def is_chain(self) -> bool:
        return bool(np.array_equal(self.parents, chain_parents(self.num_joints)))

    @functools.cached_property  # the tree is immutable; a node checks it on every answer
    def topology_hash(self) -> str:
        """16 hex digits of SHA-256 over the parent array alone: equal for equal parents whatever the names.

        The order is part of the shape: the same tree listed in another order is another joint layout for
        the policy, and hashes differently.
        """
        return hashlib.sha256(_HASH_PREFIX + self.parents.astype("<i8").tobytes()).hexdigest()[:16]

    @functools.cached_property
    def layout_hash(self) -> str:
        """16 hex digits of SHA-256 over the joint names in order and the parent array: equal for two trees
        that put the same joints in the same places (what a policy's answer depends on), whatever the root's
        name."""
        names = "\0".join(self.names).encode()
        return hashlib.sha256(_LAYOUT_PREFIX + self.parents.astype("<i8").tobytes() + names).hexdigest()[:16]

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, KinematicTree):
            return NotImplemented
        return (self.names, self.root_link, self.parents.tobytes()) == (
            other.names,
            other.root_link,
            other.parents.tobytes(),
        )

    def __hash__(self) -> int:
        return hash((self.names, self.root_link, self.parents.tobytes()))

    # -- constructors ------------------------------------------------------------------
    @classmethod
    def from_parents(
        cls, parents: Sequence[int] | np.ndarray, names: Sequence[str], root_link: str | None = None
    ) -> KinematicTree:
        """A tree from its parent array (parents[j] < j, or -1 off the root) and its joint names."""
        return cls(names, parents, root_link)

    @classmethod
    def chain(cls, n: int, names: Sequence[str] | None = None, root_link: str | None = "torso") -> KinematicTree:
        """The chain of ``n`` joints (joint j's parent is j - 1); names default to the swimmer's."""
        if isinstance(n, bool) or not isinstance(n, numbers.Integral) or not 1 <= n <= MAX_JOINTS:
            raise TreeError(f"a chain has 1..{MAX_JOINTS} joints, got {_quote(n)}")
        return cls(swimmer_joint_names(int(n)) if names is None else names, chain_parents(int(n)), root_link)

    @classmethod
    def from_mujoco(cls, model: mujoco.MjModel) -> KinematicTree:
        """The tree of a compiled model's actuated hinges (an actuator's transmission is the joint).

        Unactuated joints are ignored and a body without an actuated hinge merges into its parent link.
        Refused: an actuator on a slide, ball or free joint, or on a tendon, site or body.
        """
        import mujoco  # here, not at the top: a robot node reading URDF never loads MuJoCo

        if not isinstance(model, mujoco.MjModel):
            raise TreeError(f"expected a compiled mujoco.MjModel, got {type(model).__name__}")
        hinges_of_body: dict[int, list[int]] = {}
        for a in range(model.nu):
            trn, target = int(model.actuator_trntype[a]), int(model.actuator_trnid[a, 0])
            actuator = _quote(mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_ACTUATOR, a) or f"#{a}")
            if trn not in (mujoco.mjtTrn.mjTRN_JOINT, mujoco.mjtTrn.mjTRN_JOINTINPARENT):
                kind = mujoco.mjtTrn(trn).name.removeprefix("mjTRN_").lower()
                raise TreeError(f"actuator {actuator} drives a {kind}, not a joint: only actuated hinges make a tree")
            if model.jnt_type[target] != mujoco.mjtJoint.mjJNT_HINGE:
                kind = mujoco.mjtJoint(int(model.jnt_type[target])).name.removeprefix("mjJNT_").lower()
                joint = _quote(mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, target))
                raise TreeError(f"actuator {actuator} drives {joint}, a {kind} joint: only hinges can be actuated")
            hinges = hinges_of_body.setdefault(int(model.jnt_bodyid[target]), [])
            if target not in hinges:  # several actuators on one hinge: still one joint
                hinges.append(target)
        body_parent = [int(p) for p in model.body_parentid]
        children: list[list[int]] = [[] for _ in body_parent]
        for body in range(1, len(body_parent)):
            children[body_parent[body]].append(body)
        joints: list[int] = []
        parents: list[int] = []
        base_bodies: list[int] = []  # the bodies the root's joints hang off
        stack = [(0, -1)]  # (body, index of the joint it hangs below)
        while stack:
            body, above = stack.pop()
            for j in sorted(hinges_of_body.get(body, ())):  # a body's joints in MuJoCo's (qpos) order
                if above == -1:
                    base_bodies.append(body_parent[body])
                joints.append(j)
                parents.append(above)
                above = len(joints) - 1
            stack.extend((child, above) for child in reversed(children[body]))
        names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) or "" for j in joints]
        base = _deepest_common_ancestor(base_bodies, lambda b: body_parent[b] if b else None)
        root = None if base is None else mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, base)
        return cls(names, np.array(parents, dtype=np.int64), root)

    @classmethod
    def from_urdf(cls, text: str | bytes) -> KinematicTree:
        """The tree of a URDF's actuated hinges (``read_urdf``, which says what is refused)."""
        return read_urdf(text).tree


@dataclass(frozen=True)
class UrdfRobot:
    """What a URDF says about a robot's joints: the tree of its actuated hinges, and its other joints."""

    tree: KinematicTree
    unactuated: frozenset[str]
    """names of the URDF's joints that are not in the tree: fixed joints, and hinges no ``<ros2_control>``
    command interface drives. A joint state may carry them; the policy leaves them alone."""
    effort_limits: Mapping[str, float] = field(default_factory=dict, hash=False)
    """each joint's ``<limit effort>`` as written (NaN if it does not read as a number), for the joints that
    have one; whether a limit is usable (finite, > 0) is for its reader to say (``protocol.controller``)"""


def read_urdf(text: str | bytes) -> UrdfRobot:
    """The kinematic tree of a URDF, and the names of its joints that are not actuated hinges.

    Actuated hinges are its revolute and continuous joints; when the URDF has ``<ros2_control>`` blocks (as a
    ros2_control robot's does), only those of them with a ``<command_interface>`` there. Fixed joints, and
    hinges nothing commands, merge their child link into its parent. Parsed with the standard library only.
    Refused: malformed XML, more than ``MAX_DESCRIPTION_BYTES``, prismatic / planar / floating / unknown joint
    types, mimic joints, missing or duplicate names, a joint naming a link that does not exist, a link with two
    parent joints, a cycle, more than one root link, a ``<ros2_control>`` joint the URDF does not have.
    """
    robot = _parse_robot(text)
    links: list[str] = []
    for element in robot.findall("link"):
        name = element.get("name")
        if not name:
            raise TreeError("a <link> has no name")
        links.append(name)
    if not links:
        raise TreeError("the robot has no <link>")
    _refuse_duplicates("link", links)
    known_links = set(links)
    joints = [_urdf_joint(element, known_links) for element in robot.findall("joint")]
    _refuse_duplicates("joint", [name for name, *_ in joints])
    commanded = _commanded_joints(robot, {name for name, *_ in joints})
    if commanded is not None:
        joints = [(name, hinge and name in commanded, parent, child) for name, hinge, parent, child in joints]

    parent_of: dict[str, str] = {}  # child link -> parent link
    children: dict[str, list[tuple[str, bool, str]]] = {link: [] for link in links}
    for name, actuated, parent, child in joints:
        if child in parent_of:
            raise TreeError(f"link {_quote(child)} is the child of two joints: a closed loop, not a tree")
        parent_of[child] = parent
        children[parent].append((name, actuated, child))
    roots = [link for link in links if link not in parent_of]
    if not roots:
        raise TreeError("no root link: the joints form a cycle")
    if len(roots) > 1:
        raise TreeError(f"more than one root link ({', '.join(map(_quote, roots[:3]))}): a robot is one tree")

    names: list[str] = []
    parents: list[int] = []
    base_links: list[str] = []  # the links the root's joints hang off
    reached = {roots[0]}
    # Iterative (a tree may be thousands of links deep); a joint is numbered when popped: pre-order.
    stack = [(roots[0], joint, -1) for joint in reversed(children[roots[0]])]
    while stack:
        parent, (name, actuated, child), above = stack.pop()  # above: the joint the parent link hangs below
        reached.add(child)
        if actuated:
            if above == -1:
                base_links.append(parent)
            names.append(name)
            parents.append(above)
            above = len(names) - 1
        stack.extend((child, joint, above) for joint in reversed(children[child]))
    if len(reached) < len(links):  # one parent per link and one root: the links not reached form a loop
        cyclic = next(link for link in links if link not in reached)
        raise TreeError(f"the joints form a cycle through link {_quote(cyclic)}")
    tree = KinematicTree(names, np.array(parents, dtype=np.int64), _deepest_common_ancestor(base_links, parent_of.get))
    return UrdfRobot(
        tree, frozenset(name for name, actuated, *_ in joints if not actuated), _effort_limits(robot.findall("joint"))
    )


def _effort_limits(elements: list[ET.Element]) -> dict[str, float]:
    """name -> ``<limit effort>`` of the joints that give one (NaN: not a number); not checked, not refused."""
    limits: dict[str, float] = {}
    for element in elements:
        limit = element.find("limit")
        text = None if limit is None else limit.get("effort")
        if text is not None:
            try:
                limits[element.get("name")] = float(text)
            except ValueError:
                limits[element.get("name")] = math.nan
    return limits


def _commanded_joints(robot: ET.Element, joints: set[str]) -> set[str] | None:
    """Joints a ``<ros2_control>`` block gives a command interface, or None when the URDF has no such block."""
    blocks = robot.findall("ros2_control")
    if not blocks:
        return None
    commanded: set[str] = set()
    for element in (joint for block in blocks for joint in block.findall("joint")):
        name = element.get("name")
        if name not in joints:
            raise TreeError(f"<ros2_control> names joint {_quote(name)}, which the URDF does not have")
        if element.find("command_interface") is not None:
            commanded.add(name)
    return commanded


# -- validation and parsing helpers ----------------------------------------------------------------
def _validated(names: object, parents: object, root_link: object) -> tuple[tuple[str, ...], np.ndarray]:
    """names as a tuple and parents as an int64 array, or TreeError with the first reason they are not a tree."""
    if isinstance(names, str | bytes) or not isinstance(names, Iterable):
        raise TreeError(f"joint names must be a sequence of strings, got {type(names).__name__}")
    names = tuple(names)
    if not all(isinstance(name, str) for name in names):
        raise TreeError("joint names must be strings")
    if root_link is not None and not isinstance(root_link, str):
        raise TreeError(f"the root link's name must be a string or None, got {type(root_link).__name__}")
    count = len(names)
    if count == 0:
        raise TreeError("empty tree: no actuated hinge joint")
    if count > MAX_JOINTS:
        raise TreeError(f"{count} actuated joints, more than the maximum of {MAX_JOINTS}")
    try:
        array = np.asarray(parents)
    except (TypeError, ValueError, OverflowError) as err:
        raise TreeError(f"parents is not an integer array: {type(err).__name__}") from None
    if array.ndim != 1 or array.dtype.kind not in "iu":
        raise TreeError(f"parents must be a 1-D integer array, got {array.dtype} of shape {array.shape}")
    if array.shape != (count,):
        raise TreeError(f"{array.size} parents for {count} joint names")
    if ((array < -1) | (array >= count)).any():  # compared before any cast: a huge uint64 must not wrap
        j = int(np.flatnonzero((array < -1) | (array >= count))[0])
        raise TreeError(f"joint {j} has parent {array[j]}: not -1 (the root) nor a joint index below {count}")
    array = array.astype(np.int64)
    for j in range(count):
        k, steps = j, 0
        while k != -1 and steps <= count:  # more steps than joints: the walk from j went round a loop
            k, steps = int(array[k]), steps + 1
        if k != -1:
            raise TreeError(f"the joints' parents form a cycle (reached from joint {j}, {_quote(names[j])})")
    late = np.flatnonzero(array >= np.arange(count))
    if late.size:
        j = int(late[0])
        raise TreeError(f"joint {j}'s parent {array[j]} comes after it: joints must be in topological order")
    bad_name = joint_name_error(names)
    if bad_name is not None:
        raise TreeError(bad_name)
    _refuse_duplicates("joint", names)
    return names, array


def _refuse_duplicates(kind: str, names: Sequence[str]) -> None:
    seen: set[str] = set()
    for name in names:
        if name in seen:
            raise TreeError(f"duplicate {kind} name {_quote(name)}")
        seen.add(name)


def _parse_robot(text: object) -> ET.Element:
    """The <robot> element of a URDF, refused before parsing when it is too large."""
    if not isinstance(text, str | bytes):
        raise TreeError(f"a URDF is str or bytes, got {type(text).__name__}")
    # len(str) is at most its UTF-8 length, so the cheap test first; then the exact one.
    too_large = len(text) > MAX_DESCRIPTION_BYTES
    if isinstance(text, str) and not too_large:
        too_large = len(text.encode(errors="replace")) > MAX_DESCRIPTION_BYTES
    if too_large:
        raise TreeError(f"robot description of more than {MAX_DESCRIPTION_BYTES} bytes")
    try:
        robot = ET.fromstring(text)  # expat >= 2.4 bounds entity expansion (no "billion laughs")
    except (ET.ParseError, ValueError) as err:  # ValueError: text that is not valid Unicode
        raise TreeError(f"malformed XML: {str(err).splitlines()[0] if str(err) else type(err).__name__}") from None
    if robot.tag != "robot":
        raise TreeError(f"the root element is {_quote(robot.tag)}, not <robot>")
    return robot


def _urdf_joint(element: ET.Element, links: set[str]) -> tuple[str, bool, str, str]:
    """(name, actuated, parent link, child link) of one <joint>, or TreeError."""
    name, kind = element.get("name"), element.get("type")
    if not name:
        raise TreeError("a <joint> has no name")
    ends = []
    for end in ("parent", "child"):
        tag = element.find(end)
        link = None if tag is None else tag.get("link")
        if not link:
            raise TreeError(f"joint {_quote(name)} has no <{end} link=...>")
        if link not in links:
            raise TreeError(f"joint {_quote(name)} names {end} link {_quote(link)}, which does not exist")
        ends.append(link)
    if kind not in (*URDF_HINGE_TYPES, "fixed"):
        why = "cannot be actuated as a hinge" if kind in ("prismatic", "planar", "floating") else "is unknown"
        raise TreeError(f"joint {_quote(name)} has type {_quote(kind)}, which {why} (revolute, continuous or fixed)")
    if element.find("mimic") is not None:
        raise TreeError(f"joint {_quote(name)} mimics another joint: mimic joints are not supported")
    if ends[0] == ends[1]:
        raise TreeError(f"joint {_quote(name)} connects link {_quote(ends[0])} to itself: a cycle")
    return name, kind in URDF_HINGE_TYPES, ends[0], ends[1]


def _deepest_common_ancestor(nodes: list, parent_of) -> object:
    """The deepest node that is each node or one of its ancestors; ``parent_of(node)`` is None at the root."""
    if not nodes:
        return None

    def lineage(node) -> list:
        path = []
        while node is not None:
            path.append(node)
            node = parent_of(node)
        return path

    common = set(lineage(nodes[0]))
    for node in set(nodes[1:]):
        common &= set(lineage(node))
    return next(node for node in lineage(nodes[0]) if node in common)
