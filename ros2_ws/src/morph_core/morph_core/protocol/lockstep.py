"""Lockstep: the sim steps only once efforts answering its latest published state have arrived.

``LockstepGate`` is the bookkeeping of that loop, without ROS and without a clock
of its own (``now`` in seconds is passed in). A node tells it what it published
and which answers arrived, and asks it on each timer tick what to do:

- ``Action.PUBLISH``: nothing published yet and someone listens: publish the
  first state (before anyone listens it would be lost);
- ``Action.RESEND``: the latest state got no answer in time: publish it again,
  so a lost message or a late-starting controller cannot stall the loop for
  good (after ``first_resend`` until a controller has ever answered, then after
  ``resend_after``);
- ``Action.STEP``: the answer is in: step (when the real-time pacing allows)
  and call ``stepped``.

Answers may be tagged with the stamp of the state they answer (``msgs.stamps``);
tagged answers for any other state are stale and dropped, so a re-sent state
answered twice cannot shift the loop by a step. Untagged answers are taken.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable

FIRST_RESEND = 0.2
"""Re-send period [s] until a controller has answered once: a reader that matched a
moment after the first publication missed it."""


class Action(enum.Enum):
    NONE = "none"
    PUBLISH = "publish"
    RESEND = "resend"
    STEP = "step"


class LockstepGate:
    """Which published state awaits its answer, and whether to step, publish or re-send."""

    def __init__(self, resend_after: float, first_resend: float = FIRST_RESEND):
        self.resend_after = resend_after
        """seconds without an answer before the state is re-sent (the sim's effort timeout)"""
        self.first_resend = first_resend
        self.resends = 0
        self.stale_answers = 0
        self.ever_answered = False
        self.latest_ns: int | None = None
        """stamp [ns] of the latest published state, the only one answers may name"""
        self.awaiting = False
        """the latest published state has no answer yet"""
        self.answered = False
        """the awaited answer arrived: step when due"""
        self._published_at = -math.inf

    def restart(self) -> None:
        """Forget the awaited state (lockstep switched on or off, the sim reset): the next
        state published starts the loop again."""
        self.awaiting = False
        self.answered = False

    def published(self, stamp_ns: int, now: float) -> None:
        """A state stamped ``stamp_ns`` went out at ``now``; its answer is awaited."""
        self.latest_ns = stamp_ns
        self.awaiting = True
        self.answered = False
        self._published_at = now

    def is_stale(self, answers_ns: int | None) -> bool:
        """Whether efforts tagged as answering the state ``answers_ns`` (None: untagged) must be
        dropped: they answer a state other than the latest published one. Counts them."""
        if answers_ns is None or answers_ns == self.latest_ns:
            return False
        self.stale_answers += 1
        return True

    def answer(self) -> bool:
        """Efforts were accepted; True when they are the awaited answer (the loop may step)."""
        if not self.awaiting:
            return False
        self.ever_answered = True
        self.awaiting = False
        self.answered = True
        return True

    def stepped(self) -> None:
        """The sim stepped on the answer; the state it publishes next awaits a new one."""
        self.answered = False

    def poll(self, now: float, has_listener: Callable[[], bool]) -> Action:
        """What the loop should do at ``now``; ``has_listener`` is asked only before the first publication."""
        if self.answered:
            return Action.STEP
        if not self.awaiting:
            return Action.PUBLISH if has_listener() else Action.NONE
        timeout = self.resend_after if self.ever_answered else self.first_resend
        if now - self._published_at > timeout:
            self.resends += 1
            return Action.RESEND
        return Action.NONE
