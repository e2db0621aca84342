"""LockstepGate: first publication, re-sends, answers, stale tags; driven with explicit times, no DDS."""

from morph_core.protocol.lockstep import FIRST_RESEND, Action, LockstepGate


def _never_asked():
    raise AssertionError("has_listener must not be asked once a state is out")


def test_first_state_waits_for_a_listener():
    gate = LockstepGate(resend_after=1.0)
    assert gate.poll(0.0, lambda: False) is Action.NONE
    assert gate.poll(0.1, lambda: True) is Action.PUBLISH
    gate.published(0, now=0.1)
    assert gate.poll(0.1 + FIRST_RESEND / 2, _never_asked) is Action.NONE


def test_resend_fast_until_a_controller_ever_answered_then_after_resend_after():
    gate = LockstepGate(resend_after=1.0)
    gate.published(0, now=0.0)
    assert gate.poll(FIRST_RESEND - 0.01, _never_asked) is Action.NONE
    assert gate.poll(FIRST_RESEND + 0.01, _never_asked) is Action.RESEND
    assert gate.resends == 1
    gate.published(0, now=0.21)  # the re-send
    assert gate.answer()
    assert gate.poll(0.22, _never_asked) is Action.STEP
    gate.stepped()
    gate.published(40_000_000, now=0.3)
    # A controller has answered once: a slow answer is given the full resend_after.
    assert gate.poll(0.3 + 2 * FIRST_RESEND, _never_asked) is Action.NONE
    assert gate.poll(1.31, _never_asked) is Action.RESEND
    assert gate.resends == 2


def test_step_once_per_answer():
    gate = LockstepGate(resend_after=1.0)
    gate.published(0, now=0.0)
    assert gate.answer()
    assert not gate.answer()  # a second answer to the same state does not step twice
    assert gate.poll(0.01, _never_asked) is Action.STEP
    assert gate.poll(0.02, _never_asked) is Action.STEP  # still due until the sim stepped
    gate.stepped()
    gate.published(40_000_000, now=0.03)
    assert gate.poll(0.04, _never_asked) is Action.NONE  # the new state waits for its own answer


def test_tagged_answers_for_other_states_are_stale():
    gate = LockstepGate(resend_after=1.0)
    assert gate.is_stale(0)  # nothing published: no tag can be right
    gate.published(0, now=0.0)
    assert not gate.is_stale(0) and not gate.is_stale(None)
    gate.answer()
    gate.stepped()
    gate.published(40_000_000, now=0.1)
    assert gate.is_stale(0)  # the second answer to a re-sent state
    assert not gate.is_stale(40_000_000) and not gate.is_stale(None)
    assert gate.stale_answers == 2


def test_a_resent_state_answered_twice_does_not_shift_the_loop():
    """s0 is re-sent; both answers (tagged s0) arrive after the sim has moved on to s1."""
    gate = LockstepGate(resend_after=1.0)
    gate.published(0, now=0.0)
    assert gate.poll(0.25, _never_asked) is Action.RESEND
    gate.published(0, now=0.25)
    steps = []
    for tag, now in ((0, 0.3), (0, 0.31), (40_000_000, 0.35)):
        if gate.is_stale(tag) or not gate.answer():
            continue
        assert gate.poll(now, _never_asked) is Action.STEP
        gate.stepped()
        steps.append(tag)
        gate.published(tag + 40_000_000, now)
    assert steps == [0, 40_000_000]
    assert gate.stale_answers == 1


def test_restart_publishes_again():
    gate = LockstepGate(resend_after=1.0)
    gate.published(0, now=0.0)
    gate.answer()
    gate.restart()
    assert not gate.answered
    assert gate.poll(0.01, lambda: True) is Action.PUBLISH
