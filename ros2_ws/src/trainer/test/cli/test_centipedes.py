"""Centipedes through the swimmers' tools: morph-train (``--bodies centipede:...``, resumed bit for bit),
morph-eval on trained and zero-shot sizes, morph-render. Small sizes and runs: seconds each."""

from __future__ import annotations

import csv
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from PIL import Image

from morph_core.algo.checkpoint import load_training_state
from morph_core.algo.run_dir import RunDir
from morph_core.algo.small_runs import small
from morph_core.algo.train import TrainConfig, train
from morph_core.policy.config import PolicyConfig
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.weights import load_checkpoint, untrained_weights

SMALL = small(bodies="centipede:2-3", checkpoint_interval=128)


@pytest.fixture(scope="module")
def centipede_run(tmp_path_factory):
    return train(TrainConfig(total_timesteps=384, seed=3, **SMALL), tmp_path_factory.mktemp("run") / "a")


def test_a_centipede_run_has_twelve_globals_and_resumes_bit_for_bit(centipede_run, tmp_path):
    policy = load_checkpoint(RunDir(centipede_run).checkpoints / "policy_00000384.safetensors")
    assert policy.config.global_features == 12  # from the body mix, not the swimmer's default
    part = train(TrainConfig(total_timesteps=128, seed=3, **SMALL), tmp_path / "b")
    train(TrainConfig(total_timesteps=384, seed=3, **SMALL), part, resume=True)
    (wa, ma), (wb, mb) = (
        load_training_state(RunDir(centipede_run).state),
        load_training_state(RunDir(part).state),
    )
    assert wa.keys() == wb.keys() and ma["sections"]["swimmers"] == mb["sections"]["swimmers"]
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k  # weights, Adam, RNGs, MuJoCo states and root positions
    with RunDir(centipede_run).progress.open() as f:
        rows = list(csv.DictReader(f))
    with RunDir(part).progress.open() as f:
        assert [r["return_mean"] for r in csv.DictReader(f)] == [r["return_mean"] for r in rows]
    assert {"return_d8", "return_d12"} <= rows[0].keys()  # action dimensions 4 x leg pairs
    assert any(r["return_mean"] not in ("", "nan") for r in rows)  # centipedes fell or timed out: episodes ended


@pytest.mark.slow
def test_morph_eval_on_trained_and_zero_shot_centipedes(centipede_run, capsys):
    from trainer.cli.eval import main

    assert main(["--run", str(centipede_run), "--bodies", "centipede:2,centipede:5", "--episodes", "2"]) == 0
    with RunDir(centipede_run).evaluation.open() as f:
        rows = list(csv.DictReader(f))
    assert {(r["body"], r["num_joints"]) for r in rows} == {("centipede-2", "8"), ("centipede-5", "20")}  # no chains
    assert len(rows) == 3 * 2 * 2  # 3 checkpoints x 2 bodies x 2 episodes
    ckpt = str(RunDir(centipede_run).checkpoints / "policy_00000384.safetensors")
    assert main(["--checkpoint", ckpt, "--bodies", "centipede:6", "--episodes", "1"]) == 0
    assert "| centipede-6 | 24 |" in capsys.readouterr().out


def test_a_swimmer_policy_cannot_evaluate_a_centipede(tmp_path):
    from morph_core.algo.evaluate import evaluate_policy
    from morph_core.env.bodies import Centipede

    with pytest.raises(ValueError, match="reads 4 global features, a walker 12"):
        evaluate_policy(untrained_weights(seed=0), [Centipede(2)], episodes=1, max_steps=2)


class _Hop(NumpyPolicy):
    """Every joint at +1 for two steps, then -1 for two: a 2-pair centipede jumps above Ant-v5's healthy
    height (1.0 m) within ~15 steps, each episode at its own step."""

    calls = 0

    def mean_actions(self, joint_pos, joint_vel, global_feats, num_joints, parents=None):
        sign, self.calls = (1.0 if self.calls % 4 < 2 else -1.0), self.calls + 1
        return np.full(joint_pos.shape, sign, np.float32)


def test_an_evaluated_centipede_stops_where_it_fell_its_length_and_distance_the_envs():
    from morph_core.algo.evaluate import evaluate_episodes
    from morph_core.env.bodies import Centipede
    from morph_core.env.centipede import MorphCentipedeEnv

    weights = untrained_weights(PolicyConfig(global_features=12))
    results = evaluate_episodes(_Hop(weights), [Centipede(2)], episodes=3, max_steps=100)[Centipede(2)]
    for k in range(3):
        env = MorphCentipedeEnv(leg_pairs=2)
        env.reset(seed=10_000 + k)
        x0, total, steps, terminated = env.data.qpos[0], 0.0, 0, False
        while not terminated and steps < 100:
            _, reward, terminated, _, info = env.step(np.full(8, 1.0 if steps % 4 < 2 else -1.0))
            total, steps = total + reward, steps + 1
        assert terminated and info["x_position"] != x0  # it jumped too high: the episode ended there
        assert (results.returns[k], results.steps[k], results.distance[k]) == (total, steps, info["x_position"] - x0)
    assert len(set(results.steps)) > 1  # the episodes ended at different steps: the batch went on without each


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_morph_render_films_a_centipede(centipede_run, tmp_path):
    gif = tmp_path / "c.gif"
    ckpt = str(RunDir(centipede_run).checkpoints / "policy_00000384.safetensors")
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"}
    args = ["--checkpoint", ckpt, "--bodies", "centipede:2", "--seconds", "0.8", "--width", "160", "--height", "96"]
    done = subprocess.run(
        [sys.executable, "-m", "trainer.cli.render", *args, "--gif", str(gif)],
        capture_output=True, text=True, timeout=300, env=env,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "centipede-2: return" in done.stderr
    with Image.open(gif) as im:
        frames = []
        for k in range(im.n_frames):
            im.seek(k)
            frames.append(np.asarray(im.convert("RGB")))
    assert len(frames) == 11 and all(f.shape == (96, 160, 3) and f.std() > 20 for f in frames)
    assert np.abs(frames[0].astype(int) - frames[-1]).mean() > 0.5  # it moved (or the camera followed it)


@pytest.mark.slow
def test_a_two_process_centipede_run_resumes_exactly_as_an_uninterrupted_run(tmp_path):
    # --processes 2: the helper steps half the centipedes and shares the 12-wide global rollout.
    two = {**SMALL, "num_envs": 4, "processes": 2, "checkpoint_interval": 256}
    straight = train(TrainConfig(total_timesteps=768, seed=5, **two), tmp_path / "a")
    part = train(TrainConfig(total_timesteps=256, seed=5, **two), tmp_path / "b")
    train(TrainConfig(total_timesteps=768, seed=5, **two), part, resume=True)
    (wa, ma), (wb, mb) = (load_training_state(RunDir(run).state) for run in (straight, part))
    assert "rng.helper1" in wa and ma["counters"]["global_step"] == mb["counters"]["global_step"] == 768
    assert load_checkpoint(RunDir(straight).checkpoints / "policy_00000768.safetensors").config.global_features == 12
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k
    with RunDir(straight).progress.open() as f, RunDir(part).progress.open() as g:
        assert [r["policy_loss"] for r in csv.DictReader(f)] == [r["policy_loss"] for r in csv.DictReader(g)]


def test_morph_eval_run_on_a_centipede_run_evaluates_its_bodies_and_the_zero_shot_sizes(centipede_run, tmp_path):
    """Neither --bodies nor --joints: the run's own centipedes and 5, 6, 8, 10 leg pairs, no swimmer chains; a
    swimmer run, or an option given, keeps the chains (2..10, 15, 20) as before."""
    from morph_core.env.bodies import Centipede
    from trainer.reports.evaluation import EvalConfig, eval_bodies, run_eval_config

    cfg = EvalConfig()
    bodies = eval_bodies(run_eval_config(centipede_run, cfg, set()))
    assert bodies == [Centipede(n) for n in (2, 3, 5, 6, 8, 10)]
    assert run_eval_config(centipede_run, cfg, {"lengths"}) is cfg
    assert run_eval_config(centipede_run, cfg, {"bodies"}) is cfg
    swimmers = tmp_path / "swimmers"
    swimmers.mkdir()
    RunDir(swimmers).config.write_text('{"bodies": "", "min_joints": 2, "max_joints": 10}')
    assert eval_bodies(run_eval_config(swimmers, cfg, set())) == [*range(2, 11), 15, 20]


def _train_cli(tmp_path, *options):
    out = tmp_path / "run"
    args = ["--out", str(out), "--total-timesteps", "64", "--num-envs", "1", "--num-steps", "64",
            "--minibatch-size", "32", "--update-epochs", "1", "--compile", "false", "--tensorboard", "false",
            "--progress-bar", "false", *options]  # fmt: skip
    run = subprocess.run([sys.executable, "-m", "trainer.cli.train", *args], capture_output=True, text=True,
                         timeout=300)  # fmt: skip
    assert run.returncode == 0, run.stderr
    import json

    return json.loads(RunDir(out).config.read_text()), run.stdout


@pytest.mark.slow
def test_morph_train_on_centipedes_takes_the_centipede_settings_unless_given(tmp_path):
    cfg, out = _train_cli(tmp_path / "a", "--bodies", "centipede:2")
    assert (cfg["learning_rate"], cfg["gamma"], cfg["gae_lambda"]) == (3e-4, 0.99, 0.95)
    assert "--learning-rate 0.0003 --gamma 0.99 --gae-lambda 0.95" in out
    cfg, out = _train_cli(tmp_path / "b", "--bodies", "centipede:2", "--learning-rate", "0.001", "--gamma", "0.9")
    assert (cfg["learning_rate"], cfg["gamma"], cfg["gae_lambda"]) == (0.001, 0.9, 0.95)
    assert "--gae-lambda 0.95" in out and "--learning-rate 0.0003" not in out
    cfg, out = _train_cli(tmp_path / "c", "--min-joints", "2", "--max-joints", "3")  # swimmers: the paper's
    assert (cfg["learning_rate"], cfg["gamma"], cfg["gae_lambda"]) == (0.01, 0.98, 0.98)
    assert "legs" not in out
