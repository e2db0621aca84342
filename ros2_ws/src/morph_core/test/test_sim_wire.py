"""The sim node's logic between its sim and its topics (``protocol.sim_wire``), without DDS: announcements,
the published joint order, the reading and counting of efforts, and the parameter rules beyond the ranges."""

from __future__ import annotations

import numpy as np
import pytest

from morph_core.msgs.effort_names import names_label
from morph_core.msgs.episode_start import EpisodeCause, unpack_episode_start
from morph_core.msgs.stamps import SILENCE_TAG, answer_tag, from_ns
from morph_core.protocol.sim_wire import EFFORTS, SimWire, make_sim

NEVER_STALE = lambda answers: False  # noqa: E731


def wire(num_joints=3, prefix="", shuffle_seed=None, topology="", **kwargs):
    sim, _ = make_sim(num_joints, 0, 0, topology, "", seed=5, effort_timeout=None, **kwargs)
    return SimWire(sim, prefix, "topology" if topology else None, shuffle_seed)


def test_each_episode_is_announced_once_before_its_states():
    w = wire()
    label, data = w.announcement()
    start = unpack_episode_start(0, label, data)
    assert (start.episode, start.stamp_ns, start.num_joints) == (0, w.sim.stamp_ns, 3)
    assert w.announcement() is None  # the next state of the same episode
    w.sim.advance(0.0)
    w.sim.reset(EpisodeCause.RESET)
    label, data = w.announcement()
    assert unpack_episode_start(0, label, data).episode == 1 and w.announcement() is None


def test_a_joint_state_lists_the_tree_order_or_a_shuffled_one_with_its_values():
    plain = wire(num_joints=5)
    out = plain.joint_state()
    assert list(out.names) == plain.sim.joint_names() and np.array_equal(out.position, plain.sim.joint_positions)
    shuffled = wire(num_joints=5, shuffle_seed=1)
    shuffled.sim.advance(0.0)
    out = shuffled.joint_state()
    tree_order = shuffled.sim.joint_names()
    assert sorted(out.names) == sorted(tree_order) and list(out.names) != tree_order  # seed 1 draws another order
    for name, position in zip(out.names, out.position, strict=True):
        assert position == shuffled.sim.joint_positions[tree_order.index(name)]
    assert shuffled.joint_state().names == out.names  # a state published again keeps its order


def test_a_new_prefix_renames_the_joints_and_maps_efforts_by_the_new_names():
    w = wire()
    w.set_prefix("left/")
    assert all(name.startswith("left/") for name in w.joint_state().names)
    names = [f"left/{name}" for name in w.sim.joint_names()]
    assert w.take_efforts(["", names_label(tuple(names))], [0.1, 0.2, 0.3], 0.0, False, NEVER_STALE).applied
    old = w.sim.joint_names()
    taken = w.take_efforts(["", names_label(tuple(old))], [0.1, 0.2, 0.3], 0.0, False, NEVER_STALE)
    assert not taken.applied and "unknown_joint" in w.counts.inputs[EFFORTS].rejected


def test_efforts_are_applied_ignored_or_rejected_and_counted():
    w = wire()
    assert w.take_efforts([], [0.5, -0.5, 0.0], 0.0, False, NEVER_STALE).applied
    taken = w.take_efforts([], [0.5, 0.5], 0.0, False, NEVER_STALE)  # one value short
    assert not taken.applied and taken.rejection.startswith("rejected effort command (1 so far): ")
    assert w.take_efforts([SILENCE_TAG], [0.0] * 3, 0.0, True, NEVER_STALE) == w.take_efforts(
        [SILENCE_TAG], [0.0] * 3, 0.0, True, NEVER_STALE
    )
    first = w.sim.stamp_ns
    w.sim.advance(0.0)
    w.sim.reset(EpisodeCause.RESET)
    sec, nanosec = from_ns(first)
    assert not w.take_efforts([answer_tag(sec, nanosec)], [0.1] * 3, 0.0, False, NEVER_STALE).applied
    count = w.counts.inputs[EFFORTS]
    assert (w.silence_ignored, w.old_episode_answers) == (2, 1)
    assert count.received == 5 and dict(count.ignored) == {"silence": 2, "old_episode": 1}
    assert dict(count.rejected) == {"efforts": 1}


def test_a_fixed_body_refuses_another_num_joints_and_a_chain_takes_any():
    spec = wire(topology="y:2x2")
    n = spec.sim.num_joints
    assert spec.refusal("num_joints", n) is None  # the node's own report of a new body
    reason = spec.refusal("num_joints", n + 1)
    assert "topology" in reason and f"{n} joints" in reason
    assert wire().refusal("num_joints", 11) is None


@pytest.mark.parametrize("bad", ["x" * 300, "caf\u00e9/", "a\tb/", 7])
def test_a_prefix_that_cannot_start_joint_names_is_refused_by_name(bad):
    assert wire().refusal("joint_prefix", bad).startswith("joint_prefix ")
    if isinstance(bad, str):
        with pytest.raises(ValueError, match="joint_prefix must be at most"):
            wire(prefix=bad)
    assert wire().refusal("joint_prefix", "left/") is None
    assert wire().refusal("episode_steps", -1) is None  # ranges are the descriptors' (rclpy), not repeated here


def test_garbled_effort_commands_get_a_verdict_never_an_exception():
    rng = np.random.default_rng(3)
    w = wire(shuffle_seed=2)
    pieces = ["joints@", "names=", "tree=", "[", '"', "\x00", "1.5", SILENCE_TAG, "nan", "\u00e9"]
    for _ in range(500):
        labels = ["".join(rng.choice(pieces, size=rng.integers(0, 4))) for _ in range(rng.integers(0, 4))]
        data = rng.choice([0.1, -2.0, np.nan, np.inf, 1e308], size=rng.integers(0, 6)).tolist()
        taken = w.take_efforts(labels, data, 0.0, bool(rng.integers(2)), NEVER_STALE)
        assert taken.applied or taken.rejection is None or taken.rejection.startswith("rejected effort command")
    count = w.counts.inputs[EFFORTS]
    assert count.received == 500 and count.rejected_total > 0
