"""MJCF for a planar swimmer with any number of joints, Swimmer-v5 physics.

With ``num_joints=2`` the generated model is Gymnasium's ``swimmer.xml``
(same bodies, frames, inertias, joints and actuators). Longer chains append
segments of the same length behind the tail. The torso frame stays where
Swimmer-v5 puts it (at the joint between the first two segments' bodies), so
``x_velocity`` is measured at the same point for every chain length.

Trees (``swimmer_mjcf(parents)``, a ``KinematicTree`` or its parent array) are
built of the same segments: joint j's segment hangs off the rear end of its
parent's segment (the torso's rear end for -1), all hinges turn about z, so
the swimmer stays planar. A link's children leave it at rest angles
(``rest_angles_deg``): one child continues straight, as in a chain; when one
child carries a strictly larger subtree than its siblings it continues
straight (the spine) and the others branch off at 60 degrees, alternating
sides with depth (a fishbone); siblings of equal weight fan symmetrically,
30 degrees apart for two (a forked tail), at most 120 degrees in all, so no
rest direction points more than 60 degrees off the parent's axis and none
points forward. Hinge limits (+-100 degrees) are about the rest angle. Geoms
cannot touch (contact is off), so overlapping segments would not interact,
but they would hide each other in a picture. Joints and bodies are written
in depth-first pre-order, MuJoCo's numbering, so qpos order is the tree's
order: a parent array must be in pre-order (``check_parents``).

No geom can touch another (``contype`` = ``conaffinity`` = 0, as in
swimmer.xml), so the model also switches MuJoCo's collision detection off
(``<flag contact="disable"/>``): the trajectories are the same bit for bit,
and each step is ~0.9 µs cheaper (10% at 2 joints, 3% at 20;
``bench/bench_collision_off.py``).
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence
from functools import lru_cache
from typing import TYPE_CHECKING, Protocol

import numpy as np

from morph_core.constants import MAX_JOINTS, MIN_JOINTS
from morph_core.policy.index_plan import joint_depths

if TYPE_CHECKING:
    import mujoco

SEGMENT_LENGTH = 1.0
SEGMENT_RADIUS = 0.1
HINGE_RANGE_DEG = 100.0
GEAR = 150.0
FAN_DEG = 120.0
"""widest angle between the rest directions of one link's children"""
FORK_DEG = 60.0
"""largest angle between two neighbouring siblings' rest directions (and a side branch's off a spine)"""
TREE_CACHE_SIZE = 1024
"""compiled tree models kept (least recently used dropped): a random training mix meets many shapes"""

_HEADER = """<mujoco model="swimmer{n}">
  <compiler angle="degree" inertiafromgeom="true"/>
  <option density="4000" integrator="RK4" timestep="0.01" viscosity="0.1">
    <flag contact="disable"/>
  </option>
  <default>
    <geom conaffinity="0" condim="1" contype="0" material="geom" rgba="0.8 0.6 .4 1"/>
    <joint armature="0.1"/>
  </default>
  <asset>
    <texture builtin="gradient" height="100" rgb1="1 1 1" rgb2="0 0 0" type="skybox" width="100"/>
    <texture builtin="flat" height="1278" mark="cross" markrgb="1 1 1" name="texgeom" random="0.01"
             rgb1="0.8 0.6 0.4" rgb2="0.8 0.6 0.4" type="cube" width="127"/>
    <texture builtin="checker" height="100" name="texplane" rgb1="0 0 0" rgb2="0.8 0.8 0.8" type="2d" width="100"/>
    <material name="MatPlane" reflectance="0.5" shininess="1" specular="1" texrepeat="30 30" texture="texplane"/>
    <material name="geom" texture="texgeom" texuniform="true"/>
  </asset>
  <worldbody>
    <light cutoff="100" diffuse="1 1 1" dir="-0 0 -1.3" directional="true" exponent="1" pos="0 0 1.3"
           specular=".1 .1 .1"/>
    <geom condim="3" material="MatPlane" name="floor" pos="0 0 -0.1" rgba="0.8 0.9 0.8 1" size="40 40 0.1"
          type="plane"/>
    <body name="torso" pos="0 0 0">
      <camera name="track" mode="trackcom" pos="0 -3 3" xyaxes="1 0 0 0 1 1"/>
      <geom density="1000" fromto="1.5 0 0 0.5 0 0" size="{r}" type="capsule"/>
      <joint axis="1 0 0" name="slider1" pos="0 0 0" type="slide"/>
      <joint axis="0 1 0" name="slider2" pos="0 0 0" type="slide"/>
      <joint axis="0 0 1" name="free_body_rot" pos="0 0 0" type="hinge"/>
"""

_SEGMENT = """{ind}<body name="{name}" pos="{pos} 0 0">
{ind}  <geom density="1000" fromto="0 0 0 -{length} 0 0" size="{r}" type="capsule"/>
{ind}  <joint axis="0 0 1" limited="true" name="motor{k}_rot" pos="0 0 0" range="-{rng} {rng}" type="hinge"/>
"""


def segment_body_name(k: int, num_joints: int) -> str:
    """Body names match swimmer.xml for two joints ("mid", "back")."""
    if num_joints == 2:
        return ("mid", "back")[k - 1]
    return f"seg{k}"


def check_num_joints(num_joints: int) -> int:
    if isinstance(num_joints, bool) or not isinstance(num_joints, numbers.Integral):
        raise TypeError(f"num_joints must be an integer, got {num_joints!r}")
    n = int(num_joints)
    if not MIN_JOINTS <= n <= MAX_JOINTS:
        raise ValueError(f"num_joints must be in {MIN_JOINTS}..{MAX_JOINTS}, got {n}")
    return n


class HasParents(Protocol):
    """A tree as its parent array: ``policy.tree.KinematicTree`` (which imports this module, so it is named
    here by what is read of it)."""

    parents: Sequence[int] | np.ndarray


Body = int | Sequence[int] | np.ndarray | HasParents
"""a chain length, or a tree: a ``KinematicTree`` or its parent array"""


def check_parents(parents) -> tuple[int, ...]:
    """A parent array (parents[j] in -1..j-1, -1 = off the torso) as a tuple, checked to be in depth-first
    pre-order (each joint hangs off the previous joint or one of its ancestors, or the torso), which is how
    MuJoCo numbers the bodies of the MJCF written here. ValueError otherwise."""
    if isinstance(parents, str | bytes):
        raise TypeError(f"parents must be a sequence of integers, got {type(parents).__name__}")
    try:
        array = np.asarray(parents)
    except (TypeError, ValueError) as err:
        raise TypeError(f"parents must be a sequence of integers: {err}") from None
    if array.ndim != 1 or (array.size and array.dtype.kind not in "iu"):
        raise TypeError(f"parents must be a 1-D sequence of integers, got {array.dtype} of shape {array.shape}")
    n = array.shape[0]
    if not MIN_JOINTS <= n <= MAX_JOINTS:
        raise ValueError(f"a swimmer has {MIN_JOINTS}..{MAX_JOINTS} joints, got {n} parents")
    out = tuple(int(p) for p in array)
    path: list[int] = [-1]  # the torso, then the joints from it down to the last joint
    for j, p in enumerate(out):
        if p not in path:
            raise ValueError(
                f"parents[{j}] = {p}: joint {j} must hang off the torso (-1) or off joint {j - 1} or one of its "
                "ancestors (joints in topological, depth-first pre-order)"
            )
        del path[path.index(p) + 1 :]
        path.append(j)
    return out


def body_parents(body) -> tuple[int, ...]:
    """The parent array of a body: a chain length (int), a ``KinematicTree`` or a parent array."""
    if isinstance(body, numbers.Integral) and not isinstance(body, bool):
        return tuple(range(-1, check_num_joints(body) - 1))
    parents = getattr(body, "parents", body)  # a KinematicTree
    if isinstance(parents, str | bytes) or not isinstance(parents, Sequence | np.ndarray):
        raise TypeError(
            f"a body is a chain length (num_joints, an int), a KinematicTree or a parent array, got {body!r:.60}"
        )
    return check_parents(parents)


def _is_chain(parents: tuple[int, ...]) -> bool:
    return parents == tuple(range(-1, len(parents) - 1))


def rest_angles_deg(parents: Sequence[int]) -> list[float]:
    """Each joint's rest angle (degrees about z, relative to its parent segment's axis): see the module
    docstring. 0 for every joint of a chain."""
    n = len(parents)
    size = [1] * n  # joints in each joint's subtree
    for j in range(n - 1, -1, -1):
        if parents[j] >= 0:
            size[parents[j]] += size[j]
    depth = joint_depths(parents)  # that of the joint's parent link (torso: 0)
    children: dict[int, list[int]] = {}
    for j, p in enumerate(parents):
        children.setdefault(p, []).append(j)
    angles = [0.0] * n
    for kids in children.values():
        c = len(kids)
        if c == 1:
            continue
        sizes = sorted((size[k] for k in kids), reverse=True)
        if sizes[0] > sizes[1]:  # a spine goes on straight, the side branches alternate sides with depth
            main = max(kids, key=lambda k: size[k])
            side = 1.0 if depth[kids[0]] % 2 == 0 else -1.0
            sides = [s * a for a in (FORK_DEG, FORK_DEG / 2) for s in (side, -side)]
            for k, angle in zip([k for k in kids if k != main], sides, strict=False):
                angles[k] = angle
        else:
            step = min(FORK_DEG, FAN_DEG / (c - 1))
            for i, k in enumerate(kids):
                angles[k] = (i - (c - 1) / 2) * step
    return angles


def swimmer_mjcf(body: Body) -> str:
    """MJCF text of a swimmer: ``body`` a chain length (``num_joints`` actuated hinges, num_joints + 1
    segments; the text of the chain is unchanged), or a tree (a ``KinematicTree`` or its parent array;
    a tree that is a chain gives the chain's text)."""
    if isinstance(body, numbers.Integral) and not isinstance(body, bool):
        return _chain_mjcf(body)
    parents = body_parents(body)
    return _chain_mjcf(len(parents)) if _is_chain(parents) else _tree_mjcf(parents)


def _tree_mjcf(parents: tuple[int, ...]) -> str:
    n = len(parents)
    angles = rest_angles_deg(parents)
    children: dict[int, list[int]] = {}
    for j, p in enumerate(parents):
        children.setdefault(p, []).append(j)
    parts = [_HEADER.format(n=f"{n}_tree", r=SEGMENT_RADIUS)]
    # Iterative depth-first writing: open a body, push a closing tag, then its children (pre-order).
    stack: list[tuple[int, int] | str] = [(j, 6) for j in reversed(children.get(-1, []))]
    while stack:
        top = stack.pop()
        if isinstance(top, str):
            parts.append(top)
            continue
        j, depth = top
        ind = " " * depth
        text = _SEGMENT.format(
            ind=ind,
            name=f"seg{j + 1}",
            pos=0.5 if parents[j] < 0 else -SEGMENT_LENGTH,
            length=SEGMENT_LENGTH,
            r=SEGMENT_RADIUS,
            k=j + 1,
            rng=HINGE_RANGE_DEG,
        )
        if angles[j] != 0.0:
            text = text.replace(' 0 0">', f' 0 0" euler="0 0 {angles[j]:g}">', 1)
        parts.append(text)
        stack.append(f"{ind}</body>\n")
        stack.extend((k, depth + 2) for k in reversed(children.get(j, [])))
    parts.append("    </body>\n  </worldbody>\n  <actuator>\n")
    for k in range(1, n + 1):
        parts.append(f'    <motor ctrllimited="true" ctrlrange="-1 1" gear="{GEAR}" joint="motor{k}_rot"/>\n')
    parts.append("  </actuator>\n</mujoco>\n")
    return "".join(parts)


def _chain_mjcf(num_joints: int) -> str:
    n = check_num_joints(num_joints)
    parts = [_HEADER.format(n=n, r=SEGMENT_RADIUS)]
    indent = "      "
    for k in range(1, n + 1):
        # The first segment hangs off the torso's rear end (x = 0.5), each later
        # one off the previous segment's rear end (x = -1 in its parent frame).
        pos = 0.5 if k == 1 else -SEGMENT_LENGTH
        parts.append(
            _SEGMENT.format(
                ind=indent,
                name=segment_body_name(k, n),
                pos=pos,
                length=SEGMENT_LENGTH,
                r=SEGMENT_RADIUS,
                k=k,
                rng=HINGE_RANGE_DEG,
            )
        )
        indent += "  "
    for _ in range(n):
        indent = indent[:-2]
        parts.append(f"{indent}</body>\n")
    parts.append("    </body>\n  </worldbody>\n  <actuator>\n")
    for k in range(1, n + 1):
        parts.append(f'    <motor ctrllimited="true" ctrlrange="-1 1" gear="{GEAR}" joint="motor{k}_rot"/>\n')
    parts.append("  </actuator>\n</mujoco>\n")
    return "".join(parts)


def swimmer_model(body: Body) -> mujoco.MjModel:
    """Compiled model, built from the MJCF string once per shape (a chain length, or a tree's parent
    array: the last ``TREE_CACHE_SIZE`` trees are kept). A tree that is a chain gets the chain's model.

    The cached model is shared: callers must treat it as read-only and keep
    their state in their own ``MjData``.
    """
    if isinstance(body, numbers.Integral) and not isinstance(body, bool):
        return _chain_model(check_num_joints(body))
    parents = body_parents(body)
    return _chain_model(len(parents)) if _is_chain(parents) else _tree_model(parents)


@lru_cache(maxsize=MAX_JOINTS)
def _chain_model(num_joints: int) -> mujoco.MjModel:
    import mujoco  # here, not at the top: the joint limits above serve nodes that never simulate

    return mujoco.MjModel.from_xml_string(_chain_mjcf(num_joints))


@lru_cache(maxsize=TREE_CACHE_SIZE)
def _tree_model(parents: tuple[int, ...]) -> mujoco.MjModel:
    import mujoco  # as in _chain_model: nodes that never simulate read this module

    return mujoco.MjModel.from_xml_string(_tree_mjcf(parents))
