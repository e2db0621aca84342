"""MJCF of generated legged bodies: 4, 6 or 8 legs of 2 or 3 hinges on a round, long or wide torso.

A ``LeggedBody`` (legs, joints per leg, torso, seed) is a body drawn once from its own
generator (``numpy.random.default_rng`` over the four numbers), so a label names one body for good
(``legged-6x3-long-s17``). Ranges are this module's design (``LEGGED_*`` below), chosen as a
spread of plausible small walkers, not fitted to any robot: Gymnasium's Ant is held out and never
generated. The physics and the task are Ant-v5's (``env.centipede``): the header, options, joint
defaults (armature 1, damping 1), floor contacts only (body geoms ``conaffinity`` 0), RK4 at 0.01 s,
motors with ctrlrange [-1, 1].

Torso: ``round`` a sphere; ``long`` a capsule along x (the walking direction); ``wide`` a capsule
along y. The hips sit on the torso's outline seen from above, an ellipse of half-axes (a, b): the
legs come in left/right pairs (mirror images in the xz plane), pair k at angle phi_k from the front,
spread evenly between a front and a back angle drawn per body, each jittered; a hip may sit a little
below the torso's centre line. A leg points outward along the ellipse's normal, splayed by a few
degrees.

A leg, from the hip: 2 joints: a hip about a near-vertical axis (swings the leg forward and back) on a
thigh rising or level at rest, then a knee about the horizontal axis across the leg on a shin pointing
down and out. 3 joints: a short coxa carries the hip swing, then a hip lift about the axis across the
leg, then the knee. Every axis is tilted from its nominal direction by a few degrees (drawn per body,
mirrored for the right leg). Signs follow the centipede's (``centipede_model``): a positive swing moves
a leg forward (+x), a positive lift or knee presses its foot down, on both sides, since the right
leg's axes are the left's mirrored as axes are (``(-x, y, -z)``).

At rest (every hinge at 0) the feet are the lowest points; a body whose torso would not clear the
floor by ``LEGGED_CLEARANCE`` there gets a steeper shin (and if that is not enough a longer one). The
root starts ``LEGGED_DROP`` above the rest pose's height (clear of the reset noise's +-0.1 m). The
hip lift and the knee give little way upward from rest (``LEGGED_FOLD_DEG``): at zero action the body
settles onto those limits, as Ant settles onto its ankle limits. Its standing height
(``settled_height``) is the root's height after 4 s at zero action from that start, no noise.
Healthy heights are Ant-v5's rule carried over by standing height: Ant-v5 keeps the torso in
(0.2, 1.0) m, and by the same measure Ant stands at ``ANT_STANDING_HEIGHT`` (0.38 m), so a generated
body is healthy within ``HEALTHY_FRACTIONS`` x its standing height.

Masses: geom density drawn per body; motor strength as a torque per weight and leg length
(gear = k M g (thigh + shin), k drawn per body), so light and heavy bodies are equally able.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property, lru_cache
from typing import TYPE_CHECKING

import numpy as np

from morph_core.env.centipede_model import _FREE_JOINT, _OPEN, ANT_TIMESTEP

if TYPE_CHECKING:
    import mujoco

LEGGED_LEGS = (4, 6, 8)
LEGGED_JOINTS_PER_LEG = (2, 3)
TORSOS = ("round", "long", "wide")
MAX_SEED = 10**9
# -- the family's ranges (uniform draws), metres, degrees, kg/m^3 -------------------------------------------
LEGGED_TORSO_RADIUS = (0.12, 0.3)
"""a round torso's radius; a long or wide torso's capsule radius is 0.6..0.9 of a draw from it"""
LEGGED_TORSO_HALF_LENGTH = (0.15, 0.5)
"""a long or wide torso's capsule half length (beyond its radius)"""
LEGGED_THIGH = (0.15, 0.45)
LEGGED_SHIN = (0.25, 0.7)
LEGGED_COXA = (0.05, 0.15)
LEGGED_LEG_RADIUS = (0.03, 0.07)
LEGGED_THIGH_RISE_DEG = (0.0, 25.0)
LEGGED_SHIN_DROP_DEG = (35.0, 75.0)
LEGGED_FRONT_DEG = (20.0, 50.0)
"""angle from the front (+x) of the foremost pair's hips"""
LEGGED_BACK_DEG = (130.0, 160.0)
LEGGED_JITTER_DEG = 6.0
LEGGED_SPLAY_DEG = 12.0
LEGGED_AXIS_TILT_DEG = 15.0
LEGGED_HIP_DROP = (-0.3, 0.1)
"""hip height as a fraction of the torso's radius (negative: below the centre line)"""
LEGGED_SWING_DEG = (20.0, 40.0)
"""half range of the hip swing, about rest"""
LEGGED_LIFT_DEG = (15.0, 35.0)
LEGGED_KNEE_DEG = (25.0, 45.0)
"""how far the hip lift and the knee press the foot down from rest"""
LEGGED_FOLD_DEG = (2.0, 6.0)
"""how far the hip lift and the knee let the foot up from rest: the joint limit carries the body's weight at
rest, as Ant's ankle range does"""
LEGGED_DENSITY = (5.0, 25.0)
LEGGED_STRENGTH = (8.0, 30.0)
"""k of gear = k M g (thigh + shin). At 3..10 (before 2026-12-06) a gait did not pay for its control cost
under Ant-v5's reward (summed over every motor): a generalist trained 3.25M steps on ``legged:4-8x2-3``
learned to stand still, every body's best return, while this trainer's ant (k 19.8 by this measure)
walks from scratch. The range now spans motors as able as Ant's, and weaker and stronger ones."""
LEGGED_CLEARANCE = 0.05
LEGGED_DROP = 0.12
ANT_STANDING_HEIGHT = 0.3825
"""Ant's ``settled_height`` (``centipede_model.ant_model``; checked in ``test_legged``)"""
SETTLE_STEPS = 400
"""control steps of 0.05 s at zero action that ``settled_height`` waits: 4 s (Ant is still sinking at 2 s)"""
HEALTHY_FRACTIONS = (0.2 / ANT_STANDING_HEIGHT, 1.0 / ANT_STANDING_HEIGHT)
"""Ant-v5's healthy z range (0.2, 1.0) over its standing height"""
GRAVITY = 9.81


def _u(rng: np.random.Generator, lo_hi) -> float:
    return float(rng.uniform(*lo_hi))


def _rotate(v: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """``v`` turned by ``angle`` (radians) about unit ``axis`` (Rodrigues)."""
    c, s = math.cos(angle), math.sin(angle)
    return v * c + np.cross(axis, v) * s + axis * np.dot(axis, v) * (1 - c)


def _tilted(nominal: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``nominal`` tilted by up to ``LEGGED_AXIS_TILT_DEG`` in a random direction."""
    other = np.cross(nominal, [0.3, 0.5, 0.8])
    other /= np.linalg.norm(other)
    axis = _rotate(other, nominal, rng.uniform(0, 2 * math.pi))
    out = _rotate(nominal, axis, math.radians(rng.uniform(0, LEGGED_AXIS_TILT_DEG)))
    return out / np.linalg.norm(out)


def _mirror_point(p: np.ndarray) -> np.ndarray:
    return p * np.array([1.0, -1.0, 1.0])


def _mirror_axis(a: np.ndarray) -> np.ndarray:
    """An axis (a pseudovector) under the mirror y -> -y: the same motion, mirrored, for the same sign."""
    return a * np.array([-1.0, 1.0, -1.0])


def _v(x) -> str:
    return " ".join(f"{float(c):.6g}" for c in x)


def _capsule_volume(radius: float, length: float) -> float:
    return math.pi * radius**2 * length + 4 / 3 * math.pi * radius**3


@dataclass(frozen=True)
class LeggedBody:
    """One generated legged body (module docstring); ``legs`` in ``LEGGED_LEGS``, ``joints_per_leg`` in
    ``LEGGED_JOINTS_PER_LEG``, ``torso`` in ``TORSOS``, ``seed`` in 0..``MAX_SEED``."""

    legs: int
    joints_per_leg: int
    torso: str
    seed: int

    def __post_init__(self):
        if self.legs not in LEGGED_LEGS:
            raise ValueError(f"a legged body has {LEGGED_LEGS} legs, got {self.legs!r}")
        if self.joints_per_leg not in LEGGED_JOINTS_PER_LEG:
            raise ValueError(f"a legged body's legs have {LEGGED_JOINTS_PER_LEG} joints, got {self.joints_per_leg!r}")
        if self.torso not in TORSOS:
            raise ValueError(f"a legged body's torso is one of {TORSOS}, got {self.torso!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or not 0 <= self.seed <= MAX_SEED:
            raise ValueError(f"a legged body's seed is an integer in 0..{MAX_SEED}, got {self.seed!r}")

    @property
    def num_joints(self) -> int:
        return self.legs * self.joints_per_leg

    @property
    def label(self) -> str:
        return f"legged-{self.legs}x{self.joints_per_leg}-{self.torso}-s{self.seed}"

    @cached_property
    def design(self) -> LeggedDesign:
        return _design(self)

    @property
    def standing_height(self) -> float:
        """``settled_height`` of the body (computed once per body)."""
        return _standing_height(self)

    @property
    def healthy_z_range(self) -> tuple[float, float]:
        h = self.standing_height
        return HEALTHY_FRACTIONS[0] * h, HEALTHY_FRACTIONS[1] * h

    def mjcf(self) -> str:
        return self.design.mjcf

    def model(self) -> mujoco.MjModel:
        """The compiled body, shared and read-only (an LRU of 256 bodies)."""
        return _legged_model(self)


@dataclass(frozen=True)
class LeggedDesign:
    mjcf: str
    rest_height: float
    """the root's height with every hinge at 0 and the lowest foot on the floor"""
    mass: float


def settled_height(model: mujoco.MjModel, steps: int = SETTLE_STEPS) -> float:
    """The root's height (qpos[2]) after ``steps`` control steps (5 physics steps each) at zero action from
    ``qpos0``, no noise: where a body of a free root comes to stand on its joint limits."""
    import mujoco  # MuJoCo (the sim extra) only to simulate: ``env.bodies`` reads this module's labels without it

    data = mujoco.MjData(model)
    mujoco.mj_step(model, data, nstep=5 * steps)
    return float(data.qpos[2])


@lru_cache(maxsize=4096)
def _standing_height(body: LeggedBody) -> float:
    return settled_height(body.model())


@lru_cache(maxsize=256)
def _legged_model(body: LeggedBody) -> mujoco.MjModel:
    import mujoco  # MuJoCo only to compile, as in settled_height

    return mujoco.MjModel.from_xml_string(body.mjcf())


def _design(body: LeggedBody) -> LeggedDesign:
    rng = np.random.default_rng([body.legs, body.joints_per_leg, TORSOS.index(body.torso), body.seed, 51])
    three = body.joints_per_leg == 3
    density = _u(rng, LEGGED_DENSITY)
    # torso: its outline's half axes (a along x, b along y) and its geom
    r = _u(rng, LEGGED_TORSO_RADIUS)
    if body.torso == "round":
        a = b = r
        torso_geom = f'<geom name="torso_geom" pos="0 0 0" size="{r:.6g}" type="sphere"/>'
        volume = 4 / 3 * math.pi * r**3
    else:
        r *= rng.uniform(0.6, 0.9)
        half = _u(rng, LEGGED_TORSO_HALF_LENGTH)
        end = (half, 0.0, 0.0) if body.torso == "long" else (0.0, half, 0.0)
        a, b = (half + r, r) if body.torso == "long" else (r, half + r)
        torso_geom = (f'<geom name="torso_geom" fromto="{_v(np.negative(end))} {_v(end)}" size="{r:.6g}" '
                      'type="capsule"/>')  # fmt: skip
        volume = _capsule_volume(r, 2 * half)
    pairs = body.legs // 2
    front, back = math.radians(_u(rng, LEGGED_FRONT_DEG)), math.radians(_u(rng, LEGGED_BACK_DEG))
    thigh, shin = _u(rng, LEGGED_THIGH), _u(rng, LEGGED_SHIN)
    coxa = _u(rng, LEGGED_COXA) if three else 0.0
    leg_r = min(_u(rng, LEGGED_LEG_RADIUS), 0.25 * thigh)
    rise, drop = math.radians(_u(rng, LEGGED_THIGH_RISE_DEG)), math.radians(_u(rng, LEGGED_SHIN_DROP_DEG))
    hip_z = _u(rng, LEGGED_HIP_DROP) * r
    # the torso must clear the floor at rest: steepen the shin, then lengthen it
    need = r + LEGGED_CLEARANCE + leg_r + hip_z + thigh * math.sin(rise)
    if shin * math.sin(drop) < need:
        drop = min(math.radians(80.0), math.asin(min(1.0, need / shin)))
        shin = max(shin, need / math.sin(drop))
    swing = _u(rng, LEGGED_SWING_DEG)
    ranges = [(-swing, swing)] + ([(-_u(rng, LEGGED_FOLD_DEG), _u(rng, LEGGED_LIFT_DEG))] if three else [])
    ranges.append((-_u(rng, LEGGED_FOLD_DEG), _u(rng, LEGGED_KNEE_DEG)))
    z = np.array([0.0, 0.0, 1.0])
    legs_xml, joint_names, lowest = [], [], 0.0
    leg_volume = 0.0
    for k in range(pairs):
        phi = front + (back - front) * (k / (pairs - 1)) + math.radians(rng.uniform(-1, 1) * LEGGED_JITTER_DEG)
        hip = np.array([a * math.cos(phi), b * math.sin(phi), hip_z])
        normal = np.array([math.cos(phi) / a, math.sin(phi) / b, 0.0])
        out = _rotate(normal / np.linalg.norm(normal), z, math.radians(rng.uniform(-1, 1) * LEGGED_SPLAY_DEG))
        across = np.cross(z, out)  # horizontal, across the leg: a positive turn about it presses the foot down
        swing_axis = _tilted(-z if np.cross(z, out)[0] < 0 else z, rng)  # positive swings forward (+x)
        lift_axis, knee_axis = _tilted(across, rng), _tilted(across, rng)
        thigh_vec = thigh * (math.cos(rise) * out + math.sin(rise) * z)
        shin_vec = shin * (math.cos(drop) * out - math.sin(drop) * z)
        lowest = min(lowest, hip_z + thigh_vec[2] + shin_vec[2] - leg_r)
        for side in ("left", "right"):
            m = _mirror_point if side == "right" else (lambda p: p)
            ma = _mirror_axis if side == "right" else (lambda p: p)
            name = f"{side}_{k}"
            axes = [ma(swing_axis)] + ([ma(lift_axis)] if three else []) + [ma(knee_axis)]
            parts_ = ["swing"] + (["lift"] if three else []) + ["knee"]
            names = [f"{part}_{name}" for part in parts_]
            joint_names += names
            segs = ([m(coxa * out)] if three else []) + [m(thigh_vec), m(shin_vec)]
            legs_xml.append(_leg_xml(name, m(hip), segs, axes, names, ranges, leg_r))
    for seg in (coxa, thigh, shin):
        if seg > 0:
            leg_volume += _capsule_volume(leg_r, seg)
    mass = density * (volume + body.legs * leg_volume)
    gear = _u(rng, LEGGED_STRENGTH) * mass * GRAVITY * (thigh + shin)
    header = _OPEN.format(name=body.label, dt=ANT_TIMESTEP, root="torso", z=f"{LEGGED_DROP - lowest:.6g}")
    header = header.replace('density="5.0"', f'density="{density:.6g}"')
    text = (
        header + f"      {torso_geom}\n" + _FREE_JOINT + "".join(legs_xml)
        + "    </body>\n  </worldbody>\n  <actuator>\n"
        + "".join(f'    <motor ctrllimited="true" ctrlrange="-1.0 1.0" gear="{gear:.6g}" joint="{j}"/>\n'
                  for j in joint_names)
        + "  </actuator>\n</mujoco>\n"
    )  # fmt: skip
    return LeggedDesign(text, -lowest, mass)


def _leg_xml(name, hip, segs, axes, joint_names, ranges, radius) -> str:
    """Nested bodies: the first hinge at the hip, each next one at the previous segment's end."""
    indent = "      "
    out = [f'{indent}<body name="{name}_leg" pos="{_v(hip)}">\n']
    depth = 1
    hinge = 0
    for i, seg in enumerate(segs):
        inner = indent + "  " * depth
        if i > 0:
            out.append(f'{inner}<body name="{name}_seg{i}" pos="{_v(segs[i - 1])}">\n')
            depth += 1
            inner = indent + "  " * depth
        lo, hi = ranges[hinge]
        out.append(f'{inner}<joint axis="{_v(axes[hinge])}" name="{joint_names[hinge]}" pos="0 0 0" '
                   f'range="{lo:.4g} {hi:.4g}" type="hinge"/>\n')  # fmt: skip
        hinge += 1
        out.append(f'{inner}<geom fromto="0 0 0 {_v(seg)}" name="{name}_seg{i}_geom" size="{radius:.6g}" '
                   'type="capsule"/>\n')  # fmt: skip
    for d in range(depth, 0, -1):
        out.append(f"{indent}{'  ' * (d - 1)}</body>\n")
    return "".join(out)
