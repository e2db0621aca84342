"""Live training without DDS (``trainer.live.in_process``): lost states cut episodes into runs as the live
trainer cuts them, the behaviour policy lags the set number of versions, and the run directory is a live run's."""

from __future__ import annotations

import csv
import json

import pytest

from morph_core.algo.run_dir import RunDir
from morph_core.algo.small_runs import small_config
from morph_core.algo.train import TrainConfig
from trainer.live.in_process import InProcessOptions, main, train_in_process
from trainer.live.learner import LIVE_LEARNING_RATE

TINY = small_config(
    num_envs=1, num_steps=256, minibatch_size=64, update_epochs=1, total_timesteps=1200, min_joints=2, max_joints=4
)


def rows(run_dir) -> list[dict]:
    with open(RunDir(run_dir).progress) as f:
        return list(csv.DictReader(f))


@pytest.mark.slow
def test_whole_episodes_without_loss_and_runs_with_it(tmp_path):
    whole = rows(train_in_process(TINY, InProcessOptions(episode_steps=100), tmp_path / "whole", log=lambda _: 0)
                 .run_dir)  # fmt: skip
    # Episodes of 100 transitions: an update of >= 256 samples takes 3 whole episodes.
    assert all(int(r["pool_episodes"]) == 3 and int(r["data_steps"]) == 300 for r in whole)
    cut = rows(train_in_process(TINY, InProcessOptions(episode_steps=100, drop_states=0.2), tmp_path / "cut",
                                log=lambda _: 0).run_dir)  # fmt: skip
    # A lost state costs the transitions into and out of it and splits the episode: many short runs.
    assert all(int(r["pool_episodes"]) > 3 * 5 for r in cut)
    assert sum(float(r["return_mean"]) for r in cut) != sum(float(r["return_mean"]) for r in whole)


@pytest.mark.parametrize("lag", [0, 2])
def test_the_behaviour_policy_lags_the_set_number_of_versions(tmp_path, lag):
    got = rows(train_in_process(TINY, InProcessOptions(lag=lag, episode_steps=100), tmp_path, log=lambda _: 0)
               .run_dir)  # fmt: skip
    lags = [float(r["version_lag_mean"]) for r in got]
    # The first updates' data can only be as old as version 0; later ones are exactly `lag` behind.
    assert lags == [min(lag, i) for i in range(len(got))]
    weights = [float(r["is_weight_mean"]) for r in got]
    assert weights[0] == pytest.approx(1.0, abs=1e-4)
    assert (weights[-1] == pytest.approx(1.0, abs=1e-4)) == (lag == 0)


def test_cli_refuses_bad_options_and_an_existing_run(tmp_path, capsys):
    for bad in (["--lag", "-1"], ["--drop-states", "1.0"], ["--episode-steps", "1"]):
        with pytest.raises(SystemExit):
            main(["--out", str(tmp_path / "x"), *bad])
        assert "error" in capsys.readouterr().err
    (tmp_path / "run").mkdir()
    RunDir(tmp_path / "run").config.write_text("{}")
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path / "run")])
    assert "already holds a run" in capsys.readouterr().err


def test_cli_starts_from_the_live_learning_rate_unless_given_one(tmp_path):
    tiny = ["--num-envs", "1", "--num-steps", "128", "--minibatch-size", "64", "--update-epochs", "1",
            "--total-timesteps", "128", "--min-joints", "2", "--max-joints", "3", "--compile", "false",
            "--tensorboard", "false", "--episode-steps", "64"]  # fmt: skip
    for given, expected in (([], LIVE_LEARNING_RATE), (["--learning-rate", "0.01"], 0.01)):
        out = tmp_path / f"run{len(given)}"
        assert main(["--out", str(out), *tiny, *given]) == 0
        assert json.loads(RunDir(out).config.read_text())["learning_rate"] == expected
        assert {float(r["learning_rate"]) for r in rows(out)} == {expected}
    assert LIVE_LEARNING_RATE < TrainConfig().learning_rate


def test_lost_states_are_warned_about_and_a_restarted_sim_is_not():
    import dataclasses

    import numpy as np

    from morph_core.msgs.records import JointStateRecord
    from morph_core.policy.actor_critic import GraphActorCritic
    from morph_core.protocol.loopback import SamplingController, record_episodes
    from morph_core.protocol.transitions import TransitionAssembler
    from trainer.live.trainer_node import lost_messages_warning  # rclpy is imported, nothing is started

    policy = GraphActorCritic()
    first = record_episodes(SamplingController(policy, 1), [(3, 50)], seed=1)
    again = record_episodes(SamplingController(policy, 2), [(3, 50)], seed=2)  # the sim restarted: clock from 0
    shift = first[-1].log_ns
    restarted = first + [dataclasses.replace(r, log_ns=r.log_ns + shift) for r in again]
    asm = TransitionAssembler()
    asm.push_many(restarted)
    asm.flush()
    assert asm.stats.boundaries_stamp_gap >= 1 and asm.stats.lost_state_gaps == 0
    assert lost_messages_warning(asm.stats.lost_state_gaps, asm.stats.transitions) is None

    states = [i for i, r in enumerate(first) if isinstance(r, JointStateRecord)]
    lost = {states[10], states[30]}
    asm = TransitionAssembler()
    asm.push_many([r for i, r in enumerate(first) if i not in lost])
    asm.flush()
    assert asm.stats.lost_state_gaps == 2
    warning = lost_messages_warning(asm.stats.lost_state_gaps, asm.stats.transitions)
    assert warning.startswith("2 stamp gaps") and f"one per {np.round(asm.stats.transitions / 2):.0f}" in warning
