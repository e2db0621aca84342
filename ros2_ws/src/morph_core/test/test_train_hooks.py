"""``train``'s row hook: what a Ray Tune trial reports is each progress row, told when its step's state is saved."""

import csv

from morph_core.algo.run_dir import RunDir
from morph_core.algo.train import TrainConfig, train


def test_on_row_hears_every_logged_row_and_each_saved_step(tmp_path):
    cfg = TrainConfig(
        total_timesteps=768, num_envs=2, num_steps=128, minibatch_size=64, update_epochs=1,
        checkpoint_interval=512, compile=False, progress_bar=False, tensorboard=False,
    )  # fmt: skip
    heard = []
    train(cfg, tmp_path, on_row=lambda row, saved: heard.append((row["global_step"], saved)))
    with open(RunDir(tmp_path).progress) as f:
        logged = [int(r["global_step"]) for r in csv.DictReader(f)]
    assert [step for step, _ in heard] == logged == [256, 512, 768]
    assert [saved for _, saved in heard] == [False, True, True]  # the mark at 512, and the run's end
    saved_steps = [step for step, _ in RunDir(tmp_path).saved_checkpoints()]
    assert saved_steps == [step for step, saved in heard if saved]
