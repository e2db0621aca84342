"""The settings of one PPO update: the trust-region rule and its parameters, epochs, minibatch size, loss
weights, and how samples of an older policy enter (``UpdateConfig``). Every trainer's PPO settings extend it
(``ppo_config.PPOConfig``), so they are written once, here."""

from __future__ import annotations

from dataclasses import dataclass

from morph_core.algo.trust_region import get_rule

OFF_POLICY_OBJECTIVES = ("decoupled", "behaviour")
"""how samples of an older policy enter the update (``algo.off_policy``): ``decoupled``, the ratio against the
proximal policy and each sample weighted by min(pi_prox / pi_behav, c); ``behaviour``, PPO's own loss with the
ratio against the behaviour policy (a sample whose ratio starts outside the clip range pulls only back towards
it)"""


@dataclass
class UpdateConfig:
    """Settings of one update, defaults the paper's. The one definition of these fields: ``ppo_config.PPOConfig``
    extends it (they are options and ``config.json`` keys as they are), and ``update`` takes this part of it
    (``PPOConfig.update_config``). Not frozen, so that a trainer's config can be one."""

    rule: str = "compensated"
    """trust-region rule, a name from algo.trust_region.RULES: 'fixed' clips r to 1 +- eps,
    'compensated' to 1 +- eps*sqrt(dim A) per sample"""
    clip_eps: float = 0.111
    """base clip range eps"""
    update_epochs: int = 10
    """passes over each batch"""
    minibatch_size: int = 256
    """samples per gradient step"""
    vf_coef: float = 0.5
    """value loss weight"""
    ent_coef: float = 0.0
    """entropy bonus weight"""
    max_grad_norm: float = 0.5
    """global gradient-norm clip"""
    proximal_weight_cap: float = 1.0
    """c of the truncated importance weight min(pi_prox / pi_behav, c) on off-policy samples (training from
    recorded data, algo.train_from_data); simulator rollouts are on-policy and carry no weight"""
    kl_target: float = 0.01
    """target KL of the kl-* rules: the KL penalty doubles/halves beta when the update's KL is above
    1.5x / below 1/1.5 of it, KL early stopping ends the epochs above it (per joint for the -per-joint rules)"""
    kl_beta: float = 1.0
    """initial beta of the kl-penalty rules"""
    kl_adaptive: bool = True
    """adapt the kl-penalty rules' beta to kl_target after each update (Schulman et al. 2017); false keeps
    beta = kl_beta"""
    off_policy_objective: str = "decoupled"
    """how samples of an older policy (bags, live) enter the update: 'decoupled' (ratio against the policy as
    the update starts, each sample weighted by min(pi_prox / pi_behav, proximal_weight_cap)) or 'behaviour'
    (PPO's own loss, the ratio against the policy that acted); simulator rollouts are on-policy either way"""

    def __post_init__(self):
        rule = get_rule(self.rule)  # a clear error for an unknown name
        if self.off_policy_objective not in OFF_POLICY_OBJECTIVES:
            raise ValueError(f"off_policy_objective must be one of {OFF_POLICY_OBJECTIVES}, "
                             f"got {self.off_policy_objective!r}")  # fmt: skip
        if self.off_policy_objective == "behaviour" and rule.uses_old_gaussian:
            raise ValueError(f"rule {rule.name!r} needs the old policy's Gaussian, which only the decoupled "
                             "objective has (the behaviour policy's means are not kept)")  # fmt: skip
        if not (self.kl_target > 0 and self.kl_beta > 0):  # also refuses NaN
            raise ValueError(f"kl_target and kl_beta must be > 0, got {self.kl_target}, {self.kl_beta}")
        if self.update_epochs < 1 or self.minibatch_size < 2:
            raise ValueError(f"need update_epochs >= 1 and minibatch_size >= 2 (advantages are normalised within a "
                             f"minibatch), got {self.update_epochs}, {self.minibatch_size}")  # fmt: skip
        if not self.proximal_weight_cap > 0:  # also refuses NaN
            raise ValueError(f"proximal_weight_cap must be > 0, got {self.proximal_weight_cap}")
