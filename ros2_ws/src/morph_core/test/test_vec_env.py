"""The vectorised swimmers: stepping on several threads changes nothing, results stay in env order."""

import numpy as np
import pytest

from morph_core.env.reward import applied_action
from morph_core.env.swimmer_env import MorphSwimmerEnv
from morph_core.env.vec_env import EnvThreads, SwimmerVecEnv
from morph_core.policy.chains import pad_observations


def test_threads_return_results_in_the_order_asked():
    threads = EnvThreads(3)
    try:
        assert threads.map(lambda i: i * i, [5, 1, 4, 2, 3, 0, 6]) == [25, 1, 16, 4, 9, 0, 36]
        assert threads.map(lambda i: i, []) == []
    finally:
        threads.close()
    with pytest.raises(ValueError, match="num_threads"):
        EnvThreads(0)


def test_two_threads_step_the_swimmers_exactly_as_one():
    # Short episodes, so resets (chain lengths redrawn) and truncations happen within the test.
    envs = [SwimmerVecEnv(5, (2, 6), seed=3, max_episode_steps=7, num_threads=k) for k in (1, 2)]
    rng = np.random.default_rng(0)
    ended = 0
    try:
        for _ in range(20):
            actions = rng.uniform(-1, 1, (5, 6)).astype(np.float32)
            a, b = (e.step(actions) for e in envs)
            for field in ("reward", "terminated", "truncated"):
                np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
            for field in ("joint_pos", "joint_vel", "global_feats", "num_joints"):
                np.testing.assert_array_equal(getattr(a.obs, field), getattr(b.obs, field))
            assert a.final_obs.keys() == b.final_obs.keys() and a.episodes == b.episodes
            ended += len(a.episodes)
        assert ended >= 10  # every swimmer was reset (and redrew its length) along the way
    finally:
        for e in envs:
            e.close()


def test_the_vector_env_gives_gymnasium_steps_numbers_bit_for_bit():
    """Its swimmers step with ``advance`` and write their rows in place; plain Gymnasium ``step`` calls and
    ``pad_observations`` on the same seeds give the same rewards, observations and resets, bit for bit."""
    vec = SwimmerVecEnv(4, (2, 6), seed=11, max_episode_steps=9)
    plain = [MorphSwimmerEnv(num_joints=(2, 6)) for _ in range(4)]
    obs = [env.reset(seed=11 + i)[0] for i, env in enumerate(plain)]
    steps = np.zeros(4, int)
    rng = np.random.default_rng(1)
    # Every 5th action goes beyond the motors' range: both clip it to [-1, 1].
    for t in range(30):
        for got, want in zip(_arrays(vec.observations()), pad_observations(obs, 6), strict=True):
            np.testing.assert_array_equal(got, want)
        actions = rng.uniform(-1.5 if t % 5 == 0 else -1, 1.5 if t % 5 == 0 else 1, (4, 6)).astype(np.float32)
        result = vec.step(actions)
        for i, env in enumerate(plain):
            o, r, term, _, _ = env.step(applied_action(actions[i, : env.num_joints]))
            steps[i] += 1
            assert result.reward[i] == r and result.terminated[i] == term
            if steps[i] == 9:
                assert result.truncated[i]
                for key in ("joint_pos", "joint_vel", "global"):
                    np.testing.assert_array_equal(result.final_obs[i][key], o[key])
                o, steps[i] = env.reset()[0], 0
            obs[i] = o
    with pytest.raises(ValueError, match="NaN or inf"):
        vec.step(np.full((4, 6), np.nan, np.float32))
    vec.close()


def _arrays(p):
    return p.joint_pos, p.joint_vel, p.global_feats, p.num_joints


# -- centipedes ------------------------------------------------------------------------------------------------
def test_centipedes_step_with_twelve_globals_fall_and_reset():
    from morph_core.env.centipede import MorphCentipedeEnv

    envs = SwimmerVecEnv(2, "centipede:2-3", seed=3)
    assert envs.global_features == 12 and envs.max_joints == 12
    obs = envs.observations()
    assert obs.global_feats.shape == (2, 12)
    # row 0 is MorphCentipedeEnv(leg_pairs=(2, 3)) reset with seed 3, to the bit
    ref = MorphCentipedeEnv(leg_pairs=(2, 3))
    ref_obs, info = ref.reset(seed=3)
    n = info["leg_pairs"] * 4
    assert obs.num_joints[0] == n and np.array_equal(obs.global_feats[0], ref_obs["global"].astype(np.float32))
    rng = np.random.default_rng(0)
    labels, terminated = set(), 0
    for _ in range(200):
        actions = rng.uniform(-1, 1, (2, 12)).astype(np.float32)
        if ref is not None:
            ref_obs, r, term, _, _ = ref.step(applied_action(actions[0, :n]).astype(np.float64))
        step = envs.step(actions)
        if ref is not None:
            assert step.reward[0] == r and step.terminated[0] == term
            if term:
                assert np.array_equal(step.final_obs[0]["global"], ref_obs["global"])
                ref = None
            else:
                assert np.array_equal(step.obs.global_feats[0], ref_obs["global"].astype(np.float32))
        terminated += int(step.terminated.sum())
        labels |= {e.body for e in step.episodes}
        assert (step.obs.joint_pos[np.arange(12) >= step.obs.num_joints[:, None]] == 0).all()
    assert terminated > 0 and labels <= {"centipede-2", "centipede-3"} and labels


@pytest.mark.parametrize("spec", ["centipede:2-3", "2-3,y:1x1,centipede:2"])
def test_a_restored_centipede_run_goes_on_bit_for_bit(spec):
    envs = SwimmerVecEnv(3, spec, seed=1, max_episode_steps=50)  # time limits too, inside the test
    rng = np.random.default_rng(1)
    for _ in range(40):
        envs.step(rng.uniform(-1, 1, (3, envs.max_joints)).astype(np.float32))
    meta, arrays = envs.get_state()
    again = SwimmerVecEnv(3, spec, seed=77, max_episode_steps=50)
    again.set_state(meta, arrays)
    pairs = zip(envs.observations().arrays(), again.observations().arrays(), strict=True)
    assert all(np.array_equal(a, b) for a, b in pairs)
    ended = 0
    for _ in range(80):
        actions = rng.uniform(-1, 1, (3, envs.max_joints)).astype(np.float32)
        a, b = envs.step(actions), again.step(actions)
        assert np.array_equal(a.reward, b.reward) and np.array_equal(a.terminated, b.terminated)
        assert all(np.array_equal(x, y) for x, y in zip(a.obs.arrays(), b.obs.arrays(), strict=True))
        assert a.episodes == b.episodes
        ended += len(a.episodes)
    assert ended > 0  # the draws after a reset (the generators' states) were restored too


def test_mixed_specs_pad_a_swimmers_globals():
    envs = SwimmerVecEnv(4, "2,centipede:2", seed=0)
    obs = envs.observations()
    swimmers = obs.num_joints == 2
    assert swimmers.any() and (~swimmers).any()
    assert (obs.global_feats[swimmers, 4:] == 0).all() and (obs.global_feats[~swimmers, 5] > 0.5).all()  # z


def test_a_step_without_copies_hands_out_the_rows_the_envs_write():
    envs = SwimmerVecEnv(3, (2, 5), seed=0, max_episode_steps=4)
    again = SwimmerVecEnv(3, (2, 5), seed=0, max_episode_steps=4)
    rng = np.random.default_rng(1)
    try:
        for _ in range(9):  # resets on the way
            actions = rng.uniform(-1, 1, (3, 5)).astype(np.float32)
            live, copied = envs.step(actions, copy_obs=False), again.step(actions)
            assert live.obs is envs.live_observations()
            for got, want in zip(live.obs.arrays(), copied.obs.arrays(), strict=True):
                np.testing.assert_array_equal(got, want)
            np.testing.assert_array_equal(live.reward, copied.reward)
            assert live.episodes == copied.episodes
    finally:
        envs.close()
        again.close()
