"""Deterministic evaluation of a policy on chosen chain lengths, all episodes stepped as one batch.

The mean action comes from the NumPy form of the policy (``policy.numpy_actor``, tested equal to the
torch policy to 1e-5): one batched forward pass per step, without torch's per-operation overhead.
"""

from __future__ import annotations

import numpy as np

from morph_core.env.reward import applied_action
from morph_core.env.swimmer_batch import SwimmerBatch
from morph_core.env.vec_env import MAX_EPISODE_STEPS
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
    all ``len(lengths) * episodes`` swimmers, and the swimmers of a length step in
    one MuJoCo call (``SwimmerBatch``, on ``num_threads`` threads).
    """
    lengths = list(dict.fromkeys(lengths))  # a length asked twice is evaluated once
    groups = [SwimmerBatch(n, [seed + k for k in range(episodes)], num_threads) for n in lengths]
    # The swimmers' observations, padded, one row each; a length's swimmers are rows g*episodes.. of group g.
    count, width = len(lengths) * episodes, max(lengths)
    pos, vel = np.zeros((count, width), np.float32), np.zeros((count, width), np.float32)
    glob, num_joints = np.zeros((count, 4), np.float32), np.repeat(np.array(lengths, dtype=np.int64), episodes)
    rows = [slice(g * episodes, (g + 1) * episodes) for g in range(len(lengths))]
    for swimmers, r in zip(groups, rows, strict=True):
        swimmers.write_observation(pos[r], vel[r], glob[r])
    returns = np.zeros(count)
    alive = np.ones(count, dtype=bool)
    applied = np.zeros((count, width))
    actor = policy if isinstance(policy, NumpyPolicy) else NumpyPolicy(policy)
    for _ in range(max_steps):
        idx = np.flatnonzero(alive)
        if idx.size == 0:
            break
        if idx.size == count:  # every swimmer still going (the usual case)
            applied = applied_action(actor.mean_actions(pos, vel, glob, num_joints)).astype(np.float64)
        else:  # the ended swimmers' rows keep their last actions and are not stepped
            applied[idx] = applied_action(actor.mean_actions(pos[idx], vel[idx], glob[idx], num_joints[idx]))
        for swimmers, r in zip(groups, rows, strict=True):
            going = np.flatnonzero(alive[r])
            if going.size == swimmers.size:
                reward, diverged = swimmers.advance(applied[r, : swimmers.num_joints])
            elif going.size:
                reward, diverged = swimmers.advance(applied[r][going, : swimmers.num_joints], going)
            else:
                continue
            returns[r][going] += reward
            alive[r][going] = ~diverged
            swimmers.write_observation(pos[r], vel[r], glob[r])
    return {n: returns[r].copy() for n, r in zip(lengths, rows, strict=True)}
