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
stepped with, in the env's joint order) so a replay can be compared against
what the records say.

Trees and joint names. The swimmer may be a tree (``SwimmerSim.rebuild(tree)``). With
``describe`` the sim's ``robot_description`` is recorded too
(``DescriptionRecord``: ``env.urdf.swimmer_urdf`` of the body, before the
first state of each new body, as the sim node publishes it), and the
controller reads every state through it by joint name
(``protocol.joint_map``), as the policy node does; without one it reads the
joints as a chain in the message's order. ``shuffle_seed`` lists each
state's joints in a random order of its own (the sim's shuffling option);
``name_efforts`` labels each effort command with its joints' names
(``msgs.effort_names``). Answers go out in the order of the state they
answer, restricted to the tree's joints (``JointOrder.message_names``),
``policy_info``'s arrays and ``joint_names`` too, as the policy node sends
them; the sim applies them by name. With none of these options and a chain,
the records are what they always were.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from morph_core.env.model import body_parents
from morph_core.env.sim import SwimmerSim
from morph_core.env.urdf import swimmer_urdf
from morph_core.msgs.joint_state import YawUnwrapper, chain_batch, global_features, quaternion_from_yaw, world_to_body
from morph_core.msgs.policy_info import pack_policy_info, unpack_policy_info
from morph_core.msgs.records import (
    DescriptionRecord,
    EffortRecord,
    EpisodeStartRecord,
    JointStateRecord,
    OdometryRecord,
    Record,
)
from morph_core.msgs.stamps import seconds_to_ns
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.chains import ChainBatch
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.tree import KinematicTree
from morph_core.protocol.joint_map import JointMap, JointOrder

Controller = Callable[[np.ndarray, np.ndarray, np.ndarray, "np.ndarray | None"], tuple[np.ndarray, dict | None]]
"""(joint_pos, joint_vel, global, parents) -> (action before any clip, policy_info fields or None); joints in the
tree's order, ``parents`` its parent array, None for a chain"""


class SamplingController:
    """The policy node with ``deterministic:=false``: samples from the policy with its own torch generator."""

    def __init__(self, policy: GraphActorCritic, seed: int = 0):
        self.policy = policy
        self.generator = torch.Generator().manual_seed(seed)

    def __call__(self, pos, vel, glob, parents=None):
        if parents is None:
            batch = chain_batch(pos, vel, glob)
        else:
            n = len(pos)
            batch = ChainBatch.from_padded(pos[None], vel[None], np.asarray(glob)[None], [n], parents=parents[None])
        action, _, _, mean = self.policy.act(batch, generator=self.generator)
        a, mu = action[0].double().numpy(), mean[0].double().numpy()
        return a, pack_policy_info(a, mu, float(self.policy.log_std.detach()))


class MeanController:
    """The policy node with ``deterministic:=true``: the mean action (NumPy forward), no policy_info."""

    def __init__(self, policy: GraphActorCritic):
        self.numpy_policy = NumpyPolicy(policy)

    def __call__(self, pos, vel, glob, parents=None):
        return self.numpy_policy.mean(pos, vel, glob, parents).astype(np.float64), None


class GaussianController:
    """Random actions a ~ N(mean, exp(log_std)^2) from a NumPy generator, with their policy_info."""

    def __init__(self, mean: float = 0.0, log_std: float = 0.0, seed: int = 0, with_policy_info: bool = True):
        self.mean, self.log_std, self.with_policy_info = mean, log_std, with_policy_info
        self.rng = np.random.default_rng(seed)

    def __call__(self, pos, vel, glob, parents=None):
        mu = np.full(len(pos), self.mean)
        a = mu + np.exp(self.log_std) * self.rng.standard_normal(len(pos))
        return a, (pack_policy_info(a, mu, self.log_std) if self.with_policy_info else None)


@dataclass(frozen=True)
class StepTruth:
    """What happened at one state: the env's observation there and the action the env was stepped with."""

    stamp_ns: int
    episode: int
    observation: dict
    """the env's joints (its order) and global features at the state"""
    action: np.ndarray | None
    """the controller's action (before the sim's clip, in the env's joint order); None if the state was never
    stepped from"""


class LoopbackRecording:
    """A ``SwimmerSim`` (of chains or trees) driven in lockstep by ``controller``; ``records`` is what a
    recorder would hold. ``describe``, ``shuffle_seed`` and ``name_efforts``: see the module docstring."""

    def __init__(
        self,
        sim: SwimmerSim,
        controller: Controller,
        joint_prefix: str = "",
        log_step_ns: int = 1000,
        *,
        describe: bool = False,
        shuffle_seed: int | None = None,
        name_efforts: bool = False,
    ):
        if sim.effort_timeout is not None:
            raise ValueError("the loopback runs on sim time only: build the SwimmerSim with effort_timeout=None")
        self.sim = sim
        self.controller = controller
        self.prefix = joint_prefix
        self.describe = describe
        self.name_efforts = name_efforts
        self.records: list[Record] = []
        self.truth: list[StepTruth] = []
        self._shuffle = None if shuffle_seed is None else np.random.default_rng(shuffle_seed)
        self._log_step = log_step_ns
        self._log_ns = 0
        self._ticks = 0  # control periods elapsed, resets included: stamps never repeat
        self._episode = 0
        self._unwrap = YawUnwrapper()
        self._robot: tuple | None = None  # (names, parents) the unwrapping last restarted for
        self._joint_map = JointMap()  # the controller's (the policy node's): the latest description's
        self._described: tuple[int, ...] | None = None  # the parents of the body last described
        self._order: JointOrder | None = None  # the answered state's joints on the controller's tree
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
            order = self._order
            if late is not None and late(i):
                self._step(stamp, None)
                self.records += self._state_records()
                self.records += self._answer_records(stamp, effort, info, order)
                self.sim.command(self._in_env_order(effort, order), 0.0)
                self._state_published = True
            else:
                self.records += self._answer_records(stamp, effort, info, order)
                self.sim.command(self._in_env_order(effort, order), 0.0)
                self._step(stamp, self._in_env_order(action, order))
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
            self.records += self._answer_records(self.stamp_ns, np.clip(action, -1.0, 1.0), info, self._order)

    def new_episode(
        self,
        num_joints: int | KinematicTree | None = None,
        announce: bool = True,
        same_stamp: bool = False,
    ) -> None:
        """End the episode (``finish``) and reset the swimmer, optionally to another body (a chain length, or a
        tree; None keeps the body). The new first state is stamped one period after
        the last one (``same_stamp``: with the last one's stamp, as a sim that rebuilds without stepping its
        clock), and announced unless ``announce`` is False."""
        self.finish()
        if num_joints is None:
            num_joints = self.sim.num_joints if self.sim.tree.is_chain else self.sim.tree
        self.sim.rebuild(num_joints)
        self._ticks += not same_stamp
        self._episode += 1
        self._announce_next = announce
        self._state_published = False

    # -- messages ---------------------------------------------------------------
    def _body(self) -> int | KinematicTree:
        """The sim's body: its tree (any sim that says), else its chain length."""
        tree = getattr(self.sim, "tree", None)
        return self.sim.num_joints if tree is None else tree

    def _answer(self) -> tuple[np.ndarray, dict | None]:
        """The controller's answer to the current state (in the order of the tree it reads the state on), from
        its messages as the policy node builds it."""
        state = next(r for r in reversed(self.records) if isinstance(r, JointStateRecord))
        odom = next(r for r in reversed(self.records) if isinstance(r, OdometryRecord))
        order = self._order = self._joint_map.order(state.names)
        tree = order.tree
        robot = (tree.names, tree.parents.tobytes())
        if robot != self._robot:  # another robot (not another order of the same joints): its yaw starts afresh
            self._robot = robot
            self._unwrap.reset()
        glob = global_features(odom.orientation_xyzw, odom.body_linear_xy, odom.angular_z, self._unwrap)
        parents = None if tree.is_chain else tree.parents
        return self.controller(order.to_tree(state.position), order.to_tree(state.velocity), glob, parents)

    def _in_env_order(self, values: np.ndarray, order: JointOrder) -> np.ndarray:
        """Per-joint values in the order of the controller's tree, in the env's joint order (by name)."""
        env_names = tuple(self.sim.joint_names(self.prefix))
        if order.tree.names == env_names:
            return values
        at = {name: j for j, name in enumerate(order.tree.names)}
        return values[[at[name] for name in env_names]]

    def _state_records(self) -> list[Record]:
        stamp, torso = self.stamp_ns, self.sim.torso()
        out: list[Record] = []
        if self.describe and body_parents(self._body()) != self._described:
            text = swimmer_urdf(self._body(), self.prefix)  # as the sim node publishes it
            out.append(DescriptionRecord(self._log(), text))
            self._joint_map = JointMap.from_urdf(text)  # the policy node reads the states on it from now on
            self._described = body_parents(self._body())
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
        if self._shuffle is None:
            out.append(JointStateRecord(self._log(), stamp, names, pos, vel, applied))
        else:
            k = self._shuffle.permutation(len(names))
            out.append(JointStateRecord(self._log(), stamp, tuple(names[i] for i in k), pos[k], vel[k], applied[k]))
        observation = {
            "joint_pos": pos,
            "joint_vel": vel,
            "global": np.array([torso.yaw, torso.yaw_rate, torso.vx, torso.vy]),
        }
        self.truth.append(StepTruth(stamp, self._episode, observation, None))
        return out

    def _answer_records(self, stamp: int, effort: np.ndarray, info: dict | None, order: JointOrder) -> list[Record]:
        """The effort command and policy_info answering the state ``order`` read (values in its tree's order),
        in the state's order (``message_names``)."""
        names = order.message_names
        effort = order.to_message(effort).astype(np.float64)
        named = (names, order.tree.layout_hash) if self.name_efforts else (None, None)  # as the policy node names them
        out: list[Record] = [EffortRecord(self._log(), stamp, effort, *named)]
        if info is not None:
            fields = {k: order.to_message(v) for k, v in info.items()}
            out.append(unpack_policy_info(self._log(), stamp, names, **fields))
        return out


def body_sim(body: int | KinematicTree, seed: int) -> SwimmerSim:
    """A seeded sim with this first body (a tree: built as a rebuild after the seeded reset), no effort timeout."""
    if isinstance(body, KinematicTree):
        sim = SwimmerSim(body.num_joints, seed=seed, effort_timeout=None)
        sim.rebuild(body)
        return sim
    return SwimmerSim(body, seed=seed, effort_timeout=None)


def record_episodes(controller: Controller, episodes, seed: int = 0, **options) -> list:
    """Records of consecutive episodes ``((body, steps), ...)`` of one seeded sim under ``controller``: a body
    is a chain length or a ``KinematicTree``; ``options`` are ``LoopbackRecording``'s (``describe``,
    ``shuffle_seed``, ``name_efforts``, ``joint_prefix``)."""
    loop = LoopbackRecording(body_sim(episodes[0][0], seed), controller, **options)
    for i, (body, steps) in enumerate(episodes):
        if i:
            loop.new_episode(body)
        loop.run(steps)
    loop.finish()
    return loop.records
