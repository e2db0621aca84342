"""Deterministic evaluation of a policy on chosen chain lengths, all episodes stepped as one batch.

The mean action comes from the NumPy form of the policy (``policy.numpy_actor``, tested equal to the
torch policy to 1e-5): one batched forward pass per step, without torch's per-operation overhead.
"""

from __future__ import annotations

from functools import partial

import numpy as np

from morph_core.env.swimmer_env import MorphSwimmerEnv
from morph_core.env.vec_env import MAX_EPISODE_STEPS, EnvThreads
from morph_core.policy.chains import pad_observations
from morph_core.policy.numpy_actor import NumpyPolicy


def evaluate_policy(
    policy,
    lengths: list[int],
    episodes: int,
    seed: int = 10_000,
    max_steps: int = MAX_EPISODE_STEPS,
    num_threads: int = 1,
) -> dict[int, np.ndarray]:
    """Return per chain length the ``episodes`` returns of the policy's mean action.

    ``policy``: a torch ``GraphActorCritic``, a ``weights.PolicyWeights`` or a ``NumpyPolicy``.
    Episode k of every length starts from reset seed ``seed + k``, so every
    checkpoint faces the same initial states. One forward pass per step serves
    all ``len(lengths) * episodes`` swimmers.
    """
    keys = [n for n in lengths for _ in range(episodes)]
    envs = [MorphSwimmerEnv(num_joints=n) for n in keys]
    obs = [env.reset(seed=seed + k % episodes)[0] for k, env in enumerate(envs)]
    returns = np.zeros(len(envs))
    alive = np.ones(len(envs), dtype=bool)
    threads = EnvThreads(num_threads)
    actor = policy if isinstance(policy, NumpyPolicy) else NumpyPolicy(policy)
    width = max(lengths)

    def step(actions: dict[int, np.ndarray], i: int) -> None:
        o, r, terminated, _, _ = envs[i].step(np.clip(actions[i], -1.0, 1.0))
        obs[i] = o
        returns[i] += r
        alive[i] = not terminated

    try:
        for _ in range(max_steps):
            idx = np.flatnonzero(alive)
            if idx.size == 0:
                break
            mean = actor.forward(*pad_observations([obs[i] for i in idx], width))[0]
            actions = {i: mean[row, : envs[i].num_joints] for row, i in enumerate(idx)}
            threads.map(partial(step, actions), idx)
    finally:
        threads.close()
    keys_arr = np.array(keys)
    return {n: returns[keys_arr == n] for n in lengths}
