"""MorphCentipede-v0: bodies of 2..16 leg pairs, Ant-v5's task, graph observations, and Gymnasium's Ant-v5 itself
as the reference (bit for bit on Ant's body, and Ant-v5's own step code run on the centipedes' models)."""

import math

import gymnasium
import mujoco
import numpy as np
import pytest
import torch
from gymnasium.envs.mujoco.ant_v5 import AntEnv

import morph_core.env.registration  # noqa: F401  (registers the ids)
from morph_core.env.centipede import GLOBAL_FEATURES, MorphCentipedeEnv
from morph_core.env.centipede_model import (
    ANT_ACTUATOR_ORDER,
    MAX_LEG_PAIRS,
    ant_model,
    centipede_joint_names,
    centipede_mjcf,
    centipede_model,
)
from morph_core.env.urdf import robot_urdf
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.chains import ChainBatch
from morph_core.policy.config import PolicyConfig
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.tree import KinematicTree, read_urdf

ENV_ID = "MorphCentipede-v0"


def _legs_parents(n: int) -> list[int]:
    return [-1 if j % 2 == 0 else j - 1 for j in range(4 * n)]  # each ankle below its hip, each hip off the root


@pytest.mark.parametrize("n", range(2, 11))
def test_every_size_builds_and_steps_with_four_joints_per_leg_pair(n):
    env = gymnasium.make(ENV_ID, leg_pairs=n)
    obs, info = env.reset(seed=n)
    u = env.unwrapped
    assert env.action_space.shape == (4 * n,)
    assert u.tree.num_joints == 4 * n and u.tree.names == centipede_joint_names(n)
    assert u.tree.root_link == "torso_0"
    assert list(obs["parents"]) == _legs_parents(n)
    assert obs["joint_pos"].shape == obs["joint_vel"].shape == (4 * n,)
    assert obs["global"].shape == (len(GLOBAL_FEATURES),) == (12,)
    assert env.observation_space.contains(obs)
    assert info["leg_pairs"] == n and info["body"] == f"centipede-{n}"
    assert u.model is centipede_model(n)  # compiled once per size, shared
    for _ in range(5):
        obs, reward, terminated, truncated, info = env.step(np.zeros(4 * n))
        assert np.isfinite(reward) and not terminated and not truncated
    # the joint state is the model's hinges after the free root, in tree order
    np.testing.assert_array_equal(obs["joint_pos"], u.data.qpos[7:])
    np.testing.assert_array_equal(obs["joint_vel"], u.data.qvel[6:])
    assert u.dt == pytest.approx(0.05)  # Ant-v5's: 5 x 0.01 s


def test_a_centipede_stands_on_its_legs_with_no_action():
    env = gymnasium.make(ENV_ID, leg_pairs=6)
    env.reset(seed=0)
    for _ in range(200):  # 10 s
        obs, _, terminated, _, info = env.step(np.zeros(24))
        assert not terminated
    assert 0.3 < obs["global"][5] < 0.75  # settled on its feet, inside the healthy range (0.2, 1.0)
    assert obs["global"][8] == pytest.approx(-1.0, abs=0.02)  # upright
    assert abs(info["x_velocity"]) < 0.05


def test_seeded_resets_redraw_sizes_reproducibly():
    def sizes_and_states(seed):
        env = gymnasium.make(ENV_ID, leg_pairs=(2, 10))
        out = []
        obs, info = env.reset(seed=seed)
        for _ in range(20):
            out.append((info["leg_pairs"], obs["joint_pos"].tobytes(), obs["global"].tobytes()))
            obs, info = env.reset()
        return out

    first = sizes_and_states(5)
    assert first == sizes_and_states(5)
    sizes = [s for s, *_ in first]
    assert len(set(sizes)) >= 4 and min(sizes) >= 2 and max(sizes) <= 10
    assert [s for s, *_ in sizes_and_states(6)] != sizes
    # a size forced by the options draws nothing for the size
    env = gymnasium.make(ENV_ID, leg_pairs=(2, 10))
    obs, info = env.reset(seed=1, options={"leg_pairs": 7})
    assert info["leg_pairs"] == 7 and obs["joint_pos"].shape == (28,)


def test_reward_terms_are_ant_v5s():
    env = gymnasium.make(ENV_ID, leg_pairs=3)
    env.reset(seed=2)
    u = env.unwrapped
    rng = np.random.default_rng(0)
    for _ in range(10):
        x_before = u.data.xpos[1, 0]
        a = rng.uniform(-1, 1, 12)
        _, reward, terminated, _, info = env.step(a)
        assert info["x_velocity"] == (u.data.xpos[1, 0] - x_before) / 0.05
        assert info["reward_forward"] == info["x_velocity"]
        assert info["reward_ctrl"] == pytest.approx(-0.5 * np.sum(a**2), rel=1e-15)
        assert info["reward_survive"] == (0.0 if terminated else 1.0)
        # contact cost: 5e-4 |clip(cfrc_ext, -1, 1)|^2, at most 6 entries of 1 per body
        assert -5e-4 * 6 * u.model.nbody <= info["reward_contact"] <= 0.0
        assert info["reward_contact"] == pytest.approx(-5e-4 * np.sum(np.clip(u.data.cfrc_ext, -1, 1) ** 2))
        terms = info["reward_forward"] + info["reward_survive"] + info["reward_ctrl"] + info["reward_contact"]
        assert reward == pytest.approx(terms, abs=1e-12)


def test_contact_forces_are_skipped_only_when_nothing_reads_them():
    paid = gymnasium.make(ENV_ID, leg_pairs=2)
    free = gymnasium.make(ENV_ID, leg_pairs=2, contact_cost_weight=0.0)
    for env in (paid, free):
        env.reset(seed=4)
    for _ in range(20):
        a = np.full(8, 0.3)
        o1, r1, *_, i1 = paid.step(a)
        o2, r2, *_, i2 = free.step(a)
        # the same physics (rnePostConstraint only fills force fields), the cost alone missing
        np.testing.assert_array_equal(paid.unwrapped.data.qpos, free.unwrapped.data.qpos)
        assert i2["reward_contact"] == 0.0 and r1 == pytest.approx(r2 + i1["reward_contact"], abs=1e-12)
    assert not free.unwrapped.data.cfrc_ext.any()


def test_an_unhealthy_body_ends_the_episode():
    env = gymnasium.make(ENV_ID, leg_pairs=4)
    env.reset(seed=0)
    u = env.unwrapped
    u.data.qpos[2] = 1.5  # thrown above the healthy range (0.2, 1.0)
    mujoco.mj_forward(u.model, u.data)
    _, _, terminated, _, info = env.step(np.zeros(16))
    assert terminated and info["reward_survive"] == 0.0 and not info["physics_unstable"]
    # kept going when asked not to terminate, as Ant-v5's terminate_when_unhealthy=False
    env = gymnasium.make(ENV_ID, leg_pairs=4, terminate_when_unhealthy=False)
    env.reset(seed=0)
    env.unwrapped.data.qpos[2] = 1.5
    _, _, terminated, _, info = env.step(np.zeros(16))
    assert not terminated and info["reward_survive"] == 0.0


def test_a_flipped_torso_shows_in_the_global_features():
    # Upside down (half a turn about x): gravity points up in the root's frame. Ant-v5's health rule reads the
    # height alone, so a body on its back at a healthy height goes on (the same as Ant-v5; docs/centipedes.md).
    env = gymnasium.make(ENV_ID, leg_pairs=3, reset_noise_scale=0.0)
    env.reset(seed=0)
    u = env.unwrapped
    u.data.qpos[3:7] = [0.0, 1.0, 0.0, 0.0]
    mujoco.mj_forward(u.model, u.data)
    obs, *_ = env.step(np.zeros(12))
    assert obs["global"][8] == pytest.approx(1.0, abs=1e-3)  # gravity_z in the body frame


def test_a_state_that_blows_up_ends_the_episode():
    env = gymnasium.make(ENV_ID, leg_pairs=2)
    env.reset(seed=0)
    env.unwrapped.data.qvel[6] = 1e30  # MuJoCo resets such a state and warns
    _, _, terminated, _, info = env.step(np.zeros(8))
    assert terminated and info["physics_unstable"]


def test_global_features_mean_what_they_say():
    env = gymnasium.make(ENV_ID, leg_pairs=2, reset_noise_scale=0.0)
    obs, _ = env.reset(seed=0)
    expected = dict.fromkeys(GLOBAL_FEATURES, 0.0) | {"z": 0.75, "gravity_z": -1.0}
    np.testing.assert_array_equal(obs["global"], [expected[k] for k in GLOBAL_FEATURES])
    u = env.unwrapped
    # turned 90 degrees to the left (about z), moving forward along its own x and turning at 0.5 rad/s
    u.data.qpos[3:7] = [math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)]
    u.data.qvel[0:6] = [0.0, 1.0, 0.0, 0.0, 0.0, 0.5]  # world linear, body angular (MuJoCo's free joint)
    glob = u._observation()["global"]
    feats = dict(zip(GLOBAL_FEATURES, glob, strict=True))
    assert feats["yaw"] == pytest.approx(math.pi / 2)
    assert feats["yaw_rate"] == pytest.approx(0.5) and feats["wz"] == pytest.approx(0.5)
    assert (feats["vx"], feats["vy"]) == (0.0, 1.0)
    np.testing.assert_allclose([feats["gravity_x"], feats["gravity_y"], feats["gravity_z"]], [0, 0, -1], atol=1e-15)
    # the padded row a vectorised loop writes holds the same values
    pos, vel, g = np.ones(12), np.ones(12), np.zeros(12)
    u.write_observation(pos, vel, g)
    np.testing.assert_array_equal(g, glob)
    np.testing.assert_array_equal(pos[:8], u.data.qpos[7:])
    assert not pos[8:].any() and not vel[8:].any()


# -- Gymnasium's Ant-v5 -----------------------------------------------------------------------------------------
def _ant_action_order(tree: KinematicTree) -> list[int]:
    return [tree.names.index(name) for name in ANT_ACTUATOR_ORDER]


@pytest.mark.parametrize("seed, scale", [(3, 1.0), (4, 1.0), (5, 0.2)])
def test_the_ant_layout_is_ant_v5_bit_for_bit(seed, scale):
    # The same bodies (ant.xml, written by this code's leg writer), the same reset noise, step, reward,
    # termination and observation: equal to the last bit until the episode ends (a fall, or 1000 steps).
    ant = gymnasium.make("Ant-v5")
    mine = gymnasium.make(ENV_ID, leg_pairs=2, layout="ant", observation_mode="flat")
    o_ant, _ = ant.reset(seed=seed)
    o_mine, _ = mine.reset(seed=seed)
    np.testing.assert_array_equal(o_mine, o_ant)
    to_ant = _ant_action_order(mine.unwrapped.tree)
    rng = np.random.default_rng(seed)
    steps = 0
    while True:
        a = scale * rng.uniform(-1.2, 1.2, 8)  # beyond the ctrl range too: MuJoCo clamps, the cost does not
        o_ant, r_ant, term_ant, trunc_ant, i_ant = ant.step(a[to_ant])
        o_mine, r_mine, term_mine, trunc_mine, i_mine = mine.step(a)
        steps += 1
        np.testing.assert_array_equal(o_mine, o_ant)
        np.testing.assert_array_equal(mine.unwrapped.data.qpos, ant.unwrapped.data.qpos)
        assert (r_mine, term_mine, trunc_mine) == (r_ant, term_ant, trunc_ant)
        for key, value in i_ant.items():
            assert i_mine[key] == value, key
        if term_ant or trunc_ant:
            break
    assert steps > 10
    if scale < 1:
        assert trunc_ant and steps == 1000  # a gentle policy keeps it up for the whole episode


def test_the_ant_layouts_model_is_ant_xmls():
    ref, mine = gymnasium.make("Ant-v5").unwrapped.model, ant_model()
    fields = ("body_mass", "body_inertia", "body_pos", "body_ipos", "jnt_axis", "jnt_range", "dof_armature")
    fields += ("dof_damping", "geom_size", "geom_friction", "geom_margin", "actuator_gear", "actuator_trnid")
    for field in fields:
        np.testing.assert_array_equal(getattr(mine, field), getattr(ref, field), err_msg=field)


@pytest.mark.parametrize("n", [2, 3])
def test_ant_v5s_own_step_on_a_centipede_pays_what_the_env_pays(n, tmp_path):
    # Ant-v5's code (its step, reward, termination, observation) on the centipede's own model, loaded from a
    # file as Gymnasium loads models: the env is Ant-v5's task on another body, to the last bit.
    path = tmp_path / f"centipede{n}.xml"
    path.write_text(centipede_mjcf(n))
    ref = gymnasium.wrappers.TimeLimit(AntEnv(xml_file=str(path)), max_episode_steps=1000)
    mine = gymnasium.make(ENV_ID, leg_pairs=n, observation_mode="flat")
    o_ref, _ = ref.reset(seed=n)
    o_mine, _ = mine.reset(seed=n)
    np.testing.assert_array_equal(o_mine, o_ref)
    rng = np.random.default_rng(n)
    for _ in range(300):
        a = rng.uniform(-0.3, 0.3, 4 * n)  # tree order is the actuators' order for centipedes
        o_ref, r_ref, term_ref, trunc_ref, i_ref = ref.step(a)
        o_mine, r_mine, term_mine, trunc_mine, i_mine = mine.step(a)
        np.testing.assert_array_equal(o_mine, o_ref)
        assert (r_mine, term_mine, trunc_mine) == (r_ref, term_ref, trunc_ref)
        assert all(i_mine[k] == v for k, v in i_ref.items())
        assert not term_ref  # gentle actions: it stays up, so every step of the 300 is compared


def test_a_centipede_of_two_pairs_has_ants_legs_not_ants_body():
    # The documented differences from Ant at two leg pairs: two torso spheres (Ant: one), legs sideways in
    # pairs (Ant: diagonal), mirrored hip and ankle signs; the same per-leg masses and joint ranges.
    cent, ant = centipede_model(2), ant_model()
    leg_bodies = [b for b in range(1, cent.nbody) if not cent.body(b).name.startswith("torso")]
    np.testing.assert_allclose(sorted(cent.body_mass[leg_bodies]), sorted(ant.body_mass[2:]))
    assert cent.nbody == ant.nbody + 1  # the second segment
    np.testing.assert_allclose(cent.body_mass.sum() - ant.body_mass.sum(), ant.body_mass[1])  # one more torso
    hips = [cent.joint(f"{s}_hip_0").range for s in ("left", "right")]
    ankles = [cent.joint(f"{s}_ankle_0").range for s in ("left", "right")]
    np.testing.assert_allclose(hips, np.radians([[-30, 30]] * 2))
    np.testing.assert_allclose(ankles, np.radians([[30, 70]] * 2))


# -- bad arguments ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "bad",
    [0, -1, 1, MAX_LEG_PAIRS + 1, 10**9, 2**70, 2.0, 3.5, "3", b"3", None, True, (5, 3), (2,), (2, 3, 4), ("a", 3),
     [2, 2.5], (0, 4), (2, 10**6), {2: 3}, np.float64(3.0), float("nan")],
)  # fmt: skip
def test_bad_leg_pairs_are_a_clear_value_error(bad):
    with pytest.raises(ValueError, match="leg_pairs"):
        MorphCentipedeEnv(leg_pairs=bad)


def test_good_leg_pairs_of_other_integer_types():
    assert MorphCentipedeEnv(leg_pairs=np.int64(3)).leg_pairs == 3
    assert MorphCentipedeEnv(leg_pairs=[np.int32(2), 4]).leg_pair_range == (2, 4)


def test_other_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="ant layout has 2 leg pairs"):
        MorphCentipedeEnv(leg_pairs=3, layout="ant")
    with pytest.raises(ValueError, match="layout"):
        MorphCentipedeEnv(layout="spider")
    with pytest.raises(ValueError, match="observation_mode"):
        MorphCentipedeEnv(observation_mode="pixels")
    with pytest.raises(ValueError, match="frame_skip"):
        MorphCentipedeEnv(frame_skip=0)
    env = MorphCentipedeEnv(leg_pairs=2)
    with pytest.raises(ValueError, match="leg_pairs"):
        env.reset(seed=0, options={"leg_pairs": 99})
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(8,\)"):
        env.step(np.zeros(12))
    with pytest.raises(ValueError, match="NaN"):
        env.step(np.full(8, np.nan))


# -- the tree, its URDF, and a policy on it ----------------------------------------------------------------------
@pytest.mark.parametrize("n", [2, 3, 7])
def test_the_tree_from_mujoco_is_the_tree_its_urdf_reads_back(n):
    model = centipede_model(n)
    tree = KinematicTree.from_mujoco(model)
    robot = read_urdf(robot_urdf(model))
    assert robot.tree == tree  # names, parents and root link
    assert tree.names == centipede_joint_names(n) and list(tree.parents) == _legs_parents(n)
    # the welded segments and each leg's hip link (on no joint in MuJoCo: fixed in the URDF)
    welded = {f"torso_{k}_fixed" for k in range(1, n)} | {
        f"{s}_leg_{k}_fixed" for k in range(n) for s in ("left", "right")
    }
    assert robot.unactuated == welded


def test_a_policy_with_twelve_globals_acts_on_mixed_sizes():
    env = gymnasium.make(ENV_ID, leg_pairs=(2, 6))
    observations = [env.reset(seed=s)[0] for s in range(5)]
    assert len({len(o["joint_pos"]) for o in observations}) > 1
    torch.manual_seed(0)
    policy = GraphActorCritic(PolicyConfig(global_features=len(GLOBAL_FEATURES)))
    batch = ChainBatch.from_observations(observations)
    with torch.no_grad():
        mean, _, value = policy(batch)
    assert value.shape == (5,) and torch.isfinite(mean).all()
    fast = NumpyPolicy(policy)
    for b, o in enumerate(observations):
        single = fast.mean(o["joint_pos"], o["joint_vel"], o["global"], o["parents"])
        np.testing.assert_allclose(single, mean[b, : len(single)].numpy(), atol=1e-5)
