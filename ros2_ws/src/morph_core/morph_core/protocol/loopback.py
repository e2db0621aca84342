"""The sim and a controller in one process, recording what the two nodes would publish.

The in-process equivalent of recording a lockstep run: per control period the
sim publishes ``odom`` then ``joint_states`` (stamped with sim time, the
state's ``effort`` the command applied over the period that ended there), the
controller answers the state from those two messages with the policy node's
own ``protocol.controller.Controller`` (fed every message in the order the node
would receive it: the description, the announcement, the odometry, the state)
with an effort command tagged with the state's stamp and, when it samples, a
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
joints as a chain in the message's order.

The controllers: ``SamplingController`` (a policy node with
``deterministic:=false``: the node's NumPy sampler, seeded), ``MeanController``
(``deterministic:=true``) and ``GaussianController`` (random actions around a
constant mean, through the same sampler); each is a ``Controller``. Recordings
made before the sampler was the node's (a torch generator then) hold other
samples for the same seed. ``shuffle_seed`` lists each
state's joints in a random order of its own (the sim's shuffling option);
``name_efforts`` labels each effort command with its joints' names
(``msgs.effort_names``). Answers go out in the order of the state they
answer, restricted to the tree's joints (``JointOrder.message_names``),
``policy_info``'s arrays and ``joint_names`` too, as the policy node sends
them; the sim applies them by name. With none of these options and a chain,
the records are what they always were.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from morph_core.constants import LEGGED_GLOBAL_FEATURES, NUM_GLOBAL_FEATURES
from morph_core.env.model import body_parents
from morph_core.env.sim import SwimmerSim
from morph_core.env.urdf import swimmer_urdf
from morph_core.msgs.episode_start import EpisodeCause
from morph_core.msgs.joint_state import quaternion_from_yaw, world_to_body
from morph_core.msgs.policy_info import unpack_policy_info
from morph_core.msgs.records import (
    DescriptionRecord,
    EffortRecord,
    EpisodeStartRecord,
    JointStateRecord,
    OdometryRecord,
    Record,
)
from morph_core.msgs.stamps import seconds_to_ns
from morph_core.policy.joint_description import mujoco_descriptions
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.tree import KinematicTree
from morph_core.protocol.controller import Answer, Controller


def _numpy(policy) -> NumpyPolicy:
    """The NumPy policy of a torch ``GraphActorCritic`` (its weights now), a ``PolicyWeights``, or itself."""
    return policy if isinstance(policy, NumpyPolicy) else NumpyPolicy(policy)


class SamplingController(Controller):
    """The policy node with ``deterministic:=false``: the node's NumPy sampler, its generator seeded by ``seed``
    (``options``: ``Controller``'s)."""

    def __init__(self, policy, seed: int = 0, **options):
        super().__init__(_numpy(policy), deterministic=False, seed=seed, **options)


class MeanController(Controller):
    """The policy node with ``deterministic:=true``: the mean action, no policy_info."""

    def __init__(self, policy, **options):
        super().__init__(_numpy(policy), deterministic=True, **options)


class _ConstantGaussian:
    """A stand-in policy: every joint's mean is ``mean``; sampled as ``NumpyPolicy.sample`` samples."""

    global_features = NUM_GLOBAL_FEATURES

    def __init__(self, mean: float, log_std: float):
        self._mean, self.log_std = mean, log_std

    def mean(self, joint_pos, joint_vel, global_feats, parents=None) -> np.ndarray:
        return np.full(len(joint_pos), self._mean)

    def sample(self, joint_pos, joint_vel, global_feats, rng, parents=None) -> tuple[np.ndarray, np.ndarray]:
        mu = self.mean(joint_pos, joint_vel, global_feats)
        return mu + math.exp(self.log_std) * rng.standard_normal(mu.shape[0]), mu


class GaussianController(Controller):
    """Random actions a ~ N(mean, exp(log_std)^2) from a NumPy generator, with their policy_info."""

    def __init__(self, mean: float = 0.0, log_std: float = 0.0, seed: int = 0):
        super().__init__(_ConstantGaussian(mean, log_std), deterministic=False, seed=seed)


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
    reward: float | None = None
    """what the env paid for that step (a centipede's: Ant-v5's, contact cost included); None for others"""


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
        self._described: tuple | None = None  # the body last described: its parents (and a robot's model)
        self._joint_desc: np.ndarray | None = None  # that robot's joint descriptions, read off its compiled model
        self._latest: Answer | None = None  # the controller's answer to the state published last
        self._announce_next = True
        self._cause: str | None = None  # the next announcement's, when it says more than start/steps
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
            if self.sim.fell:  # as the sim node does: the fallen state answered, then a new episode, announced
                self.records += self._answer_records(self.stamp_ns, self._latest)
                self.sim.reset(EpisodeCause.FELL)
                self._ticks += 1
                self._episode += 1
                self._announce_next, self._cause = True, "fell"
                self.records += self._state_records()
            stamp = self.stamp_ns
            answer = self._latest
            if late is not None and late(i):
                self._step(stamp, None)
                self.records += self._state_records()
                self.records += self._answer_records(stamp, answer)
                self.sim.command(self._in_env_order(answer.efforts, answer.names), 0.0)
                self._state_published = True
            else:
                self.records += self._answer_records(stamp, answer)
                self.sim.command(self._in_env_order(answer.efforts, answer.names), 0.0)
                self._step(stamp, self._in_env_order(answer.action, answer.names))
                self._state_published = False

    def _step(self, stamp: int, action: np.ndarray | None) -> None:
        self.sim.step(0.0)
        self._ticks += 1
        stepped_with = self.sim.applied.copy() if action is None else action
        reward = getattr(self._robot(), "reward", None)
        self.truth[-1] = StepTruth(stamp, self._episode, self.truth[-1].observation, stepped_with, reward)

    def finish(self) -> None:
        """Publish the state reached last and let the controller answer it (the sim will not step again)."""
        if not self._state_published:
            self.records += self._state_records()
            self._state_published = True
            self.records += self._answer_records(self.stamp_ns, self._latest)

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
        if num_joints is None and self._robot() is not None:
            self.sim.reset()  # a robot, or centipedes of a spec: the next body is the sim's to draw
        else:
            if num_joints is None:
                num_joints = self.sim.num_joints if self.sim.tree.is_chain else self.sim.tree
            self.sim.rebuild(num_joints)
        self._ticks += not same_stamp
        self._episode += 1
        self._announce_next = announce
        self._state_published = False

    # -- messages ---------------------------------------------------------------
    def _robot(self):
        """The sim's robot model (centipedes included), None for a swimmer."""
        return getattr(self.sim, "robot", None)

    def _body(self) -> int | KinematicTree:
        """The sim's body: its tree (any sim that says), else its chain length."""
        tree = getattr(self.sim, "tree", None)
        return self.sim.num_joints if tree is None else tree

    def _in_env_order(self, values: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
        """Per-joint values, one per name of ``names``, in the env's joint order (by name)."""
        env_names = tuple(self.sim.joint_names(self.prefix))
        if names == env_names:
            return values
        at = {name: j for j, name in enumerate(names)}
        return values[[at[name] for name in env_names]]

    def _state_records(self) -> list[Record]:
        stamp = self.stamp_ns
        out: list[Record] = []
        robot = self._robot()
        # a robot's model too: two generated legged bodies of one tree differ in their joint descriptions
        body = (body_parents(self._body()), None if robot is None else getattr(robot, "model", None))
        if self.describe and body != self._described:
            # as the sim node publishes it
            text = swimmer_urdf(self._body(), self.prefix) if robot is None else self.sim.urdf(self.prefix)
            out.append(DescriptionRecord(self._log(), text))
            self._described = body
            self._joint_desc = None if body[1] is None else mujoco_descriptions(body[1])
        if self._announce_next:
            out.append(EpisodeStartRecord(self._log(), stamp, self._episode, self.sim.num_joints, self._cause))
            self._announce_next, self._cause = False, None
        odometry, glob = self._odometry(stamp)
        out.append(odometry)
        names = tuple(self.sim.joint_names(self.prefix))
        pos, vel, applied = self.sim.joint_positions, self.sim.joint_velocities, self.sim.applied.copy()
        if self._shuffle is None:
            out.append(JointStateRecord(self._log(), stamp, names, pos, vel, applied))
        else:
            k = self._shuffle.permutation(len(names))
            out.append(JointStateRecord(self._log(), stamp, tuple(names[i] for i in k), pos[k], vel[k], applied[k]))
        self._latest = self._answered(out)
        observation = {"joint_pos": pos, "joint_vel": vel, "global": glob}
        if self._joint_desc is not None:  # the compiled model's, to compare with what a controller read off the URDF
            observation["joint_desc"] = self._joint_desc
        self.truth.append(StepTruth(stamp, self._episode, observation, None))
        return out

    def _odometry(self, stamp: int) -> tuple[OdometryRecord, np.ndarray | None]:
        """The torso's odometry as the sim node publishes it, and the env's global features there (a robot's:
        those of the centipede env, None for another robot)."""
        robot = self._robot()
        if robot is None:
            t = self.sim.torso()
            body = world_to_body(t.yaw, t.vx, t.vy)
            odometry = OdometryRecord(self._log(), stamp, t.x, t.y, quaternion_from_yaw(t.yaw), body, t.yaw_rate)
            return odometry, np.array([t.yaw, t.yaw_rate, t.vx, t.vy])
        root = self.sim.odometry()
        odometry = OdometryRecord.of(self._log(), stamp, root.position, root.orientation, root.linear, root.angular)
        glob = None
        if hasattr(robot, "write_observation"):  # the centipede env's own features, for comparison
            glob, n = np.empty(LEGGED_GLOBAL_FEATURES), self.sim.num_joints
            robot.write_observation(np.empty(n), np.empty(n), glob)
        return odometry, glob

    def _answered(self, published: list[Record]) -> Answer:
        """The controller's answer to the state ``published`` ends with, fed those messages in their order as the
        policy node receives them."""
        ready = []
        for record in published:
            if isinstance(record, DescriptionRecord):
                self.controller.description(record.text)
            elif isinstance(record, EpisodeStartRecord):
                self.controller.episode_start(record.stamp_ns)
            elif isinstance(record, OdometryRecord):
                ready += self.controller.odometry(record)
            else:
                ready += self.controller.state(record, 0.0)  # its odometry is in: it is ready at once
        (state,) = ready
        return self.controller.answer(state)

    def _answer_records(self, stamp: int, answer: Answer) -> list[Record]:
        """The effort command and policy_info of ``answer`` (in the state's order, as the policy node sends them)."""
        named = (answer.names, answer.layout) if self.name_efforts else (None, None)  # as the policy node names them
        out: list[Record] = [EffortRecord(self._log(), stamp, answer.efforts.astype(np.float64), *named)]
        if answer.info is not None:
            out.append(unpack_policy_info(self._log(), stamp, answer.names, **answer.info))
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
