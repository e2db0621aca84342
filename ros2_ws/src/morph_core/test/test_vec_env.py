"""The vectorised swimmers: stepping on several threads changes nothing, results stay in env order."""

import numpy as np
import pytest

from morph_core.env.vec_env import EnvThreads, SwimmerVecEnv


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
