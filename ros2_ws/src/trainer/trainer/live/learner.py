"""The learning half of live training, without ROS: episodes in, PPO updates and weights versions out.

``trainer.live.trainer_node`` (the node) feeds ``LiveLearner.add_episode`` with the
transitions of one swimmer's episode (``protocol.transitions``) and the
weights version that sampled each step (from ``policy_info``'s
``header.frame_id``, ``msgs.policy_weights``). Once the pool holds
``TrainerConfig.batch_size`` samples (num_envs x num_steps on the command line, the paper's 6,144,
whatever the number of swimmers), ``update`` runs one PPO update on the whole
pool (whole episodes, so slightly more than a batch) with the update every data
source uses (``algo.update``) and the objective of training from data
(``algo.train_from_data``): values and GAE from the current critic, the ratio
against the proximal policy, each sample weighted by pi_prox / pi_behav
truncated at ``proximal_weight_cap``. Each update makes a new version.

Stale samples. A pair keeps acting with the version it has while the trainer
updates, so a pool mixes versions. The decoupled objective is correct for any
behaviour policy (the behaviour log-prob travels with each sample), but the
further behind, the more the truncated weights bias the update towards old
behaviour and the more samples carry weight ~0. Steps sampled by a version
more than ``max_staleness`` updates behind the current one are dropped
(counted); as versions only grow along an episode, what is dropped is the
episode's beginning, and the rest stays one unbroken episode for GAE.
Steps with no version (a policy node that does not say) are kept: the
objective still holds, only the drop cannot be applied. Steps without
policy_info (no behaviour log-prob) cannot enter PPO: the episode keeps only
its part after the last such step.

Each step carries its robot's tree (``Transition.parents``: the tree of the
pair's ``robot_description``, its joints bound by name, or without one a chain
in the ``joint_states`` message's order; ``protocol.transitions``); the values,
GAE bootstraps and the update read each sample with its own tree
(``train_from_data.Samples``). An episode is one robot: one whose
steps disagree on their joints or tree is dropped (``dropped_no_info``).

The run directory is the simulator trainer's: config.json, progress.csv
(``train_from_data.log_columns`` plus live columns), tb/, checkpoints every
``checkpoint_interval`` steps, state.safetensors (policy, Adam, generator,
counters, the run's id). ``resume`` continues from the last state; the pool
collected since the last update is lost with the process (a few seconds of
data). The run id goes with every weights message (``metadata["run"]``), and
so does the run's epoch, the time it began (kept across ``resume``): policy
nodes order weights by (epoch, version), so they take a fresh run's version 0
but refuse an old message of this run or of an earlier one.

With a ``signer`` (``protocol.trust``; ``morph-train --live --signing-key``)
every weights message is signed, and so is every weights-only checkpoint: its
.json carries the same header and signature as the message of its version
(``policy.weights.SignedWeights``), over the same bytes.

A diverged update (parameters NaN or inf) is refused: the learner keeps the
parameters, optimizer and rule state it had before it, counts it
(``rejected_updates``) and raises ``NonFiniteUpdate``; its pool is lost, the
version stays, and the policy nodes keep the last good weights.
"""

from __future__ import annotations

import dataclasses
import time
import uuid
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from morph_core.algo.config import BodiesConfig, TrainerConfig
from morph_core.algo.fit import Collected, Fit, NonFiniteUpdate, new_learner, refuse_anneal
from morph_core.algo.learner import Learner
from morph_core.algo.off_policy import with_proximal
from morph_core.algo.run import RowHook, Run, initial_policy
from morph_core.algo.train import TrainConfig
from morph_core.algo.train_from_data import EpisodeReturns, Samples, log_columns, off_policy_stats
from morph_core.algo.update import compile_ahead
from morph_core.msgs.policy_weights import pack_policy_weights
from morph_core.policy.index_plan import chain_parents
from morph_core.policy.weights import SignedWeights, write_checkpoint
from morph_core.protocol.transition_batch import TransitionBatch
from morph_core.protocol.transitions import Transition, TransitionAssembler

LIVE_LEARNING_RATE = 0.003
"""the live trainer's learning rate unless one is given: a third of the paper's 0.01 (TrainConfig's). Samples a
version stale made the decoupled update diverge at 0.01 and not at 0.003, in-process and over DDS
(docs/results.md, "Why the earlier live attempts diverged")"""


def live_train_config(**changes) -> TrainConfig:
    """TrainConfig's defaults with the live trainer's own (``LIVE_LEARNING_RATE``), then ``changes``."""
    return dataclasses.replace(TrainConfig(learning_rate=LIVE_LEARNING_RATE), **changes)


@dataclass(frozen=True)
class LiveOptions:
    """What the live node does beside PPO (TrainConfig says how it learns): the live source's config, whose
    options ``train_options`` generates from these fields (``--out``, ``--resume`` and ``--init`` are
    ``morph-train``'s own, shared by every source)."""

    namespaces: tuple[str, ...] = field(metadata={"metavar": "NS"})
    """the pairs' namespaces"""
    out: Path
    """the run directory"""
    resume: bool = False
    """continue the run in out from its last state"""
    episode_steps: int = 1000
    """episode length set on each sim when its pair joins (0: the sim's own)"""
    max_staleness: int = 2
    """drop steps sampled by weights more than this many versions old"""
    silence_timeout: float = 3.0
    """seconds without a new state before a pair's partial episode is dropped"""
    max_updates: int = 0
    """stop after this many updates (0: at --total-timesteps)"""
    # How a late policy node, reading best effort, gets the weights.
    weights_period: float = 1.0
    """seconds between re-publications of the current weights (late policy nodes)"""
    # On the pairs' own machine their control loops come first; ingest and updates take the CPU the loops leave
    # (a lockstep loop is latency-bound: docs/benchmarks.md).
    nice: int = 0
    """the trainer's niceness, 0..19 (the pairs' control loops first)"""
    # Without a key, policy nodes take the weights only with accept_unsigned_weights (tests).
    signing_key: Path | None = field(default=None, metadata={"metavar": "KEY"})
    """private key that signs the pushed weights and checkpoints (make one with morph-keys new KEY; the policy
    nodes trust KEY.pub). Without it the weights go out unsigned"""
    # A few dozen steps per message instead of four messages per step: far fewer wake-ups (docs/benchmarks.md).
    stream_chunks: bool = False
    """take each pair's messages from its policy node's stream_chunks instead of its 4 data topics"""
    init: Path | None = None
    """a policy checkpoint a new run starts from (fine-tuning; None: a fresh policy from the seed), as
    ``morph-train --init`` in the simulator and from bags"""

    def __post_init__(self):
        if not self.namespaces:
            raise ValueError("live training needs at least one namespace")
        if len(set(self.namespaces)) != len(self.namespaces):
            raise ValueError(f"namespaces given twice: {list(self.namespaces)}")
        if self.episode_steps < 0 or self.max_staleness < 0 or self.max_updates < 0:
            raise ValueError("episode_steps, max_staleness and max_updates must be >= 0")
        if not self.silence_timeout > 0:
            raise ValueError(f"silence_timeout must be > 0, got {self.silence_timeout}")
        if not self.weights_period > 0:
            raise ValueError(f"weights_period must be > 0, got {self.weights_period}")
        if not 0 <= self.nice <= 19:
            raise ValueError(f"nice must be in 0..19, got {self.nice}")


LIVE = ("live", 1)
"""the state section of the live trainer (name, version): the run's id and epoch (``msgs.policy_weights``)"""

LIVE_COLUMNS = ["version", "pool_episodes", "dropped_stale", "dropped_no_info", "version_lag_mean", "pairs"]


def live_log_columns(cfg: BodiesConfig) -> list[str]:
    return [*log_columns(cfg), *LIVE_COLUMNS]


def _tree(t: Transition) -> np.ndarray:
    """A step's parents (a chain's when it has none)."""
    return chain_parents(len(t.joint_pos)) if t.parents is None else np.asarray(t.parents)


class EpisodeCutter:
    """One pair's transitions, in the order its ``TransitionAssembler`` releases them, cut into episodes for
    ``LiveLearner.add_episode`` (the live node's one place for it).

    An episode ends at its terminated or truncated step (the assembler sets one at every boundary: an
    announcement, another robot, a stamp gap, a skipped step). ``drop`` is for a pair gone silent: the
    assembler holds the last ``settle_states`` states unjudged (500 live: many whole episodes of a short
    ``episode_steps``, and every body swap among them), so its flush holds complete episodes, which go on to
    the learner; only the episode the silence cut off is thrown away."""

    def __init__(self, learner: LiveLearner, version_of: Callable[[int], int | None]):
        """``version_of(stamp_ns)``: the weights version that sampled the step of that state (None: unknown)."""
        self.learner = learner
        self.version_of = version_of
        self.episode: list[Transition] = []
        """the run in progress: its steps released so far"""

    def take(self, transitions: Iterable[Transition]) -> None:
        """Transitions as the assembler releases them; each finished episode goes to the learner."""
        for t in transitions:
            self.episode.append(t)
            if t.truncated or t.terminated:  # the episode's last step: cut off, or a fall
                self.learner.add_episode(self.episode, [self.version_of(s.stamp_ns) for s in self.episode])
                self.episode = []

    def drop(self, assembler: TransitionAssembler) -> int:
        """The pair went silent: its ``assembler`` is flushed, every episode that ended before the silence goes
        to the learner (the last one too when the stream ended at a boundary, e.g. a new body's first state that
        got no answer) and the one the silence cut off (``TransitionAssembler.cut_off``) is thrown away. Returns
        its steps."""
        flushed = assembler.flush()
        cut = assembler.cut_off.episode if assembler.cut_off is not None else None
        self.take(t for t in flushed if t.episode != cut)
        lost = len(self.episode) + sum(t.episode == cut for t in flushed)
        self.episode = []
        return lost


class LiveLearner:
    """Pool of episodes, PPO updates, checkpoints and the current weights version (see module docstring)."""

    def __init__(
        self,
        cfg: TrainerConfig,
        run_dir: str | Path,
        *,
        resume: bool = False,
        max_staleness: int = 2,
        signer=None,
        on_row: RowHook | None = None,
        init: str | Path | None = None,
    ):
        """``signer``: a ``protocol.trust.Signer`` for the weights and checkpoints (None: unsigned). ``on_row(row,
        saved)``: the row hook, after each update (its state is always saved). ``init``: a policy checkpoint a
        new run starts from (its architecture the run's), as ``algo.train.train``'s."""
        refuse_anneal(cfg, LiveLearner)
        if max_staleness < 0:
            raise ValueError(f"max_staleness must be >= 0, got {max_staleness}")
        cfg, initial = initial_policy(cfg, init, resume)
        self.run = Run(run_dir, cfg, resume=resume, on_row=on_row)
        self.run_dir = self.run.dir
        self.max_staleness = max_staleness
        self.cfg = cfg  # on resume: the run's config.json with any overrides (``train.load_run_config``)
        self.learner, self.gen = new_learner(cfg, initial)
        self.policy = self.learner.policy
        self.run.counters.update(version=0, env_steps=0)
        self.run_id = uuid.uuid4().hex
        self.epoch = time.time_ns()
        """when the run began: orders this run's weights after every earlier run's (``msgs.policy_weights``)"""
        self.signer = signer
        self._message: tuple[int, list, bytes] | None = None  # (version, dims, data) of the latest weights
        if self.run.resuming:
            state = self.run.restore(self.learner, self.gen)  # a damaged newest state: the previous one
            live, _ = state.section(*LIVE)
            self.run_id = live["run"]
            self.epoch = int(live.get("epoch", 0))  # a state written before epochs: before every run
        else:
            self.run.start(init=init)
            self._save_state()  # version 0 is resumable too: policy nodes may already run it
        self.resumed = self.run.resuming
        self.fit = Fit(self.run, self.learner, self.gen, self)  # pushed: ``update`` runs its steps
        self._pool: list[TransitionBatch] = []
        self._pool_versions: list[np.ndarray] = []
        self.pool_size = 0
        self.dropped_stale = 0
        self.dropped_no_info = 0
        self.rejected_updates = 0

    @property
    def counters(self) -> dict:
        """global_step, iteration, last_ckpt, version, env_steps (``run.Run.counters``)"""
        return self.run.counters

    @property
    def version(self) -> int:
        return self.counters["version"]

    # -- data -------------------------------------------------------------------------
    def add_episode(self, transitions: Sequence[Transition], versions: Sequence[int | None]) -> int:
        """Take one episode (consecutive transitions, the last terminated (a fall) or truncated) and the weights
        version of each step; returns how many steps entered the pool."""
        if len(transitions) != len(versions):
            raise ValueError(f"{len(transitions)} transitions but {len(versions)} versions")
        if not transitions:
            return 0
        if not (transitions[-1].truncated or transitions[-1].terminated):
            raise ValueError("an episode handed over must end in a terminated or truncated step")
        lo = self.version - self.max_staleness
        keep_from = 0
        for i, (t, v) in enumerate(zip(transitions, versions, strict=True)):
            if not t.has_policy_info:
                self.dropped_no_info += i + 1 - keep_from
                keep_from = i + 1
            elif v is not None and v < lo:
                self.dropped_stale += i + 1 - keep_from
                keep_from = i + 1
        kept = list(transitions[keep_from:])
        if not kept:
            return 0
        n, tree = len(kept[0].joint_pos), _tree(kept[0])
        same = all(len(t.joint_pos) == n and np.array_equal(_tree(t), tree) for t in kept)
        if not same or not self.cfg.min_joints <= n <= self.cfg.max_joints:
            self.dropped_no_info += len(kept)  # a robot the run does not train on, or two robots in one episode
            return 0
        self._pool.append(TransitionBatch.from_transitions(kept))
        self._pool_versions.append(np.array([np.nan if v is None else v for v in versions[keep_from:]], np.float64))
        self.pool_size += len(kept)
        self.counters["env_steps"] += len(kept)
        return len(kept)

    def ready(self) -> bool:
        return self.pool_size >= self.cfg.batch_size

    # -- learning ---------------------------------------------------------------------
    def take_pool(self) -> tuple[list[TransitionBatch], np.ndarray]:
        """The pool's oldest episodes, just enough for a batch, and their steps' versions (NaN: unknown).

        Episodes that arrived while the last update ran stay for the next one: an update is one batch
        whatever it waited for, as in the simulator loop (episodes are whole, so a batch may exceed
        ``batch_size`` by less than one episode)."""
        n, taken = 0, 0
        while n < len(self._pool) and taken < self.cfg.batch_size:
            taken += len(self._pool[n])
            n += 1
        pool, versions = self._pool[:n], self._pool_versions[:n]
        self._pool, self._pool_versions = self._pool[n:], self._pool_versions[n:]
        self.pool_size -= taken
        return pool, np.concatenate(versions) if versions else np.zeros(0)

    def update(self, pool: tuple[list[TransitionBatch], np.ndarray] | None = None, pairs: int = 0) -> dict:
        """One PPO update on ``pool`` (default: ``take_pool()``); makes the next version, logs and
        checkpoints; returns the logged row. ``add_episode`` may run in another thread meanwhile."""
        episodes_list, versions = pool if pool is not None else self.take_pool()
        if not episodes_list:
            raise ValueError("no episodes to train on")
        try:
            return self.fit.step(self.prepare(episodes_list, versions, pairs))
        except NonFiniteUpdate as err:
            self.rejected_updates += 1
            raise NonFiniteUpdate(f"{err} ({self.rejected_updates} so far, {len(episodes_list)} episodes), "
                                  f"version {self.version} kept") from None  # fmt: skip

    # -- as fit's source (``algo.fit.Source``): pushed, one batch per ``update`` --------------------------
    name, time_column, bounded, state_every_update, guard, peers = "live training", "prepare_s", False, True, True, None

    def columns(self) -> list[str]:
        return live_log_columns(self.cfg)

    def prepare(self, episodes_list: list[TransitionBatch], versions: np.ndarray, pairs: int) -> Collected:
        """The pool as one batch: values and GAE from the current critic, the proximal policy's log-probs."""
        cfg = self.cfg
        t0 = time.perf_counter()
        data = TransitionBatch.concatenate(episodes_list)
        known = versions[np.isfinite(versions)]
        lags = self.version - known
        samples = Samples(data, cfg.max_joints)
        values, advantages, returns = samples.advantages(self.policy, cfg.gamma, cfg.gae_lambda)
        batch = with_proximal(self.policy, samples.batch(torch.arange(len(data)), values, advantages, returns))
        return Collected(batch, time.perf_counter() - t0, (data, len(episodes_list), lags, pairs))

    def updated(self, collected: Collected) -> None:
        self.counters["version"] += 1

    def finished(self) -> bool:
        return False  # no end: checkpoints every checkpoint_interval steps only

    def row(self, collected: Collected, checkpoint: bool) -> dict:
        data, episodes, lags, pairs = collected.context
        c, batch = self.counters, collected.batch
        return {
            "data_round": c["iteration"],
            "round_iteration": 1,
            "env_steps": c["env_steps"],
            "data_steps": len(data),
            "usable_steps": len(data),  # every pooled step has its behaviour log-prob (add_episode)
            "batch_size": batch.size,
            **EpisodeReturns.of(data).row(self.cfg.dims, trees=not self.cfg.body_mix.chains_only),  # as the columns
            **off_policy_stats(batch, self.cfg.proximal_weight_cap),
            "version": c["version"],
            "pool_episodes": episodes,
            "dropped_stale": self.dropped_stale,
            "dropped_no_info": self.dropped_no_info,
            "version_lag_mean": float(lags.mean()) if len(lags) else float("nan"),
            "pairs": pairs,
        }

    def state(self) -> tuple[dict, dict, None]:
        name, version = LIVE
        return {name: {"version": version, "run": self.run_id, "epoch": self.epoch}}, {}, None

    def save_policy(self, path: Path, learner: Learner, step: int) -> None:
        self._save_checkpoint(path)

    def compile_update(self) -> float:
        """Compile the update before the first batch is in (``algo.update.compile_ahead``; nothing without
        ``cfg.compile``); returns the seconds it took. The node runs it in its worker thread as it starts."""
        t0 = time.perf_counter()
        torch.set_num_threads(self.cfg.torch_threads)  # as the update runs (and compiles) it
        try:
            compile_ahead(self.learner, self.cfg.update_config(), self.cfg.max_joints, off_policy=True)
        finally:
            torch.set_num_threads(1)
        return time.perf_counter() - t0

    def _save_state(self) -> None:
        self.run.save_state(self.learner, self.gen, *self.state())

    def weights_message(self) -> tuple[list[tuple[str, int, int]], bytes]:
        """The current policy as the weights topic carries it (``msgs.policy_weights``), signed with the
        learner's signer; made once per version (a checkpoint of the version carries the same signature)."""
        if self._message is None or self._message[0] != self.version:
            meta = {"run": self.run_id, "global_step": self.counters["global_step"]}
            dims, data = pack_policy_weights(self.version, dataclasses.asdict(self.policy.config),
                                             self.policy.to_bytes(), meta, self.epoch, self.signer)  # fmt: skip
            self._message = (self.version, dims, data)
        return self._message[1], self._message[2]

    def _save_checkpoint(self, path: Path) -> None:
        """The current weights as a weights-only checkpoint: the message's bytes and, if signed, its signature."""
        dims, data = self.weights_message()
        signed = SignedWeights(dims[1][0], dims[2][0]) if len(dims) == 3 else None
        meta = {"global_step": self.counters["global_step"], "version": self.version}
        write_checkpoint(path, data, dataclasses.asdict(self.policy.config), meta, signed)

    def close(self) -> None:
        self.run.close()
