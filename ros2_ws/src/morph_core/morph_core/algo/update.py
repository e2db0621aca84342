"""One PPO update, the same for every data source: a batch of samples in, statistics out.

The simulator trainer (``algo.train``) hands it each rollout; a trainer that reads recorded (rosbag2) or live
ROS topics builds the same ``batch.RolloutBatch`` from its records. The update runs epochs of shuffled
minibatches under the chosen trust-region rule (``algo.trust_region``) and returns per-dimension statistics.
Its parts, each in a module of its own:

- ``batch``: the samples (``RolloutBatch``) and a minibatch as the loss reads it (``Minibatch``);
- ``update_config``: the update's settings (``UpdateConfig``);
- ``learner``: the policy, its flat parameters, optimizer and rule state, the compiled minibatch gradient;
- ``minibatches``: the terms fixed as the update starts, each minibatch's gradient, its partition over
  processes (``MinibatchPeers``, ``algo.data_parallel``);
- ``update_stats``: the statistics (``UpdateStats``) and their log columns;
- ``off_policy``: samples of an older policy (the proximal policy's log-probs and Gaussian, the exact KL).
"""

from __future__ import annotations

import dataclasses

import torch

from morph_core.algo.batch import RolloutBatch
from morph_core.algo.learner import Learner
from morph_core.algo.minibatches import MinibatchPeers, epoch_steps, part_gradient, part_inputs, update_terms
from morph_core.algo.off_policy import exact_kl, with_proximal
from morph_core.algo.trust_region import get_rule
from morph_core.algo.update_config import UpdateConfig
from morph_core.algo.update_stats import UpdateStats, update_stats


def update(
    learner: Learner,
    batch: RolloutBatch,
    cfg: UpdateConfig,
    generator: torch.Generator,
    peers: MinibatchPeers | None = None,
) -> UpdateStats:
    """Epochs of shuffled minibatch steps on ``batch`` under ``cfg.rule``; ``generator`` shuffles. With
    ``peers``, each minibatch is split over the processes (``minibatches.epoch_steps``)."""
    rule = get_rule(cfg.rule)
    state = learner.begin_rule_state(rule, cfg)  # e.g. the KL penalty's beta
    kl_beta = state.get("kl_beta")
    terms = update_terms(learner, batch, cfg, kl_beta)  # with the policy as the update starts
    if peers is not None:
        peers.begin(kl_beta)
    epochs = []  # each epoch's steps: (minibatch, its parts)
    for _ in range(cfg.update_epochs):
        perm = torch.randperm(batch.size, generator=generator)
        epoch = []
        for mb, parts in epoch_steps(learner, terms, batch, cfg.minibatch_size, perm, peers):
            learner.step(cfg.max_grad_norm)  # the minibatch's gradient is in learner.params.grad
            epoch.append((mb, parts))  # statistics are reduced after the loop, off the steps' path
        epochs.append(epoch)
        log_ratio = torch.cat([p.log_ratio for _, parts in epoch for p in parts])
        if rule.stop_after_epoch(log_ratio, batch.num_joints[perm], cfg):  # an epoch covers perm once
            break
    stats = update_stats(epochs, batch, terms, cfg.clip_eps, kl_beta)
    if state:
        kl = exact_kl(learner.policy, batch, terms.old_mean, terms.old_log_std) if rule.uses_old_gaussian else None
        learner.rule_state = rule.end_update(state, kl, batch.num_joints, cfg)
    return stats


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
    glob = torch.randn(n, learner.policy.config.global_features, generator=gen)  # the policy's width
    batch = RolloutBatch(num_joints, pos, vel, glob, actions,
                         -torch.rand(n, generator=gen), zeros, torch.randn(n, generator=gen), zeros)  # fmt: skip
    if described := learner.policy.config.joint_features:  # drawn after the rest: the draws above stay as they were
        desc = torch.rand(n, max_joints, described, generator=gen) * mask.unsqueeze(2)
        batch = dataclasses.replace(batch, joint_desc=desc)
    if off_policy:
        batch = with_proximal(learner.policy, batch)
    rule = get_rule(cfg.rule)
    terms = update_terms(learner, batch, cfg, rule.initial_state(cfg).get("kl_beta"))
    part_gradient(learner, terms, part_inputs(terms, batch, torch.arange(n)))
