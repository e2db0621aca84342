"""What one update measured (``UpdateStats``): mean losses over its minibatches and the per-dimension ratio
statistics, pooled over its epochs and for the first and the last alone, reduced from its steps' parts in a
few operations after the loop (``update_stats``), off the steps' path; and their log columns."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from morph_core.algo.batch import RolloutBatch
from morph_core.algo.minibatches import MinibatchPart, UpdateTerms
from morph_core.algo.ppo import PerDimensionStats

EPOCH_TAGS = ("_first", "_last")
"""the per-epoch statistics' column tags: the update's first and last epoch"""


@dataclass
class UpdateStats:
    """What one update measured: mean losses over its minibatches and per-dimension ratio statistics,
    pooled over all epochs and for the first and the last epoch alone."""

    policy_loss: float
    value_loss: float
    entropy: float
    per_dim: PerDimensionStats
    epochs: int
    """epochs run (fewer than configured if the rule stopped early)"""
    first_epoch: PerDimensionStats | None = None
    """the statistics of the first epoch alone (its first minibatch has r = 1)"""
    last_epoch: PerDimensionStats | None = None
    """the statistics of the last epoch run alone (the one that drifted furthest)"""
    kl_beta: float = math.nan
    """the KL penalty's beta during this update (NaN for rules without it)"""

    def row(self, dims) -> dict[str, float]:
        """Log columns (``epoch_columns`` lists the ones beyond the pooled statistics): the losses,
        overall and per-dimension (``dims``) statistics, pooled and per epoch."""
        row = {
            "policy_loss": self.policy_loss,
            "value_loss": self.value_loss,
            "entropy": self.entropy,
            **self.per_dim.overall(),
            **self.per_dim.summary(dims),
            "epochs": self.epochs,
            "kl_beta": self.kl_beta,
        }
        for tag, stats in zip(EPOCH_TAGS, (self.first_epoch, self.last_epoch), strict=True):
            if stats is not None:
                row |= stats.overall(tag) | stats.summary(dims, tag)
        return row


def update_columns(dims) -> list[str]:
    """The log columns of ``UpdateStats.row`` per dimension (``<name>_d<d>``) and per epoch (``epoch_columns``):
    what every trainer's log has after its own columns."""
    return [*[f"{name}_d{d}" for name in PerDimensionStats.PER_DIM for d in dims], *epoch_columns(dims)]


def epoch_columns(dims) -> list[str]:
    """The log columns of ``UpdateStats.row`` beyond the pooled statistics: epochs run, beta, and the
    first and last epoch's statistics, overall and per dimension (``<name>_first_d<d>``)."""
    return [
        "epochs", "kl_beta",
        *[f"{name}{tag}" for tag in EPOCH_TAGS for name in PerDimensionStats.OVERALL],
        *[f"{name}{tag}_d{d}" for tag in EPOCH_TAGS for name in PerDimensionStats.PER_DIM for d in dims],
    ]  # fmt: skip


def update_stats(
    epochs: list[list[tuple[torch.Tensor, list[MinibatchPart]]]],
    batch: RolloutBatch,
    terms: UpdateTerms,
    clip_eps: float,
    kl_beta: torch.Tensor | None,
) -> UpdateStats:
    """The statistics of an update from its ``epochs``' steps, each a minibatch's indices and its parts (one per
    process, in rank order); ``clip_eps`` the base eps, ``kl_beta`` the KL penalty's beta during the update."""
    steps = [step for epoch in epochs for step in epoch]
    world = len(steps[0][1])
    all_parts = [p for _, parts in steps for p in parts]
    part_losses = torch.stack([torch.stack([getattr(p, k) for p in all_parts]) for k in MinibatchPart._fields[:3]], 1)
    mb_losses = sum(part_losses[rank::world] for rank in range(world))  # [steps, 3]: each step's parts added
    index = torch.cat([mb for mb, _ in steps])
    log_ratio = torch.cat([p.log_ratio for p in all_parts])
    if all_parts[0].clip_share is not None:
        clipped = torch.cat([p.clip_share for p in all_parts])
    else:
        clipped = terms.rule.clipped(log_ratio.exp(), terms.clip_range[index])
    stats = PerDimensionStats(batch.max_joints)
    stats.add(batch.num_joints[index], log_ratio, clipped, clip_eps)
    # Every epoch covers the batch once: the first and the last epoch are the first and last N entries.
    per_epoch = []
    for part in (slice(0, batch.size), slice(len(index) - batch.size, len(index))):
        epoch = PerDimensionStats(batch.max_joints)
        epoch.add(batch.num_joints[index[part]], log_ratio[part], clipped[part], clip_eps)
        per_epoch.append(epoch)
    pg_loss, v_loss, entropy = mb_losses.mean(0).tolist()
    beta = math.nan if kl_beta is None else float(kl_beta)
    return UpdateStats(pg_loss, v_loss, entropy, stats, len(epochs), *per_epoch, kl_beta=beta)
