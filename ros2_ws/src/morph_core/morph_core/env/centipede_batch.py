"""Centipedes of one size stepped side by side for an evaluation: ``SwimmerBatch``'s interface (``size``,
``num_joints``, ``parents``, ``advance``, ``root_x``, ``write_observation``) over one ``MorphCentipedeEnv`` per episode.

``advance`` reports an episode's end where ``SwimmerBatch`` reports divergence: a centipede that falls
(Ant-v5's health rule) or blows up ends there, as in training. One env per centipede rather than one
``mujoco.batch`` call: the reward reads the root's ``xpos`` and contact forces after each step, and an
evaluation is not the hot loop.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from morph_core.env.centipede import MorphCentipedeEnv
from morph_core.env.swimmer_env import MorphSwimmerEnv


class CentipedeBatch:
    """``len(seeds)`` centipedes of ``leg_pairs`` leg pairs, centipede k reset with ``seeds[k]`` (as
    ``MorphCentipedeEnv(leg_pairs=leg_pairs).reset(seed=seeds[k])``); or ``leg_pairs`` another walker body
    (``env.legged_model.LeggedBody``, a user's MJCF: ``MorphCentipedeEnv(body=...)``)."""

    def __init__(self, leg_pairs, seeds: Sequence[int]):
        if len(seeds) < 1:
            raise ValueError("a batch needs at least one centipede")
        options = None
        if isinstance(leg_pairs, int):
            self.envs = [MorphCentipedeEnv(leg_pairs=leg_pairs) for _ in seeds]
        elif getattr(leg_pairs, "task", "walker") == "swimmer":  # a user's planar MJCF: the swimmer's task
            self.envs, options = [MorphSwimmerEnv() for _ in seeds], {"body": leg_pairs}
        else:
            self.envs = [MorphCentipedeEnv(body=leg_pairs) for _ in seeds]
        for env, seed in zip(self.envs, seeds, strict=True):
            env.reset(seed=int(seed), options=options)
        first = self.envs[0]
        self.size, self.num_joints, self.tree, self.parents = len(seeds), first.num_joints, first.tree, first.parents
        self.dt = first.dt

    def advance(self, actions: np.ndarray, ids: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """One control step of the centipedes ``ids`` (all if None), one row of ``num_joints`` applied actions
        each: their rewards and whether their episodes ended (fell, or blew up)."""
        rows = range(self.size) if ids is None else ids
        outcomes = [self.envs[k].advance(np.asarray(a, dtype=np.float64)) for k, a in zip(rows, actions, strict=True)]
        return np.array([r for r, _ in outcomes]), np.array([t for _, t in outcomes], dtype=bool)

    def root_x(self) -> np.ndarray:
        """Every centipede's root x position (Ant-v5's ``x_position``: the free joint's), metres."""
        return np.array([env.data.qpos[0] for env in self.envs])

    def write_observation(self, joint_pos: np.ndarray, joint_vel: np.ndarray, global_feats: np.ndarray) -> None:
        """Every centipede's graph observation into its row (12 global features, a swimmer's 4; wider rows keep
        zeros)."""
        width = 4 if isinstance(self.envs[0], MorphSwimmerEnv) else 12
        for k, env in enumerate(self.envs):
            env.write_observation(joint_pos[k], joint_vel[k], global_feats[k, :width])
