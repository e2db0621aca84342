"""Your own robot: any MuJoCo model (MJCF) of actuated hinges, stepped as ``SwimmerSim`` steps a swimmer.

``MjcfRobot`` offers what ``SwimmerSim`` uses of ``MorphSwimmerEnv`` (``reset``,
``num_joints``, ``tree``, ``dt``, ``model``, ``data``) and reads its own state:
nothing in it knows any particular robot.

Joints: the model's actuated hinges, in ``KinematicTree.from_mujoco``'s order
(depth-first pre-order from the root body: MuJoCo's qpos order for an MJCF
written depth-first), under their MJCF names. The root is the tree's root
link: the deepest body every actuated hinge hangs below.

Efforts: one per joint in [-1, 1] (the sim clips). Each actuator on joint j
gets ``ctrl = effort_j * max(|lo|, |hi|)`` of its ctrlrange [lo, hi] when it
is ctrllimited (MuJoCo clamps the rest), else ``ctrl = effort_j``. So zero
effort is zero ctrl (a controller gone quiet drives no motor), the sign is
kept, and +-1 reaches the range's far end: for a symmetric range [-c, c]
effort e is ctrl e * c (Gymnasium's ant.xml: [-1, 1], ctrl = effort, as the
swimmer's ``motor``).

Control period: the swimmer's 0.04 s in whole physics steps of the model's
timestep (``frame_skip = max(1, round(0.04 / timestep))``), so a policy
trained on swimmers sees states at the rate it was trained at.

Reset: keyframe 0 when the model has one, else ``qpos0``; then noise drawn
from the robot's generator (seeded by the first ``reset(seed=...)``, drawn on
by later ones): positions moved by a uniform(-s, s) velocity integrated over
1 s (``mj_integratePos``, so quaternions stay unit), velocities plus
uniform(-s, s), s = ``reset_noise_scale`` (0.1, the swimmer's).

Divergence: MuJoCo resets a state whose acceleration, velocity or position
blew up and raises a warning; ``advance`` reports it (the swimmer's rule,
with the two other warnings of the same kind).

Refused, as ``RobotModelError`` with one line naming the file (``load_robot``):
a path that is not a readable file, text that is not MJCF (malformed XML, a
root element other than ``<mujoco>``: a URDF too), a model MuJoCo does not
compile (its message), and any model that is not a tree of 1..64 actuated
hinges (``policy.tree.TreeError``: an actuator on a slide, ball or free
joint, on a tendon or site; no actuator; an unnamed or non-ASCII joint name; an
unnamed root body).
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from morph_core.env.urdf import model_name
from morph_core.policy.tree import KinematicTree, TreeError

CONTROL_PERIOD = 0.04
"""seconds per control step wanted (the swimmer's: 4 x 0.01); a model gets the nearest whole number of its steps"""
MAX_MJCF_BYTES = 50_000_000
"""largest MJCF file read; meshes it names are MuJoCo's to load"""
RESET_NOISE_SCALE = 0.1
DIVERGENCE_WARNING = mujoco.mjtWarning.mjWARN_BADQACC
"""the MuJoCo warning whose count rises when a swimmer's physics diverges (MuJoCo then resets its state)"""
DIVERGENCE_WARNINGS = (DIVERGENCE_WARNING, mujoco.mjtWarning.mjWARN_BADQVEL, mujoco.mjtWarning.mjWARN_BADQPOS)
"""MuJoCo's warnings whose count rises when it has reset a state that blew up"""

_BODY = mujoco.mjtObj.mjOBJ_BODY


class RobotModelError(ValueError):
    """A model file that cannot be simulated as a robot of actuated hinges; ``str(err)`` is one line."""


@dataclass(frozen=True)
class RootState:
    """Pose and twist of a robot's root link, as an odometry message carries them.

    frame: the root link's name (no prefix). position [m] and orientation (x, y, z, w) in the world frame;
    linear [m/s] and angular [rad/s] velocity in the root link's own frame (the child frame of ``odom``).
    """

    frame: str
    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float]
    linear: tuple[float, float, float]
    angular: tuple[float, float, float]


def _one_line(text: str) -> str:
    return "; ".join(line.strip() for line in str(text).splitlines() if line.strip())


def load_robot(path: str | os.PathLike, reset_noise_scale: float = RESET_NOISE_SCALE) -> MjcfRobot:
    """The robot of an MJCF file, or ``RobotModelError`` saying in one line why not."""
    where = str(path)
    p = Path(path)
    if not where:
        raise RobotModelError("model_file is empty")
    if not p.exists():
        raise RobotModelError(f"model file {where!r}: no such file")
    if not p.is_file():
        raise RobotModelError(f"model file {where!r} is not a regular file")
    try:
        size = p.stat().st_size
        if size > MAX_MJCF_BYTES:
            raise RobotModelError(f"model file {where!r} has {size} bytes, more than {MAX_MJCF_BYTES}")
        text = p.read_bytes()
    except OSError as err:
        raise RobotModelError(f"model file {where!r} cannot be read: {err.strerror or err}") from None
    try:
        root = ET.fromstring(text)  # expat >= 2.4 bounds entity expansion
    except (ET.ParseError, ValueError) as err:
        raise RobotModelError(f"model file {where!r} is not MJCF: malformed XML ({_one_line(err)})") from None
    if root.tag != "mujoco":
        hint = " (a URDF: give its MJCF, or convert it with MuJoCo's compile tool)" if root.tag == "robot" else ""
        raise RobotModelError(f"model file {where!r} is not MJCF: its root element is <{root.tag[:40]}>{hint}")
    try:
        model = mujoco.MjModel.from_xml_path(str(p))  # from the path: includes and meshes resolve beside it
    except Exception as err:  # MuJoCo raises ValueError; anything else it raises is a refusal all the same
        raise RobotModelError(f"model file {where!r} does not compile: {_one_line(err)}") from None
    try:
        return MjcfRobot(model, reset_noise_scale=reset_noise_scale)
    except TreeError as err:
        raise RobotModelError(f"model file {where!r}: {err}") from None


class MjcfRobot:
    """A compiled MuJoCo model run as a robot: efforts in, the actuated hinges' state and the root's out."""

    def __init__(self, model: mujoco.MjModel, reset_noise_scale: float = RESET_NOISE_SCALE):
        self.tree = KinematicTree.from_mujoco(model)  # TreeError: not a tree of actuated hinges
        self.model = model
        self.data = mujoco.MjData(model)
        self.num_joints = self.tree.num_joints
        self.joint_range = (self.num_joints, self.num_joints)
        self.reset_noise_scale = float(reset_noise_scale)
        self.name = model_name(model)
        joint_ids = np.array([mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n) for n in self.tree.names])
        self._qpos_at = model.jnt_qposadr[joint_ids].copy()
        self._qvel_at = model.jnt_dofadr[joint_ids].copy()
        # Each actuator follows its joint's effort, scaled to its ctrl range (module docstring).
        joint_of = {int(j): k for k, j in enumerate(joint_ids)}
        self._actuator_joint = np.array([joint_of[int(j)] for j in model.actuator_trnid[:, 0]], dtype=np.int64)
        far_end = np.abs(model.actuator_ctrlrange).max(axis=1)
        self._actuator_scale = np.where(model.actuator_ctrllimited.astype(bool), far_end, 1.0)
        if self.tree.root_link is None:  # it names odom's child frame and the URDF's root link
            raise TreeError("the root body (the deepest body every actuated hinge hangs below) has no name")
        self.root_body = mujoco.mj_name2id(model, _BODY, self.tree.root_link)
        self.frame_skip = max(1, round(CONTROL_PERIOD / model.opt.timestep))
        self.dt = model.opt.timestep * self.frame_skip
        self.np_random = np.random.default_rng()
        self._warnings = [self.data.warning[w] for w in DIVERGENCE_WARNINGS]

    # -- episodes and stepping ----------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None) -> None:
        """The initial state with fresh noise; ``seed`` (re)seeds the generator first. No options are taken:
        the robot's body is its model."""
        if options:
            raise ValueError(f"a robot model takes no reset options, got {sorted(options)}")
        if seed is not None:
            self.np_random = np.random.default_rng(seed)
        m, d, s = self.model, self.data, self.reset_noise_scale
        if m.nkey > 0:
            mujoco.mj_resetDataKeyframe(m, d, 0)
        else:
            mujoco.mj_resetData(m, d)
        mujoco.mj_integratePos(m, d.qpos, self.np_random.uniform(-s, s, m.nv), 1.0)
        d.qvel[:] += self.np_random.uniform(-s, s, m.nv)
        mujoco.mj_forward(m, d)

    def advance(self, efforts: np.ndarray) -> bool:
        """One control period under ``efforts`` (one per joint, tree order, in [-1, 1]); True if MuJoCo had
        to reset a state that blew up (the state now is its reset state, not one to show)."""
        self.data.ctrl[:] = self.ctrl(efforts)
        before = [w.number for w in self._warnings]
        mujoco.mj_step(self.model, self.data, nstep=self.frame_skip)
        return any(w.number > b for w, b in zip(self._warnings, before, strict=True))

    def ctrl(self, efforts: np.ndarray) -> np.ndarray:
        """The actuators' controls for ``efforts`` (one per joint, tree order): each actuator its joint's effort
        scaled to its ctrl range (the module's rule; an env stepped with its own ``step`` takes these)."""
        return efforts[self._actuator_joint] * self._actuator_scale

    # -- state ------------------------------------------------------------------------
    @property
    def joint_positions(self) -> np.ndarray:
        return self.data.qpos[self._qpos_at]

    @property
    def joint_velocities(self) -> np.ndarray:
        return self.data.qvel[self._qvel_at]

    def root_state(self) -> RootState:
        """The root link's pose and body-frame twist now (the world's, at rest, for a robot fixed to it)."""
        m, d, b = self.model, self.data, self.root_body
        # Derived quantities only (the state is untouched): mj_step recomputes them before it uses them.
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        mujoco.mj_comVel(m, d)
        twist = np.zeros(6)  # (angular, linear), in the body's frame
        mujoco.mj_objectVelocity(m, d, _BODY, b, twist, 1)
        w, x, y, z = (float(v) for v in d.xquat[b])
        return RootState(
            frame=self.tree.root_link,
            position=tuple(float(v) for v in d.xpos[b]),
            orientation=(x, y, z, w),
            linear=tuple(float(v) for v in twist[3:]),
            angular=tuple(float(v) for v in twist[:3]),
        )
