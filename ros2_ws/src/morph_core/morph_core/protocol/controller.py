"""What a policy node does between the messages it reads and the efforts it sends, written once (no ROS, no torch).

``Controller`` is the policy node without its topics: the node
(``morph_policy_node.policy_node``) keeps only its subscriptions, publishers,
parameters and timers and hands every message to one ``Controller``; the
in-process loopback (``protocol.loopback``) feeds it the records a lockstep
run publishes, in the order the node would receive them; and the transition
assembler (``protocol.transitions``) rebuilds each observation with its
``observe``. So what a policy saw, what a loopback recording says it saw and
what a trainer rebuilds from the topics are one computation, equal to the bit
(``test_controller.py``). Messages come in as ``msgs.records``:

- ``description(text)``: a ``robot_description`` (``protocol.robot_description``:
  the joint map by name, the previous one kept for states in flight);
- ``episode_start(stamp)``: an episode announcement;
- ``odometry(record)`` and ``state(record, now)``: each returns the states
  ready to answer, each paired with the odometry of its stamp
  (``protocol.pairing``; ``expired(now)`` releases one that waited too long);
- ``answer(ready)``: the efforts, in the output order (``effort_order``) and
  units (``effort_units``), the joints' names, the joint layout they were
  computed on, and, when sampling, the ``policy_info`` fields.

The global features are chosen by the policy's width
(``NumpyPolicy.global_features``, or ``global_features`` without a policy), in
the table ``GLOBAL_FEATURES``: 4, a swimmer's planar (yaw unwrapped, yaw rate,
world-frame velocity; ``msgs.joint_state.global_features``), 12, a legged
body's in 3-D (``msgs.joint_state.legged_global_features``).

Joint descriptions. A policy that reads them (``joint_features`` 11,
``policy.joint_description``) gets each joint's vector built from the
``robot_description`` adopted (``urdf_descriptions``, in the tree's order: the
order the state is laid out in), in ``Observation.joint_desc``. Such a
controller has no chain fallback: until a description is adopted a state is
refused (``JointMapError`` code ``NO_DESCRIPTION``), and a description whose
vectors cannot be built (non-finite numbers, a zero axis, an absurd size) is
rejected (code ``JOINT_DESCRIPTION``) with the last good one kept, so no NaN
ever reaches the policy. A policy that reads none costs nothing here: no
vector is built and nothing else changes.

The yaw unwrapping's reset rule, one for all three (``observe``). The
unwrapping restarts at a state when (a) it is read on another robot than the
state answered before it: another description adopted (even of the same tree:
the node cannot tell a robot swapped for an identical one) or, with none,
another chain of names; or (b) it begins an episode: one announced on
``episode_start`` for its stamp, or the clock went back (a restarted sim);
and (c) an announcement that arrives after its first state was answered
restarts it at once, so from the next state on: an answer cannot be taken
back, and the trainer rebuilds the observation the policy acted on, not the
one it should have had. A stamp gap (states lost on the way) restarts
nothing: a controller cannot see it. Before this class the three copies
disagreed: the loopback restarted only for another tree (not for a new
description of the same one), and the transitions restarted before the first
state for a late announcement and never when the clock went back; the rule
above is the node's, the only one of the three that runs on a robot, and the
only one a controller can follow without seeing the future.

Efforts (``answer``): the policy's action clipped to [-1, 1] (``normalized``,
the default), or each joint's clipped action times its URDF ``<limit
effort>`` (``urdf``: a ``JointGroupEffortController`` takes them as they are).
With ``urdf`` a description in which an actuated joint has no usable limit
(missing, zero, negative or not a number) is refused with the joint named
(``EFFORT_LIMIT``), the current one kept, and a state is refused
(``NO_EFFORT_LIMITS``) while no description has been adopted: there is no
unit to scale into. ``policy_info`` stays in the policy's units (what the
trainer's log-probabilities are of).

Sampling (``deterministic`` False) is the node's NumPy sampler
(``NumpyPolicy.sample``) on the controller's own ``numpy.random.Generator``
seeded by ``seed``: one draw of ``standard_normal(N)`` per state answered, so a
run is reproduced by its seed.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from morph_core.constants import LEGGED_GLOBAL_FEATURES, NUM_GLOBAL_FEATURES
from morph_core.msgs.joint_state import YawUnwrapper, global_features, legged_global_features, validate_joint_state
from morph_core.msgs.policy_info import pack_policy_info
from morph_core.msgs.records import JointStateRecord, OdometryRecord
from morph_core.policy.joint_description import NUM_DESCRIPTION_FEATURES, urdf_descriptions
from morph_core.policy.tree import TreeError, UrdfRobot
from morph_core.protocol.episode_tracker import EpisodeTracker
from morph_core.protocol.joint_map import JointMapError, JointOrder
from morph_core.protocol.pairing import ODOMETRY_WAIT, StatePairing
from morph_core.protocol.robot_description import DescriptionOffer, RobotDescriptions


def _planar(odom: OdometryRecord, unwrap: YawUnwrapper) -> np.ndarray:
    return global_features(odom.orientation_xyzw, odom.body_linear_xy, odom.angular_z, unwrap)


def _legged(odom: OdometryRecord, unwrap: YawUnwrapper) -> np.ndarray:
    return legged_global_features(odom.orientation_xyzw, odom.position, odom.body_linear, odom.body_angular)


GLOBAL_FEATURES: dict[int, Callable[[OdometryRecord, YawUnwrapper], np.ndarray]] = {
    NUM_GLOBAL_FEATURES: _planar,
    LEGGED_GLOBAL_FEATURES: _legged,
}
"""a policy's global width -> its features from the torso's odometry (the unwrapper: the controller's, reset by
its one rule; a feature that does not unwrap ignores it)"""


def global_width_error(width: int) -> str | None:
    """Why a policy reading ``width`` global features cannot be driven from the topics, or None."""
    if width in GLOBAL_FEATURES:
        return None
    return f"reads {width} global features; a controller builds {' or '.join(map(str, GLOBAL_FEATURES))}"


def policy_error(config) -> str | None:
    """Why a policy of ``config`` (a ``PolicyConfig``) cannot be driven from the topics, or None: a global width
    no controller builds, or a number of description features per joint other than the descriptions'
    (``NUM_DESCRIPTION_FEATURES``; a refusal in one line, not a failure at the first state)."""
    error = global_width_error(config.global_features)
    if error is not None:
        return error
    width = getattr(config, "joint_features", 0)
    if width not in (0, NUM_DESCRIPTION_FEATURES):
        return (
            f"reads {width} description features per joint; a controller builds {NUM_DESCRIPTION_FEATURES} "
            "from robot_description (policy.joint_description) or none"
        )
    return None


def check_odometry(odom: OdometryRecord) -> None:
    """Raise ``JointStateError`` if the odometry gives no features (NaN/inf, a quaternion not of unit length),
    in any width: it is checked when it arrives, and used when a state needs it."""
    global_features(odom.orientation_xyzw, odom.body_linear_xy, odom.angular_z)
    legged_global_features(odom.orientation_xyzw, odom.position, odom.body_linear, odom.body_angular)


# -- the answer's order and units -----------------------------------------------------------------
EFFORT_ORDERS = ("state", "description")
"""``effort_order`` values: efforts in the order of the state's names they answer, or in the description's
(depth-first) order of its actuated joints"""
EFFORT_UNITS = ("normalized", "urdf")
"""``effort_units`` values: the policy's [-1, 1], or each joint's times its URDF ``<limit effort>``"""
EFFORT_LIMIT = "effort_limit"
"""reason code of a description refused under ``urdf`` units: an actuated joint without a usable limit"""
NO_EFFORT_LIMITS = "no_effort_limits"
"""``JointMapError.code`` of a state refused under ``urdf`` units while no description has been adopted"""
JOINT_DESCRIPTION = "joint_description"
"""reason code of a description refused for a policy that reads joint descriptions: they cannot be built"""
NO_DESCRIPTION = "no_description"
"""``JointMapError.code`` of a state refused while a policy that reads joint descriptions has no description"""


class EffortOrderError(ValueError):
    """An ``effort_order`` or ``effort_units`` parameter that is none of its choices."""


def effort_order(value: object) -> str:
    """``value`` if it is one of ``EFFORT_ORDERS``; ``EffortOrderError`` naming the choices otherwise."""
    if value not in EFFORT_ORDERS:
        raise EffortOrderError(f"effort_order must be one of {', '.join(EFFORT_ORDERS)}; got {str(value)[:60]!r}")
    return value


def effort_units(value: object) -> str:
    """``value`` if it is one of ``EFFORT_UNITS``; ``EffortOrderError`` naming the choices otherwise."""
    if value not in EFFORT_UNITS:
        raise EffortOrderError(f"effort_units must be one of {', '.join(EFFORT_UNITS)}; got {str(value)[:60]!r}")
    return value


def effort_limit_error(robot: UrdfRobot) -> str | None:
    """Why the robot's efforts cannot be given in its URDF's units (the first actuated joint whose ``<limit
    effort>`` is missing, not a number, or not > 0), or None."""
    for name in robot.tree.names:
        limit = robot.effort_limits.get(name)
        if limit is None:
            return f"effort_units:=urdf and joint {name[:60]!r} has no <limit effort=...>"
        if not (math.isfinite(limit) and limit > 0):
            return f"effort_units:=urdf and joint {name[:60]!r} has <limit effort> {limit}, not a number > 0"
    return None


# -- the policy's answer ---------------------------------------------------------------------------
class Actor(Protocol):
    """What a controller drives: ``policy.numpy_actor.NumpyPolicy``, or a stand-in with its two methods
    (``joint_desc`` is passed only to a policy whose ``joint_features`` is not 0; a stand-in without the attribute
    reads none)."""

    log_std: float

    def mean(self, joint_pos, joint_vel, global_feats, parents=None, joint_desc=None) -> np.ndarray: ...

    def sample(
        self, joint_pos, joint_vel, global_feats, rng, parents=None, joint_desc=None
    ) -> tuple[np.ndarray, np.ndarray]: ...


class PolicyOutputError(ValueError):
    """The policy's output for a state is not finite: the state is rejected, nothing is published."""


@dataclass(frozen=True)
class Action:
    efforts: np.ndarray
    """float64 [N], clipped to the motors' [-1, 1]"""
    action: np.ndarray
    """float64 [N], before the clip: the sample, or the mean when deterministic"""
    mean: np.ndarray | None
    """the Gaussian mean (sampling only)"""


def act(
    policy: Actor,
    pos: np.ndarray,
    vel: np.ndarray,
    glob: np.ndarray,
    rng: np.random.Generator | None,
    parents: np.ndarray | None = None,
    joint_desc: np.ndarray | None = None,
) -> Action:
    """Efforts for one robot: the mean (``rng`` None) or a sample (the policy's NumPy sampler on ``rng``), its
    joints in tree order (``parents``, the tree's; None: a chain; ``joint_desc`` [N, D] their descriptions, for a
    policy that reads them). Raises ``PolicyOutputError`` if the policy's output is NaN or inf (finite weights can
    still overflow float32): a clip would turn inf into a full-scale command."""
    extra = {} if joint_desc is None else {"joint_desc": joint_desc}  # a stand-in that reads none needs no keyword
    with np.errstate(over="ignore", invalid="ignore"):  # reported below as one rejection, not a warning
        if rng is None:
            action, mean = policy.mean(pos, vel, glob, parents, **extra).astype(np.float64), None
        else:
            action, mean = policy.sample(pos, vel, glob, rng, parents, **extra)
    if not np.isfinite(action).all() or (mean is not None and not np.isfinite(mean).all()):
        raise PolicyOutputError("the policy's output for this state is not finite")
    return Action(np.clip(action, -1.0, 1.0), action, mean)


# -- the controller ---------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Ready:
    """A state ready to answer, read on the tree of the description current when it arrived."""

    stamp_ns: int
    generation: int
    """the description it was read under (``RobotDescriptions.generation``; 0: the chain fallback)"""
    order: JointOrder
    joint_pos: np.ndarray
    """float64, the tree's order"""
    joint_vel: np.ndarray
    limits: np.ndarray | None
    """each joint's effort limit in the tree's order (``urdf`` units), None in normalized units"""
    joint_desc: np.ndarray | None = None
    """float64 [N, D] the joints' descriptions in the tree's order, for a policy that reads them (else None)"""


@dataclass(frozen=True, eq=False)
class Observation:
    """What the policy reads for one state: joints in the tree's order, and its global features."""

    joint_pos: np.ndarray
    joint_vel: np.ndarray
    global_feats: np.ndarray
    parents: np.ndarray
    """the tree's parent array (-1: the torso)"""
    names: tuple[str, ...]
    """the tree's joints, in its order"""
    joint_desc: np.ndarray | None = None
    """float64 [N, D] their descriptions (``policy.joint_description``), for a policy that reads them"""


@dataclass(frozen=True, eq=False)
class Answer:
    """The answer to one state, everything in the output order (``names``)."""

    stamp_ns: int
    names: tuple[str, ...]
    layout: str
    """the joint layout the efforts were computed on (``KinematicTree.layout_hash``)"""
    efforts: np.ndarray
    """float64: the action clipped to [-1, 1], in ``effort_units``"""
    action: np.ndarray
    """the policy's action before the clip, in its own units (the mean when deterministic)"""
    info: dict[str, np.ndarray] | None
    """the ``policy_info`` point's fields (``msgs.policy_info.pack_policy_info``), when sampling"""
    observation: Observation
    described: bool
    """read on a robot_description (False: the chain fallback)"""


class Controller:
    """A policy node between messages and efforts; see the module docstring.

    ``policy``: what answers (``NumpyPolicy``; None for a controller that only ``observe``s, as the transition
    assembler's). ``global_features``, ``joint_features``: the widths without a policy. ``deterministic``: the
    mean; else a sample from the generator seeded by ``seed``, with its ``policy_info``. Both ``policy`` and
    ``deterministic`` may be changed between two answers (a node's parameters and pushed weights).
    """

    def __init__(
        self,
        policy: Actor | None = None,
        *,
        deterministic: bool = True,
        seed: int = 0,
        effort_order: str = "state",
        effort_units: str = "normalized",
        global_features: int = NUM_GLOBAL_FEATURES,
        joint_features: int = 0,
        odometry_wait: float = ODOMETRY_WAIT,
    ):
        self.policy = policy
        self.deterministic = deterministic
        self.rng = np.random.default_rng(seed)
        self.effort_order = _effort_order(effort_order)
        self.effort_units = _effort_units(effort_units)
        self._width, self._joint_width = global_features, joint_features
        urdf = self.effort_units == "urdf"
        self.descriptions = RobotDescriptions(
            effort_limit_error if urdf else None, EFFORT_LIMIT, self._describe, JOINT_DESCRIPTION
        )
        self.pairing: StatePairing[Ready] = StatePairing(odometry_wait)
        self.odom: OdometryRecord | None = None
        """the latest odometry (checked)"""
        self._unwrap = YawUnwrapper()
        self._episodes = EpisodeTracker()
        self._robot: tuple | None = None  # (description generation, tree joints) of the state observed last
        self.names: tuple[str, ...] = ()
        """the joints of the robot answered last, in the output order (a node's fail-safe zeros are for them)"""
        self.layout = ""
        """that robot's joint layout"""

    @property
    def width(self) -> int:
        """The global features the policy reads (without one: ``global_features``)."""
        return self._width if self.policy is None else int(getattr(self.policy, "global_features", self._width))

    @property
    def joint_features(self) -> int:
        """The description features per joint the policy reads (0: none; without a policy: ``joint_features``)."""
        return self._joint_width if self.policy is None else int(getattr(self.policy, "joint_features", 0))

    def _describe(self, text: object) -> np.ndarray | None:
        """A description's joint descriptions when the policy reads them (``TreeError`` if they cannot be built)."""
        return urdf_descriptions(text) if self.joint_features else None

    # -- inputs, in the order they are received ---------------------------------------------------
    def description(self, text: object) -> DescriptionOffer:
        """A ``robot_description``: adopted, unchanged or rejected (``RobotDescriptions.offer``; under ``urdf``
        units also rejected, code ``EFFORT_LIMIT``, for a joint without a usable effort limit; for a policy that
        reads joint descriptions, code ``JOINT_DESCRIPTION``, for one whose descriptions cannot be built)."""
        return self.descriptions.offer(text)

    def episode_start(self, stamp_ns: int) -> None:
        """An episode begins at the state stamped ``stamp_ns``."""
        if self._episodes.announced(stamp_ns):
            self._unwrap.reset()  # its first state was answered already: restart from the next one

    def odometry(self, odom: OdometryRecord) -> list[Ready]:
        """The torso's odometry (``JointStateError`` if it gives no features: the previous one is kept); the
        state it completes, if one was waiting for it."""
        check_odometry(odom)
        self.odom = odom
        ready = self.pairing.odometry(odom.stamp_ns)
        return [] if ready is None else [ready]

    def state(self, state: JointStateRecord, now: float) -> list[Ready]:
        """A joint state received at ``now`` (the caller's clock, seconds); the states ready to answer, in order.

        Raises ``JointStateError`` for a malformed one, ``JointMapError`` for one that does not fit the
        description (its ``code``: ``unknown_joint``, ``missing_joint``, ``previous_description`` for a state of
        the robot before a swap, ``NO_EFFORT_LIMITS``, ``NO_DESCRIPTION``, or ``JOINT_DESCRIPTION`` when the
        policy began to read descriptions after the current one was adopted and its own cannot be built)."""
        pos, vel = validate_joint_state(state.names, state.position, state.velocity)
        desc = None
        if self.joint_features:
            if self.descriptions.is_fallback:
                raise JointMapError(
                    NO_DESCRIPTION, "the policy reads joint descriptions and no robot_description has been adopted: "
                    "waiting for one (no chain fallback)",
                )  # fmt: skip
            try:
                desc = self.descriptions.joint_descriptions()
            except TreeError as err:
                raise JointMapError(JOINT_DESCRIPTION, f"the robot_description's joint descriptions: {err}") from None
        order = self.descriptions.order(tuple(state.names))
        limits = None
        if self.effort_units == "urdf":
            robot = self.descriptions.map.robot
            if robot is None:
                raise JointMapError(
                    NO_EFFORT_LIMITS, "effort_units:=urdf needs the joints' <limit effort> and no robot_description "
                    "has been adopted: nothing to scale the efforts by",
                )  # fmt: skip
            limits = np.array([robot.effort_limits[name] for name in order.tree.names], dtype=np.float64)
        ready = Ready(
            state.stamp_ns, self.descriptions.generation, order, order.to_tree(pos), order.to_tree(vel), limits, desc
        )
        return self.pairing.state(state.stamp_ns, ready, now)

    def expired(self, now: float) -> Ready | None:
        """The state that waited for its odometry longer than the wait, to answer with the latest one."""
        return self.pairing.expired(now)

    # -- observation and answer -------------------------------------------------------------------
    def observe(self, stamp_ns: int, robot: tuple, odom: OdometryRecord | None) -> np.ndarray:
        """The global features of the state stamped ``stamp_ns`` of ``robot`` (any key that differs for another
        robot: (description generation, tree joints)), from ``odom`` (None: the torso at rest at the origin).
        Call it for each state acted on, in order: the unwrapping's one reset rule (module docstring) lives
        here. Raises ``JointStateError`` for an odometry that gives no features."""
        new_episode = self._episodes.state(stamp_ns)
        if robot != self._robot or new_episode:
            self._robot = robot
            self._unwrap.reset()
        width = self.width
        if odom is None:
            return np.zeros(width)
        features = GLOBAL_FEATURES.get(width)
        if features is None:
            raise ValueError(f"the policy {global_width_error(width)}")
        return features(odom, self._unwrap)

    def answer(self, ready: Ready) -> Answer:
        """The answer to a ready state, with the latest odometry. Raises ``PolicyOutputError`` if the policy's
        output is not finite (``names`` and ``layout`` are this robot's all the same)."""
        order = ready.order
        tree = order.tree
        glob = self.observe(ready.stamp_ns, (ready.generation, tree.names), self.odom)
        by_tree = self.effort_order == "description"
        names = tree.names if by_tree else order.message_names
        self.names, self.layout = names, tree.layout_hash
        rng = None if self.deterministic else self.rng
        if bool(self.joint_features) != (ready.joint_desc is not None):  # weights that read otherwise, pushed since
            raise PolicyOutputError("the state was read for a policy that reads joint descriptions otherwise")
        out = act(self.policy, ready.joint_pos, ready.joint_vel, glob, rng, tree.parents, ready.joint_desc)
        efforts = out.efforts if ready.limits is None else out.efforts * ready.limits
        info = None
        if out.mean is not None:
            info = pack_policy_info(
                self._ordered(order, by_tree, out.action), self._ordered(order, by_tree, out.mean), self.policy.log_std
            )
        observation = Observation(ready.joint_pos, ready.joint_vel, glob, tree.parents, tree.names, ready.joint_desc)
        return Answer(
            ready.stamp_ns, names, tree.layout_hash, self._ordered(order, by_tree, efforts),
            self._ordered(order, by_tree, out.action), info, observation, ready.generation > 0,
        )  # fmt: skip

    @staticmethod
    def _ordered(order: JointOrder, by_tree: bool, values: np.ndarray) -> np.ndarray:
        return values if by_tree else order.to_message(values)


_effort_order, _effort_units = effort_order, effort_units  # the parameters shadow them in __init__
