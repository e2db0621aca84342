"""A simulated robot stepped one control period at a time, for a ROS node (or anything) to wrap.

``SwimmerSim`` owns a ``MorphSwimmerEnv`` (same physics, reset noise and
frame skip as training), or runs your own robot (``robot``: an
``env.mjcf_robot.MjcfRobot``, any MJCF of actuated hinges), and adds what a
robot-facing simulator needs: efforts held between commands and validated on
arrival, an effort timeout (zero effort when commands stop), episodes, a
chain rebuilt in place, a sim clock that never goes backwards, and the root's
pose and twist (``odometry``; the swimmer's planar torso also as ``torso``).

Bodies: ``num_joints`` an int (a fixed chain) or a range ``(lo, hi)`` (a
chain length drawn at every reset), or ``bodies`` a spec of ``env.bodies``
(trees included: one body drawn at every reset, ``MorphSwimmerEnv(bodies=...)``'s
draw), or ``robot`` (its model, every episode). Joints are in the body's tree
order (``tree``: depth-first pre-order, torso to tail for a chain), named as
in its MJCF.

Episodes are the env's: the first begins with ``env.reset(seed=seed)``, every
later one with ``env.reset()`` (the chain length or body redrawn when there
is a choice, the reset noise drawn from the same generator). So a run is
replayed exactly by a fresh ``MorphSwimmerEnv(num_joints)`` (or
``MorphSwimmerEnv(bodies=spec)``) reset the same way at the same boundaries
and stepped with the same efforts; a robot's run by a fresh ``MjcfRobot`` of
the same model, likewise. An episode
ends after ``episode_steps`` steps (0: never), on ``reset()``, on
``rebuild(n)`` (that episode has n joints, as ``env.reset(options=
{"num_joints": n})``; chains only: a sim of ``bodies`` or of a robot refuses
it, its body is drawn or given) or when the physics diverges. The clock counts on
across episodes: every state is one control period after the one before, the
first state of an episode included (a diverged state, never shown, is
replaced by the next episode's first).

Centipedes and generated legged bodies (``bodies`` of those families alone, e.g. ``centipede:3``,
``legged:4x2``): a ``MorphCentipedeEnv`` per
episode (the size drawn from the spec at every reset, Ant-v5's reset noise, its 0.05 s control period), the
joints in its tree order, the root's pose and twist in 3-D (``odometry``), its URDF from the compiled model.
A fall ends the episode as it ends in training (``MorphCentipedeEnv``'s health rule, Ant-v5's: the root's z out
of its range): the fallen state is published, and the next ``advance`` begins a new episode announced with
``EpisodeCause.FELL`` (a trainer reads it as ``terminated``, not truncated). A spec that mixes swimmers and
centipedes is refused: the sim's clock has one
control period (a swimmer's 0.04 s, a centipede's 0.05 s).

Effort units are the motors' normalised commands (the env's action, ctrl
range [-1, 1]; a swimmer's joint torque = 150 x effort; a robot's ctrl by
``mjcf_robot``'s rule). Values outside the range are clipped, as MuJoCo
would.
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from morph_core.env.bodies import WALKER_FAMILIES, BodyMix, parse_bodies
from morph_core.env.mjcf_robot import MjcfRobot, RootState
from morph_core.env.model import check_num_joints
from morph_core.env.swimmer_env import MorphSwimmerEnv
from morph_core.env.urdf import robot_urdf, swimmer_urdf
from morph_core.env.vec_env import BodyEnv
from morph_core.msgs.episode_start import EpisodeCause
from morph_core.msgs.joint_state import quaternion_from_yaw, world_to_body
from morph_core.msgs.stamps import seconds_to_ns
from morph_core.policy.tree import KinematicTree


class EffortError(ValueError):
    """An effort command that was refused; ``str(err)`` is the reason."""


@dataclass(frozen=True)
class TorsoState:
    """The torso frame (Swimmer-v5's placement) in the world frame.

    x, y [m], yaw [rad, continuous, not wrapped]; vx, vy [m/s] world-frame
    velocity of the frame's origin; yaw_rate [rad/s].
    """

    x: float
    y: float
    yaw: float
    vx: float
    vy: float
    yaw_rate: float


class CentipedeBodies:
    """Centipedes of a body spec run as ``SwimmerSim`` runs a robot model: ``MjcfRobot``'s interface over a
    ``vec_env.BodyEnv`` (the spec's draw, then Ant-v5's reset noise, from one generator)."""

    def __init__(self, bodies: BodyMix):
        if not all(isinstance(item, WALKER_FAMILIES) for item in bodies.items):
            raise ValueError(f"{str(bodies)!r} mixes swimmers and walkers: a sim runs one task (one period)")
        self.bodies = bodies
        self._env = BodyEnv(bodies)
        self.joint_range = bodies.joint_range
        self.fell, self.reward = False, 0.0

    def __getattr__(self, name):  # num_joints, tree, dt, model, data, leg_pairs
        if name == "_env":
            raise AttributeError(name)
        return getattr(self._env.env, name)

    @property
    def name(self) -> str:
        return self._env.env.body_label

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> None:
        if options:
            raise ValueError(f"centipedes of a spec take no reset options, got {sorted(options)}")
        self._env.reset(seed=seed)

    def advance(self, efforts: np.ndarray) -> bool:
        """One control period; True if MuJoCo had to reset a state that blew up. ``fell`` says whether the body
        is unhealthy after it (the env's ``terminated`` but for the blow-up), ``reward`` what the env paid."""
        self.reward, terminated = self._env.advance(efforts)
        unstable = self._env.env.unstable
        self.fell = terminated and not unstable
        return unstable

    @property
    def joint_positions(self) -> np.ndarray:
        return self._env.env.data.qpos[7:].copy()

    @property
    def joint_velocities(self) -> np.ndarray:
        return self._env.env.data.qvel[6:].copy()

    def root_state(self) -> RootState:
        """The root segment's pose and twist from its free joint: position, the unit quaternion, the linear
        velocity turned into the root's frame (MuJoCo keeps it in the world's), the angular as it is."""
        qpos, qvel = self._env.env.data.qpos, self._env.env.data.qvel
        quat = qpos[3:7] / np.linalg.norm(qpos[3:7])  # reset noise leaves it off unit length; MuJoCo normalises
        w, x, y, z = (float(v) for v in quat)
        rot = np.empty(9)
        mujoco.mju_quat2Mat(rot, quat)
        linear = rot.reshape(3, 3).T @ qvel[0:3]
        return RootState(
            frame=self.tree.root_link,
            position=tuple(float(v) for v in qpos[0:3]),
            orientation=(x, y, z, w),
            linear=tuple(float(v) for v in linear),
            angular=tuple(float(v) for v in qvel[3:6]),
        )


class SwimmerSim:
    """One swimmer; ``num_joints`` an int (a fixed chain) or an inclusive range ``(lo, hi)`` drawn from
    at every reset; or ``bodies`` (a spec or ``BodyMix``: a body drawn at every reset; ``num_joints`` is
    then unused); or your own ``robot`` (a ``MjcfRobot``).

    ``now`` arguments are the caller's clock in seconds (a node passes wall
    time: the effort timeout is about a controller going quiet, not about sim
    time); ``effort_timeout=None`` never times out.
    """

    def __init__(
        self,
        num_joints: int | tuple[int, int] = 6,
        seed: int | None = 0,
        effort_timeout: float | None = 0.25,
        episode_steps: int = 0,
        bodies: str | BodyMix | None = None,
        robot: MjcfRobot | None = None,
    ):
        if bodies is not None and robot is not None:
            raise ValueError("a sim runs swimmers of a body spec or a robot model, not both")
        mix = None if bodies is None else parse_bodies(bodies) if isinstance(bodies, str) else bodies
        if mix is not None and any(isinstance(item, WALKER_FAMILIES) for item in mix.items):
            robot = CentipedeBodies(parse_bodies(bodies) if isinstance(bodies, str) else bodies)
            bodies = None
        self.robot = robot
        """the robot model run, or None for a swimmer"""
        if robot is not None:
            self._env = robot
            self._physics = robot.advance
            self._fixed: int | KinematicTree | None = None
        else:
            self._env = MorphSwimmerEnv(num_joints=num_joints, observation_mode="graph", bodies=bodies)
            self._physics = self._swim
            fixed = bodies is None and isinstance(num_joints, numbers.Integral)
            self._fixed = self._env.joint_range[0] if fixed else None
        self.effort_timeout = effort_timeout
        self.episode_steps = check_episode_steps(episode_steps)
        """steps per episode before the next reset; 0 = episodes end only on request"""
        self._period_ns = seconds_to_ns(self._env.dt)
        self._ticks = 0
        self.steps = 0
        """control steps taken, over all episodes"""
        self.rejected = 0
        """effort commands refused so far"""
        self.timed_out = False
        """whether the last step ran on zero effort because commands had stopped"""
        self.unstable_resets = 0
        self.episode = 0
        """index of the current episode (0 = the first)"""
        self.episode_step = 0
        """steps taken in the current episode"""
        self.episode_cause = EpisodeCause.START
        """why the current episode began"""
        self.episode_start_ns = 0
        """stamp of the current episode's first state"""
        self.fell = False
        """the robot fell in the last step (a legged body: ``CentipedeBodies.fell``): the next ``advance`` begins a
        new episode (``EpisodeCause.FELL``)"""
        # The seed goes in once: later resets draw from the same generator, so a run
        # (seed, sequence of resets and efforts) is reproducible.
        self._env.reset(seed=seed)
        self._clear_efforts()

    # -- body and episodes --------------------------------------------------------
    @property
    def num_joints(self) -> int:
        return self._env.num_joints

    @property
    def tree(self) -> KinematicTree:
        """The current body's tree: its joints in the order every per-joint array here has, MJCF names."""
        return self._env.tree

    @property
    def joint_range(self) -> tuple[int, int]:
        """Joint counts the next reset may draw (lo == hi: a fixed chain, or a robot)."""
        if self._fixed is None:
            return self._env.joint_range
        n = self._fixed if isinstance(self._fixed, int) else self._fixed.num_joints
        return n, n

    @property
    def bodies(self) -> BodyMix | None:
        """The body spec drawn from, None for chains given by ``num_joints`` and for a robot."""
        if isinstance(self.robot, CentipedeBodies):
            return self.robot.bodies
        return None if self.robot is not None else self._env.bodies

    @property
    def dt(self) -> float:
        """Control period [s] (a swimmer's 0.04: 4 physics steps of 0.01; a robot's as near it as its steps go)."""
        return self._env.dt

    @property
    def time(self) -> float:
        """Sim time [s] of the current state; keeps counting across episodes so a /clock never jumps back."""
        return self._ticks * self.dt

    @property
    def stamp_ns(self) -> int:
        """Sim time of the current state in integer nanoseconds (a whole number of control periods)."""
        return self._ticks * self._period_ns

    @property
    def episode_over(self) -> bool:
        """The episode has run its ``episode_steps``, or the robot fell: the next ``advance`` resets."""
        return self.fell or 0 < self.episode_steps <= self.episode_step

    def reset(self, cause: EpisodeCause = EpisodeCause.RESET) -> None:
        """Begin a new episode, one control period after the current state: a fresh swimmer (its
        length or body redrawn when there is a choice); efforts drop to zero."""
        if isinstance(self._fixed, KinematicTree):
            self._env.reset(options={"tree": self._fixed})
        elif self._fixed is not None:
            self._env.reset(options={"num_joints": self._fixed})  # draws the same as env.reset() would
        else:
            self._env.reset()
        self._new_episode(cause)

    def rebuild(self, body: int | KinematicTree) -> None:
        """Begin a new episode with a chain of ``body`` joints, or a swimmer of the tree ``body`` (its parents;
        the joints get the swimmer's names). A fixed body is that one from now on; with a range, later resets
        draw from the range again. A sim of a body spec or of a robot refuses (ValueError): its bodies are the
        spec's or the model's."""
        if self.robot is not None:
            raise ValueError(f"the robot model {self.robot.name!r} has {self.num_joints} joints; it cannot be rebuilt")
        if self._env.bodies is not None:
            raise ValueError(f"the bodies are drawn from {str(self._env.bodies)!r}; a chain cannot be rebuilt in it")
        if isinstance(body, KinematicTree):
            fixed, options = body, {"tree": body}
        else:
            fixed = check_num_joints(body)
            options = {"num_joints": fixed}
        if self._fixed is not None:
            self._fixed = fixed
        self._env.reset(options=options)
        self._new_episode(EpisodeCause.REBUILD)

    def _new_episode(self, cause: EpisodeCause) -> None:
        self._ticks += 1
        self.episode += 1
        self.episode_step = 0
        self.episode_cause = cause
        self.episode_start_ns = self.stamp_ns
        self.fell = False
        self._clear_efforts()

    def _clear_efforts(self) -> None:
        self._effort = np.zeros(self.num_joints)
        self.applied = np.zeros(self.num_joints)
        """efforts applied over the last control period (what ``joint_efforts`` reports)"""
        self._last_command: float | None = None

    # -- efforts ----------------------------------------------------------------
    def command(self, efforts: Sequence[float], now: float) -> np.ndarray:
        """Hold ``efforts`` (one per joint, tree order) from now on; returns them clipped.

        Raises ``EffortError`` (and counts it) for a wrong length or NaN/inf; the
        previous command stays in force.
        """
        a = np.asarray(efforts, dtype=np.float64)
        if a.shape != (self.num_joints,):
            self.rejected += 1
            raise EffortError(f"expected {self.num_joints} efforts, got {a.size}")
        if not np.isfinite(a).all():
            self.rejected += 1
            raise EffortError("NaN or inf in efforts")
        self._effort = np.clip(a, -1.0, 1.0)
        self._last_command = now
        return self._effort

    def commands_stale(self, now: float) -> bool:
        """True when no command arrived for longer than the effort timeout (or none ever did)."""
        if self._last_command is None:
            return True
        return self.effort_timeout is not None and now - self._last_command > self.effort_timeout

    # -- stepping ---------------------------------------------------------------
    def step(self, now: float) -> bool:
        """Advance one control period under the held efforts (zero if stale). Returns False if the
        physics diverged, in which case a new episode began (``EpisodeCause.DIVERGED``)."""
        self.timed_out = self.commands_stale(now)
        a = np.zeros(self.num_joints) if self.timed_out else self._effort
        unstable = self._physics(a)
        self.applied = a.copy()
        self.steps += 1
        if unstable:
            # MuJoCo has already reset the state on its own; that state is never shown: the
            # next episode's first state takes its place on the clock.
            self.unstable_resets += 1
            self.reset(EpisodeCause.DIVERGED)
            return False
        self._ticks += 1
        self.episode_step += 1
        self.fell = bool(getattr(self.robot, "fell", False))  # shown, then the next advance resets
        return True

    def advance(self, now: float) -> bool:
        """The next state: one step, or the next episode's first state once this one is over.
        Returns True when a new episode began."""
        if self.episode_over:
            self.reset(EpisodeCause.FELL if self.fell else EpisodeCause.STEPS)
            return True
        return not self.step(now)

    def _swim(self, a: np.ndarray) -> bool:
        # The env's step without its observation and info (same physics, bit for bit).
        return self._env.advance(a)[1]

    # -- state ------------------------------------------------------------------
    def joint_names(self, prefix: str = "") -> list[str]:
        """The MJCF joint names in tree order (a chain's torso to tail), with ``prefix`` in front."""
        return [prefix + name for name in self.tree.names]

    @property
    def joint_positions(self) -> np.ndarray:
        return self.robot.joint_positions if self.robot is not None else self._env.data.qpos[3:].copy()

    @property
    def joint_velocities(self) -> np.ndarray:
        return self.robot.joint_velocities if self.robot is not None else self._env.data.qvel[3:].copy()

    def torso(self) -> TorsoState:
        """The swimmer's planar torso frame (a robot has none: ``odometry``)."""
        if self.robot is not None:
            raise TypeError("a robot model has no swimmer torso; its root's pose is odometry()")
        qpos, qvel = self._env.data.qpos, self._env.data.qvel
        return TorsoState(
            x=float(qpos[0]),
            y=float(qpos[1]),
            yaw=float(qpos[2]),
            vx=float(qvel[0]),
            vy=float(qvel[1]),
            yaw_rate=float(qvel[2]),
        )

    def odometry(self) -> RootState:
        """The root link's pose (world frame) and twist (its own frame), as ``odom`` carries them: a
        swimmer's torso in the plane (z = 0, yaw about z), a robot's root in 3-D."""
        if self.robot is not None:
            return self.robot.root_state()
        t = self.torso()
        return RootState(
            frame="torso",
            position=(t.x, t.y, 0.0),
            orientation=quaternion_from_yaw(t.yaw),
            linear=(*world_to_body(t.yaw, t.vx, t.vy), 0.0),
            angular=(0.0, 0.0, t.yaw_rate),
        )

    def urdf(self, prefix: str = "") -> str:
        """The current body's URDF (``env.urdf``), link and joint names behind ``prefix``."""
        if self.robot is not None:
            return robot_urdf(self.robot.model, prefix)
        return swimmer_urdf(self.tree, prefix)


def check_episode_steps(n) -> int:
    """``n`` as an episode length (0 = no limit); ValueError otherwise."""
    if not isinstance(n, numbers.Integral) or isinstance(n, bool) or n < 0:
        raise ValueError(f"episode_steps must be an integer >= 0, got {n!r}")
    return int(n)
