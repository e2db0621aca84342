"""Input counts: what a node reports on /diagnostics survives the key/value round trip, and stays bounded."""

from morph_core.protocol.episode_tracker import MAX_PENDING_STARTS, EpisodeTracker
from morph_core.protocol.input_counts import MAX_REASON_CHARS, InputCounts, from_key_values


def test_counts_round_trip_through_key_values():
    counts = InputCounts(["joint_states", "odom", "policy_weights"])
    for _ in range(5):
        counts.received("joint_states")
    counts.rejected("joint_states", "joint_state", "length mismatch: 3 names, 2 positions, 3 velocities")
    counts.rejected("joint_states", "stamp", "nanosec 2000000000 out of range")
    counts.received("policy_weights")
    counts.ignored("policy_weights", "not_newer")
    back = from_key_values(counts.to_key_values())
    assert set(back) == {"joint_states", "odom", "policy_weights"}  # every input listed, even at zero
    js = back["joint_states"]
    assert (js.received, js.rejected_total, dict(js.rejected)) == (5, 2, {"joint_state": 1, "stamp": 1})
    assert js.last_rejection == "stamp: nanosec 2000000000 out of range"
    assert back["odom"].received == 0 and back["odom"].rejected_total == 0
    assert dict(back["policy_weights"].ignored) == {"not_newer": 1}
    assert counts.summary() == "6 received, 2 rejected"


def test_a_huge_error_text_is_cut():
    counts = InputCounts(["joint_states"])
    counts.rejected("joint_states", "joint_state", "x" * 1_000_000)
    assert len(counts.inputs["joint_states"].last_rejection) == MAX_REASON_CHARS


def test_many_distinct_errors_keep_the_report_small():
    counts = InputCounts(["joint_states"])
    for i in range(10_000):
        counts.rejected("joint_states", "joint_state", f"{i} joints, more than the maximum of 64")
    assert len(counts.to_key_values()) == 5  # received, rejected, ignored, one reason, the latest text


def test_announcements_far_ahead_cannot_grow_the_tracker_without_bound():
    tracker = EpisodeTracker()
    tracker.state(1000)
    for k in range(10_000):
        tracker.announced(2000 + k)
    assert len(tracker._starts) == MAX_PENDING_STARTS
    assert tracker.state(2000)  # the nearest announced start is still recognised
