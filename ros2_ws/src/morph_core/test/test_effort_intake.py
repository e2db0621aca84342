"""The simulator's reading of effort commands (``protocol.effort_intake``), without DDS: each rule's verdict,
the shuffled orders, and garbled commands that get a verdict, never an exception."""

from __future__ import annotations

import numpy as np
import pytest

from morph_core.msgs.effort_names import names_label, tree_label
from morph_core.msgs.stamps import SILENCE_TAG, answer_tag
from morph_core.policy.tree import KinematicTree, UrdfRobot
from morph_core.protocol.effort_intake import REMEMBERED_ORDERS, ShuffledOrders, read_effort_command
from morph_core.protocol.joint_map import JointMap

NAMES = ("hip", "knee", "ankle")
BODY = JointMap(UrdfRobot(KinematicTree(NAMES, np.array([-1, 0, 1]), "torso"), frozenset()))
LATEST, START = 5_000_000_000, 2_000_000_000  # the latest published state, the episode's first


def read(labels, data=(0.1, 0.2, 0.3), lockstep=False, stale=False, orders=None):
    return read_effort_command(labels, list(data), latest_ns=LATEST, episode_start_ns=START, lockstep=lockstep,
                               is_stale=lambda answers: stale, body=BODY, orders=orders)  # fmt: skip


def test_an_untagged_command_is_taken_as_it_is():
    verdict = read([])
    assert verdict.efforts == [0.1, 0.2, 0.3] and verdict.answers is None
    assert verdict.ignored is None and verdict.rejected is None


def test_fail_safe_zeros_are_ignored_in_lockstep_only():
    assert read([SILENCE_TAG], lockstep=True).ignored == "silence"
    assert read([SILENCE_TAG]).efforts == [0.1, 0.2, 0.3]  # free running they are applied


@pytest.mark.parametrize("label", ["joints@x.1", "joints@1.5", answer_tag(6, 0)])
def test_a_tag_that_does_not_parse_or_answers_the_future_is_rejected(label):
    verdict = read([label])
    assert verdict.rejected == "tag" and verdict.efforts is None and str(verdict.error)


def test_an_answer_from_an_earlier_episode_and_a_stale_one_are_ignored():
    assert read([answer_tag(1, 0)]).ignored == "old_episode"
    assert read([answer_tag(5, 0)], lockstep=True, stale=True).ignored == "stale"
    assert read([answer_tag(5, 0)], stale=True).efforts is not None  # free running nothing is stale


def test_names_put_the_efforts_in_tree_order_and_a_wrong_set_is_rejected_by_code():
    verdict = read(["", names_label(("ankle", "hip", "knee"))], data=(3.0, 1.0, 2.0))
    np.testing.assert_array_equal(verdict.efforts, [1.0, 2.0, 3.0])
    assert read(["", names_label(("hip", "knee", "toe"))]).rejected == "unknown_joint"
    assert read(["", names_label(("hip", "knee"))], data=(1.0, 2.0)).rejected == "missing_joint"
    assert read(["", "names=[1,2"]).rejected == "names"


def test_a_command_computed_on_another_tree_is_rejected():
    assert read(["", tree_label(BODY.robot.tree.layout_hash)]).efforts is not None
    verdict = read(["", tree_label("0123456789abcdef")])
    assert verdict.rejected == "wrong_tree" and "another robot_description" in str(verdict.error)
    assert read(["", "tree=zz"]).rejected == "names"


def test_shuffled_orders_are_kept_per_state_and_map_answers_without_names():
    orders = ShuffledOrders(seed=3)
    first = orders.order_for(LATEST, NAMES)
    assert sorted(first) == sorted(NAMES) and orders.order_for(LATEST, NAMES) == first  # published again: same
    assert ShuffledOrders(seed=3).order_for(LATEST, NAMES) == first  # seeded
    data = [float(NAMES.index(n)) for n in first]  # each joint's tree index, in the published order
    np.testing.assert_array_equal(read([answer_tag(5, 0)], data, orders=orders).efforts, [0.0, 1.0, 2.0])
    np.testing.assert_array_equal(read([], data, orders=orders).efforts, [0.0, 1.0, 2.0])  # untagged: latest
    for k in range(1, REMEMBERED_ORDERS + 1):
        orders.order_for(LATEST + k, NAMES)
    assert read([answer_tag(5, 0)], data, orders=orders).rejected == "order"  # forgotten
    orders.forget()
    assert orders.answered(LATEST + 1) is None


def test_garbled_commands_get_a_verdict_never_an_exception():
    rng = np.random.default_rng(0)
    pieces = ["", SILENCE_TAG, "joints@", answer_tag(3, 5), answer_tag(9, 0), "names=", names_label(NAMES),
              'names=["hip","hip","knee"]', "tree=", tree_label("f" * 16), "\x00", "joints@1.000000000x"]  # fmt: skip
    orders = ShuffledOrders(seed=1)
    orders.order_for(LATEST, NAMES)
    for _ in range(2000):
        labels = [pieces[i] for i in rng.integers(0, len(pieces), rng.integers(0, 4))]
        data = rng.standard_normal(rng.integers(0, 5)).tolist()
        verdict = read(labels, data, lockstep=bool(rng.integers(2)), stale=bool(rng.integers(2)),
                       orders=orders if rng.integers(2) else None)  # fmt: skip
        decided = [verdict.efforts is not None, verdict.ignored is not None, verdict.rejected is not None]
        assert sum(decided) == 1, (labels, data, verdict)
        assert (verdict.rejected is None) == (verdict.error is None)
