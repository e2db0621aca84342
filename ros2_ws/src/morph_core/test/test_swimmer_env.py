"""The variable-chain swimmer: Swimmer-v5 equivalence, chain sampling, bad input."""

import gymnasium
import mujoco
import numpy as np
import pytest

import morph_core  # noqa: F401  (registers MorphSwimmer-v0)
from morph_core.env.model import MAX_JOINTS, swimmer_mjcf, swimmer_model


@pytest.mark.parametrize("seed", [0, 123])
def test_two_joints_flat_is_swimmer_v5(seed):
    ref = gymnasium.make("Swimmer-v5")
    env = gymnasium.make("MorphSwimmer-v0", num_joints=2, observation_mode="flat")
    obs_ref, _ = ref.reset(seed=seed)
    obs, _ = env.reset(seed=seed)
    np.testing.assert_allclose(obs, obs_ref, rtol=0, atol=1e-9)
    actions = np.random.default_rng(seed).uniform(-1.5, 1.5, size=(1000, 2))  # beyond ctrlrange too
    for t, a in enumerate(actions):
        o_ref, r_ref, term_ref, trunc_ref, info_ref = ref.step(a)
        o, r, term, trunc, info = env.step(a)
        np.testing.assert_allclose(o, o_ref, rtol=0, atol=1e-9, err_msg=f"step {t}")
        assert abs(r - r_ref) <= 1e-9
        assert abs(info["x_velocity"] - info_ref["x_velocity"]) <= 1e-9
        assert (term, trunc) == (term_ref, trunc_ref)
    assert trunc and trunc_ref  # both end at the 1000-step limit


@pytest.mark.parametrize("n", [1, 2, 7, 20, MAX_JOINTS])
def test_chain_dimensions(n):
    env = gymnasium.make("MorphSwimmer-v0", num_joints=n)
    obs, info = env.reset(seed=0)
    m = env.unwrapped.model
    assert (m.nq, m.nv, m.nu) == (n + 3, n + 3, n)
    assert env.action_space.shape == (n,)
    assert obs["joint_pos"].shape == obs["joint_vel"].shape == (n,)
    assert obs["global"].shape == (4,)
    np.testing.assert_array_equal(obs["edge_index"], [np.arange(n), np.arange(1, n + 1)])
    assert info["num_joints"] == n
    obs, *_ = env.step(np.zeros(n))
    assert env.observation_space.contains(obs)
    flat = gymnasium.make("MorphSwimmer-v0", num_joints=n, observation_mode="flat")
    assert flat.reset(seed=0)[0].shape == (2 * n + 4,)


def test_segments_have_swimmer_v5_geometry():
    m = swimmer_model(9)
    # every segment weighs the same as Swimmer-v5's, and the torso frame sits at x = 0
    masses = m.body_mass[1:]
    np.testing.assert_allclose(masses, masses[0])
    np.testing.assert_allclose(m.body_mass[1], swimmer_model(2).body_mass[1])
    np.testing.assert_allclose(m.body_pos[1], 0.0)
    np.testing.assert_allclose(m.jnt_range[3:], np.tile(np.deg2rad([-100.0, 100.0]), (9, 1)))
    np.testing.assert_allclose(m.actuator_gear[:, 0], 150.0)
    assert m.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4


@pytest.mark.parametrize("n", [2, 9])
def test_collision_detection_off_changes_no_trajectory(n):
    # The flag is only safe while no geom can collide; with detection back on,
    # the same controls must give the same states bit for bit.
    m = swimmer_model(n)
    assert m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT
    assert not m.geom_contype.any() and not m.geom_conaffinity.any()
    on = mujoco.MjModel.from_xml_string(swimmer_mjcf(n))
    on.opt.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    states, limited = [], 0
    for model in (m, on):
        data = mujoco.MjData(model)
        for t in range(2000):
            data.ctrl[:] = np.sin(0.05 * t + np.arange(n))
            mujoco.mj_step(model, data)
            limited += data.nefc > 0
        states.append(np.concatenate([data.qpos, data.qvel]))
    assert limited > 0  # the joint limits were hit: the constraint solver ran with detection on and off
    np.testing.assert_array_equal(states[0], states[1])


def test_models_are_cached_and_built_from_strings():
    assert swimmer_model(5) is swimmer_model(5)
    assert "motor5_rot" in swimmer_mjcf(5) and "motor6_rot" not in swimmer_mjcf(5)


def test_chain_length_drawn_from_range_with_seeded_rng():
    def lengths(seed):
        env = gymnasium.make("MorphSwimmer-v0", num_joints=(2, 10))
        out = [env.reset(seed=seed)[1]["num_joints"]]
        out += [env.reset()[1]["num_joints"] for _ in range(199)]
        return out

    a, b = lengths(7), lengths(7)
    assert a == b  # reproducible from the seed
    assert set(a) == set(range(2, 11))  # every length in 2..10 (inclusive) appears
    assert lengths(8) != a


def test_action_space_follows_chain():
    env = gymnasium.make("MorphSwimmer-v0", num_joints=(3, 4))
    for _ in range(20):
        obs, info = env.reset()
        n = info["num_joints"]
        assert env.action_space.shape == (n,) and obs["joint_pos"].shape == (n,)
        env.step(env.action_space.sample())


def test_reset_option_forces_chain_length():
    env = gymnasium.make("MorphSwimmer-v0", num_joints=(2, 10))
    _, info = env.reset(seed=0, options={"num_joints": 15})
    assert info["num_joints"] == 15 and env.unwrapped.model.nu == 15


def test_travelling_wave_swims_forward():
    # An open-loop travelling wave must move every chain forward: checks the
    # physics (viscous thrust) end to end, not just shapes.
    from morph_core.env.gait import TravellingWave, run_gait

    for n in (2, 5, 10):
        speed = run_gait(n, TravellingWave(), seconds=20.0, seed=0)
        assert speed > 0.02, (n, speed)


@pytest.mark.parametrize(
    "kwargs, error",
    [
        ({"num_joints": 0}, ValueError),
        ({"num_joints": 65}, ValueError),
        ({"num_joints": (5, 3)}, ValueError),
        ({"num_joints": (0, 3)}, ValueError),
        ({"num_joints": 2.5}, TypeError),
        ({"num_joints": "six"}, TypeError),
        ({"observation_mode": "pixels"}, ValueError),
    ],
)
def test_bad_arguments_raise_clear_errors(kwargs, error):
    from morph_core.env.swimmer_env import MorphSwimmerEnv

    with pytest.raises(error, match="num_joints|observation_mode"):
        MorphSwimmerEnv(**kwargs)


def test_bad_actions_raise_and_leave_state_untouched():
    from morph_core.env.swimmer_env import MorphSwimmerEnv

    env = MorphSwimmerEnv(num_joints=3)
    env.reset(seed=0)
    qpos = env.data.qpos.copy()
    for bad in (np.zeros(2), np.zeros(4), np.zeros((3, 1)), np.array([0.0, np.nan, 0.0]), np.array([np.inf, 0, 0])):
        with pytest.raises(ValueError, match="action"):
            env.step(bad)
    np.testing.assert_array_equal(env.data.qpos, qpos)


def test_diverging_physics_ends_the_episode_instead_of_silently_resetting():
    from morph_core.env.swimmer_env import MorphSwimmerEnv

    env = MorphSwimmerEnv(num_joints=64)
    env.reset(seed=0)
    # Huge joint speeds make the explicit integrator blow up within a step or two.
    env.data.qvel[3:] = 1e6
    terminated = info = None
    for _ in range(3):
        _, _, terminated, _, info = env.step(np.zeros(64))
        if terminated:
            break
    assert terminated and info["physics_unstable"]
