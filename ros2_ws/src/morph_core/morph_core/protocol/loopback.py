"""The sim and a controller in one process, recording what the two nodes would publish.

The in-process equivalent of recording a lockstep run: per control period the
sim publishes ``odom`` then ``joint_states`` (stamped with sim time, the
state's ``effort`` the command applied over the period that ended there), the
controller answers the state from those two messages exactly as the policy
node does (odometry of the same stamp, yaw unwrapped, ``chain_batch``) with an
effort command tagged with the state's stamp and, when it samples, a
``policy_info``; then the sim applies the command and steps. Every message
becomes the record a bag reader would decode it into (``msgs.records``), with
increasing receive times.

For tests and for data without DDS; ``truth`` keeps what actually happened
(each step's state stamp, the env's own observation, the action the env was
stepped with) so a replay can be compared against what the records say.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from morph_core.env.sim import SwimmerSim
from morph_core.msgs.joint_state import YawUnwrapper, chain_batch, global_features, quaternion_from_yaw, world_to_body
from morph_core.msgs.policy_info import pack_policy_info, unpack_policy_info
from morph_core.msgs.records import (
    EffortRecord,
    EpisodeStartRecord,
    JointStateRecord,
    OdometryRecord,
    Record,
)
from morph_core.msgs.stamps import seconds_to_ns
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.numpy_actor import NumpyPolicy

Controller = Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, dict | None]]
"""(joint_pos, joint_vel, global) -> (action before any clip, policy_info fields or None)"""


class SamplingController:
    """The policy node with ``deterministic:=false``: samples from the policy with its own torch generator."""

    def __init__(self, policy: GraphActorCritic, seed: int = 0):
        self.policy = policy
        self.generator = torch.Generator().manual_seed(seed)

    def __call__(self, pos, vel, glob):
        action, _, _, mean = self.policy.act(chain_batch(pos, vel, glob), generator=self.generator)
        a, mu = action[0].double().numpy(), mean[0].double().numpy()
        return a, pack_policy_info(a, mu, float(self.policy.log_std.detach()))


class MeanController:
    """The policy node with ``deterministic:=true``: the mean action (NumPy forward), no policy_info."""

    def __init__(self, policy: GraphActorCritic):
        self.numpy_policy = NumpyPolicy(policy)

    def __call__(self, pos, vel, glob):
        return self.numpy_policy.mean(pos, vel, glob).astype(np.float64), None


class GaussianController:
    """Random actions a ~ N(mean, exp(log_std)^2) from a NumPy generator, with their policy_info."""

    def __init__(self, mean: float = 0.0, log_std: float = 0.0, seed: int = 0, with_policy_info: bool = True):
        self.mean, self.log_std, self.with_policy_info = mean, log_std, with_policy_info
        self.rng = np.random.default_rng(seed)

    def __call__(self, pos, vel, glob):
        mu = np.full(len(pos), self.mean)
        a = mu + np.exp(self.log_std) * self.rng.standard_normal(len(pos))
        return a, (pack_policy_info(a, mu, self.log_std) if self.with_policy_info else None)


@dataclass(frozen=True)
class StepTruth:
    """What happened at one state: the env's observation there and the action the env was stepped with."""

    stamp_ns: int
    episode: int
    observation: dict
    action: np.ndarray | None
    """the controller's action (before the sim's clip); None if the state was never stepped from"""


class LoopbackRecording:
    """A ``SwimmerSim`` driven in lockstep by ``controller``; ``records`` is what a recorder would hold."""

    def __init__(self, sim: SwimmerSim, controller: Controller, joint_prefix: str = "", log_step_ns: int = 1000):
        if sim.effort_timeout is not None:
            raise ValueError("the loopback runs on sim time only: build the SwimmerSim with effort_timeout=None")
        self.sim = sim
        self.controller = controller
        self.prefix = joint_prefix
        self.records: list[Record] = []
        self.truth: list[StepTruth] = []
        self._log_step = log_step_ns
        self._log_ns = 0
        self._ticks = 0  # control periods elapsed, resets included: stamps never repeat
        self._episode = 0
        self._unwrap = YawUnwrapper()
        self._names: tuple[str, ...] = ()
        self._announce_next = True
        self._state_published = False

    @property
    def stamp_ns(self) -> int:
        """Stamp of the state the sim is in now."""
        return seconds_to_ns(self._ticks * self.sim.dt)

    def _log(self) -> int:
        self._log_ns += self._log_step
        return self._log_ns

    def run(self, steps: int, late: Callable[[int], bool] | None = None) -> None:
        """Publish, answer and step ``steps`` times; the state reached last is published by the next ``run``.

        ``late(i)`` True: the i-th answer reaches the sim only after it stepped (a free-running sim with a
        slow controller): the sim applies the command it held over that period, and the answer is received
        after the next state and held from then on.
        """
        for i in range(steps):
            if not self._state_published:
                self.records += self._state_records()
            stamp = self.stamp_ns
            action, info = self._answer()
            effort = np.clip(action, -1.0, 1.0)
            if late is not None and late(i):
                self._step(stamp, None)
                self.records += self._state_records()
                self.records += self._answer_records(stamp, effort, info)
                self.sim.command(effort, 0.0)
                self._state_published = True
            else:
                self.records += self._answer_records(stamp, effort, info)
                self.sim.command(effort, 0.0)
                self._step(stamp, action)
                self._state_published = False

    def _step(self, stamp: int, action: np.ndarray | None) -> None:
        self.sim.step(0.0)
        self._ticks += 1
        stepped_with = self.sim.applied.copy() if action is None else action
        self.truth[-1] = StepTruth(stamp, self._episode, self.truth[-1].observation, stepped_with)

    def finish(self) -> None:
        """Publish the state reached last and let the controller answer it (the sim will not step again)."""
        if not self._state_published:
            self.records += self._state_records()
            self._state_published = True
            action, info = self._answer()
            self.records += self._answer_records(self.stamp_ns, np.clip(action, -1.0, 1.0), info)

    def new_episode(self, num_joints: int | None = None, announce: bool = True, same_stamp: bool = False) -> None:
        """End the episode (``finish``) and reset the swimmer, optionally to another chain length. The new first
        state is stamped one period after the last one (``same_stamp``: with the last one's stamp, as a sim
        that rebuilds without stepping its clock), and announced unless ``announce`` is False."""
        self.finish()
        self.sim.rebuild(self.sim.num_joints if num_joints is None else num_joints)
        self._ticks += not same_stamp
        self._episode += 1
        self._announce_next = announce
        self._state_published = False

    # -- messages ---------------------------------------------------------------
    def _answer(self) -> tuple[np.ndarray, dict | None]:
        """The controller's answer to the current state, from its messages as the policy node builds it."""
        state = next(r for r in reversed(self.records) if isinstance(r, JointStateRecord))
        odom = next(r for r in reversed(self.records) if isinstance(r, OdometryRecord))
        if state.names != self._names:
            self._names = state.names
            self._unwrap.reset()
        glob = global_features(odom.orientation_xyzw, odom.body_linear_xy, odom.angular_z, self._unwrap)
        return self.controller(state.position, state.velocity, glob)

    def _state_records(self) -> list[Record]:
        stamp, torso = self.stamp_ns, self.sim.torso()
        out: list[Record] = []
        if self._announce_next:
            out.append(EpisodeStartRecord(self._log(), stamp, self._episode, self.sim.num_joints))
            self._unwrap.reset()  # the policy node restarts unwrapping with each announced episode
            self._announce_next = False
        out.append(
            OdometryRecord(
                self._log(),
                stamp,
                torso.x,
                torso.y,
                quaternion_from_yaw(torso.yaw),
                world_to_body(torso.yaw, torso.vx, torso.vy),
                torso.yaw_rate,
            )
        )
        names = tuple(self.sim.joint_names(self.prefix))
        pos, vel, applied = self.sim.joint_positions, self.sim.joint_velocities, self.sim.applied.copy()
        out.append(JointStateRecord(self._log(), stamp, names, pos, vel, applied))
        observation = {
            "joint_pos": pos,
            "joint_vel": vel,
            "global": np.array([torso.yaw, torso.yaw_rate, torso.vx, torso.vy]),
        }
        self.truth.append(StepTruth(stamp, self._episode, observation, None))
        return out

    def _answer_records(self, stamp: int, effort: np.ndarray, info: dict | None) -> list[Record]:
        out: list[Record] = [EffortRecord(self._log(), stamp, effort.astype(np.float64))]
        if info is not None:
            out.append(unpack_policy_info(self._log(), stamp, self._names, **info))
        return out


def record_episodes(controller: Controller, episodes, seed: int = 0) -> list:
    """Records of consecutive episodes ``((num_joints, steps), ...)`` of one seeded sim under ``controller``."""
    loop = LoopbackRecording(SwimmerSim(episodes[0][0], seed=seed, effort_timeout=None), controller)
    for i, (n, steps) in enumerate(episodes):
        if i:
            loop.new_episode(n)
        loop.run(steps)
    loop.finish()
    return loop.records
