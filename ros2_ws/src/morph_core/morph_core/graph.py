"""The joint graph of a swimmer chain, batched over chains of different lengths.

Links are nodes (link 0 is the torso), joints are edges: joint j connects
link j (parent) and link j+1 (child) and carries the joint state
(angle, angular velocity) as its edge attribute. A batch of chains is held
padded to its longest chain, ``J`` joints, with a validity mask; nothing
per-graph is built in Python, so a forward pass costs the same whatever
mix of lengths it holds.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

NUM_GLOBAL_FEATURES = 4  # yaw, yaw rate, vx, vy of the torso frame
NUM_EDGE_FEATURES = 2  # joint angle, joint angular velocity


@dataclass(frozen=True)
class ChainBatch:
    """B chains padded to J joints.

    joint_pos, joint_vel: [B, J] float32, zero beyond each chain's end.
    global_feats: [B, 4] float32.
    num_joints: [B] int64.
    mask: [B, J] bool, True where the joint exists.
    """

    joint_pos: torch.Tensor
    joint_vel: torch.Tensor
    global_feats: torch.Tensor
    num_joints: torch.Tensor
    mask: torch.Tensor

    @property
    def batch_size(self) -> int:
        return self.joint_pos.shape[0]

    @property
    def max_joints(self) -> int:
        return self.joint_pos.shape[1]

    @property
    def edge_attr(self) -> torch.Tensor:
        """[B, J, 2] joint states, the edge attributes."""
        return torch.stack([self.joint_pos, self.joint_vel], dim=-1)

    @classmethod
    def from_padded(cls, joint_pos, joint_vel, global_feats, num_joints, trim: bool = True) -> ChainBatch:
        """Build from padded arrays or tensors; ``trim`` drops padding beyond the longest chain."""
        pos = torch.as_tensor(joint_pos, dtype=torch.float32)
        vel = torch.as_tensor(joint_vel, dtype=torch.float32)
        glob = torch.as_tensor(global_feats, dtype=torch.float32)
        n = torch.as_tensor(num_joints, dtype=torch.int64)
        if pos.ndim != 2 or vel.shape != pos.shape:
            raise ValueError(f"joint_pos/joint_vel must both be [B, J], got {tuple(pos.shape)}, {tuple(vel.shape)}")
        if glob.shape != (pos.shape[0], NUM_GLOBAL_FEATURES) or n.shape != (pos.shape[0],):
            raise ValueError(
                f"global_feats must be [B, {NUM_GLOBAL_FEATURES}] and num_joints [B] for B={pos.shape[0]}, "
                f"got {tuple(glob.shape)}, {tuple(n.shape)}"
            )
        if n.numel() and (int(n.min()) < 1 or int(n.max()) > pos.shape[1]):
            raise ValueError(f"num_joints must be in 1..{pos.shape[1]}, got {n.tolist()}")
        if trim and n.numel():
            j = int(n.max())
            pos, vel = pos[:, :j], vel[:, :j]
        mask = torch.arange(pos.shape[1]).unsqueeze(0) < n.unsqueeze(1)
        # Zero the padding so nothing beyond a chain's end can leak into sums.
        return cls(pos * mask, vel * mask, glob, n, mask)

    @classmethod
    def from_observations(cls, observations: Sequence[dict]) -> ChainBatch:
        """Batch graph-mode observations of ``MorphSwimmer-v0`` (dicts with joint_pos, joint_vel, global)."""
        n = np.array([len(o["joint_pos"]) for o in observations], dtype=np.int64)
        j = int(n.max()) if len(n) else 0
        pos = np.zeros((len(n), j), dtype=np.float32)
        vel = np.zeros((len(n), j), dtype=np.float32)
        for i, o in enumerate(observations):
            pos[i, : n[i]] = o["joint_pos"]
            vel[i, : n[i]] = o["joint_vel"]
        glob = np.array([o["global"] for o in observations], dtype=np.float32).reshape(len(n), NUM_GLOBAL_FEATURES)
        return cls.from_padded(pos, vel, glob, n)

    def select(self, index: torch.Tensor) -> ChainBatch:
        """The sub-batch at ``index`` (e.g. a minibatch), trimmed to its own longest chain."""
        return ChainBatch.from_padded(
            self.joint_pos[index], self.joint_vel[index], self.global_feats[index], self.num_joints[index]
        )
