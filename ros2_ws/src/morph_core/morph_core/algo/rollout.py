"""Collecting a rollout: the swimmers act under a NumPy snapshot of the policy, [T, E] arrays fill up.

The simulator trainer (``algo.train``) collects into one ``Rollout``; with
several processes (``algo.data_parallel``) each collects its own swimmers
into its columns of one rollout in shared memory.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from morph_core.algo.batch import RolloutBatch
from morph_core.constants import NUM_GLOBAL_FEATURES
from morph_core.env.vec_env import Episode, PaddedObs, SwimmerVecEnv
from morph_core.policy.chains import pad_descriptions, pad_observations
from morph_core.policy.numpy_actor import NumpyPolicy


def rollout_layout(
    steps: int, envs: int, max_joints: int, global_features: int = NUM_GLOBAL_FEATURES, joint_features: int = 0
) -> dict[str, tuple[tuple[int, ...], type]]:
    """Name -> (shape, dtype) of every array of a ``Rollout``; ``global_features`` the bodies' global width
    (``SwimmerVecEnv.global_features``: 4 for swimmers, 12 with centipedes); ``joint_features`` the width of
    the joints' descriptions a policy reads (``PolicyConfig.joint_features``; 0: no ``joint_desc`` array)."""
    T, E, J = steps, envs, max_joints
    described = {"joint_desc": ((T, E, J, joint_features), np.float32)} if joint_features else {}
    return described | {
        "joint_pos": ((T, E, J), np.float32), "joint_vel": ((T, E, J), np.float32),
        "global_feats": ((T, E, global_features), np.float32), "num_joints": ((T, E), np.int64),
        "parents": ((T, E, J), np.int64),  # each joint's parent joint (-1: the torso, and at padding)
        "actions": ((T, E, J), np.float32), "log_prob": ((T, E), np.float32),
        "rewards": ((T, E), np.float32), "values": ((T, E), np.float32),
        "terminated": ((T, E), np.bool_), "truncated": ((T, E), np.bool_),
        "final_values": ((T, E), np.float32),  # V(final obs) where a time limit cut the episode
        "last_value": ((E,), np.float32),  # V(obs after the last step), GAE's bootstrap
    }  # fmt: skip


class Rollout:
    """[T, E] storage of one rollout, padded to the largest body the families allow; NumPy while
    collecting, shared with torch (no copy) for the update."""

    def __init__(
        self,
        steps: int,
        envs: int,
        max_joints: int,
        alloc: Callable[..., np.ndarray] | None = None,
        global_features: int = NUM_GLOBAL_FEATURES,
        joint_features: int = 0,
    ):
        """``alloc(name, shape, dtype)`` gives each array (zeroed); by default ``np.zeros``."""
        self.joint_desc: np.ndarray | None = None
        layout = rollout_layout(steps, envs, max_joints, global_features, joint_features)
        for name, (shape, dtype) in layout.items():
            setattr(self, name, np.zeros(shape, dtype) if alloc is None else alloc(name, shape, dtype))

    def columns(self, lo: int, hi: int) -> Rollout:
        """The swimmers lo..hi-1 of this rollout: a rollout whose arrays are views into this one's."""
        part = object.__new__(Rollout)
        part.joint_desc = None
        for name in self.names():
            array = getattr(self, name)
            setattr(part, name, array[lo:hi] if array.ndim == 1 else array[:, lo:hi])
        return part

    def names(self) -> list[str]:
        """The names of this rollout's arrays (``rollout_layout``'s: ``joint_desc`` only with descriptions)."""
        return [name for name in rollout_layout(1, 1, 1, joint_features=1) if getattr(self, name) is not None]

    def batch(self, advantages: torch.Tensor, returns: torch.Tensor) -> RolloutBatch:
        def flat(x: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(x).flatten(0, 1)

        return RolloutBatch(
            num_joints=flat(self.num_joints),
            joint_pos=flat(self.joint_pos),
            joint_vel=flat(self.joint_vel),
            global_feats=flat(self.global_feats),
            actions=flat(self.actions),
            log_prob=flat(self.log_prob),
            values=flat(self.values),
            advantages=advantages.flatten(),
            returns=returns.flatten(),
            parents=flat(self.parents),
            joint_desc=None if self.joint_desc is None else flat(self.joint_desc),
        )


def collect(
    envs: SwimmerVecEnv, actor: NumpyPolicy, rollout: Rollout, obs: PaddedObs, generator: torch.Generator
) -> tuple[PaddedObs, list[Episode]]:
    """Fill ``rollout`` by acting from ``obs``; returns the observation after it and the finished episodes.

    The action noise comes from the run's torch generator, so a resumed run draws the same noise.
    ``rollout.last_value`` gets the value of the observation after the last step.
    """
    steps, num_envs, max_joints = rollout.actions.shape
    episodes: list[Episode] = []
    for t in range(steps):
        # The policy reads this step's observation where it is (``obs`` at first, then the rows the envs
        # write into: ``step(copy_obs=False)``), and the rollout keeps a copy of it: one copy per step, not two.
        pos, vel, glob, num_joints, parents = obs.arrays()
        rollout.joint_pos[t], rollout.joint_vel[t], rollout.global_feats[t] = pos, vel, glob
        rollout.num_joints[t], rollout.parents[t] = num_joints, parents
        if rollout.joint_desc is not None:
            rollout.joint_desc[t] = obs.joint_desc
        noise = torch.randn((num_envs, max_joints), generator=generator).numpy()
        rollout.actions[t], rollout.log_prob[t], rollout.values[t], _ = actor.act(
            pos, vel, glob, num_joints, noise, parents=parents, joint_desc=obs.joint_desc
        )
        step = envs.step(rollout.actions[t], copy_obs=False)
        rollout.rewards[t], rollout.terminated[t], rollout.truncated[t] = step.reward, step.terminated, step.truncated
        # A truncated episode would have gone on: GAE bootstraps it from the value of its final observation.
        rollout.final_values[t] = 0.0
        if step.final_obs:
            trunc = [i for i in step.final_obs if step.truncated[i]]
            if trunc:
                finals = [step.final_obs[i] for i in trunc]
                final = pad_observations(finals, max_joints, with_parents=True)
                desc = pad_descriptions(finals, max_joints)
                rollout.final_values[t, trunc] = actor.forward(*final[:4], parents=final[4], joint_desc=desc)[1]
            episodes += step.episodes
        obs = step.obs
    rollout.last_value[:] = actor.forward(*obs.arrays()[:4], parents=obs.parents, joint_desc=obs.joint_desc)[1]
    return envs.observations(), episodes
