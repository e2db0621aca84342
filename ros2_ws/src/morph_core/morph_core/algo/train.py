"""PPO for graph policies on swimmers of mixed chain lengths: the simulator training loop.

One loop, in the order a reader thinks (and as CleanRL writes it): collect a
rollout from the vectorised swimmers, compute advantages, ``update`` (the
one PPO update every data source uses, ``algo.update``), log and checkpoint.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import pairwise
from pathlib import Path

import numpy as np
import torch

from morph_core.algo.config import BodiesConfig, SimConfig, TrainerConfig
from morph_core.algo.data_parallel import HelperPool, Helpers, HelperSpec
from morph_core.algo.fit import Collected, fit, new_learner, save_policy
from morph_core.algo.learner import Learner
from morph_core.algo.minibatches import minibatch_cuts
from morph_core.algo.ppo import compute_gae
from morph_core.algo.rollout_workers import LocalPool, RolloutPool, RolloutSpec, RolloutWorker, WorkerState
from morph_core.algo.run import RowHook, Run, initial_policy
from morph_core.algo.run_dir import RunDir
from morph_core.algo.update_stats import update_columns
from morph_core.env.bodies import is_chain_label
from morph_core.env.vec_env import Episode, merge_env_states, split_env_state
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.weights import CheckpointError, load_checkpoint
from morph_core.util.config_cli import check_field_types, renamed_fields, replace_nested

log = logging.getLogger(__name__)

PoolFactory = Callable[[RolloutSpec, int], RolloutPool]
"""makes the pool of ``rollout_workers`` > 1 workers for a run's rollout: ``pool(spec, workers)`` (the core
has no such pool: ``trainer.sim.ray_rollouts`` makes one of Ray actors)"""


@renamed_fields(clip_mode="rule")
@dataclass
class TrainConfig(SimConfig, TrainerConfig):
    """The simulator trainer's config: every trainer's (``config.TrainerConfig``: run, PPO, bodies, policy) and
    the simulator loop's own (``SimConfig``), flat, as ``morph-train`` takes them and a run's ``config.json``
    holds them. Its batch is the rollout, num_envs * num_steps."""

    batch_size: int = field(init=False, default=6144)
    """samples per update: num_envs * num_steps (set from them)"""

    derived = ("batch_size",)
    concerns = (*TrainerConfig.concerns, ("simulator", SimConfig))

    def __post_init__(self):
        check_field_types(self)  # before num_envs * num_steps is taken: "num_envs must be int", not the batch's
        SimConfig.__post_init__(self)
        self.batch_size = self.num_envs * self.num_steps
        TrainerConfig.__post_init__(self)
        smallest = min(b - a for a, b in pairwise(minibatch_cuts(self.batch_size, self.minibatch_size)))
        if not 1 <= self.processes <= min(self.num_envs, smallest):
            raise ValueError(f"processes must be in 1..{min(self.num_envs, smallest)} (each needs a swimmer and a "
                             f"part of every minibatch), got {self.processes}")  # fmt: skip
        if not 1 <= self.rollout_workers <= self.num_envs:
            raise ValueError(f"rollout_workers must be in 1..{self.num_envs} (each needs a swimmer), "
                             f"got {self.rollout_workers}")  # fmt: skip
        if self.rollout_workers > 1 and self.processes > 1:
            raise ValueError("rollout_workers > 1 and processes > 1 both share the swimmers out: choose one")


def log_columns(cfg: BodiesConfig) -> list[str]:
    return [
        "global_step", "iteration", "wall_time", "sps", "rollout_s", "update_s", "learning_rate", "episodes",
        "return_mean",
        *[f"return_d{d}" for d in cfg.dims],
        *([] if cfg.body_mix.chains_only else ["return_chains", "return_trees"]),  # keyed by shape as well
        "policy_loss", "value_loss", "entropy", "approx_kl", "clip_frac", "explained_variance", "log_std",
        *update_columns(cfg.dims),
    ]  # fmt: skip


SWIMMERS = ("swimmers", 1)
"""the state section of the simulator trainer (name, version): every swimmer's state (bodies, MuJoCo, RNG)"""


def train(
    cfg: TrainConfig,
    run_dir: str | Path,
    resume: bool = False,
    on_row: RowHook | None = None,
    rollout_pool: PoolFactory | None = None,
    init: str | Path | None = None,
) -> Path:
    """Train into ``run_dir`` (its files: ``run_dir.RunDir``). ``on_row(row,
    saved)`` hears each progress row once it is written and, when ``saved``, the state of its step too (a Ray
    Tune trial reports it, with the run's own state files as its checkpoint). ``rollout_pool`` makes the
    workers of ``cfg.rollout_workers`` > 1. ``init``: a policy checkpoint (.safetensors beside its .json) a new
    run starts from (fine-tuning), its architecture the run's (its global width must be the bodies')."""
    if cfg.rollout_workers > 1 and rollout_pool is None:
        raise ValueError("rollout_workers > 1 needs a pool of workers (morph-train makes one on Ray)")
    cfg, initial = initial_policy(cfg, init, resume)
    run = Run(run_dir, cfg, resume=resume, on_row=on_row)
    learner, gen = new_learner(cfg, initial)
    helpers = Helpers(helper_spec(cfg, learner), learner) if cfg.processes > 1 else None
    pool = _rollout_pool(cfg, learner, gen, helpers, rollout_pool)
    try:
        if run.resuming:
            state = run.restore(learner, gen)  # TrainingStateError when neither state file is usable
            swimmers, arrays = state.section(*SWIMMERS)
            env_parts = split_env_state(swimmers, {k: v.numpy() for k, v in arrays.items()}, pool.bounds)
            pool.set_states([WorkerState(*part, _saved_rng(state.tensors, name))
                             for part, name in zip(env_parts, pool.rng_names, strict=True)])  # fmt: skip
            _check_policy_checkpoints(run.files, run.counters["global_step"], learner.policy)
        else:
            run.start(init=init)
        fit(run, learner, gen, Rollouts(cfg, run.counters, pool, helpers))
    finally:
        pool.close()
        if helpers is not None:
            helpers.close()
    return run.dir


class Rollouts:
    """The simulator as ``fit``'s source: rollouts of the vectorised swimmers, their advantages, and the
    episodes' returns as its columns; its state is every swimmer's (``SWIMMERS``)."""

    name, time_column, bounded = "the simulator", "rollout_s", True
    state_every_update = guard = False
    save_policy = staticmethod(save_policy)

    def __init__(self, cfg: TrainConfig, counters: dict, pool: RolloutPool, helpers: Helpers | None):
        self.cfg, self.counters, self.pool, self.peers = cfg, counters, pool, helpers
        self.dims, self.trees = cfg.dims, not cfg.body_mix.chains_only  # the spec parsed once, not every iteration
        self.recent: list[Episode] = []
        self.worker_states: list[WorkerState] = []

    def columns(self) -> list[str]:
        return log_columns(self.cfg)

    def finished(self) -> bool:
        return self.counters["global_step"] >= self.cfg.total_timesteps

    def collect(self, learner: Learner) -> Collected:
        # 1. Rollout, by a NumPy snapshot of the policy: a torch forward pass over six chains
        # is mostly per-operation overhead (policy.numpy_actor, tested equal to torch).
        t0 = time.perf_counter()
        pool, rollout = self.pool, self.pool.rollout
        if not pool.collecting:  # else started after the last update (``row``)
            pool.start(learner.params.theta)
        episodes = pool.finish()
        rollout_s = time.perf_counter() - t0
        # 2. Advantages.
        advantages, returns = compute_gae(
            *map(torch.from_numpy, (rollout.rewards, rollout.values, rollout.terminated, rollout.truncated,
                                    rollout.final_values, rollout.last_value)),
            self.cfg.gamma, self.cfg.gae_lambda,
        )  # fmt: skip
        if self.peers is not None:
            self.peers.publish_advantages(advantages, returns)
        return Collected(rollout.batch(advantages, returns), rollout_s, (episodes, learner))

    def updated(self, collected: Collected) -> None:
        pass

    def row(self, collected: Collected, checkpoint: bool) -> dict:
        # The workers' next rollout starts first (their swimmers' states taken before it when a checkpoint is
        # due): the logging and saving overlap it. It writes their columns of the rollout, so nothing after
        # this reads the batch.
        episodes, learner = collected.context
        self.worker_states = self.pool.get_states() if checkpoint else []
        if not self.finished():
            self.pool.start(learner.params.theta)
        self.recent = (self.recent + episodes)[-50:]
        row = {"episodes": len(episodes), "return_mean": _mean_return(episodes)}
        for d in self.dims:
            row[f"return_d{d}"] = _mean_return([e for e in episodes if e.num_joints == d])
        if self.trees:
            row["return_chains"] = _mean_return([e for e in episodes if is_chain_label(e.body)])
            row["return_trees"] = _mean_return([e for e in episodes if not is_chain_label(e.body)])
        return row

    def state(self) -> tuple[dict, dict, dict]:
        states, pool = self.worker_states, self.pool
        swimmers, arrays = merge_env_states([(s.env_meta, s.env_arrays) for s in states])
        more_rngs = {name: s.rng for name, s in zip(pool.rng_names, states, strict=True) if name}
        name, version = SWIMMERS
        return {name: {**swimmers, "version": version}}, {f"{name}.{k}": v for k, v in arrays.items()}, more_rngs

    def progress(self) -> tuple[int, int, str]:
        return self.cfg.total_timesteps, self.counters["global_step"], "step"

    def advance(self, row: dict) -> tuple[int, dict]:
        ret = _mean_return(self.recent)
        postfix = {"ret": f"{ret:.1f}", "sps": f"{row['sps']:.0f}", "kl": f"{row['approx_kl']:.3f}"}
        return self.cfg.num_envs * self.cfg.num_steps, postfix


def _mean_return(episodes: list[Episode]) -> float:
    return float(np.mean([e.episode_return for e in episodes])) if episodes else math.nan


def rollout_spec(cfg: TrainConfig) -> RolloutSpec:
    """The rollout of a run of ``cfg``, as its rollout workers build it (``algo.rollout_workers``)."""
    return RolloutSpec(bodies=str(cfg.body_mix), num_envs=cfg.num_envs, num_steps=cfg.num_steps, seed=cfg.seed,
                       env_threads=cfg.env_threads, policy=dataclasses.asdict(cfg.policy))  # fmt: skip


def helper_spec(cfg: TrainConfig, learner: Learner) -> HelperSpec:
    """What the helper processes of a run of ``cfg`` start from (``algo.data_parallel``): ``learner``'s policy."""
    spec = dataclasses.replace(rollout_spec(cfg), policy=dataclasses.asdict(learner.policy.config))
    return HelperSpec(processes=cfg.processes, rollout=spec, update=cfg.update_config(), compile=cfg.compile)


def _rollout_pool(cfg, learner, gen, helpers, rollout_pool) -> RolloutPool:
    """Who steps the swimmers: this process alone (with the run's generator), with the helpers, or workers."""
    spec = rollout_spec(cfg)
    if cfg.rollout_workers > 1:
        return rollout_pool(spec, cfg.rollout_workers)
    if helpers is None:
        return LocalPool(RolloutWorker(spec.worker(0, 1), learner.policy, generator=gen))
    first = spec.worker(0, cfg.processes)  # this process steps the first share of the swimmers
    worker = RolloutWorker(first, learner.policy, helpers.rollout.columns(first.lo, first.hi), gen)
    return HelperPool(worker, helpers)


def _saved_rng(tensors: dict[str, torch.Tensor], name: str | None) -> torch.Tensor | None:
    """A worker's saved generator (None: the run's own, restored with the run)."""
    state = None if name is None else tensors.get(f"rng.{name}")
    if name is not None and state is None:  # a run started with fewer processes: its noise starts from its seed
        log.warning("resume: the checkpoint has no noise generator rng.%s; it starts from its seed", name)
    return state


def _check_policy_checkpoints(files: RunDir, step: int, policy: GraphActorCritic) -> None:
    """On resume: say which weights-only checkpoints are damaged (a disk fault, a copy cut short). The one of
    the resumed step is written again from the restored policy (the same weights); later ones are rewritten
    as the run passes their steps again; earlier ones cannot be remade and are only named."""
    for saved, path in files.saved_checkpoints():
        try:
            load_checkpoint(path)
        except CheckpointError as err:
            if saved == step:
                policy.save(path, metadata={"global_step": step})
                log.warning("resume: %s; written again from the resumed state", err)
            else:
                log.warning("resume: %s", err)


def load_run_config(run_dir: str | Path, overrides: dict | None = None) -> TrainConfig:
    cfg = TrainConfig.from_dict(RunDir(run_dir).read_config())
    return replace_nested(cfg, overrides or {})
