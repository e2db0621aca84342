"""The one training loop every trainer runs: ``fit(run, learner, gen, source)``, over ``Fit.step``.

A trainer is a data source and this loop. The loop owns what every run does the same way: the threads around
the update, the learning-rate annealing, the PPO update (``algo.update``), the base row (step, iteration,
timings, learning rate, the update's statistics, explained variance, log-std), the checkpoint and report timing
(``run.Run``) and the progress bar. A source (``Source``: the simulator's rollouts ``algo.train``, recorded
samples ``algo.train_from_data``, the live pool ``trainer.live.learner``) hands over batches and provides its own
columns, its state section and, for the bar, how far it has got::

    run, (learner, gen) = Run(run_dir, cfg, ...), new_learner(cfg, initial)
    ... start or restore the run, and the source's state
    fit(run, learner, gen, source)        # while not source.finished(): step(source.collect(learner))

Two shapes, one step. The simulator and the recorded data are pulled: the loop asks for the next batch, so
``fit`` is the loop. The live pool is pushed: a ROS node decides when a batch is full (its callback), and a
loop that blocked on a source would own the node's thread. So the loop's body is ``Fit.step(collected)``, a
step-wise object the live learner calls once per full batch; ``fit`` is only ``while``, the bar and ``close``
around it, so the pushed and the pulled trainer run the same update, row and checkpoint code.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import torch

from morph_core.algo.batch import RolloutBatch
from morph_core.algo.learner import Learner
from morph_core.algo.ppo import explained_variance
from morph_core.algo.run import Run
from morph_core.algo.update import update
from morph_core.algo.update_stats import UpdateStats
from morph_core.policy.actor_critic import GraphActorCritic


@dataclass
class Collected:
    """One batch a source hands the loop, with what it took to make it."""

    batch: RolloutBatch
    seconds: float
    """collecting or preparing it (the source's timing column, ``Source.time_column``)"""
    context: Any = None
    """the source's own, read back by its ``row`` (the episodes of a rollout, a live pool's lags)"""


class Source(Protocol):
    """What a data source provides the loop (see the module docstring). ``collect``, ``progress`` and ``advance``
    are the pulled loop's (``fit``); a pushed source hands ``Fit.step`` its batches itself and needs the rest."""

    name: str
    """for messages: ``"training from data"``"""
    time_column: str
    """the log column of ``Collected.seconds`` (``rollout_s``, ``prepare_s``)"""
    bounded: bool
    """whether the run's length is known (``total_timesteps``): ``anneal_lr`` needs it"""
    state_every_update: bool
    """save the state after every update, not only at checkpoints (live: policy nodes run every version)"""
    peers: Any
    """the data-parallel helpers the update averages gradients with (``algo.data_parallel``), or None"""
    guard: bool
    """refuse an update that makes the parameters non-finite (``NonFiniteUpdate``), keeping the ones before"""

    def columns(self) -> list[str]: ...
    def collect(self, learner: Learner) -> Collected: ...
    def updated(self, collected: Collected) -> None:
        """After the update, before the counters move (the source's own counting)."""

    def finished(self) -> bool:
        """No more batches (after the last one: its checkpoint is the final one)."""

    def row(self, collected: Collected, checkpoint: bool) -> dict:
        """The source's columns of this update; called once the base row's values are taken, after the update
        (the simulator starts its next rollout here, its swimmers' states first when ``checkpoint``)."""

    def state(self) -> tuple[dict, dict, dict | None]:
        """(sections, arrays, more_rngs) of ``Run.save_state``."""

    def save_policy(self, path: Path, learner: Learner, step: int) -> None: ...
    def progress(self) -> tuple[int, int, str]:
        """(total, done, unit) of the progress bar."""

    def advance(self, row: dict) -> tuple[int, dict]:
        """(how far the bar moves, its postfix) after ``row``."""


class NonFiniteUpdate(RuntimeError):
    """An update made the policy's parameters NaN or inf; the learner kept the ones before it."""


def new_learner(cfg, initial: GraphActorCritic | None) -> tuple[Learner, torch.Generator]:
    """The learner (policy, Adam, rule state) and generator a run starts with: ``initial`` (``run.initial_policy``)
    or a fresh policy from ``cfg.seed``."""
    torch.set_num_threads(1)  # before init: the orthogonal init's QR differs in its last bits with the thread count
    torch.manual_seed(cfg.seed)
    policy = GraphActorCritic(cfg.policy) if initial is None else initial
    learner = Learner.create(policy, cfg.learning_rate, cfg.adam_eps, cfg.compile)
    return learner, torch.Generator().manual_seed(cfg.seed)


def refuse_anneal(cfg, source: Source) -> None:
    if cfg.anneal_lr and not source.bounded:
        raise ValueError(f"anneal_lr needs a known run length; {source.name} has none")


class Fit:
    """The loop's body, one update at a time (``step``): what a pushed source (the live pool) calls."""

    def __init__(self, run: Run, learner: Learner, gen: torch.Generator, source: Source):
        self.run, self.learner, self.gen, self.source, self.cfg = run, learner, gen, source, run.cfg
        refuse_anneal(self.cfg, source)
        self.update_cfg = self.cfg.update_config()
        run.open_log(source.columns())

    def step(self, collected: Collected) -> dict:
        """One update on ``collected``: anneal, update, count, the row, the log, checkpoint and state when due, the
        row hook. Returns the row. ``NonFiniteUpdate`` (with ``source.guard``): nothing changed but the count."""
        cfg, run, learner, source, counters = self.cfg, self.run, self.learner, self.source, self.run.counters
        batch = collected.batch
        t1 = time.perf_counter()
        if cfg.anneal_lr:  # a function of the step count alone, so a resumed run gets the same rate
            learner.optimizer.param_groups[0]["lr"] = cfg.learning_rate * (
                1.0 - counters["global_step"] / cfg.total_timesteps
            )
        before = _learning_state(learner, self.gen) if source.guard else None
        torch.set_num_threads(cfg.torch_threads)
        stats = update(learner, batch, self.update_cfg, self.gen, peers=source.peers)
        torch.set_num_threads(1)
        if before is not None and not torch.isfinite(learner.params.theta).all():
            _restore_learning_state(learner, self.gen, before)
            raise NonFiniteUpdate(_diverged(stats, batch))
        update_s = time.perf_counter() - t1
        source.updated(collected)
        counters["iteration"] += 1
        counters["global_step"] += batch.size
        row = {
            "global_step": counters["global_step"],
            "iteration": counters["iteration"],
            "wall_time": time.time(),
            "sps": batch.size / (collected.seconds + update_s),
            source.time_column: collected.seconds,
            "update_s": update_s,
            "learning_rate": learner.optimizer.param_groups[0]["lr"],
            **stats.row(cfg.dims),
            "explained_variance": explained_variance(batch.values, batch.returns),
            "log_std": float(learner.policy.log_std.detach()),
        }
        checkpoint = run.checkpoint_due(final=source.finished())
        row.update(source.row(collected, checkpoint))
        run.log(row, stats)
        if checkpoint:
            source.save_policy(run.mark_checkpoint(), learner, counters["global_step"])
        saved = checkpoint or source.state_every_update
        if saved:
            run.save_state(learner, self.gen, *source.state())
        run.report(row, saved)
        return row


def fit(run: Run, learner: Learner, gen: torch.Generator, source: Source) -> None:
    """Train until the source has no more batches (the pulled loop: the simulator, recorded data), with the
    progress bar; closes the run's log."""
    step = Fit(run, learner, gen, source)
    bar = _progress(run.cfg, source)
    while not source.finished():
        row = step.step(source.collect(learner))
        if bar is not None:
            n, postfix = source.advance(row)
            bar.update(n)
            bar.set_postfix(**postfix)
    if bar is not None:
        bar.close()
    run.close()


def save_policy(path: Path, learner: Learner, step: int) -> None:
    """A weights-only checkpoint of the learner's policy (the default of ``Source.save_policy``)."""
    learner.policy.save(path, metadata={"global_step": step})


def _progress(cfg, source: Source):
    if not cfg.progress_bar:
        return None
    from tqdm import tqdm  # the bar only when asked: a quiet run (tests, sweeps) never loads it

    total, done, unit = source.progress()
    return tqdm(total=total, initial=done, unit=unit, dynamic_ncols=True)


def _diverged(stats: UpdateStats, batch: RolloutBatch) -> str:
    kl = stats.per_dim.overall()["approx_kl"]
    return f"the update on {batch.size} samples (approx KL {kl:.3g}) made the policy non-finite; refused"


def _learning_state(learner: Learner, gen: torch.Generator) -> tuple:
    """What an update changes (parameters, Adam, the rule's state, the generator), copied."""
    return (learner.params.theta.detach().clone(), copy.deepcopy(learner.optimizer.state_dict()),
            {k: v.clone() for k, v in learner.rule_state.items()}, gen.get_state())  # fmt: skip


def _restore_learning_state(learner: Learner, gen: torch.Generator, saved: tuple) -> None:
    theta, optimizer, rule_state, state = saved
    with torch.no_grad():
        learner.params.theta.copy_(theta)  # in place: the policy's parameters are views of it
    learner.optimizer.load_state_dict(optimizer)
    learner.rule_state = rule_state
    gen.set_state(state)
