"""Samples of an older policy in the update: the proximal policy's log-probs and Gaussian, and the exact KL
from it after an update.

Off-policy data (a bag recorded by an older policy) uses the decoupled objective of Hilton et al. 2022,
"Batch size-invariance for policy optimization": the ratio is taken against the proximal policy pi_prox (the
policy as the update starts, ``proximal_log_probs``), r = pi_theta / pi_prox, and each sample's policy term is
weighted by the truncated importance weight min(pi_prox / pi_behav, c) (c = ``proximal_weight_cap``, as
V-trace's rho-bar; ``minibatches.update_terms``). Without proximal log-probs (on-policy: pi_prox = pi_behav)
there is no weight at all, and the loss is PPO's own, bit for bit. The ``behaviour`` objective
(``update_config.OFF_POLICY_OBJECTIVES``) takes PPO's own loss on off-policy data too: the ratio against the
policy that acted, no weight.
"""

from __future__ import annotations

import dataclasses

import torch

from morph_core.algo.batch import RolloutBatch
from morph_core.algo.trust_region import LossContext, kl_per_joint
from morph_core.policy.actor_critic import GraphActorCritic


@torch.no_grad()
def proximal_means(policy: GraphActorCritic, batch: RolloutBatch, chunk: int = 1024):
    """([N, J] Gaussian means, log-std) of ``policy`` as it is now (the proximal policy) on ``batch``'s
    states, zero beyond each chain; J = the batch's width."""
    mean = torch.zeros(batch.size, batch.max_joints)
    for start in range(0, batch.size, chunk):
        stop = min(start + chunk, batch.size)
        chains, _ = batch.minibatch(torch.arange(start, stop))
        mean[start:stop, : chains.max_joints] = policy(chains)[0]
    return mean, policy.log_std.detach().clone()


@torch.no_grad()
def exact_kl(policy: GraphActorCritic, batch: RolloutBatch, old_mean, old_log_std, chunk: int = 1024) -> torch.Tensor:
    """[N] KL(pi_old || policy) of each sample over its joints, exact, pi_old the Gaussian
    (``old_mean`` [N, J], ``old_log_std``) of ``proximal_means``."""
    out = []
    for start in range(0, batch.size, chunk):
        index = torch.arange(start, min(start + chunk, batch.size))
        chains, actions = batch.minibatch(index)
        mean, log_std, _ = policy(chains)
        ctx = LossContext(
            log_ratio=None,
            advantages=None,
            clip_range=None,
            num_joints=chains.num_joints,
            mean=mean,
            log_std=log_std,
            actions=actions,
            mask=chains.mask,
            old_mean=old_mean[index, : chains.max_joints],
            old_log_std=old_log_std,
        )
        out.append(kl_per_joint(ctx).sum(1))
    return torch.cat(out)


@torch.no_grad()
def proximal_log_probs(policy: GraphActorCritic, batch: RolloutBatch, chunk: int = 1024) -> torch.Tensor:
    """[N] log-probability of each sample's action under ``policy`` as it is now (the proximal policy)."""
    out = []
    for start in range(0, batch.size, chunk):
        chains, actions = batch.minibatch(torch.arange(start, min(start + chunk, batch.size)))
        out.append(policy.log_prob(chains, actions))
    return torch.cat(out) if out else torch.zeros(0)


def with_proximal(policy: GraphActorCritic, batch: RolloutBatch) -> RolloutBatch:
    """``batch`` with its proximal log-probs computed by ``policy``: call it as the update starts."""
    return dataclasses.replace(batch, proximal_log_prob=proximal_log_probs(policy, batch))
