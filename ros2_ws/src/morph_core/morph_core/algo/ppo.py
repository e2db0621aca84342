"""PPO on mixed action dimensions: advantages, the clip rule, and the clipped losses.

Every sample carries its own action dimension d (its chain's joint count).
The importance ratio is over the sample's joint action, r = exp(sum_j log
pi_new - log pi_old). The paper's only change to PPO is the clip range:

    fixed:        r in [1 - eps, 1 + eps]
    compensated:  r in [1 - eps sqrt(d), 1 + eps sqrt(d)]
"""

from __future__ import annotations

import math

import torch

CLIP_MODES = ("fixed", "compensated")


def clip_range(eps: float, num_joints: torch.Tensor, mode: str) -> torch.Tensor:
    """Per-sample clip range eps_i: eps, or eps * sqrt(d_i) when compensated."""
    if mode == "fixed":
        return torch.full(num_joints.shape, eps, dtype=torch.float32)
    if mode == "compensated":
        return eps * torch.sqrt(num_joints.to(torch.float32))
    raise ValueError(f"clip mode must be one of {CLIP_MODES}, got {mode!r}")


def clipped_policy_loss(ratio: torch.Tensor, advantages: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
    """PPO's pessimistic surrogate with a per-sample clip range; returns the loss to minimise."""
    unclipped = ratio * advantages
    clipped = torch.clamp(ratio, 1.0 - eps, 1.0 + eps) * advantages
    return -torch.min(unclipped, clipped).mean()


def ppo_loss(policy, batch, actions, old_log_prob, advantages, returns, eps, vf_coef: float, ent_coef: float):
    """PPO's loss on one minibatch, with advantages normalised within it.

    ``policy`` is a GraphActorCritic, ``batch`` the minibatch's ChainBatch, ``eps`` the per-sample
    clip ranges. Returns (loss, policy loss, value loss, entropy, log ratio per sample).
    """
    mean, _, value = policy(batch)
    log_ratio = policy.log_prob(batch, actions, mean) - old_log_prob
    ratio = log_ratio.exp()
    adv = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    pg_loss = clipped_policy_loss(ratio, adv, eps)
    v_loss = torch.nn.functional.mse_loss(value, returns)
    entropy = policy.entropy(batch).mean()
    return pg_loss + vf_coef * v_loss - ent_coef * entropy, pg_loss, v_loss, entropy, log_ratio


def compute_gae(
    rewards: torch.Tensor,
    values: torch.Tensor,
    dones: torch.Tensor,
    next_value: torch.Tensor,
    next_done: torch.Tensor,
    gamma: float,
    gae_lambda: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Generalised advantage estimation over a [T, E] rollout.

    ``dones[t]`` marks that the observation at step t starts a new episode
    (CleanRL's convention), ``next_value`` / ``next_done`` describe the
    observation after the last step. Time-limit truncations are not dones
    here: their rewards already hold gamma * V(final obs). Returns
    (advantages, returns), both [T, E].
    """
    steps = rewards.shape[0]
    advantages = torch.zeros_like(rewards)
    last = torch.zeros_like(next_value)
    for t in reversed(range(steps)):
        if t == steps - 1:
            not_done, v_next = 1.0 - next_done, next_value
        else:
            not_done, v_next = 1.0 - dones[t + 1], values[t + 1]
        delta = rewards[t] + gamma * v_next * not_done - values[t]
        last = delta + gamma * gae_lambda * not_done * last
        advantages[t] = last
    return advantages, advantages + values


def explained_variance(pred: torch.Tensor, target: torch.Tensor) -> float:
    var = target.var()
    return math.nan if var == 0 else float(1 - (target - pred).var() / var)


class PerDimensionStats:
    """Sums over an update's minibatches, kept per action dimension d.

    Clip fraction: share of samples whose ratio left the clip range (their own
    eps_i). In-eps fraction: share with |log r| <= eps (the base eps), the
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

    @torch.no_grad()
    def add(self, num_joints, log_ratio, ratio, eps_i, base_eps: float) -> None:
        d = num_joints
        w = log_ratio.double()
        size = self.n.shape[0]
        self.n += torch.bincount(d, minlength=size)
        self.clipped += torch.bincount(d, weights=((ratio - 1).abs() > eps_i).double(), minlength=size)
        self.in_eps += torch.bincount(d, weights=(w.abs() <= base_eps).double(), minlength=size)
        self.logr += torch.bincount(d, weights=w, minlength=size)
        self.logr_sq += torch.bincount(d, weights=w * w, minlength=size)
        self.kl += torch.bincount(d, weights=((ratio - 1) - log_ratio).double(), minlength=size)

    def overall(self) -> dict[str, float]:
        """Approx KL and clip fraction over all samples, whatever their dimension."""
        n = float(self.n.sum())
        return {"approx_kl": float(self.kl.sum()) / n, "clip_frac": float(self.clipped.sum()) / n}

    def summary(self, dims) -> dict[str, float]:
        out = {}
        for d in dims:
            n = float(self.n[d])
            if n == 0:
                continue
            mean = float(self.logr[d]) / n
            out[f"clip_frac_d{d}"] = float(self.clipped[d]) / n
            out[f"in_eps_frac_d{d}"] = float(self.in_eps[d]) / n
            out[f"logr_mean_d{d}"] = mean
            out[f"logr_std_d{d}"] = math.sqrt(max(float(self.logr_sq[d]) / n - mean * mean, 0.0))
            out[f"approx_kl_d{d}"] = float(self.kl[d]) / n
        return out
