"""MJCF for a planar swimmer with any number of joints, Swimmer-v5 physics.

With ``num_joints=2`` the generated model is Gymnasium's ``swimmer.xml``
(same bodies, frames, inertias, joints and actuators). Longer chains append
segments of the same length behind the tail. The torso frame stays where
Swimmer-v5 puts it (at the joint between the first two segments' bodies), so
``x_velocity`` is measured at the same point for every chain length.

No geom can touch another (``contype`` = ``conaffinity`` = 0, as in
swimmer.xml), so the model also switches MuJoCo's collision detection off
(``<flag contact="disable"/>``): the trajectories are the same bit for bit,
and each step is ~0.9 µs cheaper (10% at 2 joints, 3% at 20;
``bench/bench_collision_off.py``).
"""

from __future__ import annotations

import numbers
from functools import lru_cache
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import mujoco

MIN_JOINTS = 1
MAX_JOINTS = 64

SEGMENT_LENGTH = 1.0
SEGMENT_RADIUS = 0.1
HINGE_RANGE_DEG = 100.0
GEAR = 150.0

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


def swimmer_mjcf(num_joints: int) -> str:
    """MJCF text of a swimmer with ``num_joints`` actuated hinges (num_joints + 1 segments)."""
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


@lru_cache(maxsize=MAX_JOINTS)
def swimmer_model(num_joints: int) -> mujoco.MjModel:
    """Compiled model, built from the MJCF string once per chain length.

    The cached model is shared: callers must treat it as read-only and keep
    their state in their own ``MjData``.
    """
    import mujoco  # here, not at the top: the joint limits above serve nodes that never simulate

    return mujoco.MjModel.from_xml_string(swimmer_mjcf(num_joints))
