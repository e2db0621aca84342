"""The settings of one PPO update: the trust-region rule and its parameters, epochs, minibatch size, loss
weights, and how samples of an older policy enter (``UpdateConfig``). The trainers' configs supply them
(``ppo_config.PPOConfig.update_config``)."""

from __future__ import annotations

from dataclasses import dataclass

from morph_core.algo.trust_region import get_rule

OFF_POLICY_OBJECTIVES = ("decoupled", "behaviour")
"""how samples of an older policy enter the update (``algo.off_policy``): ``decoupled``, the ratio against the
proximal policy and each sample weighted by min(pi_prox / pi_behav, c); ``behaviour``, PPO's own loss with the
ratio against the behaviour policy (a sample whose ratio starts outside the clip range pulls only back towards
it)"""


@dataclass(frozen=True)
class UpdateConfig:
    """Settings of one update (the trainer's config supplies them, with its defaults)."""

    rule: str
    """trust-region rule, a name from ``trust_region.RULES``"""
    clip_eps: float
    """base clip range eps"""
    update_epochs: int
    """passes over the batch"""
    minibatch_size: int
    """samples per gradient step"""
    vf_coef: float
    """value loss weight"""
    ent_coef: float
    """entropy bonus weight"""
    max_grad_norm: float
    """global gradient-norm clip"""
    proximal_weight_cap: float = 1.0
    """c of the truncated importance weight min(pi_prox / pi_behav, c) on off-policy samples"""
    kl_target: float = 0.01
    """target KL of the KL rules: the KL penalty adapts beta to it, KL early stopping stops above it"""
    kl_beta: float = 1.0
    """the KL penalty's beta as training starts"""
    kl_adaptive: bool = True
    """adapt the KL penalty's beta to kl_target after each update (Schulman et al. 2017); else it stays"""
    off_policy_objective: str = "decoupled"
    """a name from ``OFF_POLICY_OBJECTIVES``"""

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
