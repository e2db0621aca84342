"""The sim node's logic between its sim and its topics, without ROS (the node: ``swimmer_sim_node.sim_node``).

``make_sim`` builds the sim the body parameters ask for (a chain, a spec's swimmers, or a robot model), refusing
a combination that cannot run with one line. ``SimWire`` keeps what the node publishes in step with the sim: the
joint names under the prefix, the announcement of each new episode, each joint state's order (shuffled or the
tree's), and reads each effort command (``protocol.effort_intake``), counting what it took, ignored and rejected.
It also holds the parameter rules the descriptors cannot express (the ranges are the parameter table's, which
rclpy enforces). The node only converts messages, paces the sim and logs. The user's view: docs/guides/nodes.md.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from morph_core.constants import MAX_JOINTS, MAX_NAME_CHARS, MIN_JOINTS
from morph_core.env.bodies import parse_bodies
from morph_core.env.mjcf_robot import load_robot
from morph_core.env.sim import EffortError, SwimmerSim
from morph_core.msgs.episode_start import pack_episode_start
from morph_core.policy.tree import KinematicTree, UrdfRobot
from morph_core.protocol.effort_intake import ShuffledOrders, read_effort_command
from morph_core.protocol.input_counts import InputCounts
from morph_core.protocol.joint_map import JointMap

EFFORTS = "effort_commands"
"""the sim's one input, as counted"""
SWIMMER_LONGEST_NAME = len("motor64_rot")
"""the longest joint name a swimmer has: <prefix>motor<k>_rot"""
MAX_PREFIX_CHARS = MAX_NAME_CHARS - SWIMMER_LONGEST_NAME


def chain_lengths(num_joints: int, min_joints: int, max_joints: int) -> int | tuple[int, int]:
    """The sim's ``num_joints`` argument from the three parameters: a fixed chain when no range is set
    (both 0), else the range. Raises ValueError naming the parameters for anything else."""
    if min_joints == 0 and max_joints == 0:
        return num_joints
    if not MIN_JOINTS <= min_joints <= max_joints <= MAX_JOINTS:
        raise ValueError(
            f"min_joints and max_joints must both be 0 (a fixed chain of num_joints) or satisfy "
            f"{MIN_JOINTS} <= min_joints <= max_joints <= {MAX_JOINTS}; got {min_joints} and {max_joints}"
        )
    return min_joints, max_joints


def prefix_error(prefix: str, longest_name: int = SWIMMER_LONGEST_NAME) -> str | None:
    """Why ``prefix`` cannot start joint names of up to ``longest_name`` characters (a controller refuses
    names that are not short printable ASCII, ``msgs.joint_state``), or None."""
    most = MAX_NAME_CHARS - longest_name
    if len(prefix) > most or not (prefix.isascii() and prefix.isprintable()):
        return f"must be at most {most} printable ASCII characters"
    return None


def make_sim(
    num_joints: int, min_joints: int, max_joints: int, topology: str, model_file: str, **kwargs
) -> tuple[SwimmerSim, str]:
    """The sim the body parameters ask for, and a phrase naming its bodies for the log. ValueError (one line,
    naming the parameters) for a combination that is refused, a bad spec or a model file that cannot run."""
    if topology and model_file:
        raise ValueError("topology and model_file are both set: the sim runs swimmers of a spec or one robot model")
    given = "topology" if topology else "model_file" if model_file else None
    if given and (min_joints or max_joints):
        raise ValueError(f"{given} is set: min_joints and max_joints must stay 0 (its bodies are the {given}'s)")
    if topology:
        try:
            bodies = parse_bodies(topology)
        except ValueError as err:
            raise ValueError(f"topology {topology[:60]!r}: {err}") from None
        lo, hi = bodies.joint_range
        kind = "centipedes" if bodies.has_centipedes else "swimmers"  # a spec mixes no families (the sim refuses)
        return SwimmerSim(bodies=bodies, **kwargs), f"{kind} of {str(bodies)!r} ({lo}..{hi} joints)"
    if model_file:
        robot = load_robot(model_file)  # RobotModelError, a ValueError, says why not
        described = f"robot {robot.name!r} from {model_file} ({robot.num_joints} joints, root {robot.tree.root_link!r})"
        return SwimmerSim(robot=robot, **kwargs), described
    lengths = chain_lengths(num_joints, min_joints, max_joints)
    described = f"{lengths[0]}..{lengths[1]} joints" if isinstance(lengths, tuple) else f"{lengths} joints"
    return SwimmerSim(num_joints=lengths, **kwargs), f"swimmer with {described}"


@dataclass(frozen=True)
class JointStateOut:
    """A joint state's contents as published: the names and, in their order, the three arrays."""

    names: list[str] | tuple[str, ...]
    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray


@dataclass(frozen=True)
class EffortsTaken:
    """What became of one effort command: ``applied`` (the sim holds it now), or a ``rejection`` to log."""

    applied: bool = False
    rejection: str | None = None


class SimWire:
    """What the sim node publishes and how it reads efforts, kept in step with ``sim``.

    ``fixed_body`` names the parameter that fixes the bodies (``"topology"`` or ``"model_file"``; None for
    chains), so that ``num_joints`` only reports their count; ``shuffle_seed`` (None: the tree's order) seeds
    the order every joint state lists its joints in."""

    def __init__(self, sim: SwimmerSim, prefix: str, fixed_body: str | None = None, shuffle_seed: int | None = None):
        self.sim = sim
        self.fixed_body = fixed_body
        # The longest joint name a body can have: a swimmer's motor64_rot, or the robot's own.
        self.longest_name = max(map(len, sim.tree.names)) if sim.robot else SWIMMER_LONGEST_NAME
        error = prefix_error(prefix, self.longest_name)
        if error is not None:
            raise ValueError(f"joint_prefix {error}")
        self.prefix = prefix
        self.orders = ShuffledOrders(shuffle_seed) if shuffle_seed is not None else None
        self.announced = -1
        """the last episode announced"""
        self.counts = InputCounts([EFFORTS])
        """what the effort input received, rejected and ignored, by reason (on /diagnostics)"""
        self.follow_body()

    @property
    def silence_ignored(self) -> int:
        """fail-safe efforts a lockstep loop does not step on (``counts``' ignored ``silence``)"""
        return self.counts.inputs[EFFORTS].ignored["silence"]

    @property
    def old_episode_answers(self) -> int:
        """answers to a state of an episode before the current one (``counts``' ignored ``old_episode``)"""
        return self.counts.inputs[EFFORTS].ignored["old_episode"]

    # -- parameters -------------------------------------------------------------
    def refusal(self, name: str, value: object) -> str | None:
        """Why setting parameter ``name`` to ``value`` at runtime is refused beyond its descriptor (type and
        range), or None."""
        if name == "num_joints" and self.fixed_body is not None and value != self.sim.num_joints:
            # The node's own report of a new body passes (equal); a chain cannot be built in a spec or model.
            return (
                f"num_joints follows the body of {self.fixed_body} ({self.sim.num_joints} joints now) "
                f"and cannot be set while {self.fixed_body} is"
            )
        if name == "joint_prefix":
            error = prefix_error(value, self.longest_name) if isinstance(value, str) else "must be a string"
            return None if error is None else f"joint_prefix {error}"
        return None

    def set_prefix(self, prefix: str) -> None:
        self.prefix = prefix
        self.follow_body()
        if self.orders is not None:
            self.orders.forget()  # orders under the old names: a state published again gets one of the new

    def follow_body(self) -> None:
        """The published joint names and the body's joints by those names (``protocol.joint_map``), set when
        either can change: a new episode (two bodies may share names: the map's tree is the layout answers are
        checked on) and a new prefix."""
        self.names = self.sim.joint_names(self.prefix)
        tree = KinematicTree(self.names, self.sim.tree.parents, self.prefix + (self.sim.tree.root_link or ""))
        self.body = JointMap(UrdfRobot(tree, frozenset()))

    # -- what goes out ----------------------------------------------------------
    def announcement(self) -> tuple[str, list[int]] | None:
        """The ``episode_start`` layout label and data when the sim's episode has not been announced yet (it
        is announced now: the body is followed), else None. Asked before each state is published."""
        if self.sim.episode == self.announced:
            return None
        self.announced = self.sim.episode
        self.follow_body()
        return pack_episode_start(self.sim.episode, self.sim.stamp_ns, self.sim.num_joints, self.sim.episode_cause)

    def joint_state(self) -> JointStateOut:
        """The current state's names and values in the order it is published (shuffled: drawn once per stamp)."""
        sim = self.sim
        values = (sim.joint_positions, sim.joint_velocities, sim.applied)
        if self.orders is None:
            return JointStateOut(self.names, *values)
        names = self.orders.order_for(sim.stamp_ns, self.names)
        order = self.body.order(names)
        return JointStateOut(list(names), *(order.to_message(v) for v in values))

    # -- what comes in ----------------------------------------------------------
    def take_efforts(
        self, labels: Sequence[str], data, now: float, lockstep: bool, is_stale: Callable[[int], bool]
    ) -> EffortsTaken:
        """Read one effort command and apply it to the sim, counting the verdict (``protocol.effort_intake``)."""
        self.counts.received(EFFORTS)
        verdict = read_effort_command(
            labels,
            data,
            latest_ns=self.sim.stamp_ns,
            episode_start_ns=self.sim.episode_start_ns,
            lockstep=lockstep,
            is_stale=is_stale,
            body=self.body,
            orders=self.orders,
        )
        if verdict.ignored is not None:  # e.g. a controller's fail-safe zeros, which answer no state
            self.counts.ignored(EFFORTS, verdict.ignored)
            return EffortsTaken()
        if verdict.rejected is not None:
            return self._reject(verdict.rejected, verdict.error)
        try:
            self.sim.command(verdict.efforts, now)
        except EffortError as err:
            return self._reject("efforts", err)
        return EffortsTaken(applied=True)

    def _reject(self, reason: str, err: Exception) -> EffortsTaken:
        self.counts.rejected(EFFORTS, reason, str(err))
        return EffortsTaken(rejection=f"rejected effort command ({self.counts.rejected_total} so far): {err}")
