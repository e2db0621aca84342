"""One PPO update, the same for every data source: a batch of samples in, statistics out.

The simulator trainer (``algo.train``) hands it each rollout; a trainer that
reads recorded (rosbag2) or live ROS topics builds the same ``RolloutBatch``
from its records. The update runs epochs of shuffled minibatches under the
chosen trust-region rule (``algo.trust_region``) and returns per-dimension
statistics.

Off-policy data (a bag recorded by an older policy) uses the decoupled
objective of Hilton et al. 2022, "Batch size-invariance for policy
optimization": the ratio is taken against the proximal policy pi_prox (the
policy as the update starts, ``proximal_log_prob``), r = pi_theta / pi_prox,
and each sample's policy term is weighted by the truncated importance weight
min(pi_prox / pi_behav, c) (c = ``proximal_weight_cap``, as V-trace's
rho-bar). Without proximal log-probs (on-policy: pi_prox = pi_behav) there
is no weight at all, and the loss is PPO's own, bit for bit. The
``behaviour`` objective (``OFF_POLICY_OBJECTIVES``) takes PPO's own loss on
off-policy data too: the ratio against the policy that acted, no weight.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import pairwise
from typing import NamedTuple, Protocol

import torch
from torch import nn

from morph_core.algo.compiled import compiled
from morph_core.algo.param_buffer import FlatParameters
from morph_core.algo.ppo import PerDimensionStats, normalized_minibatch_advantages, ppo_loss
from morph_core.algo.trust_region import LossContext, TrustRegionRule, get_rule, kl_per_joint
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.chains import NUM_GLOBAL_FEATURES, ChainBatch
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
    """[N, 4] float32 torso yaw, yaw rate, vx, vy"""
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
    """[N] log-probability under the proximal policy (``proximal_log_probs``), for off-policy data;
    None for on-policy data, where it equals ``log_prob``"""
    parents: torch.Tensor | None = None
    """[N, J] int64 parent joint of each joint (-1: the torso, and at padding; ``policy.index_plan``); None
    when every sample is a chain, however given (checked at construction; chains-only parents become None, so
    that the update takes its chain path)"""

    def __post_init__(self):
        n, j = self.joint_pos.shape if self.joint_pos.ndim == 2 else (None, None)
        if n is None:
            raise ValueError(f"joint_pos must be [N, J], got {tuple(self.joint_pos.shape)}")
        shapes = {
            "num_joints": (n,), "joint_vel": (n, j), "global_feats": (n, NUM_GLOBAL_FEATURES), "actions": (n, j),
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
        # The padding is zero (checked at construction), so from_padded's checks and zeroing of the padding
        # would change nothing (~15 us of a step's gather).
        parents = None if self.parents is None else self.parents.numpy()[rows, :width]
        chains = ChainBatch.from_zero_padded(pos, vel, self.global_feats.numpy()[rows], num_joints, parents)
        return chains, torch.from_numpy(actions)


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

    def minibatch_gradient(self, rule: TrustRegionRule) -> Callable:
        """``minibatch_gradient`` under ``rule`` for this learner, compiled once per rule (``algo.compiled``)."""
        if rule.name not in self._gradients:
            self._gradients[rule.name] = minibatch_gradient(self.policy, self.params, rule, self.compile)
        return self._gradients[rule.name]


class _RuleLoss(nn.Module):
    """``ppo_loss`` under one rule as a module around the policy, for ``torch.func.functional_call``."""

    def __init__(self, policy: GraphActorCritic, rule: TrustRegionRule):
        super().__init__()
        self.policy = policy
        self.rule = rule

    def forward(self, *args, **kwargs):
        return ppo_loss(self.policy, *args, rule=self.rule, **kwargs)


def minibatch_gradient(
    policy: GraphActorCritic, flat: FlatParameters, rule: TrustRegionRule, compile: bool
) -> Callable:
    """``fn(theta, share, *loss_args, **loss_kwargs) -> (gradient, (loss, statistics))``: ``share`` times
    ``ppo_loss`` under ``rule`` (its arguments after the policy) as a function of the flat parameters
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

    def scaled_loss(theta, share, *args, **kwargs):
        params = {f"policy.{name}": view for name, view in flat.views(theta).items()}
        loss, pg_loss, v_loss, entropy, log_ratio, clip_share = torch.func.functional_call(module, params, args, kwargs)
        stats = {"pg_loss": pg_loss * share, "v_loss": v_loss * share, "entropy": entropy * share,
                 "log_ratio": log_ratio}  # fmt: skip
        if clip_share is not None:  # torch.func's auxiliary outputs must all be tensors
            stats["clip_share"] = clip_share
        return loss * share, {k: v.detach() for k, v in stats.items()}

    def by_autograd(theta, share, *args, **kwargs):
        theta = theta.detach().requires_grad_()
        with torch.enable_grad():
            loss, stats = scaled_loss(theta, share, *args, **kwargs)
        (grad,) = torch.autograd.grad(loss, theta)
        return grad, (loss.detach(), stats)

    return compiled(torch.func.grad_and_value(scaled_loss, has_aux=True), compile, eager=by_autograd)


OFF_POLICY_OBJECTIVES = ("decoupled", "behaviour")
"""how samples of an older policy enter the update: ``decoupled``, the ratio against the proximal policy and
each sample weighted by min(pi_prox / pi_behav, c); ``behaviour``, PPO's own loss with the ratio against
the behaviour policy (a sample whose ratio starts outside the clip range pulls only back towards it)"""


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


def epoch_columns(dims) -> list[str]:
    """The log columns of ``UpdateStats.row`` beyond the pooled statistics: epochs run, beta, and the
    first and last epoch's statistics, overall and per dimension (``<name>_first_d<d>``)."""
    return [
        "epochs", "kl_beta",
        *[f"{name}{tag}" for tag in EPOCH_TAGS for name in PerDimensionStats.OVERALL],
        *[f"{name}{tag}_d{d}" for tag in EPOCH_TAGS for name in PerDimensionStats.PER_DIM for d in dims],
    ]  # fmt: skip


def minibatch_cuts(size: int, minibatch_size: int) -> list[int]:
    """Boundaries of the minibatches of one epoch: ``minibatch_size`` samples each, the remainder last.

    A remainder of one sample joins the minibatch before it: advantages are normalised within a
    minibatch, and the standard deviation of one sample is undefined (it made every weight NaN).
    """
    if size < 2:
        raise ValueError(f"an update needs at least 2 samples (advantages are normalised), got {size}")
    cuts = [*range(0, size, minibatch_size), size]
    if len(cuts) > 2 and cuts[-1] - cuts[-2] == 1:
        del cuts[-2]
    return cuts


@dataclass
class UpdateTerms:
    """What every minibatch step of one update reads besides the batch, fixed as the update starts."""

    rule: TrustRegionRule
    gradient_fn: Callable
    """``Learner.minibatch_gradient`` of the rule"""
    old_log_prob: torch.Tensor
    """[N] the log-probs the ratio is taken against"""
    weight: torch.Tensor | None
    """[N] the truncated importance weights, or None (on-policy data, or the behaviour objective)"""
    clip_range: torch.Tensor
    """[N] the rule's clip range per sample"""
    old_mean: torch.Tensor | None
    """[N, J] the proximal policy's means, for rules that use its Gaussian"""
    extra: dict
    """further keyword arguments of the loss (the old log-std, the KL penalty's beta)"""


def update_terms(learner: Learner, batch: RolloutBatch, cfg: UpdateConfig, kl_beta: torch.Tensor | None) -> UpdateTerms:
    """The update's fixed terms, with the policy as the update starts (the proximal policy)."""
    rule = get_rule(cfg.rule)
    dims = batch.num_joints.to(torch.float32)
    clip_range = rule.clip_range(cfg.clip_eps, dims) if rule.clips_joint_ratio else torch.full_like(dims, cfg.clip_eps)
    if batch.proximal_log_prob is None or cfg.off_policy_objective == "behaviour":
        old_log_prob, weight = batch.log_prob, None
    else:
        old_log_prob = batch.proximal_log_prob
        weight = torch.clamp(torch.exp(batch.proximal_log_prob - batch.log_prob), max=cfg.proximal_weight_cap)
    extra, old_mean = {}, None  # what only some rules need, so the others' loss is called exactly as before
    if rule.uses_old_gaussian:
        old_mean, old_log_std = proximal_means(learner.policy, batch)
        extra = {"old_log_std": old_log_std}
    if kl_beta is not None:
        extra["kl_beta"] = kl_beta.to(torch.float32)
    return UpdateTerms(rule, learner.minibatch_gradient(rule), old_log_prob, weight, clip_range, old_mean, extra)


class MinibatchPart(NamedTuple):
    """One process's part of a minibatch step: its share of the mean losses and its samples' ratios."""

    pg_loss: torch.Tensor
    v_loss: torch.Tensor
    entropy: torch.Tensor
    log_ratio: torch.Tensor
    clip_share: torch.Tensor | None


PROCESS0_WEIGHT = 0.67
"""process 0's part of a split minibatch, relative to each peer's: besides its part, it gathers its next
part's samples, adds the parts, clips and steps Adam while the peers wait. At 0.67 (103 of 256 samples) a
two-process update took 0.500 s against 0.518-0.534 s at even parts; 0.5, 0.8 and 0.9 were no better
(docs/benchmarks.md)."""


def part_sizes(n: int, world: int) -> list[int]:
    """The samples of each of ``world`` parts of a minibatch of ``n``: process 0's part weighs
    ``PROCESS0_WEIGHT``, each peer's 1, rounded so that they add up to ``n``."""
    weights = [PROCESS0_WEIGHT] + [1.0] * (world - 1)
    edges = [round(n * sum(weights[: r + 1]) / sum(weights)) for r in range(world)]
    return [b - a for a, b in zip([0, *edges[:-1]], edges, strict=True)]


class PartInputs(NamedTuple):
    """What the gradient of one process's part of a minibatch reads, gathered from the batch."""

    share: float
    """the part's share of the minibatch's samples"""
    args: tuple
    """``ppo_loss``'s arguments after the policy"""
    kwargs: dict


def part_inputs(
    terms: UpdateTerms,
    batch: RolloutBatch,
    cfg: UpdateConfig,
    mb: torch.Tensor,
    advantages: torch.Tensor | None = None,
    rank: int = 0,
    world: int = 1,
) -> PartInputs:
    """The inputs of part ``rank`` of ``world`` of minibatch ``mb`` (all of it for one process).
    ``advantages``: ``mb``'s advantages normalised over all of ``mb`` (required when it is split)."""
    if world == 1:
        index, adv, normalize, share = mb, batch.advantages[mb], True, 1.0
    else:
        sizes = part_sizes(len(mb), world)
        lo = sum(sizes[:rank])
        index, adv, normalize = mb[lo : lo + sizes[rank]], advantages[lo : lo + sizes[rank]], False
        share = sizes[rank] / len(mb)
    chains, actions = batch.minibatch(index)
    extra = terms.extra
    if terms.old_mean is not None:
        extra = {**extra, "old_mean": terms.old_mean[index, : chains.max_joints]}
    weight = None if terms.weight is None else terms.weight[index]
    args = (chains, actions, terms.old_log_prob[index], adv, batch.returns[index], terms.clip_range[index], weight,
            cfg.vf_coef, cfg.ent_coef)  # fmt: skip
    return PartInputs(share, args, {"normalize_advantages": normalize, **extra})


def part_gradient(learner: Learner, terms: UpdateTerms, inputs: PartInputs) -> tuple[torch.Tensor, MinibatchPart]:
    """The gradient [P] of a part's loss at the learner's parameters, and the part's statistics, both
    scaled by the part's share of the minibatch: the parts' gradients add up to the whole minibatch's."""
    share = torch.tensor(inputs.share)  # a tensor: one compiled graph for every share
    grad, (_, stats) = terms.gradient_fn(learner.params.theta.detach(), share, *inputs.args, **inputs.kwargs)
    part = MinibatchPart(stats["pg_loss"], stats["v_loss"], stats["entropy"], stats["log_ratio"],
                         stats.get("clip_share"))  # fmt: skip
    return grad, part


class MinibatchPeers(Protocol):
    """Other processes that compute parts of every minibatch step (``algo.data_parallel``)."""

    world: int
    """processes, this one included (it computes part 0)"""

    def begin(self, kl_beta: torch.Tensor | None) -> None:
        """An update starts, with the policy as it is now."""

    def epoch(self, perm: torch.Tensor, cuts: list[int], advantages: torch.Tensor) -> None:
        """An epoch's minibatches: ``perm[cuts[k]:cuts[k + 1]]``, their advantages (each normalised over its
        minibatch) in ``perm``'s order. The peers compute their parts of each minibatch in turn, the first
        at once, each next one when the optimizer has stepped (``stepped``)."""

    def gather(self, grad: torch.Tensor) -> list[MinibatchPart]:
        """Add the peers' gradients into ``grad`` (in rank order); their statistics."""

    def stepped(self) -> None:
        """The optimizer has stepped: the peers take the new parameters."""


def update(
    learner: Learner,
    batch: RolloutBatch,
    cfg: UpdateConfig,
    generator: torch.Generator,
    peers: MinibatchPeers | None = None,
) -> UpdateStats:
    """Epochs of shuffled minibatch steps on ``batch`` under ``cfg.rule``; ``generator`` shuffles.

    With ``peers``, each minibatch is split over the processes: each computes the gradient of its part
    (advantages normalised over the whole minibatch first), this one adds them and steps; the result
    equals the one-process update to float rounding (``test_data_parallel``).
    """
    rule = get_rule(cfg.rule)
    flat, optimizer = learner.params, learner.optimizer
    # The rule's state as the learner keeps it (restored from a checkpoint), else as the rule starts it.
    state = {k: learner.rule_state.get(k, v) for k, v in rule.initial_state(cfg).items()}
    learner.rule_state = state
    kl_beta = state.get("kl_beta")
    terms = update_terms(learner, batch, cfg, kl_beta)
    if peers is not None:
        peers.begin(kl_beta)
    cuts = minibatch_cuts(batch.size, cfg.minibatch_size)
    steps: list[tuple[torch.Tensor, list[MinibatchPart]]] = []  # (minibatch, its parts) of every step
    epochs = 0
    for _ in range(cfg.update_epochs):
        epochs += 1
        perm = torch.randperm(batch.size, generator=generator)
        minibatches = [perm[start:stop] for start, stop in pairwise(cuts)]
        world, advantages = 1, [None] * len(minibatches)  # one process normalises within the loss
        if peers is not None:
            perm_advantages = normalized_minibatch_advantages(batch.advantages, perm, cuts)
            world, advantages = peers.world, [perm_advantages[a:b] for a, b in pairwise(cuts)]
            peers.epoch(perm, cuts, perm_advantages)
        own = part_inputs(terms, batch, cfg, minibatches[0], advantages[0], 0, world)
        for k, mb in enumerate(minibatches):
            grad, part = part_gradient(learner, terms, own)
            if k + 1 < len(minibatches):  # gathered while the peers finish their parts
                own = part_inputs(terms, batch, cfg, minibatches[k + 1], advantages[k + 1], 0, world)
            flat.grad.copy_(grad)
            parts = [part] if peers is None else [part, *peers.gather(flat.grad)]
            flat.clip_grad_norm_(cfg.max_grad_norm)
            flat.optimizer_step(optimizer)
            if peers is not None:
                peers.stepped()
            steps.append((mb, parts))  # statistics are reduced after the loop, off the steps' path
        epoch_log_ratio = torch.cat([p.log_ratio for _, parts in steps[-len(minibatches) :] for p in parts])
        if rule.stop_after_epoch(epoch_log_ratio, batch.num_joints[perm], cfg):  # an epoch covers perm once
            break
    # Every step's parts in order (``world`` of them, in rank order), reduced in a few operations for all steps.
    all_parts = [p for _, parts in steps for p in parts]
    part_losses = torch.stack([torch.stack([getattr(p, k) for p in all_parts]) for k in MinibatchPart._fields[:3]], 1)
    mb_losses = sum(part_losses[rank::world] for rank in range(world))  # [steps, 3]: each step's parts added
    index = torch.cat([mb for mb, _ in steps])
    log_ratio = torch.cat([p.log_ratio for p in all_parts])
    clip_range = terms.clip_range
    if all_parts[0].clip_share is not None:
        clipped = torch.cat([p.clip_share for p in all_parts])
    else:
        clipped = rule.clipped(log_ratio.exp(), clip_range[index])
    stats = PerDimensionStats(batch.max_joints)
    stats.add(batch.num_joints[index], log_ratio, clipped, cfg.clip_eps)
    # Every epoch covers the batch once: the first and the last epoch are the first and last N entries.
    per_epoch = []
    for part in (slice(0, batch.size), slice(len(index) - batch.size, len(index))):
        epoch = PerDimensionStats(batch.max_joints)
        epoch.add(batch.num_joints[index[part]], log_ratio[part], clipped[part], cfg.clip_eps)
        per_epoch.append(epoch)
    if state:
        kl = None
        if rule.uses_old_gaussian:
            kl = exact_kl(learner.policy, batch, terms.old_mean, terms.extra["old_log_std"])
        learner.rule_state = rule.end_update(state, kl, batch.num_joints, cfg)
    pg_loss, v_loss, entropy = mb_losses.mean(0).tolist()
    beta = math.nan if kl_beta is None else float(kl_beta)
    return UpdateStats(pg_loss, v_loss, entropy, stats, epochs, *per_epoch, kl_beta=beta)


def compile_ahead(learner: Learner, cfg: UpdateConfig, max_joints: int, off_policy: bool) -> None:
    """Compile the minibatch gradient now, on made-up samples (chains of 2..``max_joints`` joints, laid out as
    ``update`` lays out a real minibatch: off-policy data with its proximal log-probs), so that the first
    update runs at full speed. For a trainer that waits for its data anyway (a live one), the ~25 s of
    compiling overlap the first batch's collection instead of stalling the first update while samples
    pile up. Changes nothing an update reads: no optimizer step, no generator drawn from, the rule's state
    untouched. Without ``learner.compile`` it does nothing."""
    if not learner.compile or max_joints < 2:
        return
    n = cfg.minibatch_size
    gen = torch.Generator().manual_seed(0)  # its own: the update's shuffling stays as without the warm-up
    num_joints = torch.arange(n) % (max_joints - 1) + 2
    mask = torch.arange(max_joints) < num_joints.unsqueeze(1)
    pos, vel, actions = (torch.randn(n, max_joints, generator=gen) * mask for _ in range(3))
    zeros = torch.zeros(n)
    batch = RolloutBatch(num_joints, pos, vel, torch.randn(n, NUM_GLOBAL_FEATURES, generator=gen), actions,
                         -torch.rand(n, generator=gen), zeros, torch.randn(n, generator=gen), zeros)  # fmt: skip
    if off_policy:
        batch = with_proximal(learner.policy, batch)
    rule = get_rule(cfg.rule)
    terms = update_terms(learner, batch, cfg, rule.initial_state(cfg).get("kl_beta"))
    part_gradient(learner, terms, part_inputs(terms, batch, cfg, torch.arange(n)))


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
            None, None, None, chains.num_joints, mean, log_std, actions, chains.mask,
            old_mean[index, : chains.max_joints], old_log_std,
        )  # fmt: skip
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
