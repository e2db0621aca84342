"""Transitions from recorded (or live) topics: the records of one swimmer in, RL steps out.

Feed ``TransitionAssembler.push`` the records of ``msgs.records`` in the order
they were received (a bag's log time, or as a live subscription delivers
them); it returns the transitions that became final, in stream order.
``flush`` ends the stream. ``assemble`` does both for a finished sequence.

A transition is the step from state s (a ``joint_states`` message) to the
next state s' one control period later:

- observation: joint positions and velocities of s, and (yaw, yaw rate, vx,
  vy) rebuilt from the odometry carrying s's stamp by the policy node's own
  ``protocol.controller.Controller`` (``observe``: yaw unwrapped along the
  stream with its one reset rule, told each state's robot and each episode
  announcement in the order they were received);
- action: the sampled action of the ``policy_info`` stamped s (the behaviour
  log-prob comes with it), else the effort command answering s (then
  ``has_policy_info`` is False and the log-prob NaN: PPO cannot use the
  step); either way clip(action) must be the effort the sim reports as
  applied over the period (s'.effort), or the step is skipped;
- reward: the task's (``TransitionConfig.task``), from what the topics
  carry. ``swimmer``: Swimmer-v5's, from the torso x of s and s' (their
  odometry), the control period, and that action clipped to the motors'
  range (what the sim applied, and what the simulator loop charges:
  ``env.reward``). ``ant`` (legged bodies, the centipedes' task): Ant-v5's
  forward velocity (the root's x of s and s' over the period), healthy
  reward (s''s odometry: the root's z within ``ANT_HEALTHY_Z_RANGE``) and
  control cost (the same clipped action), by ``env.reward.ant_reward``.
  Ant-v5's contact cost is not rebuilt: the contact forces are on no topic
  (charged as zero; how far the rebuilt return lies from the env's:
  docs/centipedes.md). The observation's global features are the task's too
  (4 planar, 12 in 3-D);
- terminated: on the last transition of an episode whose successor is
  announced with the cause ``fell`` (a legged body fell: the sim published
  the fallen state, then a new episode, as the env ends one at
  ``terminated``); never otherwise (the swimmer task has no terminal states;
  the one the env has, a physics divergence, leaves no next state on the
  wire: the sim resets and announces a new episode, so that step is not
  there to keep); truncated: on the last transition before any other
  episode boundary, a skipped step or the end of the stream, with s' kept
  as ``next_*`` for the bootstrap ``gamma * V(s')``.

Pairing is by stamp: the odometry of s has s's stamp, an effort answers the
state named by its answer tag (``msgs.stamps``), a policy_info carries the
stamp of the state it answers. An untagged effort (another controller) is
taken as the answer to the latest state received before it.

The robot's graph, by joint name. A ``robot_description`` record
(``DescriptionRecord``: the robot's URDF, which the sim publishes before the
first state of each body) says which robot the states that follow are of.
The assembler keeps the latest one that reads as a robot
(``protocol.joint_map.JointMap``; one that does not is counted as
``bad_description`` and the one before it kept) and binds each state to its
tree by name as the state arrives (``JointMap.order``): a state may list the
joints in any order, another one at every state, and carry joints the robot
does not actuate. Until a description arrives (or with none at all: a chain
robot needs none) each state's joints form a chain in the message's order
(``JointMap()``, the assembler's ``joint_map`` unless given another).
Everything a transition holds is in the tree's order: the observation, the
action (a ``policy_info``'s arrays laid out by its ``joint_names``; an effort
command's by its names dimension, ``msgs.effort_names``, or, naming none, in
the order of the state it answers) and the check against the applied effort
(s'.effort is in s''s own message order, which may differ from s's: compared
joint by joint, by name); ``names`` are the tree's joints and ``parents``
(``policy.index_plan``: joint j's parent joint, -1 off the torso) its parent
array. A state that does not fit the description is skipped under the
reason ``JointMap`` gives: ``unknown_joint`` (a joint the description does
not have) or ``missing_joint`` (one of its actuated joints missing); an
answer whose joint names are not the tree's joints as ``names_mismatch``.

Episode boundaries (no transition across them): an episode announcement for
s' (``EpisodeStartRecord``), another robot (s' bound to another tree than s:
other joint names or other parents, i.e. a description that changed the tree,
or without a description another chain of names), or s' not stamped one
control period after s (a lost state, a restarted sim whose clock went
back). A different state with the latest state's own stamp is a robot
rebuilt or reset without the clock moving on (the sim node's runtime
rebuild does this): the odometry and announcement received after the old
state are the new one's, and a new episode starts with it.

Nothing is guessed: a step that cannot be rebuilt is skipped and counted
under its reason (``SkipCounts``); a message that answers no state is
counted too. A state that is re-sent unchanged (a lockstep sim re-publishes
when an answer is late) is the same state, not a new one.

Streaming: messages of one stamp arrive on several topics, in no fixed order
and sometimes late. A state's step is judged once ``settle_states`` further
states have arrived (or at ``flush``), and a transition is released once the
next one is judged (that decides its ``truncated``).
"""

from __future__ import annotations

import math
from collections import OrderedDict, deque
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field, fields

import numpy as np

from morph_core.constants import LEGGED_GLOBAL_FEATURES, MAX_JOINTS, NUM_GLOBAL_FEATURES
from morph_core.env.centipede_model import ANT_TIMESTEP
from morph_core.env.reward import (
    ANT_FRAME_SKIP,
    ANT_HEALTHY_Z_RANGE,
    CTRL_COST_WEIGHT,
    FORWARD_REWARD_WEIGHT,
    ant_reward,
    applied_action,
    swimmer_reward,
)
from morph_core.msgs.joint_state import JointStateError, validate_joint_state
from morph_core.msgs.records import (
    DescriptionRecord,
    EffortRecord,
    EpisodeStartRecord,
    JointStateRecord,
    OdometryRecord,
    PolicyInfoRecord,
    Record,
)
from morph_core.msgs.stamps import seconds_to_ns
from morph_core.policy.tree import KinematicTree, UrdfRobot
from morph_core.protocol.controller import Controller, check_odometry, global_width_error
from morph_core.protocol.joint_map import JointMap, JointMapError, JointOrder
from morph_core.protocol.transition_batch import TransitionBatch

_ANSWER_MAPS = 8  # trees whose answer layouts are kept (one robot at a time; a few across description changes)

TASKS = ("swimmer", "ant")
"""what a transition's reward and observation are: Swimmer-v5's (4 planar global features), or Ant-v5's, the
legged bodies' (12 in 3-D; falls terminate)"""
TASK_GLOBAL_FEATURES = {"swimmer": NUM_GLOBAL_FEATURES, "ant": LEGGED_GLOBAL_FEATURES}
TASK_CONTROL_PERIODS = {"swimmer": 0.04, "ant": ANT_TIMESTEP * ANT_FRAME_SKIP}
"""each task's control period [s]: the swimmer's 4 physics steps of 0.01, a centipede's 5"""


def task_of(global_features: int) -> str:
    """The task of a policy reading ``global_features`` (``TASK_GLOBAL_FEATURES``); ValueError for another width."""
    for task, width in TASK_GLOBAL_FEATURES.items():
        if width == global_features:
            return task
    raise ValueError(f"no task has {global_features} global features ({TASK_GLOBAL_FEATURES})")


_NO_CONTACT_FORCES = np.zeros((1, 6))  # Ant-v5's contact cost: its forces are on no topic, charged as zero


@dataclass(frozen=True)
class TransitionConfig:
    """How records become transitions."""

    task: str = "swimmer"
    """the reward and observation rebuilt (``TASKS``): ``swimmer`` or ``ant`` (legged bodies: centipedes)"""
    control_period: float = 0.0
    """the sim's control period [s]; 0: the task's (``TASK_CONTROL_PERIODS``: a swimmer's 0.04, a centipede's
    0.05): consecutive states of an episode are this far apart, and it is the reward's dt"""
    stamp_tolerance_ns: int = 1000
    """how far a stamp difference may be from the control period and still be consecutive"""
    applied_atol: float = 0.0
    """tolerance when checking clip(action) against the effort the sim reports as applied
    (0: bit-exact, which the nodes give: both sides are the same float64 values)"""
    settle_states: int = 10
    """a state's messages (odometry, effort, policy_info, announcement) are awaited until this many
    later states have arrived; later ones are counted as late and unused"""
    max_joints: int = MAX_JOINTS
    forward_reward_weight: float = FORWARD_REWARD_WEIGHT
    """the swimmer task's (the ant task's weights are Ant-v5's defaults, ``env.reward``)"""
    ctrl_cost_weight: float = CTRL_COST_WEIGHT

    def __post_init__(self):
        if self.task not in TASKS:
            raise ValueError(f"task must be one of {', '.join(TASKS)}, got {str(self.task)[:40]!r}")
        if not (math.isfinite(self.control_period) and self.control_period >= 0):
            raise ValueError(f"control_period must be a finite number > 0 (0: the task's), got {self.control_period}")
        if self.stamp_tolerance_ns < 0 or self.applied_atol < 0 or self.settle_states < 0:
            raise ValueError("stamp_tolerance_ns, applied_atol and settle_states must be >= 0")

    @property
    def period(self) -> float:
        """The control period [s]: ``control_period``, or the task's."""
        return self.control_period or TASK_CONTROL_PERIODS[self.task]

    @property
    def control_period_ns(self) -> int:
        return seconds_to_ns(self.period)

    @property
    def global_features(self) -> int:
        """The width of the observation's global features (the task's)."""
        return TASK_GLOBAL_FEATURES[self.task]


@dataclass
class SkipCounts:
    """What could not be used, by reason.

    Step reasons count transitions not produced (each under the first reason
    that applies; a bad state costs both transitions it belongs to). Message
    reasons count messages left unused.
    """

    # -- steps --
    no_odometry: int = 0
    """the state or the next state has no odometry with its stamp"""
    no_answer: int = 0
    """no effort and no policy_info answers the state"""
    not_applied: int = 0
    """clip(action) differs from the effort the next state reports as applied (a late answer in
    free-running mode: the sim applied an older command), or from the answering effort command"""
    no_applied_effort: int = 0
    """the next state reports no applied effort and no effort command answers the state, so the
    action cannot be checked against what the sim did"""
    ambiguous_answer: int = 0
    """several different answers to the state all fit the applied effort"""
    names_mismatch: int = 0
    """the joint names of the policy_info (or of the effort command's names dimension) are not exactly the
    joints of the state's tree"""
    malformed: int = 0
    """lengths that do not fit the state's joints, empty or duplicate joint names, too many joints"""
    non_finite: int = 0
    """NaN or inf in a message the step needs"""
    duplicate_stamp: int = 0
    """two different states (or odometries) with one stamp: which is which cannot be told"""
    unknown_joint: int = 0
    """the state names a joint the robot's description does not have (``protocol.joint_map``)"""
    missing_joint: int = 0
    """the state lacks one of the actuated joints of the robot's description"""
    wrong_tree: int = 0
    """every effort command answering the state says it was computed on another joint layout than the tree the
    state is read on (``msgs.effort_names``): the policy and this stream disagree on the robot, e.g. its
    description reached one of them late"""
    # -- messages --
    orphan_effort: int = 0
    """an effort command whose answer tag names no recorded state"""
    orphan_policy_info: int = 0
    """a policy_info stamped with no recorded state's stamp"""
    orphan_odometry: int = 0
    """an odometry stamped with no recorded state's stamp"""
    orphan_announcement: int = 0
    """an episode announcement for a state that never arrived"""
    late_message: int = 0
    """a message that arrived after its state's step had been judged (``settle_states``)"""
    bad_description: int = 0
    """a robot_description that is no robot (``policy.tree.TreeError``): the one before it stays in use"""

    STEP_REASONS = (
        "no_odometry",
        "no_answer",
        "not_applied",
        "no_applied_effort",
        "ambiguous_answer",
        "names_mismatch",
        "malformed",
        "non_finite",
        "duplicate_stamp",
        "unknown_joint",
        "missing_joint",
        "wrong_tree",
    )
    MESSAGE_REASONS = (
        "orphan_effort",
        "orphan_policy_info",
        "orphan_odometry",
        "orphan_announcement",
        "late_message",
        "bad_description",
    )

    def add(self, reason: str, count: int = 1) -> None:
        setattr(self, reason, getattr(self, reason) + count)

    def steps(self) -> dict[str, int]:
        """Steps skipped, by reason (every step reason, zeros too)."""
        return {r: getattr(self, r) for r in self.STEP_REASONS}

    def messages(self) -> dict[str, int]:
        """Messages left unused, by reason (every message reason, zeros too)."""
        return {r: getattr(self, r) for r in self.MESSAGE_REASONS}

    @property
    def steps_skipped(self) -> int:
        return sum(self.steps().values())

    @property
    def messages_unused(self) -> int:
        return sum(self.messages().values())

    def as_dict(self) -> dict[str, int]:
        return asdict(self)

    def merge(self, other: SkipCounts) -> None:
        for f in fields(self):
            self.add(f.name, getattr(other, f.name))


@dataclass
class StreamStats:
    """What the stream held, beside the skips."""

    states: int = 0
    """distinct states received"""
    resent_states: int = 0
    """states received again unchanged (ignored)"""
    boundaries_announced: int = 0
    boundaries_new_chain: int = 0
    boundaries_stamp_gap: int = 0
    clock_restarts: int = 0
    """stamp gaps where the clock went back (a restarted sim), not lost messages"""
    episodes: int = 0
    """runs of consecutive transitions released (an episode with a skipped step counts twice)"""
    transitions: int = 0
    without_policy_info: int = 0
    """transitions whose action is an effort command, with no behaviour log-prob"""
    applied_unverified: int = 0
    """transitions whose next state reports no applied effort: the answering command is trusted"""
    descriptions: int = 0
    """robot descriptions that read as a robot (one re-sent unchanged included)"""

    BOUNDARY_CAUSES = ("announced", "new_chain", "stamp_gap")

    def count_boundary(self, cause: str) -> None:
        if cause not in self.BOUNDARY_CAUSES:
            raise ValueError(f"unknown boundary cause {cause!r}")
        name = f"boundaries_{cause}"
        setattr(self, name, getattr(self, name) + 1)

    @property
    def boundaries(self) -> int:
        return self.boundaries_announced + self.boundaries_new_chain + self.boundaries_stamp_gap

    @property
    def lost_state_gaps(self) -> int:
        """stamp gaps that lost messages made (the clock going back is a restart)"""
        return self.boundaries_stamp_gap - self.clock_restarts

    def as_dict(self) -> dict[str, int]:
        return asdict(self)

    def merge(self, other: StreamStats) -> None:
        for f in fields(self):
            setattr(self, f.name, getattr(self, f.name) + getattr(other, f.name))


@dataclass(frozen=True)
class Transition:
    """One control period of one swimmer (arrays float64, joints in the order of the robot's tree)."""

    episode: int
    """run of consecutive transitions this one belongs to (0, 1, ... over the assembler's life)"""
    stamp_ns: int
    names: tuple[str, ...]
    """the tree's joints, in its order (without a description: the state's, in the message's order)"""
    joint_pos: np.ndarray
    joint_vel: np.ndarray
    global_feats: np.ndarray
    action: np.ndarray
    log_prob: float
    """behaviour log-prob of ``action``; NaN when ``has_policy_info`` is False"""
    has_policy_info: bool
    reward: float
    terminated: bool
    truncated: bool
    next_joint_pos: np.ndarray
    next_joint_vel: np.ndarray
    next_global: np.ndarray
    parents: np.ndarray | None = None
    """[N] int64 parent joint of each joint (-1: the torso), the tree's (the state's and the next state's: an
    episode has one tree); None: a chain"""


@dataclass
class _Observation:
    pos: np.ndarray
    vel: np.ndarray
    glob: np.ndarray
    x: float
    z: float


@dataclass
class _Slot:
    """Everything received for one stamp."""

    stamp: int
    born: int
    """states received when the slot was opened (its age is counted in states)"""
    state: JointStateRecord | None = None
    odom: OdometryRecord | None = None
    efforts: list[EffortRecord] = field(default_factory=list)
    infos: list[PolicyInfoRecord] = field(default_factory=list)
    announced: bool = False
    cause: str | None = None
    """the announcement's cause (``EpisodeStartRecord.cause``): "fell" terminates the step before it"""
    conflict: bool = False
    # Received after the state, while it was the latest: they may be for a rebuilt robot whose state is
    # about to come with the same stamp (see _restamp); else they are the state's own.
    later_odom: OdometryRecord | None = None
    announced_later: bool = False
    obs: _Observation | None = None
    obs_error: str | None = None
    observed: bool = False
    order: JointOrder | None = None
    """how the state's joints lay onto the robot's tree (``JointMap.order``), None if they do not"""
    order_error: str = ""
    """why they do not: the skip reason"""
    described: bool = False
    """the state was bound to a robot description (not to the fallback's chain of its names)"""
    generation: int = 0
    """the descriptions adopted before the state arrived: a new one is a new robot to the policy node (its graph,
    even one of the same tree), so the unwrapping restarts at the first state read on it"""


class TransitionAssembler:
    """Records in, transitions out, for one stream (one robot); see the module docstring."""

    def __init__(
        self,
        config: TransitionConfig | None = None,
        joint_map: JointMap | None = None,
        global_features: int | None = None,
    ):
        """``joint_map``: the robot's joints until a description in the stream replaces it (one known
        otherwise, e.g. ``JointMap.from_urdf`` of a URDF file); default ``JointMap()``, each state's joints a
        chain in the message's order. ``global_features``: the width of the policy whose observations are
        rebuilt (``protocol.controller.GLOBAL_FEATURES``: 4 a swimmer's, 12 a legged body's); default the
        config's task's (the reward is always the task's)."""
        self.config = config or TransitionConfig()
        if global_features is None:
            global_features = self.config.global_features
        if global_width_error(global_features) is not None:
            raise ValueError(f"a policy that {global_width_error(global_features)}")
        self.global_features = global_features
        self.joint_map = JointMap() if joint_map is None else joint_map
        self._generation = 0
        """descriptions adopted (kept across ``flush``): which robot, to the policy node, a state is of"""
        self._description: str | bytes | None = None  # the text ``joint_map`` was read from
        self._answer_maps: dict[KinematicTree, JointMap] = {}
        self.skips = SkipCounts()
        self.stats = StreamStats()
        self._period_ns = self.config.control_period_ns
        # A message for a state judged at most this long before the latest state is late; one for an older
        # stamp is taken as new (a restarted clock repeats stamps).
        self._late_window_ns = (2 * self.config.settle_states + 4) * self._period_ns
        self._next_episode = 0
        self.cut_off: Transition | None = None
        """the transition the last ``flush`` truncated at the stream's end, None if it ended at a boundary"""
        self._start_stream()

    def _start_stream(self) -> None:
        self._slots: dict[int, _Slot] = {}
        # Slots of messages whose state has not come (yet), oldest first: eviction looks only at these, so a
        # long settle window costs nothing per message.
        self._stateless: dict[int, _Slot] = {}
        self._sequence: deque[int] = deque()  # stamps of received states not yet judged as a step's start
        self._states_seen = 0
        self._latest_state: int | None = None  # stamp, for untagged efforts
        self._judged: OrderedDict[int, None] = OrderedDict()
        # the policy node's observation of each state (its unwrapping has memory)
        self._controller = Controller(global_features=self.global_features)
        self._held: dict | None = None  # the latest transition's fields but ``truncated``: known at the next judgement
        self._ready: list[Transition] = []

    # -- input ------------------------------------------------------------------
    def push(self, record: Record) -> list[Transition]:
        """Take one record; return the transitions that became final (possibly none)."""
        if isinstance(record, JointStateRecord):
            self._on_state(record)
        elif isinstance(record, OdometryRecord):
            slot = self._slot_for(record.stamp_ns)
            if slot is not None:
                if slot.odom is None:
                    slot.odom = record
                elif _same_odometry(slot.odom, record):
                    pass  # re-sent with its state
                elif slot.state is not None and slot.stamp == self._latest_state and slot.later_odom is None:
                    slot.later_odom = record
                else:
                    slot.conflict = True
        elif isinstance(record, EffortRecord):
            stamp = record.answers_ns if record.answers_ns is not None else self._latest_state
            if stamp is None:  # untagged, and no state yet to answer
                self.skips.orphan_effort += 1
            elif (slot := self._slot_for(stamp)) is not None:
                slot.efforts.append(record)
        elif isinstance(record, PolicyInfoRecord):
            slot = self._slot_for(record.stamp_ns)
            if slot is not None:
                slot.infos.append(record)
        elif isinstance(record, EpisodeStartRecord):
            slot = self._slot_for(record.stamp_ns)
            if slot is not None:
                slot.cause = record.cause
                if slot.state is None:
                    slot.announced = True
                else:
                    slot.announced_later = True
        elif isinstance(record, DescriptionRecord):
            self._on_description(record)
        else:
            raise TypeError(f"not a record: {type(record).__name__}")
        self._judge_settled(final=False)
        self._evict_orphans(final=False)
        out, self._ready = self._ready, []
        return out

    def push_many(self, records: Iterable[Record]) -> list[Transition]:
        out: list[Transition] = []
        for r in records:
            out += self.push(r)
        return out

    def flush(self) -> list[Transition]:
        """End of the stream: judge what is left and release every transition.

        The last state has no successor, so no transition starts at it; the
        transition into it is truncated. The assembler then starts a new stream
        (episode ids keep counting; counts accumulate). ``cut_off`` is then that
        truncated transition if the stream's end cut its episode short, None if the
        stream ended at a boundary (the last state began another episode or robot,
        or its step was skipped): what a reader that drops unfinished episodes drops.
        """
        self.cut_off = None
        self._judge_settled(final=True)
        self._evict_orphans(final=True)
        out = self._ready
        self._start_stream()
        return out

    def _slot_for(self, stamp: int) -> _Slot | None:
        """The slot for a non-state message's stamp; None (counted late) if that stamp was judged recently."""
        slot = self._slots.get(stamp)
        if slot is None:
            if stamp in self._judged and self._latest_state - stamp <= self._late_window_ns:
                self.skips.late_message += 1
                return None
            slot = self._slots[stamp] = self._stateless[stamp] = _Slot(stamp, self._states_seen)
        return slot

    def _on_description(self, record: DescriptionRecord) -> None:
        """The robot from now on: states that arrive after it are bound to its tree (the ones before it keep
        theirs). One that is no robot is counted and changes nothing."""
        if self._description is not None and record.text == self._description:
            self.stats.descriptions += 1  # re-sent (a latched publisher, to a reader that matched again)
            return
        try:
            joint_map = JointMap.from_urdf(record.text)
        except ValueError:  # policy.tree.TreeError: malformed XML, no robot, more joints than allowed, ...
            self.skips.bad_description += 1
            return
        self.stats.descriptions += 1
        self._description = record.text
        self.joint_map = joint_map
        self._generation += 1  # the states that arrive from now on are read on it, a new robot to the policy node

    def _on_state(self, record: JointStateRecord) -> None:
        stamp, latest = record.stamp_ns, self._latest_state
        slot = self._slots.get(stamp)
        if stamp == latest:
            if _same_state(slot.state, record):
                self.stats.resent_states += 1  # a lockstep sim re-sends its latest state when the answer is late
            else:
                self._restamp(slot, record)
            return
        if latest is not None and stamp < latest:
            # The clock went back (a restarted sim): what is pending belongs to the old run.
            self.stats.count_boundary("stamp_gap")
            self.stats.clock_restarts += 1
            self._cut()
            self._judged.clear()
            slot = self._slots.get(stamp)  # only messages that came before this state can be pending
        self._add_state(record, slot)

    def _restamp(self, old: _Slot, record: JointStateRecord) -> None:
        """A different state with the latest state's stamp: a robot rebuilt or reset without the clock moving
        on. The odometry and announcement received since the old state are the new state's."""
        odom, announced = old.later_odom, old.announced_later
        old.later_odom, old.announced_later = None, False
        # Without an odometry of its own, which state the stamp's odometry belongs to cannot be told.
        new = _Slot(
            record.stamp_ns, self._states_seen, odom=odom, announced=announced, conflict=odom is None,
            cause=old.cause if announced else None,
        )  # fmt: skip
        self._set_state(new, record)
        cause = "announced" if announced else "new_chain" if _other_robot(old, new) else "stamp_gap"
        self.stats.count_boundary(cause)
        self._cut()
        self._judged.pop(old.stamp, None)
        self._add_state(record, new)

    def _set_state(self, slot: _Slot, record: JointStateRecord) -> None:
        """Put the state in its slot, bound to the robot's tree as it arrives (``joint_map``)."""
        slot.state = record
        slot.described = not self.joint_map.is_fallback
        try:
            slot.order = self.joint_map.order(record.names)
        except JointMapError as err:
            slot.order, slot.order_error = None, err.code
        except ValueError:  # without a description: names that make no chain (none, twice, invalid, too many)
            slot.order, slot.order_error = None, "malformed"

    def _add_state(self, record: JointStateRecord, slot: _Slot | None) -> None:
        if slot is None:
            slot = _Slot(record.stamp_ns, self._states_seen)
        self._slots[record.stamp_ns] = slot
        self._stateless.pop(record.stamp_ns, None)
        self._set_state(slot, record)
        slot.generation = self._generation
        self._sequence.append(record.stamp_ns)
        self._states_seen += 1
        self.stats.states += 1
        self._latest_state = record.stamp_ns

    def _cut(self) -> None:
        """Judge everything pending now: nothing that follows continues it."""
        self._judge_settled(final=True)

    # -- judging ----------------------------------------------------------------
    def _judge_settled(self, final: bool) -> None:
        """Judge every pair (s, s') that has settled (settle_states states arrived after s'), or all of them
        when ``final``; releases transitions into ``_ready``."""
        settle = self.config.settle_states
        while len(self._sequence) >= 2 and (final or len(self._sequence) - 2 >= settle):
            a, b = self._slots[self._sequence[0]], self._slots[self._sequence[1]]
            step = self._judge(a, b)
            if step is None:
                if self._held is not None:  # the episode's last step into a: ended by a fall, or cut off
                    fell = b.cause == "fell" and (b.announced or b.announced_later) and a.obs is not None
                    self._ready.append(self._release(truncated=not fell, terminated=fell))
            else:
                if self._held is not None:  # the run goes on
                    step["episode"] = self._held["episode"]
                    self._ready.append(self._release(truncated=False))
                else:
                    step["episode"] = self._new_episode()
                self._held = step
            self._retire(self._sequence.popleft())
        if final:
            if self._sequence:  # the last state: no successor, no transition
                self._observe(self._slots[self._sequence[0]])
                self._retire(self._sequence.popleft())
            if self._held is not None:  # cut off by the end of the stream, not by a boundary
                self._ready.append(self._release(truncated=True))
                self.cut_off = self._ready[-1]
            self._latest_state = None

    def _evict_orphans(self, final: bool) -> None:
        """Drop (and count) messages for stamps no state came for within the settle window."""
        for slot in list(self._stateless.values()):
            if not (final or self._states_seen - slot.born > self.config.settle_states + 1):
                break  # oldest first: the rest are younger
            self._evict(slot)

    def _new_episode(self) -> int:
        self._next_episode += 1
        self.stats.episodes += 1
        return self._next_episode - 1

    def _release(self, truncated: bool, terminated: bool = False) -> Transition:
        t, self._held = Transition(**self._held, terminated=terminated, truncated=truncated), None
        self.stats.transitions += 1
        self.stats.without_policy_info += not t.has_policy_info
        return t

    def _retire(self, stamp: int) -> None:
        del self._slots[stamp]
        self._judged[stamp] = None
        while next(iter(self._judged)) < stamp - self._late_window_ns:
            self._judged.popitem(last=False)

    def _evict(self, slot: _Slot) -> None:
        del self._slots[slot.stamp]
        del self._stateless[slot.stamp]
        self.skips.orphan_effort += len(slot.efforts)
        self.skips.orphan_policy_info += len(slot.infos)
        self.skips.orphan_odometry += slot.odom is not None
        self.skips.orphan_announcement += slot.announced or slot.announced_later

    def _judge(self, a: _Slot, b: _Slot) -> dict | None:
        """The fields of the transition a -> b but its ``episode`` and ``truncated`` (set as the run goes on),
        or None (a boundary, or a skip counted under its reason)."""
        obs = self._observe(a)  # first, whatever follows: the unwrapper sees every state in order
        boundary = self._boundary(a, b)
        if boundary is not None:  # the controller restarts its unwrapping there, or not (a gap), by its own rule
            self.stats.count_boundary(boundary)
            return None
        obs_next = self._observe(b)
        reason = a.obs_error or b.obs_error
        if reason is not None:
            self.skips.add(reason)
            return None
        answer = self._answer(a, b)
        if isinstance(answer, str):
            self.skips.add(answer)
            return None
        action, log_prob, has_info = answer
        tree = a.order.tree
        cfg = self.config
        if cfg.task == "ant":
            lo, hi = ANT_HEALTHY_Z_RANGE  # the state's finiteness, the rest of the rule, is checked above
            healthy = lo <= obs_next.z <= hi
            velocity = (obs_next.x - obs.x) / cfg.period
            reward, _ = ant_reward(velocity, healthy, applied_action(action), _NO_CONTACT_FORCES)
        else:
            reward = swimmer_reward(
                obs.x, obs_next.x, cfg.period, applied_action(action), cfg.forward_reward_weight,
                cfg.ctrl_cost_weight,
            )  # fmt: skip
        return dict(
            stamp_ns=a.stamp,
            names=tree.names,
            joint_pos=obs.pos,
            joint_vel=obs.vel,
            global_feats=obs.glob,
            action=action,
            log_prob=log_prob,
            has_policy_info=has_info,
            reward=float(reward),
            next_joint_pos=obs_next.pos,
            next_joint_vel=obs_next.vel,
            next_global=obs_next.glob,
            parents=tree.parents,
        )

    def _boundary(self, a: _Slot, b: _Slot) -> str | None:
        if b.announced or b.announced_later:
            return "announced"
        if _other_robot(a, b):
            return "new_chain"
        if abs(b.stamp - a.stamp - self._period_ns) > self.config.stamp_tolerance_ns:
            return "stamp_gap"
        return None

    def _observe(self, slot: _Slot) -> _Observation | None:
        """The state's observation, built once per state in stream order (the unwrapper has memory)."""
        if slot.observed:
            return slot.obs
        slot.observed = True
        if slot.announced:  # received before the state, as the node would have (announced after: below)
            self._controller.episode_start(slot.stamp)
        self._observe_state(slot)
        if slot.announced_later:
            self._controller.episode_start(slot.stamp)
        return slot.obs

    def _observe_state(self, slot: _Slot) -> None:
        s, odom = slot.state, slot.odom
        if slot.conflict or slot.later_odom is not None:  # two odometries, one state
            slot.obs_error = "duplicate_stamp"
        elif not _finite(s.position, s.velocity, s.effort):
            slot.obs_error = "non_finite"
        else:
            try:
                pos, vel = validate_joint_state(s.names, s.position, s.velocity, self.config.max_joints)
            except JointStateError:
                slot.obs_error = "malformed"
                return
            if s.effort.size not in (0, len(s.names)):
                slot.obs_error = "malformed"
            elif slot.order is None:
                slot.obs_error = slot.order_error
            elif odom is None:
                slot.obs_error = "no_odometry"
            elif not _finite(odom.position, odom.orientation_xyzw, odom.body_linear, odom.body_angular):
                slot.obs_error = "non_finite"
            else:
                try:
                    check_odometry(odom)  # as the node does when it arrives: a bad one is never used
                except JointStateError:  # a zero quaternion, one not of unit length
                    slot.obs_error = "malformed"
                    return
                order = slot.order
                glob = self._controller.observe(slot.stamp, (slot.generation, order.tree.names), odom)
                slot.obs = _Observation(order.to_tree(pos), order.to_tree(vel), glob, float(odom.x), float(odom.z))

    def _laid_out(self, tree: KinematicTree, names: tuple[str, ...]) -> JointOrder | None:
        """How an answer's values, one per name of ``names``, lay onto ``tree`` (``JointOrder.to_tree``); None
        unless ``names`` are exactly the tree's joints (in any order)."""
        joint_map = self._answer_maps.get(tree)
        if joint_map is None:
            if len(self._answer_maps) >= _ANSWER_MAPS:
                self._answer_maps.clear()
            joint_map = self._answer_maps[tree] = JointMap(UrdfRobot(tree, frozenset()))
        try:
            return joint_map.order(names)
        except JointMapError:
            return None

    def _answer(self, a: _Slot, b: _Slot) -> tuple[np.ndarray, float, bool] | str:
        """(action, behaviour log-prob, has policy_info) for state a, in its tree's order, checked against what
        the sim applied until b (a state of the same tree, its joints perhaps listed in another order); or the
        skip reason."""
        tree = a.order.tree
        n = tree.num_joints
        infos, info_error = [], None  # (action in the tree's order, log-prob)
        for info in a.infos:
            if not _finite(info.action, info.mean, info.log_std, info.log_prob_per_joint):
                info_error = "non_finite"
            elif any(x.shape != (n,) for x in (info.action, info.mean, info.log_std, info.log_prob_per_joint)):
                info_error = "malformed"
            elif (laid := self._laid_out(tree, info.names)) is None:
                info_error = "names_mismatch"
            else:
                infos.append((laid.to_tree(info.action), info.log_prob))
        efforts, effort_error = [], None  # in the tree's order
        other_tree = 0  # answers computed on another joint layout: not answers to this state as read here
        for e in a.efforts:
            if e.layout is not None and e.layout != tree.layout_hash:
                other_tree += 1
            elif not _finite(e.effort):
                effort_error = "non_finite"
            elif e.names is None:  # in the order of the state it answers
                if e.effort.shape != (len(a.state.names),):
                    effort_error = "malformed"
                else:
                    efforts.append(a.order.to_tree(e.effort))
            elif e.effort.shape != (n,) or len(e.names) != n:
                effort_error = "malformed"
            elif (laid := self._laid_out(tree, e.names)) is None:
                effort_error = "names_mismatch"
            else:
                efforts.append(laid.to_tree(e.effort))
        if other_tree and not efforts:
            return "wrong_tree"  # its policy_info, if any, is of that other tree too
        if info_error and not infos:
            return info_error  # a sampling policy answered, but unusably: the effort alone is no substitute
        if not infos and not efforts:
            return effort_error or "no_answer"

        # What the sim applied over a -> b: the next state says (in its own message order); failing that, the
        # command answering a.
        if b.state.effort.size:
            applied = [b.order.to_tree(b.state.effort)]
        elif efforts:
            applied = efforts
        else:
            return "no_applied_effort"

        def fits(action: np.ndarray) -> bool:  # np.allclose(rtol=0) for finite arrays of one shape, faster
            clipped = np.clip(action, -1.0, 1.0)
            return any((np.abs(clipped - x) <= self.config.applied_atol).all() for x in applied)

        if infos:
            fitting = [(action, log_prob) for action, log_prob in infos if fits(action)]
            if not fitting:
                return "not_applied"
            first, first_log_prob = fitting[0]
            if any(not np.array_equal(action, first) or log_prob != first_log_prob for action, log_prob in fitting[1:]):
                return "ambiguous_answer"
            answer = first.copy(), first_log_prob, True
        else:
            fitting = [e for e in efforts if fits(e)]
            if not fitting:
                return "not_applied"
            if any(not np.array_equal(e, fitting[0]) for e in fitting[1:]):
                return "ambiguous_answer"
            answer = fitting[0].copy(), math.nan, False
        self.stats.applied_unverified += not b.state.effort.size
        return answer


@dataclass(frozen=True)
class Assembled:
    """``assemble``'s result: the transitions as arrays and what was skipped."""

    batch: TransitionBatch
    skips: SkipCounts
    stats: StreamStats


def assemble(
    records: Iterable[Record],
    config: TransitionConfig | None = None,
    joint_map: JointMap | None = None,
    global_features: int | None = None,
) -> Assembled:
    """Transitions of one finished stream of records in receive order (e.g. one bag); the arguments are
    ``TransitionAssembler``'s."""
    asm = TransitionAssembler(config, joint_map, global_features)
    transitions = asm.push_many(records) + asm.flush()
    return Assembled(TransitionBatch.from_transitions(transitions), asm.skips, asm.stats)


def _finite(*values) -> bool:
    """Every value finite: numbers, arrays or sequences of numbers (numbers without NumPy: this runs per message)."""
    for v in values:
        if isinstance(v, float | int):
            if not math.isfinite(v):
                return False
        elif not np.isfinite(np.asarray(v, dtype=np.float64)).all():
            return False
    return True


def _other_robot(a: _Slot, b: _Slot) -> bool:
    """Whether two states are of different robots: bound to trees with other joints or other parents (the
    same joints listed in another order are the same robot). A state that fits no tree is skipped under its
    reason, not a boundary, unless neither was bound to a description: then other joint names are another
    chain."""
    if a.order is not None and b.order is not None:
        ta, tb = a.order.tree, b.order.tree
        return ta is not tb and (ta.names != tb.names or not np.array_equal(ta.parents, tb.parents))
    if not a.described and not b.described:
        return a.state.names != b.state.names
    return False


def _same_state(a: JointStateRecord, b: JointStateRecord) -> bool:
    return (
        a.names == b.names
        and np.array_equal(a.position, b.position)
        and np.array_equal(a.velocity, b.velocity)
        and np.array_equal(a.effort, b.effort)
    )


def _same_odometry(a: OdometryRecord, b: OdometryRecord) -> bool:
    def fields(r: OdometryRecord) -> tuple:
        return r.position, tuple(r.orientation_xyzw), tuple(r.body_linear), tuple(r.body_angular)

    return fields(a) == fields(b)
