"""Deterministic evaluation of a policy on chosen chain lengths, all episodes stepped as one batch.

The mean action comes from the NumPy form of the policy (``policy.numpy_actor``, tested equal to the
torch policy to 1e-5): one batched forward pass per step, without torch's per-operation overhead.
"""

from __future__ import annotations

from functools import partial

import numpy as np

from morph_core.env.reward import applied_action
from morph_core.env.swimmer_env import MorphSwimmerEnv
from morph_core.env.vec_env import MAX_EPISODE_STEPS, EnvThreads
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
    width = max(lengths)
    # The swimmers' observations, padded, one row each (written in place after every step: no per-step dicts).
    pos, vel = np.zeros((len(envs), width), np.float32), np.zeros((len(envs), width), np.float32)
    glob, num_joints = np.zeros((len(envs), 4), np.float32), np.array(keys, dtype=np.int64)
    for k, env in enumerate(envs):
        env.reset(seed=seed + k % episodes)
        env.write_observation(pos[k], vel[k], glob[k])
    returns = np.zeros(len(envs))
    alive = np.ones(len(envs), dtype=bool)
    threads = EnvThreads(num_threads)
    actor = policy if isinstance(policy, NumpyPolicy) else NumpyPolicy(policy)

    def step(applied: np.ndarray, rows: dict[int, int] | None, i: int) -> tuple[float, bool]:
        outcome = envs[i].advance(applied[i if rows is None else rows[i], : keys[i]])
        envs[i].write_observation(pos[i], vel[i], glob[i])
        return outcome

    try:
        for _ in range(max_steps):
            idx = np.flatnonzero(alive)
            if idx.size == 0:
                break
            if idx.size == len(envs):  # every swimmer still going (the usual case): its row is its index
                mean, rows = actor.mean_actions(pos, vel, glob, num_joints), None
            else:
                mean = actor.mean_actions(pos[idx], vel[idx], glob[idx], num_joints[idx])
                rows = {int(i): row for row, i in enumerate(idx)}
            # clipped and cast for all swimmers in one call each, the outcomes added up as arrays
            outcomes = threads.map(partial(step, applied_action(mean).astype(np.float64), rows), idx.tolist())
            returns[idx] += np.array([r for r, _ in outcomes])
            alive[idx] = ~np.array([terminated for _, terminated in outcomes])
    finally:
        threads.close()
    keys_arr = np.array(keys)
    return {n: returns[keys_arr == n] for n in lengths}
