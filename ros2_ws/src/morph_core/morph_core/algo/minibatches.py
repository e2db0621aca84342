"""An update's minibatch steps: the terms fixed as the update starts, each minibatch's gradient, and the
partition of every minibatch over processes behind the peer interface (``MinibatchPeers``).

One process computes each minibatch's gradient whole. With peers (``algo.data_parallel``), each minibatch is
cut into parts (``part_sizes``), one per process, its advantages normalised over the whole minibatch first;
each process computes the gradient of its part, its loss scaled by the part's share, so the parts' gradients
add up to the whole minibatch's. Either way a process gathers its next part's samples while the others still
compute or step (``epoch_steps``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from itertools import pairwise
from typing import NamedTuple, Protocol

import numpy as np
import torch

from morph_core.algo.batch import Minibatch, RolloutBatch
from morph_core.algo.learner import Learner
from morph_core.algo.off_policy import proximal_means
from morph_core.algo.ppo import normalized_minibatch_advantages
from morph_core.algo.trust_region import TrustRegionRule, get_rule
from morph_core.algo.update_config import UpdateConfig


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
    vf_coef: float
    ent_coef: float
    old_mean: torch.Tensor | None = None
    """[N, J] the proximal policy's means, for rules that use its Gaussian"""
    old_log_std: torch.Tensor | None = None
    """the proximal policy's log-std, for rules that use its Gaussian"""
    kl_beta: torch.Tensor | None = None
    """the KL penalty's beta (float32), for rules that have it"""


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
    old_mean = old_log_std = None  # what only some rules need, so the others' loss reads exactly what it did
    if rule.uses_old_gaussian:
        old_mean, old_log_std = proximal_means(learner.policy, batch)
    return UpdateTerms(
        rule=rule,
        gradient_fn=learner.minibatch_gradient(rule),
        old_log_prob=old_log_prob,
        weight=weight,
        clip_range=clip_range,
        vf_coef=cfg.vf_coef,
        ent_coef=cfg.ent_coef,
        old_mean=old_mean,
        old_log_std=old_log_std,
        kl_beta=None if kl_beta is None else kl_beta.to(torch.float32),
    )


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
    minibatch: Minibatch
    """the part's samples as the loss reads them"""


def part_inputs(
    terms: UpdateTerms,
    batch: RolloutBatch,
    mb: torch.Tensor,
    advantages: torch.Tensor | None = None,
    rank: int = 0,
    world: int = 1,
) -> PartInputs:
    """The inputs of part ``rank`` of ``world`` of minibatch ``mb`` (all of it for one process).
    ``advantages``: ``mb``'s advantages normalised over all of ``mb`` (required when it is split)."""
    if world == 1:
        index, adv, normalize, share = mb, _take(batch.advantages, mb.numpy()), True, 1.0
    else:
        sizes = part_sizes(len(mb), world)
        lo = sum(sizes[:rank])
        index, adv, normalize = mb[lo : lo + sizes[rank]], advantages[lo : lo + sizes[rank]], False
        share = sizes[rank] / len(mb)
    chains, actions = batch.minibatch(index)
    rows = index.numpy()  # the per-sample terms gathered in NumPy too: a torch index costs ~5x more here
    minibatch = Minibatch(
        chains=chains,
        actions=actions,
        old_log_prob=_take(terms.old_log_prob, rows),
        advantages=adv,
        returns=_take(batch.returns, rows),
        clip_range=_take(terms.clip_range, rows),
        weight=None if terms.weight is None else _take(terms.weight, rows),
        old_mean=None if terms.old_mean is None else _take(terms.old_mean, rows, chains.max_joints),
        old_log_std=terms.old_log_std,
        kl_beta=terms.kl_beta,
        normalize_advantages=normalize,
    )
    return PartInputs(share, minibatch)


def _take(values: torch.Tensor, rows: np.ndarray, width: int | None = None) -> torch.Tensor:
    """``values[rows]`` (``values[rows, :width]`` given a width): a contiguous copy, as torch's index gives,
    of the same numbers, gathered by NumPy."""
    array = values.detach().numpy()
    return torch.from_numpy(array[rows] if width is None else array[rows, :width])


def part_gradient(learner: Learner, terms: UpdateTerms, inputs: PartInputs) -> tuple[torch.Tensor, MinibatchPart]:
    """The gradient [P] of a part's loss at the learner's parameters, and the part's statistics, both
    scaled by the part's share of the minibatch: the parts' gradients add up to the whole minibatch's."""
    share = torch.tensor(inputs.share)  # a tensor: one compiled graph for every share
    theta = learner.params.theta.detach()
    grad, (_, stats) = terms.gradient_fn(theta, share, inputs.minibatch, terms.vf_coef, terms.ent_coef)
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


def epoch_steps(
    learner: Learner,
    terms: UpdateTerms,
    batch: RolloutBatch,
    minibatch_size: int,
    perm: torch.Tensor,
    peers: MinibatchPeers | None = None,
) -> Iterator[tuple[torch.Tensor, list[MinibatchPart]]]:
    """The minibatch steps of the epoch that shuffles ``batch`` by ``perm``: for each minibatch, its indices
    and its parts' statistics (one part per process, in rank order), with its whole gradient in
    ``learner.params.grad``. The caller steps the optimizer before it asks for the next minibatch.

    With ``peers``, each minibatch is split over the processes: each computes the gradient of its part
    (advantages normalised over the whole minibatch first), this one adds them; the result equals the
    one-process update to float rounding (``test_data_parallel``).
    """
    cuts = minibatch_cuts(batch.size, minibatch_size)
    minibatches = [perm[start:stop] for start, stop in pairwise(cuts)]
    world, advantages = 1, [None] * len(minibatches)  # one process normalises within the loss
    if peers is not None:
        perm_advantages = normalized_minibatch_advantages(batch.advantages, perm, cuts)
        world, advantages = peers.world, [perm_advantages[a:b] for a, b in pairwise(cuts)]
        peers.epoch(perm, cuts, perm_advantages)
    grad_buffer = learner.params.grad
    own = part_inputs(terms, batch, minibatches[0], advantages[0], 0, world)
    for k, mb in enumerate(minibatches):
        grad, part = part_gradient(learner, terms, own)
        if k + 1 < len(minibatches):  # gathered while the peers finish their parts
            own = part_inputs(terms, batch, minibatches[k + 1], advantages[k + 1], 0, world)
        grad_buffer.copy_(grad)
        parts = [part] if peers is None else [part, *peers.gather(grad_buffer)]
        yield mb, parts  # the caller steps the optimizer
        if peers is not None:
            peers.stepped()
