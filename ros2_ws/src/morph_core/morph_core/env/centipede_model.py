"""MJCF of a centipede with any number of leg pairs, and of Gymnasium's Ant, from one leg writer.

A centipede of N leg pairs is N torso segments in a row along -x, each a pair
of legs, left (+y) and right (-y). Every number of a leg and of a segment is
Gymnasium's ``ant.xml``'s (``ANT_*`` below): a segment is Ant's torso (a
sphere of radius 0.25), a leg is Ant's leg (a 0.28 m hip link, a 0.28 m thigh
and a 0.57 m shin, capsules of radius 0.08), turned to point sideways; the
hip (about z, +-30 degrees) and the ankle (about the horizontal axis across
the leg, 30..70 degrees) are driven by gear-150 motors with ctrlrange [-1, 1].
Joint armature 1 and damping 1, geom density 5, friction (1, 0.5, 0.5),
margin 0.01, condim 3, the RK4 integrator at 0.01 s: all Ant's. Body geoms
never touch each other (``conaffinity`` 0, as in Ant), only the floor.

Segments are joined rigidly, one body welded behind the other 0.5 m apart
(NerveNet's spacing: the spheres touch). NerveNet's centipede joins them by
two actuated hinges (yaw +-20 and pitch -10..30 degrees, gear 100); those
would add two action dimensions per joint between segments, and this family
is 4 per leg pair (hip and ankle, two legs), so a body's action dimension is
its leg count's alone. Passive hinges instead would be a floppy spine the
policy neither drives nor sees (``KinematicTree.from_mujoco`` keeps actuated
hinges only), so its state would be hidden from the graph. Rigid keeps the
body fully observed by the graph and the global features.

Signs are the same on both sides: a positive hip angle swings a leg forward
(+x), a positive ankle angle presses its foot down, left or right, so one
action means the same for every leg (the policy's per-joint head is shared).
Ant's own legs keep ant.xml's axes, which differ per leg (``ant_mjcf``).

Bodies and joints are written depth first: segment k's left leg, its right
leg, then segment k+1 inside it, so MuJoCo's qpos order is the kinematic
tree's order (``KinematicTree.from_mujoco``): per segment
``left_hip_k, left_ankle_k, right_hip_k, right_ankle_k``; parents
``[-1, 0, -1, 2, -1, 4, ...]``, every leg hanging off the root link (the
first segment, ``torso_0``, with the free joint; welded segments merge into
it). Actuators follow the same order for centipedes.
"""

from __future__ import annotations

import numbers
from functools import lru_cache
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import mujoco

MIN_LEG_PAIRS = 2
"""one pair stands on a line and tips over: the family starts at two pairs (NerveNet's CentipedeFour, Ant's count)"""
MAX_LEG_PAIRS = 16
"""4 joints per pair: 64 joints, ``policy.tree.MAX_JOINTS``"""
JOINTS_PER_LEG_PAIR = 4

# Gymnasium's ant.xml, the numbers a leg, a segment and the physics are made of.
ANT_TIMESTEP = 0.01
ANT_TORSO_HEIGHT = 0.75
"""initial height of the torso (``qpos0``'s z)"""
ANT_TORSO_RADIUS = 0.25
ANT_LEG_RADIUS = 0.08
ANT_LEG_STEP = 0.2
"""x and y of Ant's hip link and thigh (0.2, 0.2): 0.28 m long; the shin is twice that"""
ANT_HIP_RANGE_DEG = (-30, 30)
ANT_ANKLE_RANGE_DEG = (30, 70)
"""for an ankle whose positive angle presses the foot down (``ant.xml`` flips axis and range on two legs)"""
ANT_GEAR = 150
SEGMENT_SPACING = 0.5
"""distance between two segments' centres (NerveNet's; the torso spheres touch)"""

_SIDE_STEP = repr(ANT_LEG_STEP * 2**0.5)  # Ant's diagonal step, sideways: the same lengths
_SIDE_SHIN = repr(2 * ANT_LEG_STEP * 2**0.5)

_OPEN = """<mujoco model="{name}">
  <compiler angle="degree" inertiafromgeom="true"/>
  <option integrator="RK4" timestep="{dt}"/>
  <default>
    <joint armature="1" damping="1" limited="true"/>
    <geom conaffinity="0" condim="3" density="5.0" friction="1 0.5 0.5" margin="0.01" rgba="0.8 0.6 0.4 1"/>
  </default>
  <asset>
    <texture builtin="gradient" height="100" rgb1="1 1 1" rgb2="0 0 0" type="skybox" width="100"/>
    <texture builtin="checker" height="100" name="texplane" rgb1="0 0 0" rgb2="0.8 0.8 0.8" type="2d" width="100"/>
    <material name="MatPlane" reflectance="0.5" shininess="1" specular="1" texrepeat="60 60" texture="texplane"/>
  </asset>
  <worldbody>
    <light cutoff="100" diffuse="1 1 1" dir="-0 0 -1.3" directional="true" exponent="1" pos="0 0 1.3"
           specular=".1 .1 .1"/>
    <geom conaffinity="1" condim="3" material="MatPlane" name="floor" pos="0 0 0" rgba="0.8 0.9 0.8 1"
          size="40 40 40" type="plane"/>
    <body name="{root}" pos="0 0 {z}">
      <camera name="track" mode="trackcom" pos="0 -3 0.3" xyaxes="1 0 0 0 0 1"/>
"""
_TORSO = """      <geom name="{root}_geom" pos="0 0 0" size="{r}" type="sphere"/>
"""
_FREE_JOINT = (
    '      <joint armature="0" damping="0" limited="false" margin="0.01" name="root" pos="0 0 0" type="free"/>\n'
)
_HEADER = _OPEN + _TORSO + _FREE_JOINT

_LEG = """{i}<body name="{leg}" pos="0 0 0">
{i}  <geom fromto="0 0 0 {sx} {sy} 0" name="{leg}_hip_geom" size="{r}" type="capsule"/>
{i}  <body name="{thigh}" pos="{sx} {sy} 0">
{i}    <joint axis="{hip_axis}" name="{hip}" pos="0 0 0" range="{hip_range}" type="hinge"/>
{i}    <geom fromto="0 0 0 {sx} {sy} 0" name="{thigh}_geom" size="{r}" type="capsule"/>
{i}    <body{shin} pos="{sx} {sy} 0">
{i}      <joint axis="{ankle_axis}" name="{ankle}" pos="0 0 0" range="{ankle_range}" type="hinge"/>
{i}      <geom fromto="0 0 0 {lx} {ly} 0" name="{leg}_shin_geom" size="{r}" type="capsule"/>
{i}    </body>
{i}  </body>
{i}</body>
"""

_MOTOR = '    <motor ctrllimited="true" ctrlrange="-1.0 1.0" gear="{gear}" joint="{joint}"/>\n'


def _range(lo_hi) -> str:
    return f"{lo_hi[0]} {lo_hi[1]}"


def _leg(indent: str, leg: str, thigh: str, shin: str | None, step, shin_step, hip, hip_axis, ankle, ankle_axis,
         ankle_range) -> str:  # fmt: skip
    return _LEG.format(
        i=indent, leg=leg, thigh=thigh, shin=f' name="{shin}"' if shin else "", sx=step[0], sy=step[1],
        lx=shin_step[0], ly=shin_step[1], r=ANT_LEG_RADIUS, hip=hip, hip_axis=hip_axis,
        hip_range=_range(ANT_HIP_RANGE_DEG), ankle=ankle, ankle_axis=ankle_axis, ankle_range=_range(ankle_range),
    )  # fmt: skip


def check_leg_pairs(leg_pairs) -> int:
    """``leg_pairs`` as an int in ``MIN_LEG_PAIRS..MAX_LEG_PAIRS``, or ValueError saying what it got."""
    if isinstance(leg_pairs, bool) or not isinstance(leg_pairs, numbers.Integral):
        raise ValueError(f"leg_pairs must be an integer (or a (lo, hi) pair of them), got {leg_pairs!r:.60}")
    n = int(leg_pairs)
    if not MIN_LEG_PAIRS <= n <= MAX_LEG_PAIRS:
        raise ValueError(f"leg_pairs must be in {MIN_LEG_PAIRS}..{MAX_LEG_PAIRS}, got {n}")
    return n


def centipede_joint_names(leg_pairs: int) -> tuple[str, ...]:
    """The actuated hinges in tree (qpos) order: per segment k, left hip and ankle, then right."""
    n = check_leg_pairs(leg_pairs)
    return tuple(f"{side}_{part}_{k}" for k in range(n) for side in ("left", "right") for part in ("hip", "ankle"))


def centipede_mjcf(leg_pairs: int) -> str:
    """MJCF text of the centipede of ``leg_pairs`` segments (module docstring)."""
    n = check_leg_pairs(leg_pairs)
    parts = [_HEADER.format(name=f"centipede{n}", dt=ANT_TIMESTEP, root="torso_0", z=ANT_TORSO_HEIGHT,
                            r=ANT_TORSO_RADIUS)]  # fmt: skip
    indent = "      "
    for k in range(n):
        if k > 0:  # welded behind the previous segment: no joint
            parts.append(f'{indent}<body name="torso_{k}" pos="-{SEGMENT_SPACING} 0 0">\n')
            indent += "  "
            parts.append(f'{indent}<geom name="torso_{k}_geom" pos="0 0 0" size="{ANT_TORSO_RADIUS}" type="sphere"/>\n')
        # left leg along +y, right along -y. Hip axes -z and +z: a positive hip swings either leg forward (+x).
        # Ankle axes -x and +x (z cross the leg's direction): a positive ankle presses either foot down.
        for side, sign, hip_axis, ankle_axis in (("left", "", "0 0 -1", "-1 0 0"), ("right", "-", "0 0 1", "1 0 0")):
            parts.append(
                _leg(indent, f"{side}_leg_{k}", f"{side}_thigh_{k}", f"{side}_shin_{k}", ("0", sign + _SIDE_STEP),
                     ("0", sign + _SIDE_SHIN), f"{side}_hip_{k}", hip_axis, f"{side}_ankle_{k}", ankle_axis,
                     ANT_ANKLE_RANGE_DEG)
            )  # fmt: skip
    for _ in range(n - 1):
        indent = indent[:-2]
        parts.append(f"{indent}</body>\n")
    parts.append("    </body>\n  </worldbody>\n  <actuator>\n")
    parts.extend(_MOTOR.format(gear=ANT_GEAR, joint=j) for j in centipede_joint_names(n))
    parts.append("  </actuator>\n</mujoco>\n")
    return "".join(parts)


# ant.xml's legs in its order: (body, aux body, hip, ankle, step, ankle axis, ankle range). Its ankle axes are
# +-(z cross the leg), and the range flips with the axis: the same joint up to the angle's sign.
_ANT_LEGS = (
    ("front_left_leg", "aux_1", "hip_1", "ankle_1", (0.2, 0.2), "-1 1 0", (30, 70)),
    ("front_right_leg", "aux_2", "hip_2", "ankle_2", (-0.2, 0.2), "1 1 0", (-70, -30)),
    ("back_leg", "aux_3", "hip_3", "ankle_3", (-0.2, -0.2), "-1 1 0", (-70, -30)),
    ("right_back_leg", "aux_4", "hip_4", "ankle_4", (0.2, -0.2), "1 1 0", (30, 70)),
)
ANT_ACTUATOR_ORDER = ("hip_4", "ankle_4", "hip_1", "ankle_1", "hip_2", "ankle_2", "hip_3", "ankle_3")
"""ant.xml's motors, in its order (Ant-v5's action order); the tree's order is hip_1, ankle_1, ..., ankle_4"""


def ant_mjcf() -> str:
    """MJCF text of Gymnasium's Ant written by this module's leg writer: ant.xml's bodies, joints, geoms,
    options and motors in ant.xml's order (its four diagonal legs on one torso), the physics the same bit for
    bit (``test_centipede``). Not a centipede (its legs are diagonal and its axes differ per leg): the
    reference that the leg, the physics and the task are Ant's."""
    parts = [_HEADER.format(name="ant", dt=ANT_TIMESTEP, root="torso", z=ANT_TORSO_HEIGHT, r=ANT_TORSO_RADIUS)]
    for leg, aux, hip, ankle, (sx, sy), ankle_axis, ankle_range in _ANT_LEGS:
        parts.append(
            _leg("      ", leg, aux, None, (sx, sy), (2 * sx, 2 * sy), hip, "0 0 1", ankle, ankle_axis, ankle_range)
        )
    parts.append("    </body>\n  </worldbody>\n  <actuator>\n")
    parts.extend(_MOTOR.format(gear=ANT_GEAR, joint=j) for j in ANT_ACTUATOR_ORDER)
    parts.append("  </actuator>\n</mujoco>\n")
    return "".join(parts)


@lru_cache(maxsize=MAX_LEG_PAIRS)
def _centipede_model(leg_pairs: int) -> mujoco.MjModel:
    import mujoco  # here, not at the top: the limits above serve code that never simulates

    return mujoco.MjModel.from_xml_string(centipede_mjcf(leg_pairs))


def centipede_model(leg_pairs: int) -> mujoco.MjModel:
    """The compiled centipede, built from its MJCF string once per size and shared: read-only, callers keep
    their state in their own ``MjData``."""
    return _centipede_model(check_leg_pairs(leg_pairs))


@lru_cache(maxsize=1)
def ant_model() -> mujoco.MjModel:
    """The compiled ``ant_mjcf()``, once; shared and read-only as ``centipede_model``'s."""
    import mujoco  # as in _centipede_model: the limits above serve code that never simulates

    return mujoco.MjModel.from_xml_string(ant_mjcf())
