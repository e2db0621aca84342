"""The table of trust-region rules: how far one PPO update may move the policy on a sample.

Every rule is defined and named here, once. The trainers' ``rule``
option (``PPOConfig.rule``), the update's policy loss, the clip-probability theory and the
comparison plots all read ``RULES``, so a rule added to the table shows up
in each of them without another edit.

Each sample carries its own action dimension d (its chain's joint count) and
its ratio is over the joint action, r = pi_new(a|s) / pi_old(a|s) =
prod_j rho_j, rho_j the ratio of joint j's Gaussian (the policy is diagonal).
The rules:

    fixed:                 clip r to [1 - eps, 1 + eps]
    compensated:           clip r to [1 - eps sqrt(d), 1 + eps sqrt(d)]   (the paper's change to PPO)
    per-joint-clip:        clip each rho_j to [1 - eps, 1 + eps] on its own (DISC, Han and Sung 2019)
    kl-penalty:            r A - beta KL(pi_old || pi_new)      (the paper's beta-surrogate; beta adaptive)
    kl-penalty-per-joint:  r A - beta KL / d                    (the same, penalising the KL per joint)
    kl-stop:               fixed, and the epochs stop once the approximate KL exceeds kl_target
    kl-stop-per-joint:     the same on the approximate KL per joint, KL / d

A rule's loss hook gets a ``LossContext`` for one minibatch and returns each
sample's surrogate objective (to be maximised); the update averages it,
weighting each sample when the data came from an older policy. Rules that
need the old policy per joint (``uses_old_gaussian``) get its Gaussian
means and log-std in the context: the update computes them with the policy
as it starts (the proximal policy, which is the behaviour policy for
on-policy data). Rules with state (the KL penalty's beta) keep it in the
learner (``initial_state``, ``end_update``), which checkpoints it. KL early
stopping uses ``stop_after_epoch``.

Why KL / d is "per joint": the old and the new policy are products of
independent per-joint Gaussians, so their KL is the sum of the per-joint
KLs, and KL / d is their mean. The paper finds the beta-surrogate's step
shrinking like 1/d (the Fisher grows like d); dividing the penalty by d
undoes that factor, as eps sqrt(d) undoes the clip's 1/sqrt(d). At d = 1
every "-per-joint" variant equals its plain rule.
"""

from __future__ import annotations

from typing import NamedTuple, Protocol

import numpy as np
import torch

from morph_core.policy.gaussian import log_density_per_joint


class RuleSettings(Protocol):
    """What a rule reads of the update's settings (``update_config.UpdateConfig`` has them; named here as a
    protocol so that this module, which the update's modules import, imports none of them)."""

    kl_target: float
    kl_beta: float
    kl_adaptive: bool


class LossContext(NamedTuple):
    """What the update hands a rule's loss hook for one minibatch of B samples (J = longest chain)."""

    log_ratio: torch.Tensor
    """[B] log pi_theta(a|s) - log pi_old(a|s) over each sample's joint action (pi_old: the proximal
    policy, which is the behaviour policy for on-policy data)"""
    advantages: torch.Tensor
    """[B] advantages, normalised within the minibatch"""
    clip_range: torch.Tensor
    """[B] the rule's clip range per sample (``TrustRegionRule.clip_range``; the base eps for rules
    that do not clip the joint ratio), computed outside the loss"""
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
    old_mean: torch.Tensor | None = None
    """[B, J] the proximal policy's means, zero beyond each chain (rules with ``uses_old_gaussian``)"""
    old_log_std: torch.Tensor | None = None
    """the proximal policy's log standard deviation (rules with ``uses_old_gaussian``)"""
    kl_beta: torch.Tensor | None = None
    """the KL penalty's coefficient beta, a 0-dim tensor (rules with state ``kl_beta``)"""


def joint_log_ratios(ctx: LossContext) -> torch.Tensor:
    """[B, J] log rho_j = log pi_new(a_j) - log pi_old(a_j) of each joint, zero beyond each chain.

    The policy is a diagonal Gaussian: the joint log ratio is the sum of these over the chain."""
    new = log_density_per_joint((ctx.actions - ctx.mean) * torch.exp(-ctx.log_std), ctx.log_std)
    old = log_density_per_joint((ctx.actions - ctx.old_mean) * torch.exp(-ctx.old_log_std), ctx.old_log_std)
    return (new - old) * ctx.mask


def kl_per_joint(ctx: LossContext) -> torch.Tensor:
    """[B, J] KL(pi_old,j || pi_new,j) of each joint's Gaussian, exactly, zero beyond each chain.

    In the theory's terms (docs/theory.md), nu = (mu_new - mu_old) / sigma_new and eta = sigma_new /
    sigma_old: KL = log eta + (1/eta^2 + nu^2) / 2 - 1/2, zero iff nu = 0 and eta = 1."""
    nu = (ctx.mean - ctx.old_mean) * torch.exp(-ctx.log_std)
    log_eta = ctx.log_std - ctx.old_log_std
    return (log_eta + 0.5 * (torch.exp(-2.0 * log_eta) + nu * nu) - 0.5) * ctx.mask


def approx_kl(log_ratio: torch.Tensor) -> torch.Tensor:
    """Each sample's estimate (r - 1) - log r of KL(pi_old || pi_new): unbiased under pi_old, never
    negative (Schulman's k3, CleanRL's approx_kl), from the joint log ratio alone. The statistics
    (``ppo.PerDimensionStats``) log this very expression."""
    return (log_ratio.exp() - 1) - log_ratio


def _array_module(x):
    """torch for tensors (the update), NumPy for arrays (the theory): each keeps its own arithmetic."""
    return torch if isinstance(x, torch.Tensor) else np


class TrustRegionRule:
    """One entry of the table. Subclasses set ``name`` and ``help`` and define the loss hook."""

    name: str = ""
    help: str = ""
    uses_old_gaussian: bool = False
    """the loss hook needs the proximal policy's per-joint Gaussian (``LossContext.old_mean``)"""

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

    def clip_share(self, ctx: LossContext) -> torch.Tensor | None:
        """[B] share of the sample's trust region left, for rules that decide it inside the loss (per
        joint); None: the update counts ``clipped`` on the joint ratio."""
        return None

    def stop_after_epoch(self, log_ratio: torch.Tensor, num_joints: torch.Tensor, cfg: RuleSettings) -> bool:
        """Whether the update ends after this epoch, given the log ratios [N] its minibatches saw
        (each before its step) and their samples' dimensions [N]."""
        return False

    def initial_state(self, cfg: RuleSettings) -> dict[str, torch.Tensor]:
        """The rule's state as training starts (kept by the learner, checkpointed with it)."""
        return {}

    def end_update(
        self, state: dict[str, torch.Tensor], kl: torch.Tensor, num_joints: torch.Tensor, cfg: RuleSettings
    ) -> dict[str, torch.Tensor]:
        """The state after an update; ``kl`` [N] each sample's exact KL(pi_prox || pi_new) over its joints
        after the update (only computed for rules that have state)."""
        return state


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


class PerJointClip(TrustRegionRule):
    """DISC's dimension-wise clipping: each joint's ratio rho_j clipped to 1 +- eps on its own.

    Per sample: A + sum_j [min(rho_j A, clip(rho_j, 1 - eps, 1 + eps) A) - A]. Summed, not averaged, over
    the joints: at rho = 1 the gradient of prod_j rho_j is sum_j grad rho_j, so the sum takes the
    sample's whole policy gradient, as PPO's joint ratio does, and only the trust region differs; the
    mean would divide each sample's gradient by its d, a bias against long chains of its own. The
    constant A - d A (no gradient) makes the objective equal r A to first order, the linearisation
    prod rho_j ~ 1 + sum (rho_j - 1), so its value compares with the other rules' (policy_loss).
    """

    name = "per-joint-clip"
    help = (
        "clip each joint's ratio to 1 +- eps on its own and sum the per-joint surrogates over the joints "
        "(DISC, Han and Sung 2019; summed so each sample keeps its whole policy gradient, as with r)"
    )
    uses_old_gaussian = True

    def surrogate(self, ctx: LossContext) -> torch.Tensor:
        rho = joint_log_ratios(ctx).exp()
        adv, eps = ctx.advantages.unsqueeze(1), ctx.clip_range.unsqueeze(1)
        per_joint = torch.min((rho - 1.0) * adv, (torch.clamp(rho, 1.0 - eps, 1.0 + eps) - 1.0) * adv)
        return ctx.advantages + (per_joint * ctx.mask).sum(1)

    def clip_share(self, ctx: LossContext) -> torch.Tensor:
        """The share of the sample's joints whose ratio left 1 +- eps."""
        with torch.no_grad():
            left = (joint_log_ratios(ctx).exp() - 1.0).abs() > ctx.clip_range.unsqueeze(1)
            return (left & ctx.mask).sum(1).to(ctx.advantages.dtype) / ctx.num_joints.to(ctx.advantages.dtype)


class KLPenalty(TrustRegionRule):
    """The beta-surrogate of Schulman et al. 2017, r A - beta KL(pi_old || pi_new), with their adaptive
    beta: after each update, beta doubles if the update's mean KL exceeds 1.5 kl_target and halves if
    it is below kl_target / 1.5 (``UpdateConfig.kl_adaptive``; off: beta stays ``kl_beta``). The KL is
    exact (Gaussians), over the sample's joints; ``per_joint`` divides it by d, in the penalty and in
    the adaptation alike."""

    uses_old_gaussian = True
    per_joint = False

    def penalised_kl(self, kl_joints: torch.Tensor, num_joints: torch.Tensor) -> torch.Tensor:
        """[B] the KL the rule penalises, from the per-sample KL over the joints."""
        return kl_joints / num_joints.to(kl_joints.dtype) if self.per_joint else kl_joints

    def surrogate(self, ctx: LossContext) -> torch.Tensor:
        kl = self.penalised_kl(kl_per_joint(ctx).sum(1), ctx.num_joints)
        return ctx.log_ratio.exp() * ctx.advantages - ctx.kl_beta * kl

    def initial_state(self, cfg: RuleSettings) -> dict[str, torch.Tensor]:
        return {"kl_beta": torch.tensor(cfg.kl_beta, dtype=torch.float64)}

    def end_update(self, state, kl, num_joints, cfg):
        if not cfg.kl_adaptive:
            return state
        mean_kl = float(self.penalised_kl(kl.double(), num_joints).mean())
        beta = state["kl_beta"]
        if mean_kl > 1.5 * cfg.kl_target:
            beta = beta * 2.0
        elif mean_kl < cfg.kl_target / 1.5:
            beta = beta / 2.0
        return {**state, "kl_beta": beta}


class KLPenaltyJoint(KLPenalty):
    name = "kl-penalty"
    help = (
        "r A - beta KL(pi_old || pi_new) over the sample's joints, beta adapted to kl_target "
        "(the paper's beta-surrogate; its step shrinks like 1/d)"
    )


class KLPenaltyPerJoint(KLPenalty):
    name = "kl-penalty-per-joint"
    help = (
        "r A - beta KL / d: the KL per joint penalised, and adapted to kl_target (undoes the "
        "beta-surrogate's 1/d, as eps*sqrt(d) undoes the clip's 1/sqrt(d))"
    )
    per_joint = True


class KLStop(FixedClip):
    """The fixed clip, and the update's epochs stop once the epoch's mean approximate KL exceeds
    kl_target (CleanRL's target_kl, which tests its last minibatch's value; the mean over the epoch's
    samples is less noisy). The KL of each minibatch is taken before its step, as logged."""

    per_joint = False

    def stop_after_epoch(self, log_ratio, num_joints, cfg) -> bool:
        kl = approx_kl(log_ratio).double()
        if self.per_joint:
            kl = kl / num_joints.double()
        return float(kl.mean()) > cfg.kl_target


class KLStopJoint(KLStop):
    name = "kl-stop"
    help = "fixed clip, and the epochs stop once the approximate KL exceeds kl_target (CleanRL's target_kl)"


class KLStopPerJoint(KLStop):
    name = "kl-stop-per-joint"
    help = "fixed clip, and the epochs stop once the approximate KL per joint (KL / d) exceeds kl_target"
    per_joint = True


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
    """The rules that clip the joint ratio to a range, the ones the clip-probability theory covers: one
    per clip range, the first of the table's rules with it (kl-stop clips as fixed does; the theory
    knows nothing of stopping, so it would only repeat fixed's case)."""
    probe = np.arange(1.0, 65.0)
    rules: list[TrustRegionRule] = []
    for rule in RULES.values():
        if rule.clips_joint_ratio and not any(
            np.array_equal(rule.clip_scale(probe), r.clip_scale(probe)) for r in rules
        ):
            rules.append(rule)
    return tuple(rules)


register(FixedClip())
register(CompensatedClip())
register(PerJointClip())
register(KLPenaltyJoint())
register(KLPenaltyPerJoint())
register(KLStopJoint())
register(KLStopPerJoint())
