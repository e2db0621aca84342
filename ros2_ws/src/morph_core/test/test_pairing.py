"""StatePairing: a joint state waits briefly for the odometry of its stamp; driven with explicit times."""

from morph_core.protocol.pairing import ODOMETRY_WAIT, StatePairing


def test_without_any_odometry_a_state_does_not_wait():
    p = StatePairing()
    assert p.state(40, "s40", now=0.0) == ["s40"]
    assert not p.pending


def test_a_state_whose_odometry_is_in_goes_at_once():
    p = StatePairing()
    assert p.odometry(40) is None
    assert p.state(40, "s40", now=0.0) == ["s40"]
    assert p.state(0, "old", now=0.0) == ["old"]  # odometry newer than the state: nothing to wait for


def test_a_state_waits_for_its_odometry():
    p = StatePairing()
    p.odometry(40)
    assert p.state(80, "s80", now=1.0) == []
    assert p.pending
    assert p.odometry(40) is None  # an older odometry does not complete it
    assert p.odometry(80) == "s80"
    assert not p.pending and p.odometry_ns == 80


def test_a_newer_state_flushes_the_waiting_one():
    p = StatePairing()
    p.odometry(40)
    assert p.state(80, "s80", now=1.0) == []
    assert p.state(120, "s120", now=1.01) == ["s80"]  # s80 goes with the odometry there is
    assert p.odometry(120) == "s120"


def test_a_state_waits_at_most_the_wait():
    p = StatePairing()
    p.odometry(40)
    p.state(80, "s80", now=1.0)
    assert p.expired(1.0 + ODOMETRY_WAIT / 2) is None
    assert p.expired(1.0 + ODOMETRY_WAIT * 1.5) == "s80"
    assert p.expired(2.0) is None and not p.pending
    assert p.odometry(80) is None  # it is gone: late odometry completes nothing
