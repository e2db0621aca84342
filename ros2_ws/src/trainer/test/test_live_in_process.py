"""Live training without DDS (``trainer.live_in_process``): lost states cut episodes into runs as the live
trainer cuts them, the behaviour policy lags the set number of versions, and the run directory is a live run's."""

from __future__ import annotations

import csv

import pytest

from morph_core.algo.train import TrainConfig
from trainer.live_in_process import InProcessOptions, main, train_in_process

TINY = TrainConfig(num_envs=1, num_steps=256, minibatch_size=64, update_epochs=1, total_timesteps=1200,
                   min_joints=2, max_joints=4, tensorboard=False, progress_bar=False, compile=False)  # fmt: skip


def rows(run_dir) -> list[dict]:
    with open(run_dir / "progress.csv") as f:
        return list(csv.DictReader(f))


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
    (tmp_path / "run" / "config.json").write_text("{}")
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path / "run")])
    assert "already holds a run" in capsys.readouterr().err
