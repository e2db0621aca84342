"""The policy node's bookkeeping around its controller, without ROS (the node: ``morph_policy_node.policy_node``).

``AnswerWatch`` counts each input (``protocol.input_counts``, sent on ``/diagnostics``) and keeps what the node
decides from its history rather than from one message: when it last answered and so when the input counts as
silent (zero efforts follow), whether the states it rejects are a hand-over between bodies (the next body's
states before its description, which the node logs as information, not as a fault), and the notices said once.
It also writes the node's lines about descriptions, pushed weights and rejections, so the node only logs them
at the severity given (a call site per severity: rclpy refuses one whose severity changes). The user's view:
docs/guides/nodes.md ("The policy node in detail").
"""

from __future__ import annotations

from dataclasses import dataclass

from morph_core.msgs.policy_weights import TOPIC as WEIGHTS
from morph_core.protocol.controller import NO_DESCRIPTION
from morph_core.protocol.input_counts import InputCounts
from morph_core.protocol.policy_updates import Offer
from morph_core.protocol.robot_description import PREVIOUS_DESCRIPTION, DescriptionOffer, RobotDescriptions
from morph_core.protocol.trust import TrustedKeys, load_trusted_keys

STATES, ODOM, EPISODES, DESCRIPTION = "joint_states", "odom", "episode_start", "robot_description"
KEYS = "trusted_keys"
"""the key files, counted as an input: each loaded or rejected with its reason"""
INPUTS = [STATES, ODOM, EPISODES, WEIGHTS, KEYS, DESCRIPTION]
WAITING = (
    f"the policy reads joint descriptions: waiting for {DESCRIPTION} (no chain fallback); states are not answered "
    "until one is adopted"
)
FALLBACK = f"no {DESCRIPTION} yet: joints taken as a chain in message order (joint 0 next to the torso)"
HANDOVER_CODES = ("missing_joint", "unknown_joint")
"""joint map codes of a state of the next body arriving before its description"""


@dataclass(frozen=True)
class Notice:
    """A line for the node's log: a warning (``warn``) or information."""

    text: str
    warn: bool = False


@dataclass(frozen=True)
class Unmapped:
    """What became of a state the joint map refused: a ``rejection`` (a fault unless a hand-over), or ignored
    with an optional ``notice``."""

    rejection: Notice | None = None
    notice: Notice | None = None
    throttled: bool = True
    """whether ``notice`` is one of many (throttled) or said once"""


class AnswerWatch:
    """The counts, rejections, silence, hand-overs and once-only notices of one policy node."""

    def __init__(self, input_timeout: float, now: float):
        self.counts = InputCounts(INPUTS)
        self.input_timeout = input_timeout
        """seconds without a state answered before zero efforts go out"""
        self.rejected = 0
        """messages rejected, the key files apart"""
        self.last_answer = now
        self.silent = False
        self.handover = False
        """the last rejected state was of a body whose description had not arrived"""
        self._said: set[str] = set()

    def once(self, key: str) -> bool:
        """True the first time only: a notice said once."""
        if key in self._said:
            return False
        self._said.add(key)
        return True

    def reject(self, what: str, reason: str, err: Exception | str, expected: bool = False) -> Notice:
        """Count one rejected message of input ``what``; the line to log (information when ``expected``)."""
        self.rejected += 1
        self.counts.rejected(what, reason, str(err))
        return Notice(f"rejected {what} ({self.rejected} so far): {err}", warn=not expected)

    def trusted_keys(self, paths: list[str]) -> tuple[TrustedKeys, list[str], list[str]]:
        """The keys of the files ``paths`` (``protocol.trust``), each file counted as an input; the lines to log
        for the keys taken and, as errors, for the files refused (their signatures will not be taken)."""
        keys, errors = load_trusted_keys(paths)
        taken = [f"trusting weights signed by {key.fingerprint} ({key.source})" for key in keys.keys.values()]
        for err in errors:
            self.counts.rejected(KEYS, "key_file", str(err))
        for _ in range(len(taken) + len(errors)):
            self.counts.received(KEYS)
        refused = [f"trusted key file refused, its signatures will not be taken: {err}" for err in errors]
        return keys, taken, refused

    # -- states and answers -----------------------------------------------------
    def answered(self, now: float) -> None:
        self.last_answer = now
        self.silent = False
        self.handover = False

    def fallback(self, generation: int) -> Notice | None:
        """The notice, once, that a state is answered on the chain fallback (``generation`` 0: no description)."""
        return Notice(FALLBACK) if generation == 0 and self.once("fallback") else None

    def unmapped(self, code: str, err: Exception, driving: bool) -> Unmapped:
        """A state the joint map refused with ``code``; ``driving``: a body was answered until now."""
        if code == NO_DESCRIPTION:  # a policy that reads joint descriptions waits for one: not a fault
            self.counts.ignored(STATES, code)
            return Unmapped(notice=Notice(WAITING) if self.once("waiting") else None, throttled=False)
        if code == PREVIOUS_DESCRIPTION:  # the robot before a swap: not malformed, not answered
            self.counts.ignored(STATES, code)
            return Unmapped(notice=Notice(f"ignored joint_states: {err}"))
        # The next body's states before its description (a sim's hand-over between bodies): information, and so
        # is the silence it causes; states that never fit (nothing answered, or silent since) warn.
        self.handover = code in HANDOVER_CODES and driving and not self.silent
        return Unmapped(rejection=self.reject(STATES, code, err, expected=self.handover))

    def silence(self, now: float, answering: bool) -> tuple[bool, Notice | None]:
        """Whether zero efforts are due now (nothing answered for ``input_timeout`` while there is a robot to
        answer, ``answering``), and the notice when the silence begins."""
        if not answering or now - self.last_answer <= self.input_timeout:
            return False, None
        if self.silent:
            return True, None
        self.silent = True
        text = f"no state answered for {self.input_timeout} s: publishing zero efforts"
        return True, Notice(text, warn=not self.handover)

    # -- descriptions and weights -----------------------------------------------
    def description(
        self, offer: DescriptionOffer, descriptions: RobotDescriptions, reads_joints: bool
    ) -> Notice | None:
        """Count an offered ``robot_description`` (``reads_joints``: the policy has no chain fallback) and say
        what became of it."""
        if offer.outcome == "unchanged":
            self.counts.ignored(DESCRIPTION, offer.code)
            return None
        if offer.outcome == "rejected":
            self.rejected += 1
            self.counts.rejected(DESCRIPTION, offer.code, offer.reason)
            kept = "the current graph kept"
            if descriptions.is_fallback:
                kept = "still waiting for one" if reads_joints else "the chain fallback kept"
            return Notice(f"rejected {DESCRIPTION} ({descriptions.rejected} so far), {kept}: {offer.reason}", True)
        robot = descriptions.map.robot
        tree = robot.tree
        shape = "a chain" if tree.is_chain else f"a tree (topology {tree.topology_hash})"
        return Notice(
            f"{DESCRIPTION}: {tree.num_joints} actuated joints, {shape}, below link {tree.root_link!r}; "
            f"{len(robot.unactuated)} other joints left alone; states are read on it by joint name from now on"
        )

    def weights(self, offer: Offer, rejected_total: int) -> Notice | None:
        """Count pushed weights (``rejected_total``: all the updates refused so far) and say what became of them."""
        if offer.outcome == "ignored":
            self.counts.ignored(WEIGHTS, offer.code)
            return None
        if offer.outcome == "rejected":
            # Counted with the other rejections; logged on its own line.
            self.counts.rejected(WEIGHTS, offer.code, offer.reason)
            self.rejected += 1
            return Notice(f"rejected {WEIGHTS} ({rejected_total} so far), current policy kept: {offer.reason}", True)
        if offer.outcome == "pending" and not offer.signer:
            return Notice(f"UNSIGNED weights version {offer.version} received (accept_unsigned_weights): "
                          "adopted at the next state", True)  # fmt: skip
        if offer.outcome == "pending":
            return Notice(
                f"weights version {offer.version} signed by {offer.signer} received: adopted at the next state"
            )
        return None


def updates_notices(accept_weights: bool, enabled: bool, accept_unsigned: bool) -> list[Notice]:
    """What a node says at start-up about taking live policy updates (``protocol.policy_updates``)."""
    notices = []
    if not accept_weights:
        notices.append(Notice(f"live policy updates are off (accept_weights:=false): {WEIGHTS} is not read"))
    elif not enabled:
        notices.append(Notice(
            f"live policy updates are OFF: no trusted key, so {WEIGHTS} is not read. To take a trainer's "
            "weights, make a key pair (morph-keys new KEY), start the trainer with --signing-key KEY and this "
            f"node with -p {KEYS}:=[KEY.pub]"
        ))  # fmt: skip
    if accept_weights and accept_unsigned:
        notices.append(Notice(
            f"accept_unsigned_weights:=true: ANY peer on this DDS domain can replace this robot's policy through "
            f"{WEIGHTS}. For tests only; use {KEYS} on a robot",
            warn=True,
        ))  # fmt: skip
    return notices
