"""One training run's lifecycle, the same for every trainer (simulator, bags, live): ``Run``.

A run is a directory, its files named by ``run_dir.RunDir``: the config it trains with (written atomically
as it starts), the progress log (``run_log.RunLog``: a row per update), the policy checkpoints (every
``checkpoint_interval`` steps and at the end) and the state (everything a resume needs, ``algo.checkpoint``;
the state it replaced is kept beside it). A trainer is a loop around it::

    run = Run(run_dir, cfg, resume=resume, on_row=on_row)
    if run.resuming:
        state = run.restore(learner, gen)                 # policy, Adam (with cfg's lr/eps), rule state, RNG
        meta, arrays = state.section("swimmers", 1)       # the trainer's own, named and versioned
    else:
        run.start()                                       # the directory and its config
    run.open_log(columns)
    while ...:
        ...                                               # collect, advantages, update
        run.counters["global_step"] += batch_size
        run.log(row, stats)
        saved = run.checkpoint_due(final)
        if saved:
            learner.policy.save(run.mark_checkpoint(), ...)
            run.save_state(learner, gen, {"swimmers": {"version": 1, ...}}, arrays)
        run.report(row, saved)                            # the row hook: on_row(row, saved)
    run.close()

``counters`` holds global_step, iteration and last_ckpt (the step of the last checkpoint) and whatever a
trainer counts beside them; it is saved with every state and restored with it.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from morph_core.algo.checkpoint import (
    ResumedState,
    restore_optimizer,
    resume_training_state,
    save_training_state,
    state_section,
    sub_dict,
)
from morph_core.algo.config import TrainerConfig
from morph_core.algo.learner import Learner
from morph_core.algo.run_dir import RunDir
from morph_core.algo.run_log import RunLog
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.util.atomic import atomic_writer

RowHook = Callable[[dict, bool], None]
"""hears a run's progress row and whether that step's state was saved: ``on_row(row, saved)``"""


@dataclass(frozen=True)
class RestoredState:
    """The state a run resumed from (``Run.restore``), for the trainer's own sections."""

    resumed: ResumedState

    @property
    def tensors(self) -> dict[str, torch.Tensor]:
        return self.resumed.tensors

    def section(self, name: str, version: int) -> tuple[dict, dict[str, torch.Tensor]]:
        """(JSON, arrays) of the trainer's section ``name``, of a layout up to ``version``
        (``checkpoint.state_section``: an older state's ``env`` field too)."""
        return state_section(self.resumed.meta, self.resumed.tensors, name, version, self.resumed.path)


class Run:
    """A training run's directory, config, log, checkpoints and resume (see the module docstring).

    ``resume``: continue the run in ``run_dir`` when it has a state (``resuming`` says whether it does; a run
    killed before its first state starts again). ``on_row``: the row hook every trainer calls after each row
    (``report``)."""

    def __init__(self, run_dir: str | Path, cfg: TrainerConfig, *, resume: bool = False, on_row: RowHook | None = None):
        self.files = RunDir(run_dir)
        self.dir = self.files.path
        self.cfg = cfg
        self.resume = resume
        self.on_row = on_row
        self.resuming = resume and self.files.has_state()
        self.counters: dict = {"global_step": 0, "iteration": 0, "last_ckpt": 0}
        self.progress: RunLog | None = None

    # -- start or resume -----------------------------------------------------------------------------
    def start(self, config: dict | None = None, init: str | Path | None = None) -> None:
        """A new run: the directory and its config (``config``: what to write, else the run's config); with
        ``init``, the checkpoint it starts from in the run's ``init`` file (a run killed before its first state
        restarts from it)."""
        self.dir.mkdir(parents=True, exist_ok=True)
        _write_json(self.files.config, self.cfg.to_dict() if config is None else config)
        if init is not None:
            _write_json(self.files.init, {"init": str(Path(init).resolve())})

    def restore(self, learner: Learner, gen: torch.Generator) -> RestoredState:
        """The newest good state (``checkpoint.resume_training_state``: a damaged one is skipped, named in the
        log) into ``learner`` (policy, Adam, the rule's state) and ``gen``; the counters too. Adam's learning
        rate and epsilon are the config's: a run resumed with a new ``learning_rate`` trains with it."""
        resumed = resume_training_state(self.files.state)
        tensors, meta = resumed.tensors, resumed.meta
        learner.policy.load_state_dict(sub_dict(tensors, "policy."))
        restore_optimizer(learner.optimizer, tensors, meta)
        for group in learner.optimizer.param_groups:
            group["lr"], group["eps"] = self.cfg.learning_rate, self.cfg.adam_eps
        learner.restore_state(tensors)
        gen.set_state(tensors["rng.torch"])
        self.counters = dict(meta["counters"])
        return RestoredState(resumed)

    # -- each update ---------------------------------------------------------------------------------
    def open_log(self, columns: list[str]) -> RunLog:
        """The progress log; a resumed run's is cut at the step it resumes from (its later rows come again)."""
        resume_step = self.counters["global_step"] if self.resume else None
        self.progress = RunLog(self.files, columns, resume_step=resume_step, tensorboard=self.cfg.tensorboard)
        return self.progress

    def log(self, row: dict, stats=None) -> None:
        """A progress row (and with the update's ``stats``, its TensorBoard histograms)."""
        self.progress.log(row)
        if stats is not None:
            self.progress.update_histograms(int(row["global_step"]), stats)

    def checkpoint_due(self, final: bool = False) -> bool:
        """Whether this step checkpoints: it crossed a multiple of ``checkpoint_interval``, or is the last."""
        step, last, every = self.counters["global_step"], self.counters["last_ckpt"], self.cfg.checkpoint_interval
        return step // every > last // every or final

    def mark_checkpoint(self) -> Path:
        """This step is checkpointed (``last_ckpt``); the path of its policy checkpoint."""
        step = self.counters["global_step"]
        self.counters["last_ckpt"] = step
        return self.files.checkpoint(step)

    def save_state(
        self,
        learner: Learner,
        gen: torch.Generator,
        sections: dict[str, dict],
        arrays: dict | None = None,
        more_rngs: dict[str, torch.Tensor] | None = None,
    ) -> None:
        """The state file (atomically, the one it replaces kept): the learner, ``gen``, the counters and
        the trainer's ``sections`` (name -> JSON with its ``version``; ``arrays`` as ``<section>.<key>``)."""
        save_training_state(self.files.state, learner.policy, learner.optimizer, gen, sections, arrays or {},
                            dict(self.counters), learner.state_tensors(), more_rngs)  # fmt: skip

    def report(self, row: dict, saved: bool) -> None:
        """The row hook: ``on_row(row, saved)`` once the row is written (and, when ``saved``, its state)."""
        if self.on_row is not None:
            self.on_row(row, saved)

    def close(self) -> None:
        if self.progress is not None:
            self.progress.close()


def _write_json(path: Path, data: dict) -> None:
    """A JSON file of the run (atomically: a reader never sees half of one)."""
    with atomic_writer(path) as f:
        json.dump(data, f, indent=2)


def initial_policy(cfg, init: str | Path | None, resume: bool):
    """``(cfg, policy)`` a new run starts from: with ``init`` (a checkpoint, fine-tuning) its policy and ``cfg``
    with the policy's architecture (the run's config says what it trains); without, ``(cfg, None)`` (a fresh
    policy from the seed). ``ValueError`` for ``init`` on a resumed run, which continues from its own state."""
    if init is None:
        return cfg, None
    if resume:
        raise ValueError("init starts a new run; a resumed run continues from its own state")
    initial = GraphActorCritic.load(init)
    return dataclasses.replace(cfg, policy=initial.config), initial
