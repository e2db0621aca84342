"""The policy being trained with what trains it: its flat parameters and optimizer, the trust-region rule's
state, and the minibatch gradient, compiled once per rule (``Learner``, ``minibatch_gradient``)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import nn

from morph_core.algo.batch import Minibatch
from morph_core.algo.compiled import compiled
from morph_core.algo.param_buffer import FlatParameters
from morph_core.algo.ppo import ppo_loss
from morph_core.algo.trust_region import RuleSettings, TrustRegionRule
from morph_core.policy.actor_critic import GraphActorCritic


@dataclass
class Learner:
    """The policy being trained, its flat parameter buffer and optimizer, the trust-region rule's state
    (e.g. the KL penalty's beta) and the (compiled) minibatch gradients."""

    policy: GraphActorCritic
    params: FlatParameters
    optimizer: torch.optim.Optimizer
    compile: bool = True
    rule_state: dict[str, torch.Tensor] = field(default_factory=dict)
    """what a rule carries from one update to the next (``TrustRegionRule.initial_state``), by name;
    empty for rules without state"""
    _gradients: dict[str, Callable] = field(default_factory=dict, repr=False)

    @classmethod
    def create(cls, policy: GraphActorCritic, learning_rate: float, adam_eps: float, compile: bool) -> Learner:
        params = FlatParameters(policy)  # one vector: the optimizer and the norm clip are a few ops
        optimizer = torch.optim.Adam([params.theta], lr=learning_rate, eps=adam_eps, fused=True)
        return cls(policy, params, params.guard(optimizer), compile)

    STATE_PREFIX = "learner."
    """prefix of the rule state's tensors in a training-state checkpoint (``algo.checkpoint``)"""

    def state_tensors(self) -> dict[str, torch.Tensor]:
        """The rule state as checkpoint tensors (none for rules without state: such files are unchanged)."""
        return {f"{self.STATE_PREFIX}{k}": v for k, v in self.rule_state.items()}

    def restore_state(self, tensors: dict[str, torch.Tensor]) -> None:
        """Take the rule state back from a checkpoint's tensors (all of them; others are ignored)."""
        prefix = self.STATE_PREFIX
        self.rule_state = {k[len(prefix) :]: v.clone() for k, v in tensors.items() if k.startswith(prefix)}

    def begin_rule_state(self, rule: TrustRegionRule, cfg: RuleSettings) -> dict[str, torch.Tensor]:
        """The rule's state as an update starts: as this learner keeps it (restored from a checkpoint), else as
        the rule starts it; kept as the learner's."""
        self.rule_state = {k: self.rule_state.get(k, v) for k, v in rule.initial_state(cfg).items()}
        return self.rule_state

    def minibatch_gradient(self, rule: TrustRegionRule) -> Callable:
        """``minibatch_gradient`` under ``rule`` for this learner, compiled once per rule (``algo.compiled``)."""
        if rule.name not in self._gradients:
            self._gradients[rule.name] = minibatch_gradient(self.policy, self.params, rule, self.compile)
        return self._gradients[rule.name]

    def step(self, max_grad_norm: float) -> None:
        """Clip the gradient in ``params.grad`` to ``max_grad_norm`` and step the optimizer."""
        self.params.clip_grad_norm_(max_grad_norm)
        self.params.optimizer_step(self.optimizer)


class _RuleLoss(nn.Module):
    """``ppo_loss`` under one rule as a module around the policy, for ``torch.func.functional_call``."""

    def __init__(self, policy: GraphActorCritic, rule: TrustRegionRule):
        super().__init__()
        self.policy = policy
        self.rule = rule

    def forward(self, mb: Minibatch, vf_coef: float, ent_coef: float):
        return ppo_loss(self.policy, mb, vf_coef, ent_coef, rule=self.rule)


def minibatch_gradient(
    policy: GraphActorCritic, flat: FlatParameters, rule: TrustRegionRule, compile: bool
) -> Callable:
    """``fn(theta, share, mb, vf_coef, ent_coef) -> (gradient, (loss, statistics))``: ``share`` times
    ``ppo_loss`` under ``rule`` on the ``batch.Minibatch`` ``mb`` as a function of the flat parameters
    ``theta`` (laid out as ``flat.theta``), and its gradient [P] with respect to them. The statistics
    (``pg_loss``, ``v_loss``, ``entropy`` times ``share``, ``log_ratio`` and, for rules that have it,
    ``clip_share``) are detached.

    Compiled, forward and backward are one graph (``torch.func.grad_and_value``) taking the parameters as
    one input: no autograd engine, no per-parameter gradient accumulation, which took a minibatch step's
    fixed cost from ~1.25 to ~0.65 ms (docs/benchmarks.md); ``algo.compiled`` calls it without
    ``torch.compile``'s per-call machinery. Eager (``compile`` False, or no C++ compiler) the same function
    is differentiated by autograd, faster than ``torch.func`` without a compiler.
    """
    module = _RuleLoss(policy, rule)

    def scaled_loss(theta, share, mb, vf_coef, ent_coef):
        params = {f"policy.{name}": view for name, view in flat.views(theta).items()}
        terms = torch.func.functional_call(module, params, (mb, vf_coef, ent_coef))
        stats = {"pg_loss": terms.pg_loss * share, "v_loss": terms.v_loss * share, "entropy": terms.entropy * share,
                 "log_ratio": terms.log_ratio}  # fmt: skip
        if terms.clip_share is not None:  # torch.func's auxiliary outputs must all be tensors
            stats["clip_share"] = terms.clip_share
        return terms.loss * share, {k: v.detach() for k, v in stats.items()}

    def by_autograd(theta, share, mb, vf_coef, ent_coef):
        theta = theta.detach().requires_grad_()
        with torch.enable_grad():
            loss, stats = scaled_loss(theta, share, mb, vf_coef, ent_coef)
        (grad,) = torch.autograd.grad(loss, theta)
        return grad, (loss.detach(), stats)

    return compiled(torch.func.grad_and_value(scaled_loss, has_aux=True), compile, eager=by_autograd)
