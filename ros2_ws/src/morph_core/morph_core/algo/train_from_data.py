"""PPO on recorded transitions (rosbag2 bags, exported ``.npz``): the training loop without a simulator.

The data are a ``protocol.transition_batch.TransitionBatch``: steps a
sampling policy took, each with the behaviour log-prob it published
(``policy_info``). Each update

1. recomputes the values of every recorded state with the trainer's own
   critic as it is now, and GAE over the recorded episodes
   (``algo.ppo.compute_gae``; a truncated step is bootstrapped on
   gamma * V(next state), as the simulator trainer does; the recorded steps
   are never terminal);
2. takes its batch: all the steps with a behaviour log-prob if they are at
   most ``batch_size`` (``PPOConfig.batch_size``, 6144 by default), else the
   next part of a seeded random permutation cut into ceil(steps /
   batch_size) near-equal parts (``iterations`` defaults to one pass: each
   step once). A batch that would leave a single sample for its last
   minibatch leaves that sample out (its advantage, normalised within the
   minibatch, would be 0/0 and turn the weights NaN). A step without
   policy_info (its message lost, or another controller acting) has no
   behaviour log-prob: it still carries its episode's rewards and values
   into GAE, but never enters an update; data with none at all are refused
   (``MissingPolicyInfoError``);
3. runs the one PPO update every data source uses (``algo.update``) under
   the run's trust-region rule, with the decoupled objective below.

Why the decoupled objective (Hilton et al. 2022, "Batch size-invariance for
policy optimization"). PPO's ratio r = pi_theta / pi_old clips against the
policy that collected the data, which on-policy is also the policy the
update starts from: the clip keeps the new policy near the current one, a
trust region. Recorded data come from an older policy pi_behav. Against it
the ratio starts away from 1 before any step is taken: samples the current
policy already moved away from sit outside [1 - eps, 1 + eps] and are
clipped (no gradient) or not clipped at all (the pessimistic minimum keeps
the unclipped term), whatever the update does, so the clip bounds the
distance to pi_behav, not the step from the current policy; the trust
region is gone. The decoupled objective takes the ratio against the
proximal policy pi_prox, the policy as the update starts
(``off_policy.with_proximal``), r = pi_theta / pi_prox, so the clip bounds the
step again, and corrects for the data's origin separately: each sample's
surrogate is weighted by the importance weight pi_prox / pi_behav,
truncated at c (``PPOConfig.proximal_weight_cap``, 1 by default, as
V-trace's rho-bar). The truncation bounds the variance a few samples the
behaviour policy rarely took would otherwise bring, at the price of a bias
towards the behaviour policy's action distribution; with c = 1 a sample the
current policy finds likelier than the behaviour did counts as on-policy,
and one it finds less likely counts less. The log weight sums over the
sample's joints, so on stale data long chains drift from 1 further than
short ones. Data recorded by the current policy (one update per recording
round) have pi_prox = pi_behav, weights 1 (up to float rounding of the log
densities, the node's float64 against the trainer's float32) and the
objective is PPO's. The value targets are GAE returns of the behaviour
policy's trajectories, uncorrected (no V-trace on the critic): a bias that
grows with the data's age.

Logged per update (``progress.csv``, TensorBoard), besides the update's
statistics per dimension as in simulator training: the mean truncated
weight, the share of samples whose weight the cap cut, the share of stale
samples (|log pi_prox - log pi_behav| > ``STALE_LOG_RATIO``), and the
recorded episodes' returns per chain length (fixed for one data set) and,
when the data hold trees (or the run's ``bodies`` do), over the chains and
over the trees apart (``return_chains``, ``return_trees``, as simulator
training logs them).

A run trains on one data set, then optionally on further ones (rounds:
record with the current policy, train, record again), policy, critic, Adam
moments and generator carrying over. The state holds a digest of the data,
so ``resume`` on other data is refused (``DataMismatchError``), and
``new_data`` starts the next round. Checkpoints and resume work as in
``algo.train``: a run killed at any moment resumes bit for bit.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from morph_core.algo.batch import RolloutBatch
from morph_core.algo.checkpoint import load_training_state, state_section
from morph_core.algo.config import BodiesConfig, TrainerConfig
from morph_core.algo.fit import Collected, fit, new_learner, refuse_anneal, save_policy
from morph_core.algo.learner import Learner
from morph_core.algo.off_policy import with_proximal
from morph_core.algo.ppo import compute_gae
from morph_core.algo.run import RowHook, Run, initial_policy
from morph_core.algo.run_dir import RunDir
from morph_core.algo.update_stats import update_columns
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.chains import ChainBatch
from morph_core.protocol.transition_batch import TransitionBatch

STALE_LOG_RATIO = 1e-3
"""a sample is stale when |log pi_prox - log pi_behav| exceeds this (float rounding of the same policy's
log-density stays below 1e-4 for 64 joints)"""


class DataMismatchError(ValueError):
    """The data do not fit the run: other data than it trains on, or chains outside its config."""


def data_digest(data: TransitionBatch) -> str:
    """SHA-256 of the transitions (every array's key, dtype, shape and bytes): the data's identity.

    Data whose every row is a chain leave ``parents`` out, so their digest is the one they had before the key
    existed (a run started on them resumes on them); any tree puts the parents in, so data that differ only in
    their graphs differ."""
    h = hashlib.sha256()
    chains = data.is_chains
    for key, a in data.arrays().items():
        if key == "parents" and chains:
            continue
        a = np.ascontiguousarray(a)
        h.update(f"{key}:{a.dtype.str}:{a.shape};".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def episode_spans(data: TransitionBatch) -> tuple[np.ndarray, np.ndarray]:
    """(first row, length) of each episode; raises ``ValueError`` unless episodes are contiguous runs that
    end in a terminated or truncated step, as ``TransitionBatch`` promises."""
    if not len(data):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    starts = np.flatnonzero(np.r_[True, data.episode[1:] != data.episode[:-1]])
    if len(np.unique(data.episode[starts])) != len(starts):
        raise ValueError("transitions of one episode are not consecutive rows")
    lengths = np.diff(np.r_[starts, len(data)])
    last = starts + lengths - 1
    if not (data.terminated[last] | data.truncated[last]).all():
        raise ValueError("an episode's last transition is neither terminated nor truncated")
    return starts, lengths


@dataclass(frozen=True)
class EpisodeReturns:
    """Undiscounted returns of the recorded episodes (runs of consecutive transitions)."""

    num_joints: np.ndarray
    """[E] chain length of each episode"""
    returns: np.ndarray
    """[E] sum of rewards"""
    lengths: np.ndarray
    """[E] transitions"""
    chains: np.ndarray | None = None
    """[E] whether each episode's body is a chain (None: all are)"""

    @classmethod
    def of(cls, data: TransitionBatch) -> EpisodeReturns:
        starts, lengths = episode_spans(data)
        sums = np.add.reduceat(data.reward, starts) if len(starts) else np.zeros(0)
        chains = None
        if not data.is_chains:
            j = np.arange(data.max_joints)
            n = data.num_joints[starts, None]
            chains = (data.parents[starts] == np.where(j < n, j - 1, -1)).all(axis=1)
        return cls(data.num_joints[starts], sums, lengths, chains)

    def row(self, dims, trees: bool = False) -> dict[str, float]:
        """Log columns: episodes, mean return overall and per chain length in ``dims``, mean reward per step;
        with ``trees`` the mean return over the chains and over the trees too."""
        out = {
            "episodes": len(self.returns),
            "return_mean": float(self.returns.mean()) if len(self.returns) else math.nan,
            "reward_rate": float(self.returns.sum() / self.lengths.sum()) if len(self.returns) else math.nan,
        }
        for d in dims:
            r = self.returns[self.num_joints == d]
            out[f"return_d{d}"] = float(r.mean()) if len(r) else math.nan
        if trees:
            chains = np.ones(len(self.returns), bool) if self.chains is None else self.chains
            for key, r in (("return_chains", self.returns[chains]), ("return_trees", self.returns[~chains])):
                out[key] = float(r.mean()) if len(r) else math.nan
        return out


def describe_bodies(data: TransitionBatch, shown: int = 6) -> str:
    """The data's bodies in a phrase: ``chains of 3..9 joints``, or with trees their joint counts and steps per
    body (``env.bodies.body_label``), e.g. ``4..5 joints: star-2x2 20, y-1x2 15 steps``."""
    lo, hi = int(data.num_joints.min()), data.max_joints
    if data.is_chains:
        return f"chains of {lo}..{hi} joints"
    bodies = list(data.steps_per_body().items())
    listed = ", ".join(f"{label} {n}" for label, n in bodies[:shown])
    more = f" and {len(bodies) - shown} more bodies" if len(bodies) > shown else ""
    return f"{lo}..{hi} joints: {listed}{more} steps"


def log_columns(cfg: BodiesConfig, trees: bool | None = None) -> list[str]:
    """The log's columns; ``trees`` (default: the run's ``bodies`` hold trees) adds the returns over the chains
    and over the trees."""
    trees = not cfg.body_mix.chains_only if trees is None else trees
    return [
        "global_step", "iteration", "data_round", "round_iteration", "env_steps", "data_steps", "usable_steps",
        "batch_size",
        "wall_time", "sps", "prepare_s", "update_s", "learning_rate",
        "episodes", "return_mean", *[f"return_d{d}" for d in cfg.dims],
        *(["return_chains", "return_trees"] if trees else []), "reward_rate",
        "policy_loss", "value_loss", "entropy", "approx_kl", "clip_frac", "explained_variance", "log_std",
        "is_weight_mean", "is_weight_capped_frac", "stale_frac", "behaviour_logr_mean",
        *update_columns(cfg.dims),
    ]  # fmt: skip


class Samples:
    """The transitions as the tensors an update needs (float32, padded to ``width`` joints, the run's
    longest chain: the update's per-dimension statistics go up to it), and the GAE layout: episodes as the
    columns of an [L, E] grid (L = longest episode), so the recursion runs L steps over E episodes at once
    rather than once per transition.

    ``parents`` [N, width] int64 (-1 at padding) is each sample's tree, None when every sample is a chain (the
    policy's chain path); the states, the truncated steps' next states (the same robot, so the same row) and
    every batch are read with it."""

    def __init__(self, data: TransitionBatch, width: int):
        if width < data.max_joints:
            raise ValueError(f"width {width} is narrower than the data's longest chain ({data.max_joints})")

        def f32(a: np.ndarray, joints: bool = False) -> torch.Tensor:
            if joints:
                a = np.pad(a, ((0, 0), (0, width - a.shape[1])))
            return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))

        self.size = len(data)
        self.num_joints = torch.from_numpy(data.num_joints.astype(np.int64))
        self.parents = None
        if not data.is_chains:
            padded = np.pad(data.parents, ((0, 0), (0, width - data.max_joints)), constant_values=-1)
            self.parents = torch.from_numpy(np.ascontiguousarray(padded, dtype=np.int64))
        self.joint_pos, self.joint_vel = f32(data.joint_pos, True), f32(data.joint_vel, True)
        self.global_feats, self.actions = f32(data.global_feats), f32(data.action, True)
        self.log_prob, self.rewards = f32(data.log_prob), f32(data.reward)
        self.terminated = torch.from_numpy(data.terminated.copy())
        self.truncated = torch.from_numpy(data.truncated.copy())
        # The bootstrap state of each truncated step (within an episode, next_* is the next row's state).
        rows = np.flatnonzero(data.truncated)
        self.truncated_rows = torch.from_numpy(rows)
        self.next_obs = (
            f32(data.next_joint_pos[rows], True),
            f32(data.next_joint_vel[rows], True),
            f32(data.next_global[rows]),
        )
        starts, lengths = episode_spans(data)
        steps = np.arange(int(lengths.max()) if len(lengths) else 0)
        self.grid_mask = torch.from_numpy(steps[:, None] < lengths[None, :])
        self.grid_rows = torch.from_numpy(starts[None, :] + steps[:, None])[self.grid_mask]

    def _grid(self, x: torch.Tensor, fill) -> torch.Tensor:
        out = torch.full(self.grid_mask.shape, fill, dtype=x.dtype)
        out[self.grid_mask] = x[self.grid_rows]
        return out

    @torch.no_grad()
    def values(self, policy: GraphActorCritic, chunk: int = 1024) -> tuple[torch.Tensor, torch.Tensor]:
        """(V of every state [N], V of every truncated step's next state [K]) under ``policy`` now."""

        def value(pos, vel, glob, nj, parents) -> torch.Tensor:
            out = []
            for s in range(0, len(nj), chunk):
                tree = None if parents is None else parents[s : s + chunk]
                chains = ChainBatch.from_padded(pos[s : s + chunk], vel[s : s + chunk], glob[s : s + chunk],
                                                nj[s : s + chunk], parents=tree)  # fmt: skip
                out.append(policy(chains)[2])
            return torch.cat(out) if out else torch.zeros(0)

        rows = self.truncated_rows
        states = value(self.joint_pos, self.joint_vel, self.global_feats, self.num_joints, self.parents)
        finals = value(*self.next_obs, self.num_joints[rows], None if self.parents is None else self.parents[rows])
        return states, finals

    def advantages(
        self, policy: GraphActorCritic, gamma: float, gae_lambda: float
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(values, advantages, returns), each [N], with the current critic."""
        values, finals = self.values(policy)
        final_values = torch.zeros(self.size)
        final_values[self.truncated_rows] = finals
        # Beyond an episode's end: terminal, so nothing flows back into the episode (it ends truncated anyway).
        adv, ret = compute_gae(
            self._grid(self.rewards, 0.0), self._grid(values, 0.0), self._grid(self.terminated, True),
            self._grid(self.truncated, False), self._grid(final_values, 0.0), torch.zeros(self.grid_mask.shape[1]),
            gamma, gae_lambda,
        )  # fmt: skip
        advantages, returns = torch.empty(self.size), torch.empty(self.size)
        advantages[self.grid_rows], returns[self.grid_rows] = adv[self.grid_mask], ret[self.grid_mask]
        return values, advantages, returns

    def batch(self, index: torch.Tensor, values, advantages, returns) -> RolloutBatch:
        """The samples at ``index``."""
        return RolloutBatch(
            num_joints=self.num_joints[index],
            joint_pos=self.joint_pos[index],
            joint_vel=self.joint_vel[index],
            global_feats=self.global_feats[index],
            actions=self.actions[index],
            log_prob=self.log_prob[index],
            values=values[index],
            advantages=advantages[index],
            returns=returns[index],
            parents=None if self.parents is None else self.parents[index],
        )


def off_policy_stats(batch: RolloutBatch, cap: float) -> dict[str, float]:
    """How far the proximal policy is from the behaviour policy on ``batch`` (``with_proximal``'s)."""
    log_w = (batch.proximal_log_prob - batch.log_prob).double()
    return {
        "is_weight_mean": float(torch.clamp(log_w.exp(), max=cap).mean()),
        "is_weight_capped_frac": float((log_w.exp() > cap).double().mean()),
        "stale_frac": float((log_w.abs() > STALE_LOG_RATIO).double().mean()),
        "behaviour_logr_mean": float(log_w.mean()),
    }


def check_data(data: TransitionBatch, cfg: BodiesConfig) -> None:
    """Raise unless PPO can train on ``data`` under ``cfg``: steps there, some with their behaviour
    log-prob (``MissingPolicyInfoError``), chains within the config's range (``DataMismatchError``: the
    log's per-dimension columns come from it), whole episodes."""
    if not len(data):
        raise ValueError("no transitions to train on")
    if not data.has_policy_info.any():
        data.require_policy_info()  # raises, saying what is missing
    if data.has_policy_info.sum() < 2:
        raise ValueError("one step with its behaviour log-prob is too few to train on (advantages are normalised)")
    lo, hi = int(data.num_joints.min()), int(data.num_joints.max())
    if lo < cfg.min_joints or hi > cfg.max_joints:
        raise DataMismatchError(
            f"the data hold chains of {lo}..{hi} joints, outside the run's min_joints..max_joints "
            f"({cfg.min_joints}..{cfg.max_joints}): set --min-joints/--max-joints to cover them"
        )
    episode_spans(data)


def check_global_width(data: TransitionBatch, policy) -> None:
    """``DataMismatchError`` unless the policy (its ``PolicyConfig``) reads the data's global features (4 a
    swimmer's, 12 a legged body's)."""
    if data.global_width != policy.global_features:
        raise DataMismatchError(
            f"the data hold {data.global_width} global features per step (4: a swimmer's, 12: a legged body's) "
            f"and the run's policy reads {policy.global_features}: set --bodies to the bodies recorded "
            "(e.g. centipede:2-4), which sets the policy's width"
        )


@dataclass
class _Round:
    """The run's current data set and how far training on it has got (saved with the state)."""

    digest: str
    steps: int
    source: list[str]
    iterations: int
    """updates to run on these data"""
    done: int = 0
    """updates run on these data"""
    order: np.ndarray | None = None
    """the current pass's permutation, when the data are cut into several batches"""


def passes_cut(steps: int, batch_size: int) -> int:
    """Batches one pass over ``steps`` samples is cut into: ceil(steps / batch_size)."""
    return -(-steps // batch_size)


DATA = ("data", 1)
"""the state section of the bag trainer (name, version): the current data set (``_Round``) and its pass's
permutation"""


def train_from_data(
    cfg: TrainerConfig,
    data: TransitionBatch,
    run_dir: str | Path,
    *,
    iterations: int | None = None,
    init: str | Path | None = None,
    resume: bool = False,
    new_data: bool = False,
    source: list[str] | None = None,
    on_row: RowHook | None = None,
) -> Path:
    """PPO updates on ``data`` into ``run_dir`` (its files: ``run_dir.RunDir``).

    ``iterations``: updates on these data (default: one pass, ceil(usable steps / batch_size); on ``resume`` the
    number the data set was started with). ``init``: a policy checkpoint (.safetensors beside its .json) to
    start a new run from, else a fresh policy seeded with ``cfg.seed``. ``resume``: continue the run in
    ``run_dir`` on the same data (else ``DataMismatchError``); with ``new_data`` too, train it further on
    new data (the next round). ``source`` names the data (bag paths), for the record. ``on_row(row, saved)``:
    the row hook (``run.Run.report``).
    """
    files = RunDir(run_dir)
    refuse_anneal(cfg, Recorded)
    if iterations is not None and iterations < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations}")
    if new_data and not resume:
        raise ValueError("new_data continues a run: it needs resume")
    if init is not None and resume:
        raise ValueError("init starts a new run; a resumed run continues from its own state")
    if resume and not files.state.exists() and files.init.exists():
        init = json.loads(files.init.read_text())["init"]  # killed before its first checkpoint
    check_data(data, cfg)
    digest = data_digest(data)
    usable = torch.from_numpy(np.flatnonzero(data.has_policy_info))  # the steps an update may take

    cfg, initial = initial_policy(cfg, init, resume=False)  # checked above: a run resumed before its first state
    check_global_width(data, cfg.policy)
    learner, gen = new_learner(cfg, initial)
    run = Run(run_dir, cfg, resume=resume, on_row=on_row)
    counters = run.counters
    counters.update(data_round=0, env_steps=0)
    current: _Round | None = None
    if run.resuming:
        state = run.restore(learner, gen)  # a damaged newest state: the previous one, named in the log
        counters = run.counters
        saved, arrays = state.section(*DATA)
        order = arrays.get("order")
        current = _Round(**{**saved["round"], "order": None if order is None else order.numpy()})
        finished = current.done >= current.iterations
        if not new_data and current.digest != digest:
            raise DataMismatchError(
                f"{run_dir} trains on other data (digest {current.digest[:12]}, {current.steps} steps from "
                f"{current.source}) than given (digest {digest[:12]}, {len(data)} steps); pass new_data "
                "(--new-data) to train it further on these"
            )
        if new_data and current.digest == digest:
            raise DataMismatchError(f"{run_dir} trains on these data already: resume it without new_data")
        if new_data and not finished:
            raise DataMismatchError(
                f"{run_dir} has {current.iterations - current.done} updates left on its data "
                f"({current.source}): finish them (resume without new_data) before training on new data"
            )
        if not new_data and iterations is not None:
            current.iterations = iterations
    elif new_data:
        raise ValueError(f"new_data: no trained state in {run_dir} to continue")
    else:
        run.start(init=init)
    if current is None or new_data:
        current = _Round(digest, len(data), list(source or []), iterations or passes_cut(len(usable), cfg.batch_size))
        counters["data_round"] += 1
        counters["env_steps"] += len(data)
    # Trees in the data, the run's bodies or a log resumed: the returns over chains and trees apart, kept for the run.
    trees = not data.is_chains or not cfg.body_mix.chains_only or (run.resuming and _logs_trees(files))
    fit(run, learner, gen, Recorded(cfg, data, usable, current, run.counters, gen, trees))
    return files.path


class Recorded:
    """Recorded transitions as ``fit``'s source: each batch all the usable steps or the next part of a pass's
    permutation, with values and advantages from the critic as it is now; its state is the data set
    (``_Round``, ``DATA``)."""

    name, time_column, bounded = "training from data", "prepare_s", False
    state_every_update = guard = False
    peers = None
    save_policy = staticmethod(save_policy)

    def __init__(self, cfg: TrainerConfig, data: TransitionBatch, usable: torch.Tensor, current: _Round, counters: dict,
                 gen: torch.Generator, trees: bool):  # fmt: skip
        self.cfg, self.data, self.usable, self.current = cfg, data, usable, current
        self.counters, self.gen = counters, gen
        self.trees = trees
        self.one_pass = passes_cut(len(usable), cfg.batch_size)
        self.samples = Samples(data, cfg.max_joints)
        self.recorded = EpisodeReturns.of(data).row(cfg.dims, trees)

    def columns(self) -> list[str]:
        return log_columns(self.cfg, self.trees)

    def finished(self) -> bool:
        return self.current.done >= self.current.iterations

    def collect(self, learner: Learner) -> Collected:
        cfg, current, usable = self.cfg, self.current, self.usable
        t0 = time.perf_counter()
        # 1. Values and advantages of every recorded step with the critic as it is now.
        values, advantages, returns = self.samples.advantages(learner.policy, cfg.gamma, cfg.gae_lambda)
        # 2. This update's samples: all, or the next part of this pass's permutation.
        if self.one_pass == 1:
            index = usable
        else:
            part = current.done % self.one_pass
            if part == 0 or current.order is None:
                current.order = torch.randperm(len(usable), generator=self.gen).numpy()
            index = usable[torch.tensor_split(torch.from_numpy(current.order), self.one_pass)[part]]
        if len(index) % cfg.minibatch_size == 1:
            index = index[:-1]  # a last minibatch of one sample: its normalised advantage would be NaN
        batch = with_proximal(learner.policy, self.samples.batch(index, values, advantages, returns))
        return Collected(batch, time.perf_counter() - t0)

    def updated(self, collected: Collected) -> None:
        self.current.done += 1

    def row(self, collected: Collected, checkpoint: bool) -> dict:
        return {
            "data_round": self.counters["data_round"],
            "round_iteration": self.current.done,
            "env_steps": self.counters["env_steps"],
            "data_steps": len(self.data),
            "usable_steps": len(self.usable),
            "batch_size": collected.batch.size,
            **self.recorded,
            **off_policy_stats(collected.batch, self.cfg.proximal_weight_cap),
        }

    def state(self) -> tuple[dict, dict, None]:
        current, (name, version) = self.current, DATA
        section = {"version": version, "round": {k: getattr(current, k) for k in ("digest", "steps", "source",
                                                                                   "iterations", "done")}}  # fmt: skip
        arrays = {} if current.order is None else {f"{name}.order": current.order}
        return {name: section}, arrays, None

    def progress(self) -> tuple[int, int, str]:
        return self.current.iterations, self.current.done, "update"

    def advance(self, row: dict) -> tuple[int, dict]:
        return 1, {"kl": f"{row['approx_kl']:.3f}", "w": f"{row['is_weight_mean']:.3f}"}


def _logs_trees(files: RunDir) -> bool:
    """Whether the run's progress log has the returns over chains and trees (an earlier round had trees)."""
    try:
        with files.progress.open() as f:
            return "return_trees" in f.readline().strip().split(",")
    except OSError:
        return False


def run_state(run_dir: str | Path) -> dict | None:
    """What a run trained from data holds (its counters and current data set: digest, steps, source,
    iterations, done), or None before its first checkpoint."""
    path = RunDir(run_dir).state
    if not path.exists():
        return None
    tensors, meta = load_training_state(path)
    return {**meta["counters"], **state_section(meta, tensors, *DATA, path)[0]["round"]}
