"""PPO's pieces on mixed action dimensions: the minibatch loss, GAE, per-dimension statistics.

Every sample carries its own action dimension d (its chain's joint count).
The importance ratio is over the sample's joint action, r = exp(sum_j log
pi_new - log pi_old); how far it may move is the trust-region rule's
business (``algo.trust_region``), the rest of PPO is the same for every rule.
"""

from __future__ import annotations

import math
from itertools import pairwise
from typing import NamedTuple

import numpy as np
import torch

from morph_core.algo.batch import Minibatch
from morph_core.algo.trust_region import LossContext, TrustRegionRule, approx_kl


class LossTerms(NamedTuple):
    """What ``ppo_loss`` returns for one minibatch of B samples."""

    loss: torch.Tensor
    """the loss minimised: policy loss + vf_coef * value loss - ent_coef * entropy"""
    pg_loss: torch.Tensor
    v_loss: torch.Tensor
    entropy: torch.Tensor
    log_ratio: torch.Tensor
    """[B] log r of each sample over its joint action"""
    clip_share: torch.Tensor | None
    """[B] the rule's clip share per sample (``TrustRegionRule.clip_share``), or None"""


def ppo_loss(policy, mb: Minibatch, vf_coef: float, ent_coef: float, rule: TrustRegionRule) -> LossTerms:
    """PPO's loss on one minibatch ``mb`` (``batch.Minibatch``) under ``rule``, with advantages normalised
    within it (unless ``mb.normalize_advantages`` is False: a part of a minibatch split over processes gets its
    advantages already normalised over the whole minibatch, ``algo.minibatches``).

    ``policy`` is a GraphActorCritic. The ratio is taken against ``mb.old_log_prob`` (the proximal policy's,
    see ``algo.off_policy``); ``mb.weight`` weights each sample's policy term, or is None (on-policy data: no
    weight at all, not a weight of one). The rule's loss hook gets a ``trust_region.LossContext``.
    """
    chains, actions = mb.chains, mb.actions
    mean, log_std, value = policy(chains)
    log_ratio = policy.log_prob(chains, actions, mean) - mb.old_log_prob
    adv = normalized_advantages(mb.advantages) if mb.normalize_advantages else mb.advantages
    ctx = LossContext(
        log_ratio=log_ratio,
        advantages=adv,
        clip_range=mb.clip_range,
        num_joints=chains.num_joints,
        mean=mean,
        log_std=log_std,
        actions=actions,
        mask=chains.mask,
        old_mean=mb.old_mean,
        old_log_std=mb.old_log_std,
        kl_beta=mb.kl_beta,
    )
    surrogate = rule.surrogate(ctx)
    pg_loss = -surrogate.mean() if mb.weight is None else -(mb.weight * surrogate).mean()
    v_loss = torch.nn.functional.mse_loss(value, mb.returns)
    entropy = policy.entropy(chains).mean()
    loss = pg_loss + vf_coef * v_loss - ent_coef * entropy
    return LossTerms(loss, pg_loss, v_loss, entropy, log_ratio, rule.clip_share(ctx))


def normalized_advantages(advantages: torch.Tensor) -> torch.Tensor:
    """Advantages scaled to mean 0 and standard deviation 1 over a minibatch."""
    return (advantages - advantages.mean()) / (advantages.std() + 1e-8)


def normalized_minibatch_advantages(advantages: torch.Tensor, perm: torch.Tensor, cuts: list[int]) -> torch.Tensor:
    """``advantages[perm]``, each minibatch ``cuts[k]:cuts[k + 1]`` of it normalised over itself: the same numbers
    as ``normalized_advantages`` on each (the means of the equal-sized leading minibatches taken as rows of one
    matrix, which reduces each row as a vector; the standard deviations one by one, as a row's can differ in its
    last bit). A few operations per epoch instead of six per minibatch."""
    x = advantages[perm]
    size = cuts[1] - cuts[0]
    rows = next((k for k in range(len(cuts) - 1) if cuts[k + 1] - cuts[k] != size), len(cuts) - 1)
    m = x[: rows * size].view(rows, size)
    std = torch.stack([row.std() for row in m])
    rest = [normalized_advantages(x[a:b]) for a, b in pairwise(cuts[rows:])]
    return torch.cat([((m - m.mean(1, keepdim=True)) / (std[:, None] + 1e-8)).flatten(), *rest])


def compute_gae(
    rewards: torch.Tensor,
    values: torch.Tensor,
    terminated: torch.Tensor,
    truncated: torch.Tensor,
    final_values: torch.Tensor,
    last_value: torch.Tensor,
    gamma: float,
    gae_lambda: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Generalised advantage estimation over a [T, E] rollout; returns (advantages, returns), both [T, E].

    Step t goes from observation t (value ``values[t]``) with reward ``rewards[t]`` to the next one.
    ``terminated[t]`` (bool): the episode ended there in a terminal state, nothing follows.
    ``truncated[t]`` (bool): a time limit cut it; it would have gone on, worth ``gamma *
    final_values[t]`` (the value of its final observation, unused elsewhere). Either way the trace
    ends there; otherwise it continues into ``values[t + 1]``, or ``last_value`` [E] after the last step.
    """
    # In NumPy: the loop runs over T steps of E numbers each, and a NumPy operation on so few costs a
    # fraction of a torch one (the same float32 operations in the same order, so the same bits).
    rewards, values, final_values, last_value = (
        x.detach().numpy() for x in (rewards, values, final_values, last_value)
    )  # fmt: skip
    truncated = truncated.numpy()
    steps = rewards.shape[0]
    advantages = np.zeros_like(rewards)
    last = np.zeros_like(last_value)
    continues = 1.0 - (terminated.numpy() | truncated).astype(rewards.dtype)
    for t in reversed(range(steps)):
        v_next = last_value if t == steps - 1 else values[t + 1]
        reward = np.where(truncated[t], rewards[t] + gamma * final_values[t], rewards[t])
        delta = reward + gamma * v_next * continues[t] - values[t]
        last = delta + gamma * gae_lambda * continues[t] * last
        advantages[t] = last
    advantages = torch.from_numpy(advantages)
    return advantages, advantages + torch.from_numpy(values)


def explained_variance(pred: torch.Tensor, target: torch.Tensor) -> float:
    var = target.var()
    return math.nan if var == 0 else float(1 - (target - pred).var() / var)


class PerDimensionStats:
    """Sums over an update's minibatches, kept per action dimension d.

    Clip fraction: share of samples whose ratio left the trust region (the
    rule's ``clipped``, e.g. outside their own eps_i; for a per-joint rule
    the share of the sample's joints, ``clip_share``). In-eps fraction: share with |log r| <= eps (the base eps), the
    quantity the paper's theory predicts. Mean and std of log r estimate
    -|nu|^2/2 and |nu|.
    """

    def __init__(self, max_dim: int):
        self.n = torch.zeros(max_dim + 1, dtype=torch.float64)
        self.clipped = torch.zeros_like(self.n)
        self.in_eps = torch.zeros_like(self.n)
        self.logr = torch.zeros_like(self.n)
        self.logr_sq = torch.zeros_like(self.n)
        self.kl = torch.zeros_like(self.n)
        self.samples: list[tuple[torch.Tensor, torch.Tensor]] = []
        """(dimension, log r) of every sample added, for the run log's histograms (``algo.tb_layout``)"""

    @torch.no_grad()
    def add(self, num_joints, log_ratio, clipped, base_eps: float) -> None:
        """``clipped``: [B] bool, the sample left the trust region (or the share of it that did, a float);
        ``base_eps`` the rule's base eps."""
        d = num_joints
        w = log_ratio.double()
        size = self.n.shape[0]
        self.n += torch.bincount(d, minlength=size)
        self.clipped += torch.bincount(d, weights=clipped.double(), minlength=size)
        self.in_eps += torch.bincount(d, weights=(w.abs() <= base_eps).double(), minlength=size)
        self.logr += torch.bincount(d, weights=w, minlength=size)
        self.logr_sq += torch.bincount(d, weights=w * w, minlength=size)
        self.kl += torch.bincount(d, weights=approx_kl(log_ratio).double(), minlength=size)
        self.samples.append((d, log_ratio.detach()))

    OVERALL = ("approx_kl", "clip_frac")
    """the columns of ``overall``"""
    PER_DIM = ("clip_frac", "in_eps_frac", "logr_mean", "logr_std", "approx_kl")
    """the statistics ``summary`` gives per dimension, as columns ``<name><tag>_d<d>``"""

    def overall(self, tag: str = "") -> dict[str, float]:
        """Approx KL and clip fraction over all samples, whatever their dimension (``<name><tag>``)."""
        n = float(self.n.sum())
        return {f"approx_kl{tag}": float(self.kl.sum()) / n, f"clip_frac{tag}": float(self.clipped.sum()) / n}

    def summary(self, dims, tag: str = "") -> dict[str, float]:
        out = {}
        for d in dims:
            n = float(self.n[d])
            if n == 0:
                continue
            mean = float(self.logr[d]) / n
            out[f"clip_frac{tag}_d{d}"] = float(self.clipped[d]) / n
            out[f"in_eps_frac{tag}_d{d}"] = float(self.in_eps[d]) / n
            out[f"logr_mean{tag}_d{d}"] = mean
            out[f"logr_std{tag}_d{d}"] = math.sqrt(max(float(self.logr_sq[d]) / n - mean * mean, 0.0))
            out[f"approx_kl{tag}_d{d}"] = float(self.kl[d]) / n
        return out
