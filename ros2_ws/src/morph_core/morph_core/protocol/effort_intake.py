"""What a simulator does with an effort command, before its physics: taken, ignored or rejected, and why.

A command (``std_msgs/Float64MultiArray`` as labels and data) is read in this order, the first that applies
deciding:

1. in lockstep, fail-safe zeros (``msgs.stamps.SILENCE_TAG``) answer no state: ignored (``silence``);
2. a tag that starts ``joints@`` but does not parse, or answers a state later than the latest published:
   rejected (``tag``);
3. an answer to a state of an earlier episode: ignored (``old_episode``);
4. in lockstep, an answer to an earlier (re-sent) state than the one awaited: ignored (``stale``), since
   taking it for the current one would shift the loop by a step;
5. a names or tree dimension that does not parse: rejected (``names``); one computed on another joint
   layout than the body's (``KinematicTree.layout_hash``): rejected (``wrong_tree``);
6. the efforts put in the body's tree order: by the names the command gives (a name the body lacks, a joint
   left out: ``unknown_joint``, ``missing_joint``), else by the order of the state it answers when the sim
   shuffles its joints (``ShuffledOrders``; forgotten: ``order``), else as they are.

The sim node counts and logs the verdict and applies the efforts (``env.sim.SwimmerSim.command`` has the
last word on their number and values); the rules are here so that tests reach them without DDS.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from morph_core.env.sim import EffortError
from morph_core.msgs.effort_names import EffortNamesError, effort_names, effort_tree
from morph_core.msgs.stamps import SILENCE_TAG, StampError, parse_answer_tag
from morph_core.protocol.joint_map import JointMap, JointMapError

REMEMBERED_ORDERS = 64
"""states whose published joint order is kept (shuffling) to map an answer without names: a lockstep loop needs
the latest only, a free-running controller answers within a few periods"""
SHUFFLE_STREAM = 0x5348_5546
"""mixed with the sim's seed to seed the shuffling's own generator, apart from the physics'"""


class ShuffledOrders:
    """The joint order of each published state of a sim that lists its joints in a new order every state:
    drawn once per stamp from its own generator (a state published again keeps its order, so an answer to
    either is the same), the last ``REMEMBERED_ORDERS`` kept to map answers that name no joints."""

    def __init__(self, seed: int):
        self._rng = np.random.default_rng([SHUFFLE_STREAM, seed])
        self._sent: OrderedDict[int, tuple[str, ...]] = OrderedDict()  # stamp -> the names as published
        self.latest: tuple[str, ...] | None = None
        """the order of the latest published state (what an untagged answer is taken to answer)"""

    def order_for(self, stamp_ns: int, names: Sequence[str]) -> tuple[str, ...]:
        """The order the state at ``stamp_ns`` lists ``names`` in: drawn the first time, kept after."""
        order = self._sent.get(stamp_ns)
        if order is None:
            order = tuple(names[i] for i in self._rng.permutation(len(names)))
            self._sent[stamp_ns] = order
            if len(self._sent) > REMEMBERED_ORDERS:
                self._sent.popitem(last=False)
        self.latest = order
        return order

    def answered(self, answers: int | None) -> tuple[str, ...] | None:
        """The order of the state an answer is for (None: the latest), or None when it is forgotten."""
        return self.latest if answers is None else self._sent.get(answers)

    def forget(self) -> None:
        """Orders under names that changed (a new prefix): a state published again gets one of the new."""
        self._sent.clear()


@dataclass(frozen=True)
class EffortVerdict:
    """What to do with a command: apply ``efforts`` (in the body's tree order), or not, with the reason."""

    efforts: Sequence[float] | np.ndarray | None = None
    answers: int | None = None
    """the stamp (ns) of the state it answers, None when untagged"""
    ignored: str | None = None
    """the reason code it is ignored for (nothing applied, nothing wrong with it)"""
    rejected: str | None = None
    """the reason code it is rejected for, ``error`` saying why"""
    error: Exception | None = None


def read_effort_command(
    labels: Sequence[str],
    data: Sequence[float],
    *,
    latest_ns: int,
    episode_start_ns: int,
    lockstep: bool,
    is_stale: Callable[[int | None], bool],
    body: JointMap,
    orders: ShuffledOrders | None,
) -> EffortVerdict:
    """The verdict on a command with layout ``labels`` and ``data``, for a sim whose latest published state is at
    ``latest_ns`` in an episode that began at ``episode_start_ns``; ``is_stale(answers)`` is the lockstep
    gate's; ``body`` the joints by name; ``orders`` the shuffled orders (None: the sim lists them in tree order)."""
    label = labels[0] if labels else ""
    if lockstep and label == SILENCE_TAG:
        return EffortVerdict(ignored="silence")
    try:
        answers = parse_answer_tag(label, strict=True)
        if answers is not None and answers > latest_ns:
            raise StampError(f"answers the state at {answers} ns, later than the latest published one")
    except StampError as err:
        return EffortVerdict(rejected="tag", error=err)
    if answers is not None and answers < episode_start_ns:
        return EffortVerdict(answers=answers, ignored="old_episode")  # a body that is gone (maybe another length)
    if lockstep and is_stale(answers):
        return EffortVerdict(answers=answers, ignored="stale")
    try:
        layout = effort_tree(labels)
    except EffortNamesError as err:
        return EffortVerdict(answers=answers, rejected="names", error=err)
    tree = body.robot.tree
    if layout is not None and layout != tree.layout_hash:
        # Typically a new body's first state answered before its robot_description reached the controller
        # (names alone cannot tell two trees apart).
        err = EffortError(f"computed on joint layout {layout}, not this body's {tree.layout_hash}: the controller "
                          "reads another robot_description than this body's")  # fmt: skip
        return EffortVerdict(answers=answers, rejected="wrong_tree", error=err)
    try:
        efforts = _in_tree_order(labels, data, answers, body, orders)
    except EffortNamesError as err:
        return EffortVerdict(answers=answers, rejected="names", error=err)
    except JointMapError as err:
        return EffortVerdict(answers=answers, rejected=err.code, error=err)
    except EffortError as err:
        return EffortVerdict(answers=answers, rejected="order", error=err)
    return EffortVerdict(efforts=efforts, answers=answers)


def _in_tree_order(labels, data, answers: int | None, body: JointMap, orders: ShuffledOrders | None):
    """The command's efforts in the body's tree order: by the names its layout gives, else by the order of the
    state it answers (shuffled; without shuffling, the order published is the tree's: as they are)."""
    names = effort_names(labels, len(data))
    if names is None:
        if orders is None:
            return data
        names = orders.answered(answers)
        if names is None:
            raise EffortError(
                f"answers the state at {answers} ns, whose joint order is no longer known "
                f"(kept for the last {REMEMBERED_ORDERS} states); name the joints"
            )
        if len(names) != len(data):
            return data  # SwimmerSim.command refuses it with the counts
    return body.order(names).to_tree(np.asarray(data, dtype=np.float64))
