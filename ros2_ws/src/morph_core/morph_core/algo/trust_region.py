"""The table of trust-region rules: how far one PPO update may move the policy on a sample.

Every rule is defined and named here, once. The trainer's ``clip_mode``
option, the update's policy loss, the clip-probability theory and the
comparison plots all read ``RULES``, so a rule added to the table shows up
in each of them without another edit.

Each sample carries its own action dimension d (its chain's joint count) and
its ratio is over the joint action, r = pi_new(a|s) / pi_old(a|s). Today's rules:

    fixed:        clip r to [1 - eps, 1 + eps]
    compensated:  clip r to [1 - eps sqrt(d), 1 + eps sqrt(d)]   (the paper's change to PPO)

A rule's loss hook gets a ``LossContext`` for one minibatch and returns each
sample's surrogate objective (to be maximised); the update averages it,
weighting each sample when the data came from an older policy. The context
carries the new policy's per-joint quantities too, so rules that are not a
clip range on the joint ratio fit the same hook: per-joint clipping (DISC:
each joint's ratio clipped on its own) and the KL-penalty objective (KL
between the old and the new Gaussian per sample) need, besides what is
here, the old policy's per-joint means, which ``policy_info`` records and
the proximal policy can compute; KL early stopping uses
``stop_after_epoch``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch


class LossContext(NamedTuple):
    """What the update hands a rule's loss hook for one minibatch of B samples (J = longest chain)."""

    log_ratio: torch.Tensor
    """[B] log pi_theta(a|s) - log pi_old(a|s) over each sample's joint action (pi_old: the proximal
    policy, which is the behaviour policy for on-policy data)"""
    advantages: torch.Tensor
    """[B] advantages, normalised within the minibatch"""
    clip_range: torch.Tensor
    """[B] the rule's clip range per sample (``TrustRegionRule.clip_range``), computed outside the loss"""
    num_joints: torch.Tensor
    """[B] chain length d of each sample"""
    mean: torch.Tensor
    """[B, J] the new policy's Gaussian means, zero beyond each chain"""
    log_std: torch.Tensor
    """the new policy's log standard deviation (a scalar shared by all joints)"""
    actions: torch.Tensor
    """[B, J] the actions taken, zero beyond each chain"""
    mask: torch.Tensor
    """[B, J] True where a joint exists"""


def _array_module(x):
    """torch for tensors (the update), NumPy for arrays (the theory): each keeps its own arithmetic."""
    return torch if isinstance(x, torch.Tensor) else np


class TrustRegionRule:
    """One entry of the table. Subclasses set ``name`` and ``help`` and define the loss hook."""

    name: str = ""
    help: str = ""

    def clip_scale(self, dim):
        """Factor on the base eps for a sample of dimension ``dim`` (float tensor or array), or None
        when the rule does not clip the joint ratio (the clip-probability theory then does not apply)."""
        return None

    @property
    def clips_joint_ratio(self) -> bool:
        return self.clip_scale(np.ones(1)) is not None

    def clip_range(self, eps, dim):
        """Per-sample clip range ``eps * clip_scale(dim)``; ``dim`` a float tensor or a float array."""
        scale = self.clip_scale(dim)
        if scale is None:
            raise ValueError(f"trust-region rule {self.name!r} has no clip range on the joint ratio")
        return eps * scale

    def surrogate(self, ctx: LossContext) -> torch.Tensor:
        """[B] each sample's surrogate objective, to be maximised (the update negates and averages it)."""
        raise NotImplementedError

    def clipped(self, ratio: torch.Tensor, clip_range: torch.Tensor) -> torch.Tensor:
        """[B] bool: the sample's ratio left the trust region (counted as the clip fraction)."""
        return (ratio - 1).abs() > clip_range

    def stop_after_epoch(self, log_ratios: list[torch.Tensor]) -> bool:
        """Whether the update ends after this epoch, given its minibatches' log ratios (no rule stops today)."""
        return False


class ClippedRatio(TrustRegionRule):
    """PPO's pessimistic clipped surrogate, min(r A, clip(r, 1 - eps_i, 1 + eps_i) A), eps_i per sample."""

    def surrogate(self, ctx: LossContext) -> torch.Tensor:
        ratio = ctx.log_ratio.exp()
        unclipped = ratio * ctx.advantages
        clipped = torch.clamp(ratio, 1.0 - ctx.clip_range, 1.0 + ctx.clip_range) * ctx.advantages
        return torch.min(unclipped, clipped)


class FixedClip(ClippedRatio):
    name = "fixed"
    help = "clip r to 1 +- eps whatever the action dimension (PPO as published)"

    def clip_scale(self, dim):
        return _array_module(dim).ones_like(dim)


class CompensatedClip(ClippedRatio):
    name = "compensated"
    help = "clip r to 1 +- eps*sqrt(d), d the sample's action dimension (the paper's rule)"

    def clip_scale(self, dim):
        return _array_module(dim).sqrt(dim)


RULES: dict[str, TrustRegionRule] = {}
"""Every rule by name, in the order they are listed and plotted."""


def register(rule: TrustRegionRule) -> TrustRegionRule:
    """Add ``rule`` to the table (its name must be new); returns it."""
    if not rule.name or rule.name in RULES:
        raise ValueError(f"a trust-region rule needs a new name, got {rule.name!r} (have {rule_names()})")
    RULES[rule.name] = rule
    return rule


def unregister(name: str) -> None:
    """Remove a rule (for tests that register a temporary one)."""
    del RULES[name]


def rule_names() -> tuple[str, ...]:
    return tuple(RULES)


def get_rule(rule: str | TrustRegionRule) -> TrustRegionRule:
    """The table's rule of that name (a rule object is returned as it is)."""
    if isinstance(rule, TrustRegionRule):
        return rule
    try:
        return RULES[rule]
    except KeyError:
        raise ValueError(f"unknown trust-region rule {rule!r}: choose one of {rule_names()}") from None


def clip_rules() -> tuple[TrustRegionRule, ...]:
    """The rules that clip the joint ratio to a range, the ones the clip-probability theory covers."""
    return tuple(r for r in RULES.values() if r.clips_joint_ratio)


register(FixedClip())
register(CompensatedClip())
