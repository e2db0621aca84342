"""Swimmers of one body (a chain length or a kinematic tree) stepped together in one MuJoCo call (``mujoco.batch``).

Each swimmer is one row of MuJoCo's batch state (integration state: time,
qpos, qvel, controls, warm start), stepped by MuJoCo's C loop instead of one
Python call per swimmer; MuJoCo documents, and ``test_swimmer_batch`` checks,
that the trajectories are bit for bit those of one ``MjData`` per swimmer.
Every swimmer starts where ``MorphSwimmerEnv.reset(seed=...)`` puts it, and its
reward is the env's (``reward.swimmer_reward``): this is the env's ``advance``
for many swimmers at once. The evaluation uses it (110 swimmers of 11 lengths,
every step); the training rollout keeps one env per swimmer, since its chain
lengths are redrawn at every reset.
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np
from mujoco.batch import Batch

from morph_core.env.reward import swimmer_reward
from morph_core.env.swimmer_env import DIVERGENCE_WARNING, MorphSwimmerEnv, write_graph_observation
from morph_core.policy.tree import KinematicTree

_STATE = mujoco.mjtState.mjSTATE_INTEGRATION


class SwimmerBatch:
    """``len(seeds)`` swimmers of one ``body``, swimmer k reset with ``seeds[k]``: ``body`` a chain length
    (``num_joints``) or a ``KinematicTree`` (reset as ``MorphSwimmerEnv.reset(options={"tree": body})``).
    ``tree`` and ``parents`` are the env's (the swimmer's joint names).

    ``num_threads`` is MuJoCo's: threads stepping the swimmers, the caller's included.
    """

    def __init__(self, body: int | KinematicTree, seeds: Sequence[int], num_threads: int = 1):
        if num_threads < 1:
            raise ValueError(f"num_threads must be >= 1, got {num_threads}")  # MuJoCo's 0 would take every core
        if len(seeds) < 1:
            raise ValueError("a batch needs at least one swimmer")
        if isinstance(body, KinematicTree):
            env, options = MorphSwimmerEnv(num_joints=body.num_joints), {"tree": body}
        else:
            env, options = MorphSwimmerEnv(num_joints=body), None
        env.reset(options=options)
        self.num_joints, self.size = env.num_joints, len(seeds)
        self.tree, self.parents = env.tree, env.parents
        self.frame_skip, self.dt = env.frame_skip, env.dt
        self._weights = (env.forward_reward_weight, env.ctrl_cost_weight)
        self._batch = Batch(env.model, self.size, nthread=num_threads, persistent=True)
        for k, seed in enumerate(seeds):
            env.reset(seed=int(seed), options=options)  # Swimmer-v5's reset noise, as every user of the env
            mujoco.mj_getState(env.model, env.data, self._batch.state[k], _STATE)
        self._qpos, self._qvel = self._batch.bind("qpos"), self._batch.bind("qvel")
        self._ctrl = self._batch.bind("ctrl")
        self._diverged = self._batch.warning[:, DIVERGENCE_WARNING, 1]  # MuJoCo's count of that warning

    def advance(self, actions: np.ndarray, ids: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """One control step of the swimmers ``ids`` (all if None): ``actions`` are their applied actions,
        one row each (``num_joints`` float64 entries). Returns their rewards and whether their physics
        diverged (``MorphSwimmerEnv.advance``, row by row); NaN or inf in an action raises ``ValueError``."""
        if not np.isfinite(actions).all():
            raise ValueError("an action contains NaN or inf")
        rows = slice(None) if ids is None else ids
        x_before, diverged_before = self._qpos[rows, 0].copy(), self._diverged[rows].copy()
        self._ctrl[rows] = actions
        self._batch.step(ids, nstep=self.frame_skip)
        reward = swimmer_reward(x_before, self._qpos[rows, 0], self.dt, actions, *self._weights)
        return reward, self._diverged[rows] > diverged_before

    def root_x(self) -> np.ndarray:
        """Every swimmer's root x position (Swimmer-v5's ``x_position``), metres."""
        return self._qpos[:, 0].copy()

    def write_observation(self, joint_pos: np.ndarray, joint_vel: np.ndarray, global_feats: np.ndarray) -> None:
        """Every swimmer's graph observation into its row of padded arrays (``size`` rows, as
        ``MorphSwimmerEnv.write_observation`` writes one)."""
        write_graph_observation(self._qpos, self._qvel, self.num_joints, joint_pos, joint_vel, global_feats)
