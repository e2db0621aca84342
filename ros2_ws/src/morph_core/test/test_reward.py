"""The one reward definition equals what the env pays, bit for bit, and its hand-computed value."""

import numpy as np
import pytest

from morph_core.env.reward import swimmer_reward
from morph_core.env.swimmer_env import MorphSwimmerEnv


def test_reward_by_hand():
    # 0.2 m in 0.04 s = 5 m/s forward, control cost 1e-4 * (1 + 4) = 5e-4
    assert swimmer_reward(1.0, 1.2, 0.04, np.array([1.0, -2.0])) == pytest.approx(5.0 - 5e-4, abs=1e-12)


@pytest.mark.parametrize("num_joints", [1, 2, 7])
def test_env_reward_is_swimmer_reward(num_joints):
    env = MorphSwimmerEnv(num_joints=num_joints)
    env.reset(seed=3)
    rng = np.random.default_rng(0)
    x = float(env.data.qpos[0])
    for _ in range(50):
        a = rng.uniform(-1, 1, num_joints)
        _, reward, _, _, info = env.step(a)
        assert reward == swimmer_reward(x, info["x_position"], env.dt, a)  # exact, not approx
        x = info["x_position"]
