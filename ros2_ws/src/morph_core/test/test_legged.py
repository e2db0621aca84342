"""The legged family: its spec, its bodies (one body per label, stable physics, standing at zero action), Ant-v5's
task on them with healthy heights from the standing height, vectorised with 12 globals."""

from __future__ import annotations

import numpy as np
import pytest

from morph_core.env.bodies import LEGGED_TRAIN_SEEDS, LeggedFamily, body_label, is_walker, parse_bodies
from morph_core.env.centipede import MorphCentipedeEnv
from morph_core.env.centipede_model import ant_model
from morph_core.env.legged_model import (
    ANT_STANDING_HEIGHT,
    HEALTHY_FRACTIONS,
    LEGGED_JOINTS_PER_LEG,
    LEGGED_LEGS,
    TORSOS,
    LeggedBody,
    settled_height,
)
from morph_core.env.urdf import robot_urdf
from morph_core.env.vec_env import SwimmerVecEnv
from morph_core.policy.joint_description import mujoco_descriptions, urdf_descriptions
from morph_core.policy.tree import KinematicTree

KINDS = [(n, j, t) for n in LEGGED_LEGS for j in LEGGED_JOINTS_PER_LEG for t in TORSOS]


def test_the_spec_reads_legs_joints_torso_and_seeds():
    mix = parse_bodies("legged:4-8x2-3")
    (family,) = mix.items
    assert family == LeggedFamily((4, 6, 8), (2, 3), TORSOS, LEGGED_TRAIN_SEEDS)
    assert str(mix) == "legged:4-8x2-3:s0-99" and str(parse_bodies(str(mix))) == str(mix)
    assert mix.joint_range == (8, 24) and mix.global_features == 12 and mix.has_walkers and not mix.swimmers_only
    assert mix.members() is None  # 1,800 bodies
    small = parse_bodies("legged:6x3:long:s1000-1001")
    assert [b.label for b in small.members()] == ["legged-6x3-long-s1000", "legged-6x3-long-s1001"]
    assert parse_bodies("legged:5-6x2").items[0].legs == (6,)


@pytest.mark.parametrize(
    "spec, match",
    [("legged:5x2", "legs"), ("legged:10x2", "legs"), ("legged:4x4", "joints"), ("legged:4x1", "joints"),
     ("legged:4x2:square", "cannot read"), ("legged:4x2:s9-1", "empty"), ("legged:4x2:s0-99999999999", "cannot")],
)  # fmt: skip
def test_bad_legged_specs_are_refused(spec, match):
    with pytest.raises(ValueError, match=match):
        parse_bodies(spec)


def test_a_label_names_one_body_for_good():
    a, b = LeggedBody(6, 3, "wide", 7), LeggedBody(6, 3, "wide", 7)
    assert a.mjcf() == b.mjcf() and a.label == body_label(a) == "legged-6x3-wide-s7" and is_walker(a)
    assert LeggedBody(6, 3, "wide", 8).mjcf() != a.mjcf()
    draws = [parse_bodies("legged:4-8x2-3").items[0].draw(np.random.default_rng(s)) for s in range(200)]
    assert {(d.legs, d.joints_per_leg, d.torso) for d in draws} == set(KINDS)  # every kind is drawn
    assert all(LEGGED_TRAIN_SEEDS[0] <= d.seed <= LEGGED_TRAIN_SEEDS[1] for d in draws)


@pytest.mark.parametrize("legs, joints, torso", KINDS)
def test_every_kind_is_a_tree_of_legs_whose_descriptions_agree(legs, joints, torso):
    body = LeggedBody(legs, joints, torso, 3)
    model = body.model()
    tree = KinematicTree.from_mujoco(model)
    assert tree.num_joints == legs * joints and tree.root_link == "torso"
    assert (tree.parents == -1).sum() == legs  # every leg hangs off the torso
    d = mujoco_descriptions(model)
    np.testing.assert_allclose(urdf_descriptions(robot_urdf(model)), d, atol=1e-9)
    left, right = d[0 :: 2 * joints], d[joints :: 2 * joints]  # the first joints of left and right legs
    np.testing.assert_allclose(left[:, 1], -right[:, 1], atol=1e-6)  # mirror images
    assert (left[:, 1] > 0).all()


def test_ant_stands_where_the_constant_says_and_healthy_heights_follow_the_standing_height():
    assert settled_height(ant_model()) == pytest.approx(ANT_STANDING_HEIGHT, abs=1e-3)
    np.testing.assert_allclose(np.array(HEALTHY_FRACTIONS) * ANT_STANDING_HEIGHT, (0.2, 1.0))  # Ant-v5's
    body = LeggedBody(8, 2, "long", 5)
    env = MorphCentipedeEnv(body=body)
    assert env.healthy_z_range == pytest.approx(tuple(f * body.standing_height for f in HEALTHY_FRACTIONS))
    env.reset(options={"leg_pairs": 3})  # back to a centipede: Ant-v5's range again
    assert env.healthy_z_range == (0.2, 1.0) and env.body_label == "centipede-3"


@pytest.mark.parametrize("legs, joints, torso", KINDS)
def test_every_kind_stands_at_zero_action_and_stays_finite_when_jerked(legs, joints, torso):
    """The fast version of ``bench/check_body_stability.py --legged``."""
    body = LeggedBody(legs, joints, torso, 11)
    env = MorphCentipedeEnv(body=body, terminate_when_unhealthy=False)
    env.reset(seed=0)
    for _ in range(150):
        env.step(np.zeros(env.num_joints))
        assert env.is_healthy and not env.unstable
    env.reset(seed=1)
    for step in range(150):
        env.step(np.full(env.num_joints, 1.0 if step % 2 else -1.0))
        assert not env.unstable
    assert np.isfinite(env.data.qpos).all()


def test_a_legged_spec_steps_vectorised_with_twelve_globals_and_restores_exactly():
    env = SwimmerVecEnv(4, "legged:4-8x2-3,centipede:2", seed=3)
    rng = np.random.default_rng(0)
    labels = set()
    for _ in range(60):
        step = env.step(rng.uniform(-1, 1, (4, env.max_joints)).astype(np.float32))
        labels |= {e.body for e in step.episodes}
    obs = env.observations()
    assert obs.global_feats.shape == (4, 12) and env.max_joints == 24
    meta, arrays = env.get_state()
    other = SwimmerVecEnv(4, "legged:4-8x2-3,centipede:2", seed=99)
    other.set_state(meta, arrays)
    actions = rng.uniform(-1, 1, (4, env.max_joints)).astype(np.float32)
    a, b = env.step(actions), other.step(actions)
    assert np.array_equal(a.obs.joint_pos, b.obs.joint_pos) and np.array_equal(a.reward, b.reward)


def test_garbled_legged_specs_parse_or_say_why_not():
    import random

    rng = random.Random(51)
    legs = ["4", "6", "8", "4-8", "5-8", "5", "0", "8-4", "99999", "", "-1"]
    joints = ["2", "3", "2-3", "1", "4", ""]
    torsos = ["", "", ":round", ":long", ":wide", ":ant"]
    seeds = ["", ":s0", ":s5-9", ":s1000-1099", ":s9-5", ":s", ":s0-9999999999"]

    def garbled() -> str:
        spec = f"legged:{rng.choice(legs)}x{rng.choice(joints)}{rng.choice(torsos)}{rng.choice(seeds)}"
        if rng.random() < 0.3:  # a character dropped or added
            at = rng.randrange(len(spec))
            spec = spec[:at] + rng.choice(["", "x", ":", "-", ",", "7"]) + spec[at + 1 :]
        return spec

    outcomes = {"read": 0, "refused": 0}
    for _ in range(2000):
        spec = garbled()
        try:
            mix = parse_bodies(spec)
        except ValueError as err:
            assert str(err) and "\n" not in str(err)
            outcomes["refused"] += 1
            continue
        assert str(parse_bodies(str(mix))) == str(mix)
        for item in mix.items:
            if isinstance(item, LeggedFamily):
                body = item.draw(np.random.default_rng(0))
                assert body.legs in LEGGED_LEGS and body.joints_per_leg in LEGGED_JOINTS_PER_LEG
        outcomes["read"] += 1
    assert min(outcomes.values()) > 50, outcomes
