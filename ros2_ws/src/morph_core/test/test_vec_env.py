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
