"""PPO for graph policies on swimmers of mixed chain lengths: the simulator training loop.

One loop, in the order a reader thinks (and as CleanRL writes it): collect a
rollout from the vectorised swimmers, compute advantages, ``update`` (the
one PPO update every data source uses, ``algo.update``), log and checkpoint.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import pairwise
from pathlib import Path

import numpy as np
import torch

from morph_core.algo.checkpoint import (
    previous_state_path,
    restore_optimizer,
    resume_training_state,
    save_training_state,
    sub_dict,
)
from morph_core.algo.data_parallel import HelperPool, Helpers, HelperSpec
from morph_core.algo.learner import Learner
from morph_core.algo.minibatches import minibatch_cuts
from morph_core.algo.ppo import compute_gae, explained_variance
from morph_core.algo.rollout_workers import LocalPool, RolloutPool, RolloutSpec, RolloutWorker, WorkerState
from morph_core.algo.run_log import RunLog
from morph_core.algo.trust_region import rule_names
from morph_core.algo.update import update
from morph_core.algo.update_config import UpdateConfig
from morph_core.algo.update_stats import epoch_columns
from morph_core.env.bodies import BodyMix, fit_global_features, is_chain_label, parse_bodies
from morph_core.env.vec_env import Episode, merge_env_states, split_env_state
from morph_core.policy.actor_critic import GraphActorCritic, PolicyConfig
from morph_core.policy.weights import CheckpointError, load_checkpoint
from morph_core.util.atomic import atomic_writer
from morph_core.util.config_cli import check_field_types, replace_nested

log = logging.getLogger(__name__)

RowHook = Callable[[dict, bool], None]
"""hears a run's progress row and whether that step's state was saved: ``on_row(row, saved)``"""
PoolFactory = Callable[[RolloutSpec, int], RolloutPool]
"""makes the pool of ``rollout_workers`` > 1 workers for a run's rollout: ``pool(spec, workers)`` (the core
has no such pool: ``trainer.ray_rollouts`` makes one of Ray actors)"""


@dataclass
class TrainConfig:
    """PPO with per-sample clip ranges; defaults are the paper's configuration."""

    clip_mode: str = "compensated"
    """trust-region rule, a name from algo.trust_region.RULES: 'fixed' clips r to 1 +- eps,
    'compensated' to 1 +- eps*sqrt(dim A) per sample"""
    clip_eps: float = 0.111
    """base clip range eps"""
    total_timesteps: int = 1_000_000
    """env steps to train for (summed over envs)"""
    seed: int = 1
    """seed of envs, action noise and minibatch shuffling"""
    num_envs: int = 6
    """swimmers stepped together"""
    num_steps: int = 1024
    """steps per swimmer per rollout (rollout = num_envs * num_steps samples)"""
    minibatch_size: int = 256
    """samples per gradient step"""
    update_epochs: int = 10
    """passes over each rollout"""
    learning_rate: float = 0.01
    """Adam learning rate (constant unless anneal_lr)"""
    anneal_lr: bool = False
    """decay the learning rate linearly to 0 over the run (CleanRL's anneal_lr); off in the paper's configuration"""
    adam_eps: float = 1e-5
    """Adam epsilon"""
    gamma: float = 0.98
    """discount"""
    gae_lambda: float = 0.98
    """GAE lambda"""
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
    """adapt the kl-penalty rules' beta to kl_target after each update; false keeps beta = kl_beta"""
    off_policy_objective: str = "decoupled"
    """how samples of an older policy (bags, live) enter the update: 'decoupled' (ratio against the policy as
    the update starts, each sample weighted by min(pi_prox / pi_behav, proximal_weight_cap)) or 'behaviour'
    (PPO's own loss, the ratio against the policy that acted); simulator rollouts are on-policy either way"""
    min_joints: int = 2
    """shortest chain drawn at a reset; with ``bodies``, the fewest joints its bodies have (set from it)"""
    max_joints: int = 10
    """longest chain drawn at a reset; with ``bodies``, the most joints its bodies have (set from it)"""
    bodies: str = ""
    """the bodies drawn at each reset, in ``env.bodies``' grammar: chains and trees, e.g. '2-10,random:3-10'
    (chains of 2..10 joints or random trees of 3..10); empty: chains of min_joints..max_joints"""
    checkpoint_interval: int = 6000
    """env steps between checkpoints (taken at the end of the update that crosses the mark)"""
    torch_threads: int = 1
    """torch intra-op threads in the update (rollout inference always uses 1)"""
    env_threads: int = 1
    """threads stepping the swimmers (MuJoCo releases the GIL) in each process"""
    processes: int = 1
    """processes sharing the swimmers and every minibatch's gradient (algo.data_parallel); 2 uses both cores
    of a 2-core machine. The action noise's random streams depend on it, so a run keeps its count"""
    rollout_workers: int = 1
    """rollout workers (Ray actors, ``morph-train --rollout-workers``) that each step a share of the swimmers
    (``algo.rollout_workers.env_bounds``) while this process updates; 1: this process steps them all. Worker
    r draws its action noise from worker_seed(seed, r) (``algo.rollout_workers``), so the noise, like
    ``processes``', depends on the count and a run keeps it"""
    compile: bool = True
    """compile the minibatch loss and its backward into one Inductor graph (algo.compiled; ~1.5x faster
    update, ~15-30 s to compile once; falls back to eager mode with a warning where Inductor cannot run)"""
    tensorboard: bool = True
    """also write TensorBoard scalars"""
    progress_bar: bool = True
    """show a progress bar"""
    policy: PolicyConfig = field(default_factory=PolicyConfig)

    def __post_init__(self):
        if isinstance(self.policy, dict):
            self.policy = PolicyConfig.from_dict(self.policy)
        if not isinstance(self.policy, PolicyConfig):
            raise TypeError(f"policy must be a JSON object of policy fields, got {self.policy!r}")
        check_field_types(self)
        if self.clip_mode not in rule_names():
            raise ValueError(f"clip_mode must be one of {rule_names()}, got {self.clip_mode!r}")
        if not 1 <= self.min_joints <= self.max_joints <= 64:
            raise ValueError(f"need 1 <= min_joints <= max_joints <= 64, got {self.min_joints}, {self.max_joints}")
        if self.bodies:  # parsed here, so that a bad spec is refused before anything runs
            self._joint_range_from_bodies()
        self.policy = fit_global_features(self.policy, self.body_mix)  # 12 with centipedes
        for name in ("num_envs", "num_steps", "minibatch_size", "update_epochs", "total_timesteps"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.minibatch_size > self.batch_size:
            raise ValueError(f"minibatch_size {self.minibatch_size} exceeds the rollout size {self.batch_size}")
        smallest = min(b - a for a, b in pairwise(minibatch_cuts(self.batch_size, self.minibatch_size)))
        if not 1 <= self.processes <= min(self.num_envs, smallest):
            raise ValueError(f"processes must be in 1..{min(self.num_envs, smallest)} (each needs a swimmer and a "
                             f"part of every minibatch), got {self.processes}")  # fmt: skip
        if not 1 <= self.rollout_workers <= self.num_envs:
            raise ValueError(f"rollout_workers must be in 1..{self.num_envs} (each needs a swimmer), "
                             f"got {self.rollout_workers}")  # fmt: skip
        if self.rollout_workers > 1 and self.processes > 1:
            raise ValueError("rollout_workers > 1 and processes > 1 both share the swimmers out: choose one")
        if self.clip_eps <= 0:
            raise ValueError(f"clip_eps must be > 0, got {self.clip_eps}")
        self.update_config()  # the update's own checks: weight cap, KL settings, objective and rule together

    @property
    def batch_size(self) -> int:
        return self.num_envs * self.num_steps

    def _joint_range_from_bodies(self) -> None:
        """min_joints..max_joints become the bodies' joint range (the action dimensions they draw), which
        every reader of a run's config takes for the trained range; a range given that disagrees is refused."""
        lo, hi = parse_bodies(self.bodies).joint_range
        defaults = tuple(f.default for f in dataclasses.fields(self) if f.name in ("min_joints", "max_joints"))
        if (self.min_joints, self.max_joints) not in (defaults, (lo, hi)):
            raise ValueError(f"min_joints..max_joints ({self.min_joints}..{self.max_joints}) disagree with bodies "
                             f"{self.bodies!r} ({lo}..{hi} joints): give bodies alone")  # fmt: skip
        self.min_joints, self.max_joints = lo, hi

    @property
    def body_mix(self) -> BodyMix:
        """The bodies of this run's swimmers (``bodies``, or the chains of min_joints..max_joints)."""
        return parse_bodies(self.bodies or f"{self.min_joints}-{self.max_joints}")

    @property
    def dims(self) -> range:
        """The action dimensions d the run's bodies can have: the keys of its per-dimension statistics."""
        lo, hi = self.body_mix.joint_range
        return range(lo, hi + 1)

    def update_config(self) -> UpdateConfig:
        return UpdateConfig(
            rule=self.clip_mode,
            clip_eps=self.clip_eps,
            update_epochs=self.update_epochs,
            minibatch_size=self.minibatch_size,
            vf_coef=self.vf_coef,
            ent_coef=self.ent_coef,
            max_grad_norm=self.max_grad_norm,
            proximal_weight_cap=self.proximal_weight_cap,
            kl_target=self.kl_target,
            kl_beta=self.kl_beta,
            kl_adaptive=self.kl_adaptive,
            off_policy_objective=self.off_policy_objective,
        )

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown train config fields: {sorted(unknown)}")
        return cls(**d)


def log_columns(cfg: TrainConfig) -> list[str]:
    per_dim = ["clip_frac", "in_eps_frac", "logr_mean", "logr_std", "approx_kl"]
    return [
        "global_step", "iteration", "wall_time", "sps", "rollout_s", "update_s", "learning_rate", "episodes",
        "return_mean",
        *[f"return_d{d}" for d in cfg.dims],
        *([] if cfg.body_mix.chains_only else ["return_chains", "return_trees"]),  # keyed by shape as well
        "policy_loss", "value_loss", "entropy", "approx_kl", "clip_frac", "explained_variance", "log_std",
        *[f"{name}_d{d}" for name in per_dim for d in cfg.dims],
        *epoch_columns(cfg.dims),
    ]  # fmt: skip


def train(
    cfg: TrainConfig,
    run_dir: str | Path,
    resume: bool = False,
    on_row: RowHook | None = None,
    rollout_pool: PoolFactory | None = None,
) -> Path:
    """Train into ``run_dir`` (config.json, progress.csv, tb/, checkpoints/, state.safetensors). ``on_row(row,
    saved)`` hears each progress row once it is written and, when ``saved``, the state of its step too (a Ray
    Tune trial reports it, with the run's own state files as its checkpoint). ``rollout_pool`` makes the
    workers of ``cfg.rollout_workers`` > 1."""
    run_dir = Path(run_dir)
    state_path = run_dir / "state.safetensors"
    ckpt_dir = run_dir / "checkpoints"

    # Threads before init: the orthogonal init's QR differs in its last bits with the thread count.
    torch.set_num_threads(1)
    torch.manual_seed(cfg.seed)
    policy = GraphActorCritic(cfg.policy)
    learner = Learner.create(policy, cfg.learning_rate, cfg.adam_eps, cfg.compile)
    optimizer = learner.optimizer
    gen = torch.Generator().manual_seed(cfg.seed)
    if cfg.rollout_workers > 1 and rollout_pool is None:
        raise ValueError("rollout_workers > 1 needs a pool of workers (morph-train makes one on Ray)")
    helpers = Helpers(helper_spec(cfg, learner), learner) if cfg.processes > 1 else None
    pool = _rollout_pool(cfg, learner, gen, helpers, rollout_pool)
    try:
        global_step, iteration, last_ckpt = 0, 0, 0
        if resume and (state_path.exists() or previous_state_path(state_path).exists()):
            resumed = resume_training_state(state_path)  # TrainingStateError when neither state file is usable
            tensors, meta = resumed.tensors, resumed.meta
            policy.load_state_dict(sub_dict(tensors, "policy."))
            restore_optimizer(optimizer, tensors, meta)
            learner.restore_state(tensors)
            gen.set_state(tensors["rng.torch"])
            env_arrays = {k: v.numpy() for k, v in sub_dict(tensors, "env.").items()}
            env_parts = split_env_state(meta["env"], env_arrays, pool.bounds)
            pool.set_states(
                [
                    WorkerState(*part, _saved_rng(tensors, name))
                    for part, name in zip(env_parts, pool.rng_names, strict=True)
                ]
            )
            global_step, iteration, last_ckpt = (meta["counters"][k] for k in ("global_step", "iteration", "last_ckpt"))
            _check_policy_checkpoints(ckpt_dir, global_step, policy)
        else:
            run_dir.mkdir(parents=True, exist_ok=True)
            with atomic_writer(run_dir / "config.json") as f:
                json.dump(cfg.to_dict(), f, indent=2)
        _train_loop(cfg, run_dir, resume, learner, gen, pool, helpers, (global_step, iteration, last_ckpt), on_row)
    finally:
        pool.close()
        if helpers is not None:
            helpers.close()
    return run_dir


def _train_loop(cfg, run_dir, resume, learner, gen, pool: RolloutPool, helpers, counters, on_row) -> None:
    state_path, ckpt_dir = run_dir / "state.safetensors", run_dir / "checkpoints"
    policy, optimizer = learner.policy, learner.optimizer
    global_step, iteration, last_ckpt = counters
    log = RunLog(run_dir, log_columns(cfg), resume_step=global_step if resume else None, tensorboard=cfg.tensorboard)
    T, E = cfg.num_steps, cfg.num_envs
    rollout = pool.rollout
    update_cfg = cfg.update_config()
    dims, trees = cfg.dims, not cfg.body_mix.chains_only  # the spec parsed once, not at every iteration
    recent: list[Episode] = []
    bar = _progress(cfg, global_step)
    while global_step < cfg.total_timesteps:
        iteration += 1

        # 1. Rollout, by a NumPy snapshot of the policy: a torch forward pass over six chains
        # is mostly per-operation overhead (policy.numpy_actor, tested equal to torch).
        t0 = time.perf_counter()
        if not pool.collecting:  # else started after the last update (step 4)
            pool.start(learner.params.theta)
        episodes = pool.finish()
        global_step += T * E
        rollout_s = time.perf_counter() - t0

        # 2. Advantages.
        advantages, returns = compute_gae(
            *map(torch.from_numpy, (rollout.rewards, rollout.values, rollout.terminated, rollout.truncated,
                                    rollout.final_values, rollout.last_value)),
            cfg.gamma, cfg.gae_lambda,
        )  # fmt: skip
        if helpers is not None:
            helpers.publish_advantages(advantages, returns)
        batch = rollout.batch(advantages, returns)

        # 3. Update.
        t1 = time.perf_counter()
        if cfg.anneal_lr:  # a function of the step count alone, so a resumed run gets the same rate
            optimizer.param_groups[0]["lr"] = cfg.learning_rate * (1.0 - (global_step - T * E) / cfg.total_timesteps)
        torch.set_num_threads(cfg.torch_threads)
        stats = update(learner, batch, update_cfg, gen, peers=helpers)
        update_s = time.perf_counter() - t1

        # 4. Log and checkpoint. The workers' next rollout starts first (their swimmers' states taken
        # before it when a checkpoint is due): this process's logging and saving overlap it. It writes
        # their columns of the rollout, so nothing below reads the batch.
        explained = explained_variance(batch.values, batch.returns)
        checkpoint = global_step // cfg.checkpoint_interval > last_ckpt // cfg.checkpoint_interval or (
            global_step >= cfg.total_timesteps
        )
        worker_states = pool.get_states() if checkpoint else []
        if global_step < cfg.total_timesteps:
            pool.start(learner.params.theta)
        recent = (recent + episodes)[-50:]
        row = {
            "global_step": global_step,
            "iteration": iteration,
            "wall_time": time.time(),
            "sps": T * E / (rollout_s + update_s),
            "rollout_s": rollout_s,
            "update_s": update_s,
            "learning_rate": optimizer.param_groups[0]["lr"],
            "episodes": len(episodes),
            "return_mean": _mean_return(episodes),
            **stats.row(dims),
            "explained_variance": explained,
            "log_std": float(policy.log_std.detach()),
        }
        for d in dims:
            row[f"return_d{d}"] = _mean_return([e for e in episodes if e.num_joints == d])
        if trees:
            row["return_chains"] = _mean_return([e for e in episodes if is_chain_label(e.body)])
            row["return_trees"] = _mean_return([e for e in episodes if not is_chain_label(e.body)])
        log.log(row)
        log.update_histograms(global_step, stats)
        if checkpoint:
            last_ckpt = global_step
            policy.save(ckpt_dir / f"policy_{global_step:08d}.safetensors", metadata={"global_step": global_step})
            env_meta, env_arrays = merge_env_states([(s.env_meta, s.env_arrays) for s in worker_states])
            more_rngs = {name: s.rng for name, s in zip(pool.rng_names, worker_states, strict=True) if name}
            counters = {"global_step": global_step, "iteration": iteration, "last_ckpt": last_ckpt}
            save_training_state(
                state_path, policy, optimizer, gen, env_meta, env_arrays, counters, learner.state_tensors(), more_rngs
            )
        if on_row is not None:
            on_row(row, checkpoint)
        if bar is not None:
            bar.update(T * E)
            ret = _mean_return(recent)
            bar.set_postfix(ret=f"{ret:.1f}", sps=f"{row['sps']:.0f}", kl=f"{row['approx_kl']:.3f}")
    if bar is not None:
        bar.close()
    log.close()


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


def _check_policy_checkpoints(ckpt_dir: Path, step: int, policy: GraphActorCritic) -> None:
    """On resume: say which weights-only checkpoints are damaged (a disk fault, a copy cut short). The one of
    the resumed step is written again from the restored policy (the same weights); later ones are rewritten
    as the run passes their steps again; earlier ones cannot be remade and are only named."""
    for path in sorted(ckpt_dir.glob("policy_*.safetensors")):
        try:
            load_checkpoint(path)
        except CheckpointError as err:
            if path.name == f"policy_{step:08d}.safetensors":
                policy.save(path, metadata={"global_step": step})
                log.warning("resume: %s; written again from the resumed state", err)
            else:
                log.warning("resume: %s", err)


def _progress(cfg: TrainConfig, start: int):
    if not cfg.progress_bar:
        return None
    from tqdm import tqdm

    return tqdm(total=cfg.total_timesteps, initial=start, unit="step", dynamic_ncols=True)


def load_run_config(run_dir: str | Path, overrides: dict | None = None) -> TrainConfig:
    cfg = TrainConfig.from_dict(json.loads((Path(run_dir) / "config.json").read_text()))
    return replace_nested(cfg, overrides or {})
