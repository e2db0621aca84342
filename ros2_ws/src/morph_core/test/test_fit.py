"""The one training loop (``algo.fit``): pulled (``fit``) and pushed (``Fit.step``) run the same updates."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import torch

from morph_core.algo.fit import Fit, fit, new_learner, refuse_anneal
from morph_core.algo.run import Run
from morph_core.algo.run_dir import RunDir
from morph_core.algo.small_runs import small
from morph_core.algo.train import TrainConfig
from morph_core.algo.train_from_data import Recorded, _Round, data_digest
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.protocol.loopback import SamplingController, record_episodes
from morph_core.protocol.transitions import assemble

SMALL = small(num_envs=1, num_steps=32, minibatch_size=16, checkpoint_interval=64, seed=4)


@pytest.fixture(scope="module")
def data():
    torch.set_num_threads(1)
    torch.manual_seed(7)
    return assemble(record_episodes(SamplingController(GraphActorCritic().eval(), seed=1), ((3, 40), (5, 30)), 0)).batch


def _start(run_dir, cfg, data):
    run = Run(run_dir, cfg)
    learner, gen = new_learner(cfg, None)
    run.start()
    run.counters.update(data_round=1, env_steps=len(data))
    usable = torch.from_numpy(np.flatnonzero(data.has_policy_info))
    current = _Round(data_digest(data), len(data), [], iterations=4)
    return run, learner, gen, Recorded(cfg, data, usable, current, run.counters, gen, trees=False)


def _rows(run_dir):
    with RunDir(run_dir).progress.open() as f:
        return [{k: v for k, v in r.items() if not k.endswith("_s") and k not in ("sps", "wall_time")}
                for r in csv.DictReader(f)]  # fmt: skip


def test_the_pulled_loop_and_the_pushed_steps_train_alike(tmp_path, data):
    """``fit`` is only the ``while`` around ``Fit.step``: a source whose batches are pushed step by step (as
    the live node does) logs the same rows and saves the same checkpoints as the loop that pulls them."""
    cfg = TrainConfig(**SMALL)
    fit(*_start(tmp_path / "pulled", cfg, data))
    run, learner, gen, source = _start(tmp_path / "pushed", cfg, data)
    step = Fit(run, learner, gen, source)
    while not source.finished():
        step.step(source.collect(learner))
    run.close()
    pulled, pushed = _rows(tmp_path / "pulled"), _rows(tmp_path / "pushed")
    assert len(pulled) == 4 and pulled == pushed
    assert [r["iteration"] for r in pulled] == ["1", "2", "3", "4"] and pulled[-1]["round_iteration"] == "4"
    saved = sorted(p.name for p in RunDir(tmp_path / "pulled").checkpoints.glob("*.safetensors"))
    assert saved == sorted(p.name for p in RunDir(tmp_path / "pushed").checkpoints.glob("*.safetensors"))
    assert saved[-1] == RunDir(tmp_path).checkpoint(int(pulled[-1]["global_step"])).name  # the last step saves


def test_annealing_is_refused_for_a_source_of_unknown_length_by_its_name(data, tmp_path):
    cfg = TrainConfig(anneal_lr=True, **SMALL)
    with pytest.raises(ValueError, match="anneal_lr needs a known run length; training from data has none"):
        refuse_anneal(cfg, Recorded)
    with pytest.raises(ValueError, match="anneal_lr"):
        Fit(*_start(tmp_path / "r", cfg, data))
