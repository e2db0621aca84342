"""Live training without DDS: what the topics add to learning, isolated.

    python -m trainer.live.in_process --out runs/live-in-process/lag2-drop0.1 --lag 2 --drop-states 0.1 \\
        --seed 1 --total-timesteps 150000

The live trainer's learning half (``trainer.live.learner.LiveLearner``, the
same pool, decoupled objective, staleness rule and update) fed by swimmers
simulated in this process (``protocol.loopback``: the messages a lockstep
sim and a sampling policy node would publish), assembled by the same
``protocol.transitions``. Two things the topics bring are set by hand:

- ``--lag``: the behaviour policy is the learner's policy ``lag`` versions
  back (a pair acts with the weights it has while the trainer updates);
  one version per episode, where a live pair may switch mid-episode.
- ``--drop-states``: each ``joint_states`` message is lost with this
  probability, as a queue that overflows loses it. A lost state is a stamp
  gap: the episode is cut there into runs, each bootstrapped at its end,
  exactly as the live trainer cuts it.

One swimmer at a time; chain lengths drawn from the config's
``min_joints..max_joints`` per episode as the live sims draw them. The run
directory is a live run's (``progress.csv`` with the live columns), so
``trainer.live.compare`` and ``trainer.reports.summary`` read it.
"""

from __future__ import annotations

import argparse
import copy
import sys
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from morph_core.algo.run_dir import RunDir
from morph_core.algo.train import TrainConfig
from morph_core.msgs.records import JointStateRecord
from morph_core.protocol.loopback import SamplingController, record_episodes
from morph_core.protocol.transitions import TransitionAssembler
from morph_core.util.config_cli import CommandLineParser, add_dataclass_options, overrides_from_args, replace_nested
from trainer.live.learner import EpisodeCutter, LiveLearner, NonFiniteUpdate, live_train_config


@dataclass(frozen=True)
class InProcessOptions:
    """What stands in for the topics (TrainConfig says how it learns)."""

    lag: int = 0
    """versions the behaviour policy lags behind the learner"""
    drop_states: float = 0.0
    """probability that a joint_states message is lost (a stamp gap cuts the episode there)"""
    episode_steps: int = 1000
    """control steps per episode"""

    def __post_init__(self):
        if self.lag < 0 or self.episode_steps < 2:
            raise ValueError(f"need lag >= 0 and episode_steps >= 2, got {self.lag}, {self.episode_steps}")
        if not 0.0 <= self.drop_states < 1.0:
            raise ValueError(f"drop_states must be in [0, 1), got {self.drop_states}")


def train_in_process(cfg: TrainConfig, options: InProcessOptions, out: Path, log=print) -> LiveLearner:
    """Train until ``cfg.total_timesteps`` (see module docstring); returns the learner (closed)."""
    learner = LiveLearner(cfg, out, max_staleness=options.lag)  # keep what the lag makes stale, no more
    behaviours = deque([(learner.version, copy.deepcopy(learner.policy))], maxlen=options.lag + 1)
    rng = np.random.default_rng(cfg.seed)
    episode = 0
    try:
        while learner.counters["global_step"] < cfg.total_timesteps:
            version, behaviour = behaviours[0]
            joints = int(rng.integers(cfg.min_joints, cfg.max_joints + 1))
            seed = cfg.seed * 1_000_003 + episode
            records = record_episodes(SamplingController(behaviour, seed), [(joints, options.episode_steps)], seed)
            if options.drop_states:
                lost = rng.random(len(records)) < options.drop_states
                records = [r for r, x in zip(records, lost, strict=True) if not (x and isinstance(r, JointStateRecord))]
            assembler = TransitionAssembler()
            cutter = EpisodeCutter(learner, lambda _stamp, v=version: v)  # the live node's cut into episodes
            cutter.take(assembler.push_many(records) + assembler.flush())
            episode += 1
            if learner.ready():
                try:
                    row = learner.update()
                except NonFiniteUpdate as err:  # as the live node: that pool is lost, the policy kept
                    log(f"update refused: {err}")
                    continue
                behaviours.append((learner.version, copy.deepcopy(learner.policy)))
                log(f"update {row['iteration']}: step {row['global_step']}, {row['pool_episodes']} runs, return "
                    f"{row['return_mean']:.2f}, approx KL {row['approx_kl']:.3g}, weight {row['is_weight_mean']:.3f}, "
                    f"lag {row['version_lag_mean']:.2f}")  # fmt: skip
    finally:
        learner.close()
    return learner


def main(argv: list[str] | None = None) -> int:
    parser = CommandLineParser(
        prog="python -m trainer.live.in_process",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--out", type=Path, required=True, help="run directory (a fresh one)")
    add_dataclass_options(parser, InProcessOptions)
    add_dataclass_options(parser, TrainConfig, skip=("anneal_lr",), defaults=live_train_config())
    args = parser.parse_args(argv)
    if RunDir(args.out).config.exists():
        parser.error(f"{args.out} already holds a run")
    try:
        options = replace_nested(InProcessOptions(), overrides_from_args(args, InProcessOptions))
        cfg = replace_nested(live_train_config(progress_bar=False), overrides_from_args(args, TrainConfig))
    except ValueError as err:
        parser.error(str(err))
    train_in_process(cfg, options, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
