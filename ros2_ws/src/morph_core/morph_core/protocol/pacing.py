"""Real-time pacing of a stepped simulation: is the next step due, so that sim time follows wall time?

Plain arithmetic on the caller's clock (``now`` in seconds, e.g. ``time.monotonic()``),
so a node calls it from its timer and a test drives it with made-up times.
"""

from __future__ import annotations

MAX_LAG = 0.5
"""Behind schedule by more than this much sim time [s] (a stall), pacing restarts from now
instead of bursting through the backlog."""

LOCKSTEP_POLL = 0.01
"""Timer period [s] of a lockstep loop at real-time factor 0: steps happen on arriving
efforts, the timer only re-publishes unanswered states."""

MIN_PERIOD = 0.001


class RealTimePacer:
    """Sim time tracks ``real_time_factor`` x wall time from an anchor; factor 0 = every step due at once."""

    def __init__(self, real_time_factor: float = 1.0, max_lag: float = MAX_LAG):
        self.real_time_factor = real_time_factor
        self.max_lag = max_lag
        self._anchor_wall = 0.0
        self._anchor_sim = 0.0

    def restart(self, now: float, sim_time: float) -> None:
        """Anchor the schedule here: sim time ``sim_time`` at wall time ``now``."""
        self._anchor_wall, self._anchor_sim = now, sim_time

    def due(self, now: float, sim_time: float, next_time: float) -> bool:
        """Whether the sim, at ``sim_time`` now, may advance to ``next_time``."""
        if self.real_time_factor == 0:
            return True
        target = self._anchor_sim + self.real_time_factor * (now - self._anchor_wall)
        if target - sim_time > self.max_lag:
            self.restart(now, sim_time)
            return True
        return next_time <= target + 1e-9


def tick_period(dt: float, real_time_factor: float, lockstep: bool) -> float:
    """Period [s] of the timer that drives a sim of control period ``dt``.

    Free-running at factor 0 the timer fires continuously (each tick runs a budget of
    steps); otherwise once per control period of wall time, at most every millisecond.
    """
    if real_time_factor == 0:
        return LOCKSTEP_POLL if lockstep else 0.0
    return max(dt / real_time_factor, MIN_PERIOD)
