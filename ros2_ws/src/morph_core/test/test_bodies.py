"""Body families: the spec grammar, the shapes drawn, chain draws as before, labels, and a fuzzed parser."""

import time

import numpy as np
import pytest

from morph_core.constants import MAX_JOINTS
from morph_core.env.bodies import (
    RANDOM_MAX_BRANCHING,
    STAR_MAX_ARMS,
    BodyMix,
    _named_labels,
    body_label,
    parse_bodies,
)
from morph_core.env.model import check_parents
from morph_core.env.swimmer_env import MorphSwimmerEnv
from morph_core.policy.tree import KinematicTree, swimmer_joint_names


@pytest.mark.parametrize(
    ("spec", "canonical", "joint_range", "chains_only"),
    [
        ("6", "6", (6, 6), True),
        ("2-10", "2-10", (2, 10), True),
        (" chain:3-3 ", "3", (3, 3), True),
        ("2-4,8", "2-4,8", (2, 8), True),
        ("star:3x2", "star:3x2", (6, 6), False),
        ("y:1x2", "y:1x2", (5, 5), False),
        ("comb:4", "comb:4", (7, 7), False),
        ("star:2-3x1-2", "star:2-3x1-2", (2, 6), False),
        ("random:3-10", "random:3-10:b2", (3, 10), False),
        ("2-10, random:3-12:b3", "2-10,random:3-12:b3", (2, 12), False),
    ],
)
def test_specs_parse_to_their_canonical_text(spec, canonical, joint_range, chains_only):
    mix = parse_bodies(spec)
    assert str(mix) == canonical and parse_bodies(str(mix)) == mix
    assert mix.joint_range == joint_range and mix.max_joints == joint_range[1]
    assert mix.chains_only == chains_only


def test_named_shapes_are_the_trees_the_grammar_says():
    (star,) = parse_bodies("star:3x2").members()
    np.testing.assert_array_equal(star.parents, [-1, 0, -1, 2, -1, 4])  # three arms of two joints off the torso
    (y,) = parse_bodies("y:2x2").members()
    np.testing.assert_array_equal(y.parents, [-1, 0, 1, 2, 1, 4])  # stem of 2, two branches of 2 off its end
    (comb,) = parse_bodies("comb:3").members()
    np.testing.assert_array_equal(comb.parents, [-1, 0, 0, 2, 2])  # spine 0, 2, 4; teeth 1, 3
    for tree, label in ((star, "star-3x2"), (y, "y-2x2"), (comb, "comb-3")):
        assert tree.names == swimmer_joint_names(tree.num_joints) and tree.root_link == "torso"
        assert body_label(tree) == label
        check_parents(tree.parents)  # pre-order: MuJoCo's order


def test_members_of_a_finite_mix_in_spec_order_without_repeats():
    members = parse_bodies("2-3,star:2x1,3,y:1x1").members()
    assert [body_label(t) for t in members] == ["chain-2", "chain-3", "star-2x1", "y-1x1"]
    assert parse_bodies("2-3,random:4").members() is None


def test_labels_of_chains_named_shapes_and_other_trees():
    assert body_label(KinematicTree.chain(7)) == "chain-7"
    other = KinematicTree(swimmer_joint_names(4), [-1, 0, 0, -1], "torso")
    assert body_label(other) == "tree-" + other.topology_hash[:8]
    renamed = KinematicTree([f"j{k}" for k in range(6)], [-1, 0, -1, 2, -1, 4])  # the label is the shape's
    assert body_label(renamed) == "star-3x2"
    assert len(set(_named_labels().values())) == len(_named_labels())  # no two named shapes share a tree


def test_a_chain_spec_draws_as_num_joints_always_has():
    # Same seeds -> same lengths, reset noise and trajectories as MorphSwimmerEnv(num_joints=(lo, hi)).
    for spec, num_joints in (("2-10", (2, 10)), ("chain:5", 5), ("4-4", (4, 4))):
        old, new = MorphSwimmerEnv(num_joints=num_joints), MorphSwimmerEnv(bodies=spec)
        actions = np.random.default_rng(1)
        for episode in range(12):
            seed = 3 if episode == 0 else None
            (o1, i1), (o2, i2) = old.reset(seed=seed), new.reset(seed=seed)
            assert i1["num_joints"] == i2["num_joints"] and i2["body"] == f"chain-{i2['num_joints']}"
            for _ in range(5):
                a = actions.uniform(-1, 1, new.num_joints)
                o1, r1, *_ = old.step(a)
                o2, r2, *_ = new.step(a)
                assert r1 == r2
                for key in o1:
                    np.testing.assert_array_equal(o1[key], o2[key])
        assert old.np_random.bit_generator.state == new.np_random.bit_generator.state


def test_a_mix_draws_an_item_uniformly_then_a_member():
    mix = parse_bodies("2,star:2-3x1,random:4-6:b3")
    rng = np.random.default_rng(0)
    labels = [body_label(mix.draw(rng)) for _ in range(600)]
    chains, stars = labels.count("chain-2"), sum(label.startswith("star-") for label in labels)
    assert 150 < chains < 260 and 150 < stars < 260  # each of three items about 200 times
    assert {"star-2x1", "star-3x1"} <= set(labels)
    again = np.random.default_rng(0)
    assert [body_label(mix.draw(again)) for _ in range(600)] == labels  # the rng decides everything


@pytest.mark.parametrize("branching", range(1, RANDOM_MAX_BRANCHING + 1))
def test_random_trees_keep_their_size_and_branching_limit(branching):
    mix = parse_bodies(f"random:1-30:b{branching}")
    rng = np.random.default_rng(branching)
    shapes, sizes = set(), set()
    for _ in range(300):
        tree = mix.draw(rng)
        check_parents(tree.parents)  # pre-order, as the MJCF is written
        children = np.bincount(tree.parents + 1, minlength=tree.num_joints + 1)  # per link, torso first
        assert children.max() <= branching
        sizes.add(tree.num_joints)
        shapes.add(tree.topology_hash)
        assert tree.is_chain or branching > 1
    assert min(sizes) == 1 and max(sizes) == 30
    assert len(shapes) == 30 if branching == 1 else len(shapes) > 250  # b1: only the 30 chains


@pytest.mark.parametrize(
    ("spec", "reason"),
    [
        ("", "empty body spec"),
        ("   ", "empty body spec"),
        ("2,,3", "empty item"),
        ("2,", "empty item"),
        ("0", "at least 1"),
        ("65", "at most 64"),
        ("10-2", "empty range"),
        ("octopus:3", "unknown body family 'octopus'"),
        ("star:1x3", "star arms must be at least 2"),
        (f"star:{STAR_MAX_ARMS + 1}x1", f"star arms must be at most {STAR_MAX_ARMS}"),
        ("star:4x9", "more than a tree's maximum of 32"),
        ("y:0x2", "y stem joints must be at least 1"),
        ("y:1x0", "y branch joints must be at least 1"),
        ("comb:2", "comb spine joints must be at least 3"),
        ("comb:17", "more than a tree's maximum of 32"),
        ("y:31x1", "more than a tree's maximum of 32"),
        ("random:3-10:b0", "branching must be in"),
        (f"random:3-10:b{RANDOM_MAX_BRANCHING + 1}", "branching must be in"),
        ("random:3-33", "at most 32"),
        ("star:3", "cannot read body item"),
        ("2 - 4", "cannot read body item"),
        ("x" * 2000, "longer than"),
        ("centipede:1", "centipede leg pairs must be at least 2"),
        ("centipede:17", "centipede leg pairs must be at most 16"),
        ("centipede:4-2", "empty range"),
        ("centipede:", "cannot read body item"),
        ("centipede:2x3", "cannot read body item"),
        ("centipedes:3", "unknown body family 'centipedes'"),
    ],
)
def test_bad_specs_say_why(spec, reason):
    with pytest.raises(ValueError, match=reason):
        parse_bodies(spec)


def test_a_spec_is_a_string():
    with pytest.raises(ValueError, match="string"):
        parse_bodies(5)
    with pytest.raises(TypeError, match="bodies"):
        MorphSwimmerEnv(bodies=5)


def test_fuzzed_specs_parse_or_raise_value_error_only():
    rng = np.random.default_rng(2024)
    alphabet = list("0123456789-,:x bXé\n") + ["star:", "y:", "comb:", "random:", "chain:", ":b", "64", "99999"]
    alphabet += ["centipede:", "centipede:2", "16"]
    parsed, centipedes, started = 0, 0, time.monotonic()
    for _ in range(5000):
        spec = "".join(rng.choice(alphabet, size=int(rng.integers(0, 14))))
        try:
            mix = parse_bodies(spec)
        except ValueError:
            continue
        parsed += 1
        centipedes += mix.has_centipedes
        assert isinstance(mix, BodyMix) and parse_bodies(str(mix)) == mix
        lo, hi = mix.joint_range
        assert 1 <= lo <= hi <= MAX_JOINTS
        body = mix.draw(rng)
        assert lo <= body.num_joints <= hi
        assert mix.global_features == (12 if mix.has_centipedes else 4)
    assert parsed > 100  # the fuzzer reaches valid specs too, not only errors
    assert centipedes > 10  # and specs with centipedes among them
    assert time.monotonic() - started < 60


@pytest.mark.slow
def test_drawn_trees_swim_without_diverging_under_random_and_bang_bang_actions():
    # The fast version of bench/check_body_stability.py (its full sweep is quoted in docs/bodies.md).
    from morph_core.env.swimmer_batch import SwimmerBatch

    rng = np.random.default_rng(0)
    trees = parse_bodies("star:2-4x1-3,y:1-3x1-3,comb:3-6").members()
    trees += [parse_bodies(f"random:4-16:b{b}").draw(rng) for b in range(2, RANDOM_MAX_BRANCHING + 1) for _ in range(6)]
    trees += [parse_bodies(spec).first() for spec in ("star:4x8", "y:14x9", "comb:16", "star:2x16")]  # the largest
    for tree in trees:
        n = tree.num_joints
        batch = SwimmerBatch(tree, [0, 1, 2, 3])
        diverged = np.zeros(4, dtype=bool)
        for step in range(150):
            flip = 1.0 if step % 2 == 0 else -1.0
            bang = 1.0 if (step // 10) % 2 == 0 else -1.0
            actions = np.stack(
                [
                    rng.uniform(-1, 1, n),  # random
                    np.full(n, flip),  # all +1 / -1, switching every step
                    np.full(n, bang),  # all +1 / -1, switching every 10 steps
                    bang * np.where(np.arange(n) % 2 == 0, 1.0, -1.0),  # alternating signs
                ]
            )
            diverged |= batch.advance(actions)[1]
        assert not diverged.any(), (body_label(tree), tree.parents.tolist(), diverged)
        state = np.zeros((4, n)), np.zeros((4, n)), np.zeros((4, 4))
        batch.write_observation(*state)
        assert all(np.isfinite(part).all() for part in state)


# -- centipedes ------------------------------------------------------------------------------------------------
def test_a_centipede_family_reads_draws_and_labels():
    from morph_core.env.bodies import Centipede, body_label

    mix = parse_bodies("centipede:2-4")
    assert str(mix) == "centipede:2-4" and parse_bodies("centipede:3") == parse_bodies("centipede:3-3")
    assert mix.joint_range == (8, 16) and mix.global_features == 12 and not mix.chains_only
    assert mix.members() == [Centipede(2), Centipede(3), Centipede(4)]
    assert [body_label(m) for m in mix.members()] == ["centipede-2", "centipede-3", "centipede-4"]
    assert mix.first() == Centipede(2) and Centipede(3).tree.num_joints == 12
    # the draw is MorphCentipedeEnv(leg_pairs=(2, 4))'s from the same generator
    from gymnasium.utils import seeding

    from morph_core.env.centipede import MorphCentipedeEnv

    env = MorphCentipedeEnv(leg_pairs=(2, 4))
    sizes = [env.reset(seed=seed)[1]["leg_pairs"] for seed in range(20)]
    assert [mix.draw(seeding.np_random(seed)[0]).leg_pairs for seed in range(20)] == sizes
    assert set(sizes) == {2, 3, 4}


def test_swimmers_and_centipedes_mix_with_twelve_globals():
    mix = parse_bodies("2-3,centipede:2")
    assert mix.has_centipedes and mix.global_features == 12 and mix.joint_range == (2, 8)
    assert parse_bodies("2-4,y:2x2").global_features == 4
    with pytest.raises(ValueError, match="holds walkers"):
        MorphSwimmerEnv(bodies="2,centipede:2")


def test_the_policy_takes_the_mixs_global_width():
    from morph_core.env.bodies import fit_global_features
    from morph_core.policy.config import PolicyConfig

    assert fit_global_features(PolicyConfig(), parse_bodies("centipede:2")).global_features == 12
    assert fit_global_features(PolicyConfig(), parse_bodies("2-4")) == PolicyConfig()
    with pytest.raises(ValueError, match="give 4 global features, the policy reads 12"):
        fit_global_features(PolicyConfig(global_features=12), parse_bodies("2-4"))
