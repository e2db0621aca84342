"""A swimmer simulation stepped one control period at a time, for a ROS node (or anything) to wrap.

``SwimmerSim`` owns a ``MorphSwimmerEnv`` (same physics, reset noise and
frame skip as training) and adds what a robot-facing simulator needs:
efforts held between commands and validated on arrival, an effort timeout
(zero effort when commands stop), a chain rebuilt in place, a sim clock that
never goes backwards, and the torso's pose and twist.

Effort units are the motors' normalised commands (the env's action, ctrl
range [-1, 1]; joint torque = 150 x effort). Values outside the range are
clipped, as MuJoCo would.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from morph_core.env.model import check_num_joints
from morph_core.env.swimmer_env import MorphSwimmerEnv


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


class SwimmerSim:
    """One swimmer of ``num_joints`` joints.

    ``now`` arguments are the caller's clock in seconds (a node passes wall
    time: the effort timeout is about a controller going quiet, not about sim
    time); ``effort_timeout=None`` never times out.
    """

    def __init__(self, num_joints: int = 6, seed: int | None = 0, effort_timeout: float | None = 0.25):
        self._env = MorphSwimmerEnv(num_joints=check_num_joints(num_joints), observation_mode="graph")
        self.effort_timeout = effort_timeout
        self.time = 0.0
        """sim time [s]; keeps counting across rebuilds so a /clock never jumps back"""
        self.steps = 0
        self.rejected = 0
        """effort commands refused so far"""
        self.timed_out = False
        """whether the last step ran on zero effort because commands had stopped"""
        self.unstable_resets = 0
        self._seeded = seed
        self._reset()

    # -- chain ------------------------------------------------------------------
    @property
    def num_joints(self) -> int:
        return self._env.num_joints

    @property
    def dt(self) -> float:
        """Control period [s] (0.04: 4 physics steps of 0.01)."""
        return self._env.dt

    def rebuild(self, num_joints: int) -> None:
        """Replace the chain by one of ``num_joints`` joints, freshly reset; efforts drop to zero."""
        n = check_num_joints(num_joints)
        self._env.reset(options={"num_joints": n})
        self._clear_efforts()

    def _reset(self) -> None:
        # The seed goes in once: later rebuilds draw from the same generator, so a
        # run (seed, sequence of rebuilds) is reproducible.
        self._env.reset(seed=self._seeded)
        self._clear_efforts()

    def _clear_efforts(self) -> None:
        self._effort = np.zeros(self.num_joints)
        self.applied = np.zeros(self.num_joints)
        """efforts applied over the last control period (what ``joint_efforts`` reports)"""
        self._last_command: float | None = None

    # -- efforts ----------------------------------------------------------------
    def command(self, efforts: Sequence[float], now: float) -> np.ndarray:
        """Hold ``efforts`` (one per joint, chain order) from now on; returns them clipped.

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
        physics diverged, in which case the swimmer was reset to a fresh chain of the same length."""
        self.timed_out = self.commands_stale(now)
        a = np.zeros(self.num_joints) if self.timed_out else self._effort
        _, _, unstable, _, _ = self._env.step(a)
        self.applied = a.copy()
        self.steps += 1
        self.time = self.steps * self.dt
        if unstable:
            self.unstable_resets += 1
            self.rebuild(self.num_joints)
        return not unstable

    # -- state ------------------------------------------------------------------
    def joint_names(self, prefix: str = "") -> list[str]:
        """The MJCF joint names, torso to tail, with ``prefix`` in front."""
        return [f"{prefix}motor{k}_rot" for k in range(1, self.num_joints + 1)]

    @property
    def joint_positions(self) -> np.ndarray:
        return self._env.data.qpos[3:].copy()

    @property
    def joint_velocities(self) -> np.ndarray:
        return self._env.data.qvel[3:].copy()

    def torso(self) -> TorsoState:
        qpos, qvel = self._env.data.qpos, self._env.data.qvel
        return TorsoState(
            x=float(qpos[0]),
            y=float(qpos[1]),
            yaw=float(qpos[2]),
            vx=float(qvel[0]),
            vy=float(qvel[1]),
            yaw_rate=float(qvel[2]),
        )
