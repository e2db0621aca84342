"""KinematicTree: the swimmer's chains from every source, branched trees from URDF and MJCF, refusals, fuzzing.

The branched robots are written once as a small spec (nested links, each with how it hangs off its parent)
and turned into both a URDF and an MJCF here, so one expected parent array checks both readers.
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import os
import random
import subprocess
import sys
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pytest

from morph_core.constants import MAX_JOINTS
from morph_core.env.model import swimmer_model
from morph_core.env.urdf import swimmer_urdf
from morph_core.policy.tree import MAX_DESCRIPTION_BYTES, KinematicTree, TreeError

# -- one robot, two formats ------------------------------------------------------------------------
# A link: (name, how it hangs off its parent, children). "hinge": one actuated hinge; "hinge2": two
# (URDF: through a dummy link; MJCF: two hinges in one body); "fixed": URDF fixed joint, MJCF body
# without joint; "passive": URDF fixed joint, MJCF unactuated hinge.


def link(name, kind="hinge", *children):
    return (name, kind, list(children))


def joint_names(node) -> list[str]:
    name, kind, _ = node
    return {"hinge": [f"{name}_j"], "hinge2": [f"{name}_j1", f"{name}_j2"]}.get(kind, [])


def to_urdf(root, reverse_joints=False, seed=None) -> str:
    links, joints = [], []

    def visit(parent_name, node):
        name, kind, children = node
        links.append(f'<link name="{name}"/>')
        if kind == "hinge2":
            links.append(f'<link name="{name}_dummy"/>')
            joints.append(_urdf_joint(f"{name}_j1", "revolute", parent_name, f"{name}_dummy"))
            joints.append(_urdf_joint(f"{name}_j2", "continuous", f"{name}_dummy", name))
        elif kind == "hinge":
            joints.append(_urdf_joint(f"{name}_j", "revolute", parent_name, name))
        elif parent_name is not None:
            joints.append(_urdf_joint(f"{name}_fixed", "fixed", parent_name, name))
        for child in children:
            visit(name, child)

    visit(None, root)
    if reverse_joints:  # siblings come in document order: reversing the joints mirrors the tree
        joints.reverse()
    if seed is not None:  # the links' order means nothing
        random.Random(seed).shuffle(links)
    return '<?xml version="1.0"?>\n<robot name="r">\n' + "\n".join(links + joints) + "\n</robot>\n"


def _urdf_joint(name, kind, parent, child) -> str:
    return (
        f'<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
        '<origin xyz="0.1 0 0"/><axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>'
    )


def to_mjcf(root) -> str:
    body, motors = [], []

    def visit(node, depth):
        name, kind, children = node
        pad = "  " * depth
        body.append(f'{pad}<body name="{name}" pos="0.1 0 0"><geom size="0.05"/>')
        if kind is None:  # the root floats, as the swimmer's torso does: an unactuated joint, merged
            body.append(f'{pad}  <freejoint name="{name}_free"/>')
        for joint, axis in zip(joint_names(node), ("0 0 1", "0 1 0"), strict=False):  # two: a universal joint
            body.append(f'{pad}  <joint name="{joint}" type="hinge" axis="{axis}"/>')
            motors.append(f'<motor name="{joint}_motor" joint="{joint}"/>')
        if kind == "passive":
            body.append(f'{pad}  <joint name="{name}_passive" type="hinge"/>')
        for child in children:
            visit(child, depth + 1)
        body.append(f"{pad}</body>")

    visit(root, 1)
    motors.reverse()  # the actuators' order means nothing
    return (
        "<mujoco><worldbody>\n"
        + "\n".join(body)
        + "\n</worldbody><actuator>"
        + "".join(motors)
        + "</actuator></mujoco>"
    )


def from_mjcf(text: str) -> KinematicTree:
    return KinematicTree.from_mujoco(mujoco.MjModel.from_xml_string(text))


def mirrored(node):
    name, kind, children = node
    return (name, kind, [mirrored(c) for c in reversed(children)])


def expected_parents(root) -> tuple[list[str], list[int]]:
    """Pre-order from the root, recursively: the reference for the readers' iterative walks."""
    names, parents = [], []

    def visit(node, above):
        for joint in joint_names(node):
            names.append(joint)
            parents.append(above)
            above = len(names) - 1
        for child in node[2]:
            visit(child, above)

    for child in root[2]:
        visit(child, -1)
    return names, parents


def arm(prefix, length):
    """``length`` links in a line, each on a hinge."""
    node = None
    for k in reversed(range(length)):
        node = link(f"{prefix}{k}", "hinge", *([node] if node else []))
    return node


Y = link("torso", None, link("stem", "hinge", arm("left", 2), arm("right", 2)))
STAR = link("torso", None, *(arm(f"arm{a}_", 2) for a in range(4)))
COMB = link(
    "torso", None, link("s0", "hinge", link("t0"), link("s1", "hinge", link("t1"), link("s2", "hinge", link("t2"))))
)
MERGED = link(
    "torso",
    None,
    link("mount", "fixed", link("shoulder", "hinge2", link("camera", "passive"), link("elbow"))),
    link("fin", "passive", link("fin_tip")),
)

SHAPES = {
    "Y": (Y, [-1, 0, 1, 0, 3]),
    "star": (STAR, [-1, 0, -1, 2, -1, 4, -1, 6]),
    "comb": (COMB, [-1, 0, 0, 2, 2, 4]),
    "merged": (MERGED, [-1, 0, 1, -1]),
}


# -- the swimmer --------------------------------------------------------------------------------------
def test_chain_is_the_swimmer_from_urdf_and_mujoco_for_every_length():
    for n in range(1, MAX_JOINTS + 1):
        chain = KinematicTree.chain(n)
        model = swimmer_model(n)
        assert KinematicTree.from_urdf(swimmer_urdf(n)) == chain
        assert KinematicTree.from_mujoco(model) == chain
        # the tree's order is MuJoCo's qpos order of the hinges
        hinges = sorted(
            (model.jnt_qposadr[j], mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j))
            for j in model.actuator_trnid[:, 0]
        )
        assert chain.names == tuple(name for _, name in hinges)
        assert chain.is_chain and chain.num_joints == n and chain.root_link == "torso"
        assert chain.parent_links.tolist() == list(range(n))


def test_prefixed_swimmer_urdf():
    tree = KinematicTree.from_urdf(swimmer_urdf(3, prefix="sw1/"))
    assert tree == KinematicTree.chain(
        3, names=["sw1/motor1_rot", "sw1/motor2_rot", "sw1/motor3_rot"], root_link="sw1/torso"
    )
    assert tree.topology_hash == KinematicTree.chain(3).topology_hash


def test_chain_links_are_todays_chain_graph():
    import torch

    from morph_core.policy.chains import PackedChains

    for n in (1, 5):
        packed = PackedChains.from_mask(torch.zeros(1, n), torch.zeros(1, n), torch.ones(1, n, dtype=torch.bool))
        child = packed.joint_link.numpy()  # joint j's child link; its parent link is the slot before
        tree = KinematicTree.chain(n)
        assert np.array_equal(child, np.arange(n) + 1)
        assert np.array_equal(tree.parent_links, child - 1)


# -- branched trees --------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", SHAPES)
def test_branched_urdf_and_mjcf_give_the_expected_tree(shape):
    spec, parents = SHAPES[shape]
    names, reference = expected_parents(spec)
    assert reference == parents  # the hand-written answer and the recursive reference agree
    from_urdf = KinematicTree.from_urdf(to_urdf(spec, seed=1))
    assert from_urdf == KinematicTree.from_parents(parents, names, root_link="torso")
    from_mujoco = from_mjcf(to_mjcf(spec))
    assert from_mujoco == from_urdf and from_mujoco.topology_hash == from_urdf.topology_hash
    assert from_urdf.parent_links.tolist() == [p + 1 for p in parents]
    assert not from_urdf.is_chain


def test_the_shapes_hash_apart():
    trees = [KinematicTree.from_urdf(to_urdf(spec)) for spec, _ in SHAPES.values()]
    assert len({tree.topology_hash for tree in trees + [KinematicTree.chain(5)]}) == len(SHAPES) + 1


def test_document_order_orders_siblings():
    for spec, _ in SHAPES.values():
        tree = KinematicTree.from_urdf(to_urdf(spec, reverse_joints=True, seed=2))
        assert tree == KinematicTree.from_urdf(to_urdf(mirrored(spec)))
        assert tree == from_mjcf(to_mjcf(mirrored(spec)))


def test_fixed_and_unactuated_bodies_merge():
    # MERGED without its fixed / passive links (mount, camera, fin) is the same tree: they merged.
    bare = link("torso", None, link("shoulder", "hinge2", link("elbow")), link("fin_tip"))
    for tree in (KinematicTree.from_urdf(to_urdf(MERGED)), from_mjcf(to_mjcf(MERGED))):
        assert tree == KinematicTree.from_urdf(to_urdf(bare)) == from_mjcf(to_mjcf(bare))
        assert tree.names == ("shoulder_j1", "shoulder_j2", "elbow_j", "fin_tip_j")


def test_root_link_is_the_deepest_link_above_every_joint():
    base_on_mount = link("ground", None, link("base", "fixed", arm("a", 2), arm("b", 1)))
    assert KinematicTree.from_urdf(to_urdf(base_on_mount)).root_link == "base"
    assert from_mjcf(to_mjcf(base_on_mount)).root_link == "base"
    fixed_arm = "<mujoco><worldbody><body name='l1'><joint name='j1'/><geom size='.1'/></body></worldbody>"
    fixed_arm += "<actuator><motor joint='j1'/></actuator></mujoco>"
    assert from_mjcf(fixed_arm).root_link == "world"  # MuJoCo's world body


# -- the hash and the type ------------------------------------------------------------------------
def all_parent_arrays(max_joints):
    for j in range(1, max_joints + 1):
        yield from (list(p) for p in itertools.product(*(range(-1, k) for k in range(j))))


def test_topology_hash_differs_between_shapes_and_ignores_names():
    shapes = list(all_parent_arrays(5))  # every ordered tree of up to 5 joints: 153
    hashes = {KinematicTree.from_parents(p, [f"j{k}" for k in range(len(p))]).topology_hash for p in shapes}
    assert len(hashes) == len(shapes) == 153
    renamed = KinematicTree.chain(7, names=[f"other{k}" for k in range(7)], root_link=None)
    assert renamed.topology_hash == KinematicTree.chain(7).topology_hash
    assert renamed != KinematicTree.chain(7)
    assert len(renamed.topology_hash) == 16 and set(renamed.topology_hash) <= set("0123456789abcdef")


def test_topology_hash_is_stable_across_processes():
    shapes = [p for p in all_parent_arrays(4)]
    here = [KinematicTree.from_parents(p, [f"j{k}" for k in range(len(p))]).topology_hash for p in shapes]
    code = (
        "from morph_core.policy.tree import KinematicTree as K\n"
        f"for p in {shapes!r}: print(K.from_parents(p, ['n%d' % k for k in range(len(p))]).topology_hash)\n"
    )
    for seed in ("0", "12345"):
        out = subprocess.run(
            [sys.executable, "-c", code],
            capture_output=True,
            text=True,
            check=True,
            env={**os.environ, "PYTHONHASHSEED": seed},
        )
        assert out.stdout.split() == here


def test_tree_is_immutable_and_hashable():
    parents = np.array([-1, 0, 0])
    tree = KinematicTree.from_parents(parents, ["a", "b", "c"])
    parents[2] = 1  # the caller's array is not the tree's
    assert tree.parents.tolist() == [-1, 0, 0]
    for array in (tree.parents, tree.parent_links):
        assert array.dtype == np.int64
        with pytest.raises(ValueError):
            array[0] = 3
        with pytest.raises(ValueError):
            array.setflags(write=True)
    with pytest.raises(dataclasses.FrozenInstanceError):
        tree.names = ("x", "y", "z")
    same = KinematicTree.from_parents([-1, 0, 0], ("a", "b", "c"))
    assert tree == same and hash(tree) == hash(same) and len({tree, same, KinematicTree.chain(3)}) == 2


# -- refusals -------------------------------------------------------------------------------------------
def urdf(*elements: str) -> str:
    return '<robot name="r">' + "".join(elements) + "</robot>"


def links(*names: str) -> str:
    return "".join(f'<link name="{n}"/>' for n in names)


def joint(name, kind, parent, child, extra="") -> str:
    return f'<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>{extra}</joint>'


def long_chain(n: int) -> str:
    return urdf(
        links(*(f"l{k}" for k in range(n + 1))), *(joint(f"j{k}", "revolute", f"l{k}", f"l{k + 1}") for k in range(n))
    )


BILLION_LAUGHS = (
    '<?xml version="1.0"?><!DOCTYPE r [<!ENTITY a "aaaaaaaaaa">'
    + "".join(f'<!ENTITY {c} "{("&" + p + ";") * 10}">' for p, c in zip("abcdefgh", "bcdefghi", strict=True))
    + ']><robot name="&i;"><link name="&i;"/></robot>'
)

URDF_REFUSALS = {
    "cycle without root": (
        urdf(links("a", "b"), joint("x", "revolute", "a", "b"), joint("y", "revolute", "b", "a")),
        "cycle",
    ),
    "cycle beside the root": (
        urdf(
            links("r", "a", "b", "c"),
            joint("w", "revolute", "r", "a"),
            joint("x", "revolute", "b", "c"),
            joint("y", "fixed", "c", "b"),
        ),
        "cycle through link 'b'",
    ),
    "self loop": (urdf(links("a"), joint("x", "revolute", "a", "a")), "to itself"),
    "closed loop": (
        urdf(
            links("r", "a", "b"),
            joint("x", "revolute", "r", "a"),
            joint("y", "revolute", "r", "b"),
            joint("z", "revolute", "a", "b"),
        ),
        "link 'b' is the child of two joints",
    ),
    "two roots": (urdf(links("a", "b", "c"), joint("x", "revolute", "a", "b")), "more than one root link ('a', 'c')"),
    "duplicate joint": (
        urdf(links("a", "b", "c"), joint("x", "revolute", "a", "b"), joint("x", "revolute", "b", "c")),
        "duplicate joint name 'x'",
    ),
    "duplicate link": (urdf(links("a", "b", "b"), joint("x", "revolute", "a", "b")), "duplicate link name 'b'"),
    "prismatic": (
        urdf(links("a", "b"), joint("x", "prismatic", "a", "b")),
        "'prismatic', which cannot be actuated as a hinge",
    ),
    "planar": (urdf(links("a", "b"), joint("x", "planar", "a", "b")), "'planar', which cannot be actuated as a hinge"),
    "floating": (
        urdf(links("a", "b"), joint("x", "floating", "a", "b")),
        "'floating', which cannot be actuated as a hinge",
    ),
    "unknown type": (urdf(links("a", "b"), joint("x", "ball", "a", "b")), "'ball', which is unknown"),
    "no type": (
        urdf(links("a", "b"), '<joint name="x"><parent link="a"/><child link="b"/></joint>'),
        "None, which is unknown",
    ),
    "mimic": (
        urdf(
            links("a", "b", "c"),
            joint("x", "revolute", "a", "b"),
            joint("y", "revolute", "b", "c", '<mimic joint="x"/>'),
        ),
        "joint 'y' mimics another joint",
    ),
    "65 joints": (long_chain(MAX_JOINTS + 1), "65 actuated joints, more than the maximum of 64"),
    "only fixed joints": (urdf(links("a", "b"), joint("x", "fixed", "a", "b")), "empty tree"),
    "no links": (urdf(), "no <link>"),
    "missing link": (
        urdf(links("a"), joint("x", "revolute", "a", "ghost")),
        "child link 'ghost', which does not exist",
    ),
    "missing parent": (
        urdf(links("a"), '<joint name="x" type="revolute"><child link="a"/></joint>'),
        "no <parent link=...>",
    ),
    "unnamed link": (urdf("<link/>"), "a <link> has no name"),
    "unnamed joint": (
        urdf(links("a", "b"), '<joint type="fixed"><parent link="a"/><child link="b"/></joint>'),
        "a <joint> has no name",
    ),
    "bad joint name": (urdf(links("a", "b"), joint("caf\u00e9", "revolute", "a", "b")), "not printable ASCII"),
    "malformed": ('<robot name="r"><link name="a"></robot>', "malformed XML: mismatched tag"),
    "truncated": (long_chain(3)[:-9], "malformed XML"),
    "empty text": ("", "malformed XML"),
    "not a robot": ('<sdf version="1.9"/>', "the root element is 'sdf', not <robot>"),
    "entity expansion": (BILLION_LAUGHS, "malformed XML: limit on input amplification"),
    "too large": (long_chain(2)[:-8] + " " * MAX_DESCRIPTION_BYTES + "</robot>", "more than 10000000 bytes"),
    "too large bytes": (long_chain(2).encode() + b" " * MAX_DESCRIPTION_BYTES, "more than 10000000 bytes"),
    "invalid unicode": ("<robot name='\ud800'/>", "malformed XML"),
    "not text": (None, "a URDF is str or bytes, got NoneType"),
}


@pytest.mark.parametrize("case", URDF_REFUSALS)
def test_urdf_refusals(case):
    text, reason = URDF_REFUSALS[case]
    with pytest.raises(TreeError) as err:
        KinematicTree.from_urdf(text)
    assert reason in str(err.value) and "\n" not in str(err.value)


def test_a_valid_description_just_under_the_limit_is_read():
    text = long_chain(2)
    padded = text[:-8] + " " * (MAX_DESCRIPTION_BYTES - len(text)) + "</robot>"
    assert len(padded.encode()) == MAX_DESCRIPTION_BYTES
    assert KinematicTree.from_urdf(padded) == KinematicTree.from_parents([-1, 0], ["j0", "j1"], root_link="l0")


def mjcf_with(joint_xml: str, actuator_xml: str, extra: str = "") -> str:
    return (
        f"<mujoco><worldbody><body name='b'><geom size='.1'/>{joint_xml}<site name='s'/></body></worldbody>"
        f"{extra}<actuator>{actuator_xml}</actuator></mujoco>"
    )


MJCF_REFUSALS = {
    "slide": (
        mjcf_with("<joint name='j' type='slide'/>", "<motor name='m' joint='j'/>"),
        "actuator 'm' drives 'j', a slide joint",
    ),
    "ball": (mjcf_with("<joint name='j' type='ball'/>", "<motor name='m' joint='j'/>"), "drives 'j', a ball joint"),
    "free": (mjcf_with("<freejoint name='j'/>", "<motor name='m' joint='j'/>"), "drives 'j', a free joint"),
    "tendon": (
        mjcf_with(
            "<joint name='j'/>",
            "<motor name='m' tendon='t'/>",
            "<tendon><fixed name='t'><joint joint='j' coef='1'/></fixed></tendon>",
        ),
        "actuator 'm' drives a tendon, not a joint",
    ),
    "site": (mjcf_with("<joint name='j'/>", "<motor name='m' site='s'/>"), "actuator 'm' drives a site, not a joint"),
    "no actuator": (mjcf_with("<joint name='j'/>", ""), "empty tree"),
    "65 joints": (
        to_mjcf(link("torso", None, *(link(f"arm{k}") for k in range(MAX_JOINTS + 1)))),
        "65 actuated joints",
    ),
}


@pytest.mark.parametrize("case", MJCF_REFUSALS)
def test_mujoco_refusals(case):
    text, reason = MJCF_REFUSALS[case]
    with pytest.raises(TreeError) as err:
        from_mjcf(text)
    assert reason in str(err.value) and "\n" not in str(err.value)


def test_mujoco_refuses_what_is_not_a_model():
    with pytest.raises(TreeError, match="expected a compiled mujoco.MjModel, got str"):
        KinematicTree.from_mujoco(swimmer_urdf(2))


def test_several_actuators_on_one_hinge_make_one_joint():
    text = mjcf_with("<joint name='j'/>", "<motor joint='j'/><position joint='j'/>")
    assert from_mjcf(text) == KinematicTree.from_parents([-1], ["j"], root_link="world")


PARENT_REFUSALS = {
    "cycle": (([1, 0], ["a", "b"]), "parents form a cycle (reached from joint 0, 'a')"),
    "self parent": (([-1, 1], ["a", "b"]), "cycle"),
    "out of order": (([1, -1], ["a", "b"]), "joint 0's parent 1 comes after it"),
    "out of range": (([-1, 2], ["a", "b"]), "joint 1 has parent 2"),
    "below -1": (([-2], ["a"]), "joint 0 has parent -2"),
    "huge unsigned": ((np.array([2**64 - 1], dtype=np.uint64), ["a"]), "joint 0 has parent"),
    "too large for int64": (([2**70], ["a"]), "parents"),
    "float": (([-1.0], ["a"]), "1-D integer array, got float64"),
    "bool": (([True], ["a"]), "1-D integer array, got bool"),
    "2-D": (([[-1]], ["a"]), "1-D integer array"),
    "ragged": (([[-1], [0, 1]], ["a", "b"]), "parents"),
    "count mismatch": (([-1, 0], ["a"]), "2 parents for 1 joint names"),
    "empty": (([], []), "empty tree"),
    "65 joints": ((np.arange(-1, 64), [f"j{k}" for k in range(65)]), "65 actuated joints"),
    "duplicate": (([-1, 0], ["a", "a"]), "duplicate joint name 'a'"),
    "empty name": (([-1], [""]), "joint name 0 has 0 characters"),
    "long name": (([-1], ["x" * 257]), "joint name 0 has 257 characters"),
    "names as str": (([-1], "a"), "joint names must be a sequence of strings, got str"),
    "non-str name": (([-1], [3]), "joint names must be strings"),
}


@pytest.mark.parametrize("case", PARENT_REFUSALS)
def test_from_parents_refusals(case):
    args, reason = PARENT_REFUSALS[case]
    with pytest.raises(TreeError) as err:
        KinematicTree.from_parents(*args)
    assert reason in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("n", [0, -1, 65, 2.0, True, "3", None])
def test_chain_refusals(n):
    with pytest.raises(TreeError, match=r"a chain has 1\.\.64 joints"):
        KinematicTree.chain(n)


# -- random trees and fuzzing --------------------------------------------------------------------------
def random_spec(rng: random.Random, num_links: int):
    """A random tree of links hanging off "root" by random kinds, deep or bushy by chance."""
    nodes = [link("root", None)]
    for k in range(1, num_links):
        kind = rng.choices(["hinge", "hinge2", "fixed", "passive"], weights=[5, 1, 2, 2])[0]
        node = link(f"n{k}", kind)
        parent = nodes[-1] if rng.random() < 0.5 else rng.choice(nodes)
        parent[2].append(node)
        nodes.append(node)
    return nodes[0]


def test_random_trees_read_the_same_from_urdf_mjcf_and_the_reference():
    rng = random.Random(7)
    refused = 0
    for trial in range(60):
        spec = random_spec(rng, rng.choice([1, 2, 100]) if trial % 10 == 0 else rng.randrange(1, 80))
        names, parents = expected_parents(spec)
        readings = []
        for read, text in ((KinematicTree.from_urdf, to_urdf(spec, seed=trial)), (from_mjcf, to_mjcf(spec))):
            try:
                readings.append(read(text))
            except TreeError as err:
                readings.append(str(err))
        if 1 <= len(names) <= MAX_JOINTS:
            assert readings[0] == readings[1]
            assert readings[0].names == tuple(names) and readings[0].parents.tolist() == parents
        else:  # no joint, or too many: both refuse for the same reason
            refused += 1
            assert readings[0] == readings[1] and isinstance(readings[0], str)
    assert 0 < refused < 30  # both branches ran


HINGES = ("revolute", "continuous")


def assert_tree_read_right(tree: KinematicTree, text: str | bytes) -> None:
    """The tree's invariants, and each joint's parent found bottom-up in the text: a second walk, the other way."""
    assert 1 <= tree.num_joints <= MAX_JOINTS and len(tree.parents) == tree.num_joints
    assert all(-1 <= p < j for j, p in enumerate(tree.parents.tolist()))
    assert len(set(tree.names)) == tree.num_joints and not tree.parents.flags.writeable
    assert KinematicTree.from_parents(tree.parents, tree.names, tree.root_link) == tree
    robot = ET.fromstring(text)
    joints = {j.get("name"): j for j in robot.findall("joint")}
    above_link = {j.find("child").get("link"): j for j in joints.values()}
    assert set(tree.names) == {name for name, j in joints.items() if j.get("type") in HINGES}
    for k, name in enumerate(tree.names):
        parent, link_name = -1, joints[name].find("parent").get("link")
        while link_name in above_link:
            up = above_link[link_name]
            if up.get("type") in HINGES:
                parent = tree.names.index(up.get("name"))
                break
            link_name = up.find("parent").get("link")
        assert tree.parents[k] == parent, (name, tree)


def deep_or_wide_urdf(rng: random.Random) -> str:
    """Thousands of fixed links in a line or off one link, with a few hinges among them (no recursion here)."""
    n = rng.randrange(500, 3000)
    deep = rng.random() < 0.5
    joints = [
        joint(f"j{k}", "revolute" if rng.random() < 0.01 else "fixed", f"l{k - 1}" if deep else "l0", f"l{k}")
        for k in range(1, n)
    ]
    return urdf(links(*(f"l{k}" for k in range(n))), *joints)


JOINT_TYPES = ("revolute", "continuous", "fixed", "prismatic", "planar", "floating", "ball", "", "Revolute")
TAGS = ("link", "joint", "parent", "child", "mimic", "robot", "origin", "axis")


def mutate(robot: ET.Element, rng: random.Random) -> None:
    """One random edit of the element tree: delete, duplicate, rename, retype, add, swap or move."""
    elements = list(robot.iter())
    parent_of = {child: parent for parent in elements for child in parent}
    values = [v for el in elements for v in el.attrib.values()] + ["", " ", "x", "\u00e9", "a" * 300, "0", "-1"]
    el = rng.choice(elements)
    op = rng.randrange(7)
    if op == 0 and el in parent_of:
        parent_of[el].remove(el)
    elif op == 1 and el in parent_of:
        parent_of[el].insert(rng.randrange(len(parent_of[el]) + 1), copy.deepcopy(el))
    elif op == 2 and el.attrib:
        el.set(rng.choice(sorted(el.attrib)), rng.choice(values))
    elif op == 3:
        rng.choice(robot.findall("joint") or [el]).set("type", rng.choice(JOINT_TYPES))
    elif op == 4:
        el.set(rng.choice(["name", "type", "link", "joint", "zz"]), rng.choice(values))
    elif op == 5:
        el.append(ET.Element(rng.choice(TAGS), {rng.choice(["name", "link", "type"]): rng.choice(values)}))
    elif op == 6 and (joints := robot.findall("joint")):
        j = rng.choice(joints)
        ends = j.find("parent"), j.find("child")
        if None not in ends:
            a, b = ends[0].get("link"), ends[1].get("link")
            ends[0].set("link", b or ""), ends[1].set("link", a or "")


def corrupt(data: bytes, rng: random.Random) -> bytes:
    """One random edit of the bytes: truncate, overwrite, insert, or replace everything."""
    op = rng.randrange(4)
    at = rng.randrange(len(data) + 1)
    noise = rng.randbytes(rng.randrange(1, 16))
    if op == 0:
        return data[:at]
    if op == 1:
        return data[:at] + noise + data[at + len(noise) :]
    if op == 2:
        return data[:at] + noise + data[at:]
    return rng.randbytes(rng.randrange(64))


@pytest.mark.slow
def test_fuzzed_urdfs_give_a_valid_tree_or_a_tree_error():
    rng = random.Random(20261204)
    swimmers = [swimmer_urdf(n) for n in (1, 2, 5, 64)]
    outcomes = {"tree": 0, "refused": 0}
    for trial in range(3000):
        pick = rng.random()
        if pick < 0.03:
            base = deep_or_wide_urdf(rng)
        elif pick < 0.4:
            base = rng.choice(swimmers)
        else:  # up to ~110 links: some have more than 64 hinges
            base = to_urdf(random_spec(rng, rng.randrange(1, 110)), reverse_joints=rng.random() < 0.5, seed=trial)
        robot = ET.fromstring(base)
        for _ in range(rng.randrange(4)):
            mutate(robot, rng)
        text: str | bytes = ET.tostring(robot, encoding="unicode")
        if rng.random() < 0.25:
            text = corrupt(text.encode(), rng)
        try:
            tree = KinematicTree.from_urdf(text)
        except TreeError as err:
            assert str(err) and "\n" not in str(err)
            outcomes["refused"] += 1
            continue
        assert_tree_read_right(tree, text)
        outcomes["tree"] += 1
    assert min(outcomes.values()) > 300, outcomes  # both outcomes well exercised
