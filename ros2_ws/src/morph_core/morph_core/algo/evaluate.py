"""Deterministic evaluation of a policy on chosen bodies (chain lengths, trees), all episodes stepped as one batch.

The mean action comes from the NumPy form of the policy (``policy.numpy_actor``, tested equal to the
torch policy to 1e-5): one batched forward pass per step, without torch's per-operation overhead.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from morph_core.env.bodies import Centipede, is_walker
from morph_core.env.centipede_batch import CentipedeBatch
from morph_core.env.mjcf_body import MjcfBody
from morph_core.env.model import swimmer_model
from morph_core.env.reward import applied_action
from morph_core.env.swimmer_batch import SwimmerBatch
from morph_core.env.vec_env import MAX_EPISODE_STEPS, model_descriptions
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.tree import KinematicTree

Body = int | KinematicTree | Centipede
"""a chain length, a tree, or a centipede (an episode of it ends when it falls)"""


@dataclass(frozen=True)
class Episodes:
    """One body's evaluation episodes, an entry per episode."""

    returns: np.ndarray
    steps: np.ndarray
    """control steps the episode lasted (``max_steps`` unless it ended early: a fall, a blow-up)"""
    distance: np.ndarray
    """the root's x displacement from reset to the episode's end, metres (forward is +x for both families):
    what tells walking or swimming from standing or drifting where the returns alone do not (of a swimmer whose
    physics blew up: where MuJoCo's reset left it, as the env's ``x_position`` says)"""


def evaluate_policy(
    policy,
    bodies: Sequence[Body],
    episodes: int,
    seed: int = 10_000,
    max_steps: int = MAX_EPISODE_STEPS,
    num_threads: int = 1,
) -> dict[Body, np.ndarray]:
    """Return per body the ``episodes`` returns of the policy's mean action (``evaluate_episodes``'
    returns)."""
    results = evaluate_episodes(policy, bodies, episodes, seed, max_steps, num_threads)
    return {body: result.returns for body, result in results.items()}


def evaluate_episodes(
    policy,
    bodies: Sequence[Body],
    episodes: int,
    seed: int = 10_000,
    max_steps: int = MAX_EPISODE_STEPS,
    num_threads: int = 1,
) -> dict[Body, Episodes]:
    """Return per body (as given: a chain length, a ``KinematicTree`` or a ``Centipede``) the ``episodes``
    episodes of the policy's mean action: returns, lengths and distances.

    ``policy``: a torch ``GraphActorCritic``, a ``weights.PolicyWeights`` or a ``NumpyPolicy``.
    Episode k of every body starts from reset seed ``seed + k``, so every
    checkpoint faces the same initial states. One forward pass per step serves
    all ``len(bodies) * episodes`` swimmers, and the swimmers of a body step in
    one MuJoCo call (``SwimmerBatch``, on ``num_threads`` threads).
    """
    bodies = list(dict.fromkeys(bodies))  # a body asked twice is evaluated once
    seeds = [seed + k for k in range(episodes)]
    groups = [
        CentipedeBatch(body.leg_pairs, seeds)
        if isinstance(body, Centipede)
        else CentipedeBatch(body, seeds)
        if is_walker(body) or isinstance(body, MjcfBody)
        else SwimmerBatch(body, seeds, num_threads)
        for body in bodies
    ]
    actor = policy if isinstance(policy, NumpyPolicy) else NumpyPolicy(policy)
    # The swimmers' observations, padded, one row each; a body's swimmers are rows g*episodes.. of group g.
    count, width = len(bodies) * episodes, max(g.num_joints for g in groups)
    pos, vel = np.zeros((count, width), np.float32), np.zeros((count, width), np.float32)
    global_width = actor.global_features  # the policy's; a swimmer's 4 features padded to it
    if global_width < 12 and any(is_walker(b) for b in bodies):
        raise ValueError(f"this policy reads {global_width} global features, a walker 12: train it on walkers")
    glob = np.zeros((count, global_width), np.float32)
    num_joints = np.repeat(np.array([g.num_joints for g in groups], dtype=np.int64), episodes)
    parents = np.full((count, width), -1, np.int64)
    rows = [slice(g * episodes, (g + 1) * episodes) for g in range(len(bodies))]
    for swimmers, r in zip(groups, rows, strict=True):
        parents[r, : swimmers.num_joints] = swimmers.parents
    desc = None  # the joints' descriptions, for a policy that reads them
    if getattr(actor, "joint_features", 0):  # (an actor without the attribute reads none)
        desc = np.zeros((count, width, actor.joint_features), np.float32)
        for swimmers, r in zip(groups, rows, strict=True):
            model = swimmers.envs[0].model if isinstance(swimmers, CentipedeBatch) else swimmer_model(swimmers.parents)
            desc[r, : swimmers.num_joints] = model_descriptions(model)
    described = {} if desc is None else {"joint_desc": desc}
    for swimmers, r in zip(groups, rows, strict=True):
        swimmers.write_observation(pos[r], vel[r], glob[r])
    returns, steps = np.zeros(count), np.zeros(count, dtype=np.int64)
    x_start = np.concatenate([g.root_x() for g in groups])
    alive = np.ones(count, dtype=bool)
    applied = np.zeros((count, width))
    for _ in range(max_steps):
        idx = np.flatnonzero(alive)
        if idx.size == 0:
            break
        if idx.size == count:  # every swimmer still going (the usual case)
            applied = applied_action(actor.mean_actions(pos, vel, glob, num_joints, parents, **described)).astype(
                np.float64
            )
        else:  # the ended swimmers' rows keep their last actions and are not stepped
            applied[idx] = applied_action(
                actor.mean_actions(
                    pos[idx],
                    vel[idx],
                    glob[idx],
                    num_joints[idx],
                    parents[idx],
                    **({} if desc is None else {"joint_desc": desc[idx]}),
                )
            )
        for swimmers, r in zip(groups, rows, strict=True):
            going = np.flatnonzero(alive[r])
            if going.size == swimmers.size:
                reward, diverged = swimmers.advance(applied[r, : swimmers.num_joints])
            elif going.size:
                reward, diverged = swimmers.advance(applied[r][going, : swimmers.num_joints], going)
            else:
                continue
            returns[r][going] += reward
            steps[r][going] += 1
            alive[r][going] = ~diverged
            swimmers.write_observation(pos[r], vel[r], glob[r])
    distance = np.concatenate([g.root_x() for g in groups]) - x_start  # an ended episode's root was not stepped since
    return {
        body: Episodes(returns[r].copy(), steps[r].copy(), distance[r].copy())
        for body, r in zip(bodies, rows, strict=True)
    }
