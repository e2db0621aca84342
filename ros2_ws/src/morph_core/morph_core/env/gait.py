"""Open-loop travelling-wave gait: a policy-free baseline that swims any chain, and any tree by depth."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from morph_core.env.swimmer_env import MorphSwimmerEnv
from morph_core.policy.index_plan import joint_depths
from morph_core.policy.tree import KinematicTree


@dataclass(frozen=True)
class TravellingWave:
    """a_j(t) = amplitude * sin(2 pi frequency t - depth_j * phase_lag), a wave running from head to tail:
    down a chain joint by joint (depth_j = j), down every branch of a tree at once (depth_j = joints between
    joint j and the torso)."""

    amplitude: float = 1.0
    frequency: float = 0.5  # Hz
    phase_lag: float = 2 * np.pi / 5  # rad between a joint and its parent

    def __call__(self, t: float, num_joints: int, depth: np.ndarray | None = None) -> np.ndarray:
        """The actions at time ``t``; ``depth`` [num_joints] for a tree (``joint_depths``), None for a chain."""
        d = np.arange(num_joints) if depth is None else depth
        return self.amplitude * np.sin(2 * np.pi * self.frequency * t - d * self.phase_lag)


def run_gait(body: int | KinematicTree, gait: TravellingWave, seconds: float, seed: int = 0) -> float:
    """Swim a chain of ``body`` joints, or the tree ``body``, for ``seconds`` of sim time; return the mean
    forward speed of the torso (m/s)."""
    env = MorphSwimmerEnv(num_joints=body if isinstance(body, int) else body.num_joints)
    env.reset(seed=seed, options=None if isinstance(body, int) else {"tree": body})
    depth = None if env.tree.is_chain else joint_depths(env.parents)
    x0 = float(env.data.qpos[0])
    steps = int(round(seconds / env.dt))
    for k in range(steps):
        env.step(gait(k * env.dt, env.num_joints, depth))
    return (float(env.data.qpos[0]) - x0) / (steps * env.dt)
