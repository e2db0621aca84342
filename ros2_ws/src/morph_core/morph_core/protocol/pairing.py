"""Pairing each joint state with the odometry of the same stamp, for a controller.

A simulator publishes the torso's odometry and the joint state of one instant
together, but they travel on two topics and may arrive in either order. A
state must not be paired with the previous instant's odometry (a lockstep
loop would stop being deterministic), so a state whose odometry has not
arrived yet waits for it, briefly:

- odometry with the state's stamp (or a later one) completes it;
- a newer state flushes it (it goes with the odometry there is);
- after ``wait`` seconds it goes with the odometry there is.

A state arriving when no odometry was ever seen does not wait (a publisher of
joint states alone). ``StatePairing`` holds only stamps and the caller's
payloads; ``now`` is the caller's clock in seconds.
"""

from __future__ import annotations

from typing import Generic, TypeVar

ODOMETRY_WAIT = 0.02
"""Longest a state waits [s] for its odometry before going with the latest one."""

S = TypeVar("S")


class StatePairing(Generic[S]):
    """Decides when each state (an opaque payload ``S``) is ready to act on."""

    def __init__(self, wait: float = ODOMETRY_WAIT):
        self.wait = wait
        self.odometry_ns: int | None = None
        """stamp [ns] of the latest odometry, None before the first"""
        self._pending: tuple[int, S, float] | None = None

    @property
    def pending(self) -> bool:
        return self._pending is not None

    def odometry(self, stamp_ns: int) -> S | None:
        """Odometry stamped ``stamp_ns`` arrived (the caller keeps its content); returns the
        waiting state it completes, if any."""
        self.odometry_ns = stamp_ns
        if self._pending is not None and stamp_ns >= self._pending[0]:
            return self._take()
        return None

    def state(self, stamp_ns: int, state: S, now: float) -> list[S]:
        """A state stamped ``stamp_ns`` arrived at ``now``; returns the states ready to act on, in order
        (a state that was waiting, then this one if its odometry is in)."""
        ready = [] if self._pending is None else [self._take()]
        if self.odometry_ns is None or self.odometry_ns >= stamp_ns:
            ready.append(state)
        else:
            self._pending = (stamp_ns, state, now)
        return ready

    def expired(self, now: float) -> S | None:
        """The waiting state if it has waited longer than ``wait`` at ``now`` (it goes with the
        latest odometry), else None."""
        if self._pending is not None and now - self._pending[2] > self.wait:
            return self._take()
        return None

    def _take(self) -> S:
        state = self._pending[1]
        self._pending = None
        return state
