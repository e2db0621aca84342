"""RealTimePacer and tick_period: sim time follows real_time_factor x wall time; a stall restarts the pacing."""

import pytest

from morph_core.protocol.pacing import LOCKSTEP_POLL, MAX_LAG, RealTimePacer, tick_period

DT = 0.04


def _steps_at(pacer: RealTimePacer, now: float, sim_time: float, limit: int = 1000) -> tuple[int, float]:
    """Steps a free-running loop would take at wall time ``now``, and the sim time it reaches."""
    n = 0
    while n < limit and pacer.due(now, sim_time, sim_time + DT):
        sim_time += DT
        n += 1
    return n, sim_time


@pytest.mark.parametrize("factor", [0.5, 1.0, 4.0])
def test_sim_time_tracks_the_factor(factor):
    pacer = RealTimePacer(factor)
    pacer.restart(100.0, 0.0)
    sim_time = 0.0
    for k in range(1, 51):
        now = 100.0 + k * 0.01
        _, sim_time = _steps_at(pacer, now, sim_time)
        assert factor * (now - 100.0) - DT < sim_time <= factor * (now - 100.0) + 1e-9


def test_step_due_exactly_one_period_later():
    pacer = RealTimePacer(1.0)
    pacer.restart(5.0, 2.0)
    assert not pacer.due(5.0 + DT - 1e-6, 2.0, 2.0 + DT)
    assert pacer.due(5.0 + DT, 2.0, 2.0 + DT)
    # a bigger jump (two periods) waits twice as long
    assert not pacer.due(5.0 + DT, 2.0, 2.0 + 2 * DT)


def test_factor_zero_is_always_due():
    pacer = RealTimePacer(0.0)
    pacer.restart(0.0, 0.0)
    assert _steps_at(pacer, 0.0, 1e6, limit=50)[0] == 50


def test_a_short_lag_is_caught_up_a_stall_is_not():
    pacer = RealTimePacer(1.0)
    pacer.restart(0.0, 0.0)
    n, _ = _steps_at(pacer, MAX_LAG - 0.1, 0.0)
    assert n == round((MAX_LAG - 0.1) / DT)  # the backlog is worked off
    pacer.restart(0.0, 0.0)
    n, sim_time = _steps_at(pacer, 3.0, 0.0)
    assert n == 1  # restarted from now: one step, no burst
    assert _steps_at(pacer, 3.0 + DT, sim_time)[0] == 0  # that step was one period ahead of the new anchor
    assert _steps_at(pacer, 3.0 + 2 * DT, sim_time)[0] == 1


def test_tick_period():
    assert tick_period(DT, 1.0, lockstep=False) == pytest.approx(DT)
    assert tick_period(DT, 2.0, lockstep=True) == pytest.approx(DT / 2)
    assert tick_period(DT, 0.0, lockstep=False) == 0.0
    assert tick_period(DT, 0.0, lockstep=True) == LOCKSTEP_POLL
    assert tick_period(DT, 1000.0, lockstep=False) == 0.001
