"""The samples an update takes: a ``RolloutBatch`` of mixed chains and trees, and each ``Minibatch`` of it
as the loss reads it.

Every data source (the simulator's rollouts, recorded bags, live topics) builds the same ``RolloutBatch``;
the update cuts it into minibatches (``algo.minibatches``). A ``Minibatch`` crosses the compiled boundary
whole: ``algo.compiled`` flattens a dataclass into its tensors and rebuilds it inside the graph, so the loss
reads its inputs by name, not by position.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from morph_core.constants import NUM_GLOBAL_FEATURES
from morph_core.policy.chains import ChainBatch
from morph_core.policy.index_plan import check_parents, is_chain


@dataclass(frozen=True)
class RolloutBatch:
    """N samples of chains of mixed length, padded to J joints; everything the update needs.

    Beyond each chain's end, joint states and actions must be zero (checked): minibatches are cut
    to their own longest chain, and only padding may be cut.
    """

    num_joints: torch.Tensor
    """[N] int64 chain length (action dimension) of each sample"""
    joint_pos: torch.Tensor
    """[N, J] float32 joint angles"""
    joint_vel: torch.Tensor
    """[N, J] float32 joint angular velocities"""
    global_feats: torch.Tensor
    """[N, G] float32 global features (G = the policy's ``global_features``: a swimmer's 4, torso yaw, yaw
    rate, vx, vy; a centipede's 12)"""
    actions: torch.Tensor
    """[N, J] float32 actions taken (before any clip to the motors' range)"""
    log_prob: torch.Tensor
    """[N] log-probability of the action under the behaviour policy (the one that acted)"""
    values: torch.Tensor
    """[N] value estimates of the states (for explained variance)"""
    advantages: torch.Tensor
    """[N] advantage estimates"""
    returns: torch.Tensor
    """[N] value targets"""
    proximal_log_prob: torch.Tensor | None = None
    """[N] log-probability under the proximal policy (``off_policy.proximal_log_probs``), for off-policy data;
    None for on-policy data, where it equals ``log_prob``"""
    parents: torch.Tensor | None = None
    """[N, J] int64 parent joint of each joint (-1: the torso, and at padding; ``policy.index_plan``); None
    when every sample is a chain, however given (checked at construction; chains-only parents become None, so
    that the update takes its chain path)"""
    joint_desc: torch.Tensor | None = None
    """[N, J, D] float32 each joint's description (``policy.joint_description``; zero at padding) for a policy
    that reads them (``PolicyConfig.joint_features`` = D); None: none"""

    def __post_init__(self):
        n, j = self.joint_pos.shape if self.joint_pos.ndim == 2 else (None, None)
        if n is None:
            raise ValueError(f"joint_pos must be [N, J], got {tuple(self.joint_pos.shape)}")
        g = self.global_feats.shape[1] if self.global_feats.ndim == 2 and self.global_feats.shape[1] else 0
        shapes = {  # the global width is the data's (a swimmer's 4, a centipede's 12); the policy checks its own
            "num_joints": (n,), "joint_vel": (n, j), "global_feats": (n, g or NUM_GLOBAL_FEATURES), "actions": (n, j),
            "log_prob": (n,), "values": (n,), "advantages": (n,), "returns": (n,),
        }  # fmt: skip
        if self.proximal_log_prob is not None:
            shapes["proximal_log_prob"] = (n,)
        for name, shape in shapes.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ValueError(f"RolloutBatch.{name} must be {list(shape)} for N={n}, J={j}, got {list(got)}")
        if self.num_joints.dtype != torch.int64:
            raise ValueError(f"RolloutBatch.num_joints must be int64, got {self.num_joints.dtype}")
        if self.parents is not None:
            if tuple(self.parents.shape) != (n, j) or self.parents.dtype != torch.int64:
                raise ValueError(f"RolloutBatch.parents must be [{n}, {j}] int64, got {list(self.parents.shape)} "
                                 f"{self.parents.dtype}")  # fmt: skip
            mask = (torch.arange(j) < self.num_joints.unsqueeze(1)).numpy()
            parents = check_parents(self.parents.numpy(), mask)
            object.__setattr__(self, "parents", None if is_chain(parents, mask) else torch.from_numpy(parents))
        if self.joint_desc is not None:
            d = self.joint_desc
            if d.ndim != 3 or tuple(d.shape[:2]) != (n, j) or d.dtype != torch.float32:
                got = f"{list(d.shape)} {d.dtype}"
                raise ValueError(f"RolloutBatch.joint_desc must be [{n}, {j}, D] float32, got {got}")
            if not torch.isfinite(d).all():
                raise ValueError("RolloutBatch.joint_desc holds NaN or inf")
        if n and (int(self.num_joints.min()) < 1 or int(self.num_joints.max()) > j):
            raise ValueError(f"RolloutBatch.num_joints must be in 1..{j}")
        for name in [*shapes][1:]:
            if not torch.isfinite(getattr(self, name)).all():
                raise ValueError(f"RolloutBatch.{name} holds NaN or inf")
        padding = torch.arange(j) >= self.num_joints.unsqueeze(1)
        for name in ("joint_pos", "joint_vel", "actions"):
            if (getattr(self, name)[padding] != 0).any():
                raise ValueError(f"RolloutBatch.{name} is not zero beyond each chain's end")

    @property
    def size(self) -> int:
        return self.num_joints.shape[0]

    @property
    def max_joints(self) -> int:
        return self.joint_pos.shape[1]

    def minibatch(self, index: torch.Tensor) -> tuple[ChainBatch, torch.Tensor]:
        """The chains at ``index`` (padding trimmed to their longest chain) and their actions, cut alike."""
        rows = index.numpy()  # gathered in NumPy: this runs before every minibatch step
        num_joints = self.num_joints.numpy()[rows]
        width = int(num_joints.max()) if rows.size else 0
        pos, vel, actions = (x.numpy()[rows, :width] for x in (self.joint_pos, self.joint_vel, self.actions))
        # The padding is zero and the parents were checked at construction (-1 at padding), so
        # from_padded's checks and zeroing, and check_parents again, would change nothing (~15 us of a
        # step's gather, and the trees' check another ~1.5 us per sample row); whether the rows are all
        # chains is still asked, as it picks the network's path.
        mask = np.arange(width) < num_joints[:, None]
        tree = None
        if self.parents is not None:
            parents = self.parents.numpy()[rows, :width]
            tree = None if is_chain(parents, mask) else torch.from_numpy(parents)
        desc = (
            None
            if self.joint_desc is None
            else torch.from_numpy(np.ascontiguousarray(self.joint_desc.numpy()[rows, :width]))
        )
        arrays = (pos, vel, self.global_feats.numpy()[rows], num_joints, mask)
        return ChainBatch(*map(torch.from_numpy, arrays), tree, desc), torch.from_numpy(actions)


@dataclass(frozen=True)
class Minibatch:
    """One minibatch of B samples (or one process's part of one) as ``ppo.ppo_loss`` reads it, J its longest
    chain: the samples, what the ratio is taken against, and the proximal policy's Gaussian for the rules that
    use it. The argument of the compiled minibatch gradient (``learner.minibatch_gradient``); which optional
    fields are None is part of the layout a graph is compiled for."""

    chains: ChainBatch
    """the states, padding trimmed to the longest chain"""
    actions: torch.Tensor
    """[B, J] the actions taken, zero beyond each chain"""
    old_log_prob: torch.Tensor
    """[B] the log-probs the ratio is taken against (the proximal policy's, or the behaviour policy's)"""
    advantages: torch.Tensor
    """[B] advantages: raw (normalised within the loss), or already normalised over the whole minibatch"""
    returns: torch.Tensor
    """[B] value targets"""
    clip_range: torch.Tensor
    """[B] the rule's clip range per sample (``TrustRegionRule.clip_range``)"""
    weight: torch.Tensor | None = None
    """[B] each sample's importance weight on the policy term; None (on-policy data: no weight at all, not a
    weight of one)"""
    old_mean: torch.Tensor | None = None
    """[B, J] the proximal policy's means (rules with ``uses_old_gaussian``)"""
    old_log_std: torch.Tensor | None = None
    """the proximal policy's log standard deviation (rules with ``uses_old_gaussian``)"""
    kl_beta: torch.Tensor | None = None
    """the KL penalty's coefficient, a 0-dim tensor (rules with state ``kl_beta``)"""
    normalize_advantages: bool = True
    """normalise ``advantages`` within this minibatch; False for a part of a minibatch split over processes,
    whose advantages come normalised over the whole minibatch (``algo.minibatches``)"""
