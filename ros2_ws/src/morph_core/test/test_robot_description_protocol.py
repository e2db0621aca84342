"""RobotDescriptions: the description a policy node acts on, swaps, refusals, and states of the robot before a swap."""

from __future__ import annotations

import random

import numpy as np
import pytest

from morph_core.constants import MAX_JOINTS
from morph_core.env.bodies import y_parents
from morph_core.env.urdf import swimmer_urdf
from morph_core.policy.tree import MAX_DESCRIPTION_BYTES, TreeError, read_urdf
from morph_core.protocol.joint_map import JointMapError
from morph_core.protocol.robot_description import (
    DESCRIPTION,
    PREVIOUS_DESCRIPTION,
    UNCHANGED,
    RobotDescriptions,
)


def urdf(parents, names=None, fixed=(), uncommanded=()) -> str:
    """A URDF of hinges with ``parents`` (joint j under joint parents[j]'s child link, -1: the base), named
    ``names`` (default j0, j1...), plus a fixed joint per name in ``fixed`` (off the base); the hinges in
    ``uncommanded`` get no command interface in a ``<ros2_control>`` block (only written when there are any)."""
    names = list(names or (f"j{k}" for k in range(len(parents))))
    links = ["base", *(f"l{k}" for k in range(len(parents))), *(f"f{k}" for k in range(len(fixed)))]
    parts = [f'<link name="{n}"/>' for n in links]
    for k, (p, name) in enumerate(zip(parents, names, strict=True)):
        parent = "base" if p < 0 else f"l{p}"
        parts.append(f'<joint name="{name}" type="revolute"><parent link="{parent}"/><child link="l{k}"/></joint>')
    parts += [
        f'<joint name="{name}" type="fixed"><parent link="base"/><child link="f{k}"/></joint>'
        for k, name in enumerate(fixed)
    ]
    if uncommanded:
        command = '<command_interface name="effort"/>'
        rows = [
            f'<joint name="{n}">{"" if n in uncommanded else command}<state_interface name="position"/></joint>'
            for n in names
        ]
        parts.append('<ros2_control name="hw" type="system">' + "".join(rows) + "</ros2_control>")
    return '<robot name="r">' + "".join(parts) + "</robot>"


CHAIN3 = urdf([-1, 0, 1])
Y = urdf(y_parents(2, 2))  # j0 - j1, then j2 - j3 and j4 - j5 off j1's link


def test_fallback_until_a_description_and_a_chain_in_message_order():
    d = RobotDescriptions()
    assert d.is_fallback and d.generation == 0 and d.previous is None
    order = d.order(("b", "a", "c"))
    assert order.tree.names == ("b", "a", "c") and order.tree.is_chain and order.in_message_order
    assert d.order(("x", "y")).tree.parents.tolist() == [-1, 0]  # any names: a chain of them


def test_a_description_maps_states_by_name_in_any_order():
    d = RobotDescriptions()
    assert d.offer(Y).outcome == "adopted"
    assert not d.is_fallback and d.generation == 1 and d.previous is None  # the fallback is no previous
    tree = d.map.robot.tree
    assert list(tree.parents) == y_parents(2, 2)
    names = list(tree.names)
    random.Random(3).shuffle(names)
    order = d.order(tuple(names))
    values = np.array([float(n[1:]) for n in names])  # each joint's own number, wherever it is
    np.testing.assert_array_equal(order.to_tree(values), np.arange(6.0))
    assert order.message_names == tuple(names)
    np.testing.assert_array_equal(order.to_message(order.to_tree(values)), values)


def test_unactuated_joints_left_out_and_unknown_or_missing_ones_refused():
    d = RobotDescriptions()
    d.offer(urdf([-1, 0, 0], fixed=["camera_mount"], uncommanded=["j2"]))
    assert d.map.robot.tree.names == ("j0", "j1")
    assert d.map.robot.unactuated == {"camera_mount", "j2"}
    order = d.order(("j2", "j1", "camera_mount", "j0"))
    np.testing.assert_array_equal(order.to_tree(np.array([2.0, 1.0, 9.0, 0.0])), [0.0, 1.0])
    assert order.message_names == ("j1", "j0")
    with pytest.raises(JointMapError, match="'wheel'") as err:
        d.order(("j0", "j1", "wheel"))
    assert err.value.code == "unknown_joint"
    with pytest.raises(JointMapError, match="lacks 1 .*'j1'") as err:
        d.order(("j0", "j2"))
    assert err.value.code == "missing_joint"


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("not xml <", "malformed XML"),
        ("<robot", "malformed XML"),
        ("", "malformed XML"),
        ("<robot/>", "no <link>"),
        ("<rob" + " " * MAX_DESCRIPTION_BYTES + "/>", "more than 10000000 bytes"),
        (urdf([-1, 0]).replace('child link="l0"', 'child link="base"'), "cycle"),
        ('<robot><link name="a"/><link name="b"/></robot>', "more than one root"),
        (urdf([-1, 0], names=["j", "j"]), "duplicate joint name"),
        (urdf(list(range(-1, MAX_JOINTS))), f"{MAX_JOINTS + 1} actuated joints, more than the maximum"),
        (b"\xff\xfe<robot/>", "malformed XML"),
        (None, "str or bytes"),
    ],
    ids=[
        "garbage",
        "cut",
        "empty",
        "no_link",
        "too_large",
        "cycle",
        "two_roots",
        "duplicate",
        "65_joints",
        "bad_bytes",
        "none",
    ],  # fmt: skip
)
def test_a_bad_description_is_rejected_with_its_reason_and_the_current_graph_kept(text, words):
    d = RobotDescriptions()
    d.offer(CHAIN3)
    offer = d.offer(text)
    assert offer.outcome == "rejected" and offer.code == DESCRIPTION
    assert words in offer.reason and "\n" not in offer.reason
    assert d.rejected == 1 and d.last_error == offer.reason and d.generation == 1
    assert d.map.robot.tree.names == ("j0", "j1", "j2")  # kept
    d.order(("j2", "j0", "j1"))  # a state of it still fits
    # Before any description, a bad one leaves the fallback in place.
    fresh = RobotDescriptions()
    assert fresh.offer(text).outcome == "rejected" and fresh.is_fallback
    assert fresh.order(("q", "r")).tree.names == ("q", "r")


def test_the_same_text_again_changes_nothing():
    d = RobotDescriptions()
    d.offer(CHAIN3)
    current = d.map
    assert d.offer(CHAIN3) == d.offer(str(CHAIN3)) and d.offer(CHAIN3).code == UNCHANGED
    assert d.map is current and d.generation == 1 and d.unchanged == 3 and d.previous is None


def test_a_swap_tells_states_of_the_robot_before_it_apart():
    d = RobotDescriptions()
    d.offer(CHAIN3)
    d.offer(urdf([-1, 0, 1, 2, 3], names=[f"k{i}" for i in range(5)]))
    assert d.generation == 2 and d.previous.robot.tree.names == ("j0", "j1", "j2")
    assert d.order(tuple(f"k{i}" for i in range(5))).tree.num_joints == 5
    with pytest.raises(JointMapError, match="previous robot_description") as err:
        d.order(("j1", "j0", "j2"))  # the old chain, in flight
    assert err.value.code == PREVIOUS_DESCRIPTION
    with pytest.raises(JointMapError) as err:
        d.order(("k0", "nope"))  # fits neither: the current map's reason
    assert err.value.code == "unknown_joint" and "'nope'" in str(err.value)
    # A chain grown by two joints with the same names: the old states lack the new joints.
    d.offer(urdf([-1, 0, 1, 2, 3, 4, 5], names=[f"k{i}" for i in range(7)]))
    with pytest.raises(JointMapError) as err:
        d.order(tuple(f"k{i}" for i in range(5)))
    assert err.value.code == PREVIOUS_DESCRIPTION and "lacks 2" in str(err.value)
    # Only the one before the current is remembered.
    with pytest.raises(JointMapError) as err:
        d.order(("j0", "j1", "j2"))
    assert err.value.code == "unknown_joint"


def test_alternating_two_robots_reuses_their_maps():
    a, b = CHAIN3, swimmer_urdf(y_parents(2, 2))
    d = RobotDescriptions()
    d.offer(a)
    d.offer(b)
    map_a, map_b = d.previous, d.map
    for k in range(10):
        assert d.offer(a if k % 2 == 0 else b).outcome == "adopted"
        assert d.map is (map_a if k % 2 == 0 else map_b)
    assert d.generation == 12 and d.adopted == 12


def test_offers_never_raise_on_random_bytes_and_mutated_urdfs():
    """Anything that comes off the wire is adopted or rejected with a reason; nothing else escapes."""
    rng = random.Random(38)
    good = swimmer_urdf(y_parents(2, 2))
    d = RobotDescriptions()
    outcomes = set()
    for _ in range(1500):
        r = rng.random()
        if r < 0.3:
            text = bytes(rng.randrange(256) for _ in range(rng.randrange(60)))
        elif r < 0.8:
            i, j = sorted(rng.randrange(len(good)) for _ in range(2))
            text = good[:i] + rng.choice(["", "<", ">", '"', "</robot>", "<link name='x'/>", "\x00"]) + good[j:]
        else:
            text = good.replace("motor", rng.choice(["motor", "m", "", "j\t"]), rng.randrange(8))
        try:
            offer = d.offer(text)
        except Exception as err:  # noqa: BLE001 - the point of the test
            raise AssertionError(f"offer raised {type(err).__name__}: {err} for {text[:200]!r}") from None
        outcomes.add(offer.outcome)
        if offer.outcome == "rejected":
            assert offer.reason and "\n" not in offer.reason
    assert {"adopted", "rejected"} <= outcomes  # the mutations made both kinds


def test_the_reason_is_the_tree_readers():
    # The protocol adds no reading of its own: a rejection's reason is read_urdf's TreeError.
    slider = Y.replace('"j3" type="revolute"', '"j3" type="prismatic"')
    with pytest.raises(TreeError) as err:
        read_urdf(slider)
    assert RobotDescriptions().offer(slider).reason == str(err.value)
