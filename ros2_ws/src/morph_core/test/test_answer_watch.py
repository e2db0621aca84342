"""The policy node's bookkeeping (``protocol.answer_watch``), without DDS: silence after the input timeout, hand-overs
logged as information, notices said once, descriptions and weights counted with their lines."""

from __future__ import annotations

from morph_core.env.sim import SwimmerSim
from morph_core.msgs.policy_weights import TOPIC as WEIGHTS
from morph_core.protocol.answer_watch import (
    DESCRIPTION,
    FALLBACK,
    KEYS,
    STATES,
    WAITING,
    AnswerWatch,
    updates_notices,
)
from morph_core.protocol.controller import NO_DESCRIPTION
from morph_core.protocol.policy_updates import Offer
from morph_core.protocol.robot_description import PREVIOUS_DESCRIPTION, RobotDescriptions
from morph_core.protocol.trust import write_key_pair


def test_silence_begins_after_the_input_timeout_is_said_once_and_ends_with_an_answer():
    watch = AnswerWatch(input_timeout=0.5, now=10.0)
    assert watch.silence(10.5, answering=True) == (False, None)  # not longer than the timeout yet
    assert watch.silence(11.0, answering=False) == (False, None)  # no robot answered: nothing to zero
    due, notice = watch.silence(11.0, answering=True)
    assert due and notice.warn and notice.text == "no state answered for 0.5 s: publishing zero efforts"
    assert watch.silence(11.04, answering=True) == (True, None)  # zeros go on, the line is not repeated
    watch.answered(11.1)
    assert watch.silence(11.2, answering=True) == (False, None) and not watch.silent
    assert watch.silence(11.7, answering=True)[1] is not None  # a new silence is said again


def test_a_hand_over_between_bodies_is_information_and_so_is_its_silence():
    watch = AnswerWatch(input_timeout=0.5, now=0.0)
    unmapped = watch.unmapped("missing_joint", ValueError("lacks 2 joints"), driving=True)
    assert not unmapped.rejection.warn and unmapped.rejection.text == "rejected joint_states (1 so far): lacks 2 joints"
    due, notice = watch.silence(1.0, answering=True)
    assert due and not notice.warn
    # Silent since: a state that does not fit is no hand-over any more.
    assert watch.unmapped("unknown_joint", ValueError("x"), driving=True).rejection.warn
    assert watch.counts.inputs[STATES].rejected == {"missing_joint": 1, "unknown_joint": 1}


def test_a_state_that_never_fit_warns():
    watch = AnswerWatch(input_timeout=0.5, now=0.0)
    assert watch.unmapped("missing_joint", ValueError("x"), driving=False).rejection.warn  # nothing answered yet
    assert watch.unmapped("duplicate", ValueError("x"), driving=True).rejection.warn and not watch.handover
    assert watch.rejected == 2


def test_waiting_for_a_description_is_said_once_and_states_before_a_swap_are_ignored():
    watch = AnswerWatch(input_timeout=0.5, now=0.0)
    first = watch.unmapped(NO_DESCRIPTION, ValueError("no description"), driving=False)
    assert first.rejection is None and first.notice.text == WAITING and not first.throttled
    assert watch.unmapped(NO_DESCRIPTION, ValueError("no description"), driving=False).notice is None
    previous = watch.unmapped(PREVIOUS_DESCRIPTION, ValueError("fits the previous"), driving=True)
    assert previous.rejection is None and previous.notice.text == "ignored joint_states: fits the previous"
    assert watch.counts.inputs[STATES].ignored == {NO_DESCRIPTION: 2, PREVIOUS_DESCRIPTION: 1}
    assert watch.rejected == 0 and not watch.handover


def test_the_chain_fallback_is_said_once_at_the_first_state_answered_on_it():
    watch = AnswerWatch(input_timeout=0.5, now=0.0)
    assert watch.fallback(generation=1) is None  # a description: no fallback
    assert watch.fallback(generation=0).text == FALLBACK
    assert watch.fallback(generation=0) is None


def test_descriptions_are_counted_and_described():
    watch, descriptions = AnswerWatch(input_timeout=0.5, now=0.0), RobotDescriptions()
    rejected = descriptions.offer("<robot")
    notice = watch.description(rejected, descriptions, reads_joints=False)
    assert notice.warn and notice.text.startswith("rejected robot_description (1 so far), the chain fallback kept: ")
    assert "still waiting for one" in watch.description(rejected, descriptions, reads_joints=True).text
    urdf = SwimmerSim(num_joints=4, seed=0).urdf()
    notice = watch.description(descriptions.offer(urdf), descriptions, reads_joints=False)
    assert not notice.warn and notice.text.startswith("robot_description: 4 actuated joints, a chain, below link")
    assert watch.description(descriptions.offer(urdf), descriptions, reads_joints=False) is None  # unchanged
    assert "the current graph kept" in watch.description(rejected, descriptions, reads_joints=False).text
    count = watch.counts.inputs[DESCRIPTION]
    assert count.rejected_total == 3 and count.ignored_total == 1 and watch.rejected == 3


def test_pushed_weights_are_counted_and_described():
    watch = AnswerWatch(input_timeout=0.5, now=0.0)
    assert watch.weights(Offer("ignored", 4, code="not_newer"), 0) is None
    notice = watch.weights(Offer("rejected", 5, "a bad signature", "bad_signature"), 3)
    assert notice.warn and notice.text == f"rejected {WEIGHTS} (3 so far), current policy kept: a bad signature"
    unsigned = watch.weights(Offer("pending", 6), 3)
    assert unsigned.warn and unsigned.text.startswith("UNSIGNED weights version 6 received")
    signed = watch.weights(Offer("pending", 7, signer="SHA256:abc"), 3)
    assert not signed.warn and "version 7 signed by SHA256:abc received" in signed.text
    count = watch.counts.inputs[WEIGHTS]
    assert count.ignored == {"not_newer": 1} and count.rejected == {"bad_signature": 1} and watch.rejected == 1


def test_what_a_node_says_about_live_updates_at_start_up():
    assert "accept_weights:=false" in updates_notices(False, True, True)[0].text
    assert len(updates_notices(False, True, True)) == 1  # off: unsigned weights are not read either
    (off,) = updates_notices(True, False, False)
    assert "OFF: no trusted key" in off.text and f"-p {KEYS}:=" in off.text and not off.warn
    assert updates_notices(True, True, False) == []
    (loud,) = updates_notices(True, True, True)
    assert loud.warn and "ANY peer" in loud.text


def test_key_files_are_counted_each_taken_or_refused_with_its_line(tmp_path):
    signer = write_key_pair(tmp_path / "trainer")
    garbage = tmp_path / "garbage.pub"
    garbage.write_text("not a key\n")
    watch = AnswerWatch(input_timeout=0.5, now=0.0)
    keys, taken, refused = watch.trusted_keys([str(tmp_path / "trainer.pub"), str(garbage), str(tmp_path / "none")])
    assert list(keys.keys) == [signer.fingerprint] and taken == [f"trusting weights signed by {signer.fingerprint} "
                                                                   f"({tmp_path / 'trainer.pub'})"]  # fmt: skip
    assert len(refused) == 2 and all(line.startswith("trusted key file refused") for line in refused)
    count = watch.counts.inputs[KEYS]
    assert count.received == 3 and count.rejected == {"key_file": 2} and watch.rejected == 0
