"""PPO for graph policies on swimmers of mixed chain lengths: the training loop.

One loop, in the order a reader thinks: collect a rollout from the
vectorised swimmers, bootstrap and compute GAE, then epochs of minibatch
updates with the per-sample clip range, then log and checkpoint.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from morph_core.algo.checkpoint import load_training_state, restore_optimizer, save_training_state, sub_dict
from morph_core.algo.compiled import compiled
from morph_core.algo.param_buffer import flatten_parameters
from morph_core.algo.ppo import (
    CLIP_MODES,
    PerDimensionStats,
    clip_range,
    compute_gae,
    explained_variance,
    ppo_loss,
)
from morph_core.algo.run_log import RunLog
from morph_core.env.vec_env import PaddedObs, SwimmerVecEnv
from morph_core.policy.actor_critic import GraphActorCritic, PolicyConfig
from morph_core.policy.chains import ChainBatch, pad_observations
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.util.atomic import atomic_writer
from morph_core.util.config_cli import replace_nested


@dataclass
class TrainConfig:
    """PPO with per-sample clip ranges; defaults are the paper's configuration."""

    clip_mode: str = "compensated"
    """'fixed': clip r to 1 +- eps; 'compensated': 1 +- eps*sqrt(dim A) per sample"""
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
    min_joints: int = 2
    """shortest chain drawn at a reset"""
    max_joints: int = 10
    """longest chain drawn at a reset"""
    checkpoint_interval: int = 6000
    """env steps between checkpoints (taken at the end of the update that crosses the mark)"""
    torch_threads: int = 1
    """torch intra-op threads in the update (rollout inference always uses 1)"""
    env_threads: int = 1
    """threads stepping the swimmers (MuJoCo releases the GIL); 2 uses both cores of a 2-core machine"""
    compile: bool = True
    """torch.compile the minibatch loss and its backward (~1.5x faster update, ~20 s to compile once;
    falls back to eager mode with a warning where Inductor cannot run)"""
    tensorboard: bool = True
    """also write TensorBoard scalars"""
    progress_bar: bool = True
    """show a progress bar"""
    policy: PolicyConfig = field(default_factory=PolicyConfig)

    def __post_init__(self):
        if isinstance(self.policy, dict):
            self.policy = PolicyConfig.from_dict(self.policy)
        if self.clip_mode not in CLIP_MODES:
            raise ValueError(f"clip_mode must be one of {CLIP_MODES}, got {self.clip_mode!r}")
        if not 1 <= self.min_joints <= self.max_joints <= 64:
            raise ValueError(f"need 1 <= min_joints <= max_joints <= 64, got {self.min_joints}, {self.max_joints}")
        for name in ("num_envs", "num_steps", "minibatch_size", "update_epochs", "total_timesteps"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.minibatch_size > self.batch_size:
            raise ValueError(f"minibatch_size {self.minibatch_size} exceeds the rollout size {self.batch_size}")
        if self.clip_eps <= 0:
            raise ValueError(f"clip_eps must be > 0, got {self.clip_eps}")

    @property
    def batch_size(self) -> int:
        return self.num_envs * self.num_steps

    @property
    def dims(self) -> range:
        return range(self.min_joints, self.max_joints + 1)

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
        "policy_loss", "value_loss", "entropy", "approx_kl", "clip_frac", "explained_variance", "log_std",
        *[f"{name}_d{d}" for name in per_dim for d in cfg.dims],
    ]  # fmt: skip


def _arrays(obs: PaddedObs) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    return obs.joint_pos, obs.joint_vel, obs.global_feats, obs.num_joints


def train(cfg: TrainConfig, run_dir: str | Path, resume: bool = False) -> Path:
    """Train into ``run_dir`` (config.json, progress.csv, tb/, checkpoints/, state.safetensors)."""
    run_dir = Path(run_dir)
    state_path = run_dir / "state.safetensors"
    ckpt_dir = run_dir / "checkpoints"

    envs = SwimmerVecEnv(cfg.num_envs, (cfg.min_joints, cfg.max_joints), seed=cfg.seed, num_threads=cfg.env_threads)
    # Threads before init: the orthogonal init's QR differs in its last bits with the thread count.
    torch.set_num_threads(1)
    torch.manual_seed(cfg.seed)
    policy = GraphActorCritic(cfg.policy)
    theta = flatten_parameters(policy)  # all parameters as one vector: optimizer and clip are a few ops
    optimizer = torch.optim.Adam([theta], lr=cfg.learning_rate, eps=cfg.adam_eps, fused=True)
    loss_fn = compiled(ppo_loss, cfg.compile)
    gen = torch.Generator().manual_seed(cfg.seed)
    global_step, iteration, last_ckpt = 0, 0, 0
    if resume and state_path.exists():
        tensors, meta = load_training_state(state_path)
        policy.load_state_dict(sub_dict(tensors, "policy."))
        restore_optimizer(optimizer, tensors, meta)
        gen.set_state(tensors["rng.torch"])
        envs.set_state(meta["env"], {k: v.numpy() for k, v in sub_dict(tensors, "env.").items()})
        global_step, iteration, last_ckpt = (meta["counters"][k] for k in ("global_step", "iteration", "last_ckpt"))
    else:
        run_dir.mkdir(parents=True, exist_ok=True)
        with atomic_writer(run_dir / "config.json") as f:
            json.dump(cfg.to_dict(), f, indent=2)
    log = RunLog(run_dir, log_columns(cfg), resume_step=global_step if resume else None, tensorboard=cfg.tensorboard)

    # Rollout storage, padded to the longest chain the range allows; NumPy during the rollout,
    # shared with torch (no copy) for the update.
    T, E, J = cfg.num_steps, cfg.num_envs, cfg.max_joints
    obs_pos, obs_vel = np.zeros((T, E, J), np.float32), np.zeros((T, E, J), np.float32)
    obs_glob, obs_n = np.zeros((T, E, 4), np.float32), np.zeros((T, E), np.int64)
    actions, logprobs = np.zeros((T, E, J), np.float32), np.zeros((T, E), np.float32)
    rewards, dones, values = np.zeros((T, E), np.float32), np.zeros((T, E), np.float32), np.zeros((T, E), np.float32)

    obs = envs.observations()
    next_done = np.zeros(E, np.float32)
    recent: list[tuple[int, float, int]] = []
    bar = _progress(cfg, global_step)
    while global_step < cfg.total_timesteps:
        iteration += 1
        t0 = time.perf_counter()
        episodes: list[tuple[int, float, int]] = []

        # 1. Rollout, by a NumPy snapshot of the policy: a torch forward pass over six chains
        # is mostly per-operation overhead (policy_numpy, tested equal to torch).
        actor = NumpyPolicy(policy)
        for t in range(T):
            obs_pos[t], obs_vel[t], obs_glob[t], obs_n[t] = _arrays(obs)
            dones[t] = next_done
            noise = torch.randn((E, J), generator=gen).numpy()
            actions[t], logprobs[t], values[t], _ = actor.act(*_arrays(obs), noise)
            step = envs.step(actions[t])
            rewards[t] = step.reward
            # Time-limit bootstrapping: a truncated episode would have gone on, worth gamma * V(final obs).
            trunc = [i for i in step.final_obs if step.truncated[i]]
            if trunc:
                final = pad_observations([step.final_obs[i] for i in trunc], J)
                rewards[t, trunc] += cfg.gamma * actor.forward(*final)[1]
            next_done = (step.terminated | step.truncated).astype(np.float32)
            obs = step.obs
            episodes += step.episodes
            global_step += E
        rollout_s = time.perf_counter() - t0

        # 2. Advantages.
        next_value = torch.from_numpy(actor.forward(*_arrays(obs))[1])
        # A truncation was bootstrapped above; for GAE it cuts the trace like a termination.
        advantages, returns = compute_gae(
            *map(torch.from_numpy, (rewards, values, dones)), next_value, torch.from_numpy(next_done),
            cfg.gamma, cfg.gae_lambda,
        )  # fmt: skip

        # 3. Update: epochs of shuffled minibatches, each sample clipped at its own eps_i.
        t1 = time.perf_counter()
        if cfg.anneal_lr:  # a function of the step count alone, so a resumed run gets the same rate
            optimizer.param_groups[0]["lr"] = cfg.learning_rate * (1.0 - (global_step - T * E) / cfg.total_timesteps)
        torch.set_num_threads(cfg.torch_threads)
        b_pos, b_vel, b_glob, b_n = (torch.from_numpy(x).flatten(0, 1) for x in (obs_pos, obs_vel, obs_glob, obs_n))
        b_actions, b_logprobs = torch.from_numpy(actions).flatten(0, 1), torch.from_numpy(logprobs).flatten()
        b_adv, b_returns, b_values = advantages.flatten(), returns.flatten(), torch.from_numpy(values).flatten()
        b_eps = clip_range(cfg.clip_eps, b_n, cfg.clip_mode)
        mb_losses, mb_index, mb_log_ratio = [], [], []
        for _ in range(cfg.update_epochs):
            perm = torch.randperm(cfg.batch_size, generator=gen)
            for start in range(0, cfg.batch_size, cfg.minibatch_size):
                mb = perm[start : start + cfg.minibatch_size]
                batch = ChainBatch.from_padded(b_pos[mb], b_vel[mb], b_glob[mb], b_n[mb])
                loss, pg_loss, v_loss, entropy, log_ratio = loss_fn(
                    policy,
                    batch,
                    b_actions[mb, : batch.max_joints],
                    b_logprobs[mb],
                    b_adv[mb],
                    b_returns[mb],
                    b_eps[mb],
                    cfg.vf_coef,
                    cfg.ent_coef,
                )
                theta.grad.zero_()
                loss.backward()
                torch.nn.utils.clip_grad_norm_(theta, cfg.max_grad_norm)
                optimizer.step()
                # Statistics are reduced once per update, not per minibatch.
                mb_losses.append(torch.stack([pg_loss, v_loss, entropy]).detach())
                mb_index.append(mb)
                mb_log_ratio.append(log_ratio.detach())
        index, log_ratio = torch.cat(mb_index), torch.cat(mb_log_ratio)
        stats = PerDimensionStats(cfg.max_joints)
        stats.add(b_n[index], log_ratio, log_ratio.exp(), b_eps[index], cfg.clip_eps)
        pg_loss, v_loss, entropy = torch.stack(mb_losses).mean(0).tolist()
        update_s = time.perf_counter() - t1

        # 4. Log and checkpoint.
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
            "return_mean": float(np.mean([r for _, r, _ in episodes])) if episodes else math.nan,
            "policy_loss": pg_loss,
            "value_loss": v_loss,
            "entropy": entropy,
            **stats.overall(),
            "explained_variance": explained_variance(b_values, b_returns),
            "log_std": float(policy.log_std.detach()),
            **stats.summary(cfg.dims),
        }
        for d in cfg.dims:
            rs = [r for n, r, _ in episodes if n == d]
            row[f"return_d{d}"] = float(np.mean(rs)) if rs else math.nan
        log.log(row)
        if global_step // cfg.checkpoint_interval > last_ckpt // cfg.checkpoint_interval or (
            global_step >= cfg.total_timesteps
        ):
            last_ckpt = global_step
            policy.save(ckpt_dir / f"policy_{global_step:08d}.safetensors", metadata={"global_step": global_step})
            env_meta, env_arrays = envs.get_state()
            counters = {"global_step": global_step, "iteration": iteration, "last_ckpt": last_ckpt}
            save_training_state(state_path, policy, optimizer, gen, env_meta, env_arrays, counters)
        if bar is not None:
            bar.update(T * E)
            ret = np.mean([r for _, r, _ in recent]) if recent else float("nan")
            bar.set_postfix(ret=f"{ret:.1f}", sps=f"{row['sps']:.0f}", kl=f"{row['approx_kl']:.3f}")
    if bar is not None:
        bar.close()
    envs.close()
    log.close()
    return run_dir


def _progress(cfg: TrainConfig, start: int):
    if not cfg.progress_bar:
        return None
    from tqdm import tqdm

    return tqdm(total=cfg.total_timesteps, initial=start, unit="step", dynamic_ncols=True)


def load_run_config(run_dir: str | Path, overrides: dict | None = None) -> TrainConfig:
    cfg = TrainConfig.from_dict(json.loads((Path(run_dir) / "config.json").read_text()))
    return replace_nested(cfg, overrides or {})
