"""JointMap (a state's joints onto the description's tree, by name) and the effort command's names dimension.

Each is fuzzed as the policy node feeds it: random name lists (checked by ``validate_joint_state`` first,
as the node does) against random trees, and random labels and garbage for the names dimension. Only the
documented errors may come out, each with a one-line reason.
"""

from __future__ import annotations

import json
import random
import string

import numpy as np
import pytest

from morph_core.constants import MAX_JOINTS
from morph_core.msgs.effort_names import (
    NAMES_PREFIX,
    EffortNamesError,
    effort_names,
    effort_tree,
    names_label,
    tree_label,
)
from morph_core.msgs.joint_state import JointStateError, validate_joint_state
from morph_core.policy.tree import KinematicTree, UrdfRobot
from morph_core.protocol.joint_map import JointMap, JointMapError

PRINTABLE = string.printable[:95]  # printable ASCII, space included: what a joint name may hold


def robot(parents, names, unactuated=()) -> UrdfRobot:
    return UrdfRobot(KinematicTree.from_parents(parents, names), frozenset(unactuated))


TREE = robot([-1, 0, 1, 0, 3, -1], ["hip_l", "knee_l", "ankle_l", "hip_r", "knee_r", "neck"], ["camera", "wheel"])


# -- JointMap ---------------------------------------------------------------------------------------------------
def test_tree_order_states_are_taken_as_they_are():
    order = JointMap(TREE).order(TREE.tree.names)
    assert order.in_message_order and order.index.tolist() == list(range(6))
    values = np.arange(6.0)
    assert order.to_tree(values) is values and order.to_message(values) is values  # no copy on the common path
    assert order.message_names == TREE.tree.names and order.tree is TREE.tree


def test_any_order_and_unactuated_joints_map_by_name():
    jm = JointMap(TREE)
    names = ("camera", "neck", "knee_r", "hip_l", "wheel", "ankle_l", "hip_r", "knee_l")
    order = jm.order(names)
    assert not order.in_message_order
    values = np.array([100.0 + i for i in range(len(names))])  # the message's i-th value is 100 + i
    tree_values = order.to_tree(values)
    assert [names[int(v) - 100] for v in tree_values] == list(TREE.tree.names)
    assert order.message_names == ("neck", "knee_r", "hip_l", "ankle_l", "hip_r", "knee_l")  # no camera, wheel
    # Back in the message's order, unactuated joints left out: the value each named joint had.
    back = order.to_message(tree_values)
    assert [names[int(v) - 100] for v in back] == list(order.message_names)
    with pytest.raises(ValueError, match="read-only"):
        order.index[0] = 3


def test_orders_are_cached_and_bounded():
    jm = JointMap(TREE)
    names = TREE.tree.names
    assert jm.order(names) is jm.order(tuple(names))
    rng = random.Random(0)
    for _ in range(100):
        shuffled = list(names)
        rng.shuffle(shuffled)
        jm.order(tuple(shuffled))
    assert len(jm._orders) <= 16


def test_unknown_and_missing_joints_are_refused_with_a_reason():
    jm = JointMap(TREE)
    with pytest.raises(JointMapError) as err:
        jm.order((*TREE.tree.names, "tail"))
    assert err.value.code == "unknown_joint" and "'tail'" in str(err.value) and "6 actuated joints" in str(err.value)
    with pytest.raises(JointMapError) as err:
        jm.order(("hip_l", "knee_l", "camera"))
    assert err.value.code == "missing_joint"
    assert "lacks 4 of" in str(err.value) and "'ankle_l'" in str(err.value) and "and 0 more" not in str(err.value)
    with pytest.raises(JointMapError, match="x{40}'") as err:
        jm.order(("x" * 256,))  # a long name is cut short in the reason
    assert len(str(err.value)) < 300


def test_the_fallback_is_a_chain_in_message_order():
    jm = JointMap()
    assert jm.is_fallback and not JointMap(TREE).is_fallback
    order = jm.order(("c", "a", "b"))
    assert order.tree.names == ("c", "a", "b") and order.tree.is_chain and order.in_message_order
    assert order.tree.root_link is None


def test_from_urdf_reads_the_description():
    text = (
        '<robot name="r"><link name="b"/><link name="x"/><link name="y"/>'
        '<joint name="a1" type="continuous"><parent link="b"/><child link="x"/></joint>'
        '<joint name="f" type="fixed"><parent link="x"/><child link="y"/></joint></robot>'
    )
    jm = JointMap.from_urdf(text)
    assert jm.robot.tree.names == ("a1",) and jm.robot.unactuated == {"f"}
    assert jm.order(("f", "a1")).message_names == ("a1",)


def _random_tree(rng: random.Random, names: list[str]) -> UrdfRobot:
    n = rng.randint(1, min(12, len(names) - 1))
    actuated, rest = names[:n], names[n:]
    parents = [rng.randrange(-1, j) if j else -1 for j in range(n)]
    return robot(parents, actuated, rest[: rng.randint(0, len(rest))])


def _random_names(rng: random.Random, pool: list[str]) -> list[str]:
    r = rng.random()
    if r < 0.5:  # drawn from the robot's names (and others): the interesting cases
        return rng.sample(pool, rng.randint(0, len(pool)))
    if r < 0.7:  # with a repeat, which validate_joint_state refuses
        names = rng.sample(pool, rng.randint(1, len(pool)))
        return [*names, rng.choice(names)]
    if r < 0.8:
        return ["".join(rng.choice(PRINTABLE) for _ in range(rng.randint(0, 300))) for _ in range(rng.randint(0, 3))]
    if r < 0.9:
        return [f"n{k}" for k in range(rng.choice([MAX_JOINTS, MAX_JOINTS + 1, 200]))]
    return [rng.choice(["", "é", "\x00", "a\nb", "x" * 257, "ok"]) for _ in range(rng.randint(1, 4))]


def test_fuzzed_name_lists_map_or_say_why():
    """A node's path: validate_joint_state, then the map. Every outcome is a mapping whose arrays fit,
    or JointStateError / JointMapError with a one-line reason; nothing else."""
    rng = random.Random(38)
    outcomes: dict[str, int] = {}
    for _ in range(3000):
        pool = [f"j{k}" if rng.random() < 0.8 else rng.choice(["a,b", 'q"t', "s p", "\\"]) + str(k) for k in range(14)]
        pool = list(dict.fromkeys(pool))
        jm = JointMap(_random_tree(rng, pool)) if rng.random() < 0.8 else JointMap()
        names = _random_names(rng, pool)
        values = np.array([rng.uniform(-3, 3) for _ in names])
        try:
            validate_joint_state(names, values, values)
            order = jm.order(tuple(names))
        except (JointStateError, JointMapError) as err:
            assert str(err) and "\n" not in str(err), err
            key = getattr(err, "code", "joint_state")
            outcomes[key] = outcomes.get(key, 0) + 1
            continue
        outcomes["mapped"] = outcomes.get("mapped", 0) + 1
        tree = order.tree
        in_tree = order.to_tree(values)
        assert in_tree.shape == (tree.num_joints,)
        position = {name: i for i, name in enumerate(names)}
        np.testing.assert_array_equal(in_tree, [values[position[name]] for name in tree.names])
        assert set(order.message_names) == set(tree.names)
        assert list(order.message_names) == [name for name in names if name in set(tree.names)]
        np.testing.assert_array_equal(order.to_message(in_tree), [values[position[n]] for n in order.message_names])
    assert {"mapped", "joint_state", "unknown_joint", "missing_joint"} <= set(outcomes), outcomes


# -- the names dimension -------------------------------------------------------------------------------------------
def test_names_round_trip_through_the_label():
    names = ("j0", "a,b", 'say "hi"', "back\\slash", " lead", "]", "names=x")
    label = names_label(names)
    assert label.startswith(NAMES_PREFIX) and json.loads(label[len(NAMES_PREFIX) :]) == list(names)
    assert effort_names(["joints@1.000000000", label, "untrained_policy"], len(names)) == names
    assert names_label(names) is label  # cached: a node sends the same names every step


def test_no_names_dimension_means_the_state_order():
    assert effort_names([], 3) is None
    assert effort_names(["joints@1.000000000"], 3) is None
    assert effort_names([names_label(("a",))], 1) is None  # dim[0] is the answer's tag, never the names
    assert effort_names(["joints@1.000000000", "untrained_policy"], 2) is None


@pytest.mark.parametrize(
    ("labels", "count", "words"),
    [
        (
            [
                "t",
                'names=["a"',
            ],
            1,
            "is not JSON",
        ),
        (["t", "names="], 0, "is not JSON"),
        (["t", 'names={"a": 1}'], 1, "not a JSON list of strings"),
        (["t", "names=[1, 2]"], 2, "not a JSON list of strings"),
        (["t", 'names="a"'], 1, "not a JSON list of strings"),
        (["t", 'names=["a", "a"]'], 2, "names a joint twice"),
        (["t", 'names=["a", "b"]'], 3, "names 2 joints for 3 efforts"),
        (["t", names_label(("a",)), names_label(("a",))], 1, "2 names dimensions"),
        (["t", "names=" + "[" * 100_000], 1, "is not JSON"),
    ],
    ids=["cut", "empty", "object", "numbers", "string", "twice", "count", "two_dims", "deep"],
)
def test_a_bad_names_dimension_says_why(labels, count, words):
    with pytest.raises(EffortNamesError, match=words) as err:
        effort_names(labels, count)
    assert "\n" not in str(err.value)


def test_fuzzed_labels_give_names_none_or_a_reason():
    rng = random.Random(39)
    seen = set()
    pieces = ['"', "[", "]", ",", "{", "}", ":", "null", "1", "\\", "\\u0000", "a", " ", "names=", "true"]
    for _ in range(5000):
        labels = []
        for _ in range(rng.randint(0, 4)):
            r = rng.random()
            if r < 0.3:
                names = tuple(
                    "".join(rng.choice(PRINTABLE) for _ in range(rng.randint(1, 8))) for _ in range(rng.randint(0, 5))
                )
                labels.append(names_label(names))
            elif r < 0.7:
                labels.append(NAMES_PREFIX + "".join(rng.choice(pieces) for _ in range(rng.randint(0, 12))))
            else:
                labels.append("".join(rng.choice(PRINTABLE + "é\x00\n") for _ in range(rng.randint(0, 20))))
        count = rng.randint(0, 6)
        try:
            got = effort_names(labels, count)
        except EffortNamesError as err:
            assert str(err) and "\n" not in str(err)
            seen.add("error")
            continue
        if got is None:
            seen.add("none")
            assert not any(label.startswith(NAMES_PREFIX) for label in labels[1:])
        else:
            seen.add("names")
            assert len(got) == count == len(set(got)) and all(isinstance(n, str) for n in got)
    assert seen == {"error", "none", "names"}


def test_the_layout_hash_tells_equal_named_trees_and_orders_apart():
    names = tuple(f"motor{k}_rot" for k in range(1, 7))
    y = KinematicTree.from_parents([-1, 0, 1, 2, 1, 4], names, "torso")
    star = KinematicTree.from_parents([-1, 0, -1, 2, -1, 4], names, "torso")
    assert y.layout_hash != star.layout_hash  # same names, other places
    renamed_root = KinematicTree.from_parents(y.parents, names, "base")
    assert renamed_root.layout_hash == y.layout_hash  # the root's name is no joint's place
    swapped = KinematicTree.from_parents(y.parents, (names[1], names[0], *names[2:]), "torso")
    assert swapped.layout_hash != y.layout_hash  # the same shape, two joints exchanged
    assert star.topology_hash != y.topology_hash and KinematicTree.chain(6).topology_hash == KinematicTree.chain(
        6, [f"j{k}" for k in range(6)]
    ).topology_hash  # fmt: skip


def test_the_tree_dimension_round_trips_and_bad_ones_say_why():
    layout = KinematicTree.chain(3).layout_hash
    assert effort_tree(["joints@1.000000000", names_label(("a",)), tree_label(layout)]) == layout
    assert effort_tree(["joints@1.000000000", names_label(("a",))]) is None
    assert effort_tree([tree_label(layout)]) is None  # dim[0] is the answer tag, never read as a tree
    for labels in (["t", "tree=xyz"], ["t", "tree=" + "A" * 16], ["t", tree_label(layout), tree_label(layout)]):
        with pytest.raises(EffortNamesError, match="tree dimension"):
            effort_tree(labels)


def test_fuzzed_tree_labels_give_a_layout_none_or_a_reason():
    rng = random.Random(3)
    for _ in range(2000):
        label = "tree=" + "".join(rng.choice(string.hexdigits + string.printable) for _ in range(rng.randint(0, 20)))
        try:
            got = effort_tree(["x", label])
        except EffortNamesError as err:
            assert "tree dimension" in str(err)
        else:
            assert got is not None and len(got) == 16 and set(got) <= set("0123456789abcdef")
