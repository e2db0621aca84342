"""Which states begin an episode, for a controller that keeps memory along an episode.

The policy node unwraps the torso's yaw across messages; a new episode's
swimmer starts afresh near yaw 0, so the unwrapping must restart with the
episode's first state (as in training, and as ``protocol.transitions``
rebuilds the features from a recording). Announcements (``episode_start``)
and states travel on different topics, so an announcement may be handled
before its first state (the usual case: it is published first) or after it.
``EpisodeTracker`` is told both, in the order the controller handles them:

- ``state(stamp)`` for each state acted on: True when the state begins an
  announced episode (or a new stream: its stamp is earlier than the last
  one's, a restarted sim);
- ``announced(stamp)`` for each announcement: True when its first state was
  handled already (the announcement came late): restart the memory now,
  which is right from the next state on.
"""

from __future__ import annotations

MAX_PENDING_STARTS = 64
"""announced starts not reached yet that are kept; a sim announces one episode at a time, so more is a
faulty or hostile peer, and the farthest ones are dropped to keep memory flat"""


class EpisodeTracker:
    """Episode starts announced but not reached yet, and the stamp of the last state handled."""

    def __init__(self):
        self._starts: set[int] = set()
        self._last_ns: int | None = None
        self._current_ns: int | None = None  # start of the episode the last state belongs to

    def state(self, stamp_ns: int) -> bool:
        """A state stamped ``stamp_ns`` is acted on; True when the controller's memory must restart first."""
        restarted = self._last_ns is not None and stamp_ns < self._last_ns
        reached = {s for s in self._starts if s <= stamp_ns}
        self._starts -= reached
        self._last_ns = stamp_ns
        if restarted:
            self._current_ns = stamp_ns
        if reached:
            self._current_ns = max(reached)
        return restarted or bool(reached)

    def announced(self, start_ns: int) -> bool:
        """An episode beginning at the state stamped ``start_ns`` was announced; True when that state was
        handled already (restart the memory now). Repeats and announcements of past episodes change nothing."""
        if self._current_ns is not None and start_ns <= self._current_ns:
            return False  # this episode's or an earlier one's
        if self._last_ns is not None and start_ns <= self._last_ns:
            self._current_ns = start_ns
            return True
        self._starts.add(start_ns)
        if len(self._starts) > MAX_PENDING_STARTS:
            self._starts.remove(max(self._starts))
        return False
