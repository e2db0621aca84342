"""Learning from bags alone, end to end on real nodes: trainer.bags.rounds records episodes with the sim,
the sampling policy node and morph-record (separate processes, real DDS), trains from each bag with
morph-train --from-bags, and records the next round with the checkpoint that training wrote. A failed
round stops cleanly and the same command continues."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import pytest

from morph_core.algo.run_dir import RunDir
from morph_core.algo.train_from_data import run_state

pytestmark = pytest.mark.slow  # every test here starts processes (nodes, bring-ups, installs)

ROOT = Path(__file__).resolve().parents[1]


def _rows(path):
    with path.open() as f:
        return list(csv.DictReader(f))


@pytest.mark.timeout(900)
def test_rounds_record_with_the_trained_checkpoint_and_continue_after_a_failure(tmp_path, namespace):
    out = tmp_path / "rounds"
    base = [sys.executable, "-m", "trainer.bags.rounds", "--out", str(out), "--namespace", namespace]
    base += ["--episodes-per-round", "2", "--episode-steps", "30", "--min-joints", "2", "--max-joints", "5"]
    base += ["--compare-with", str(ROOT / "docs" / "results_data" / "compensated-s*"), "--record-timeout", "240"]
    train = ["--", "--compile", "false", "--update-epochs", "2", "--tensorboard", "false"]

    # Round 1 records, then its training fails (a bad option): the round stops, saying why; the bag is kept.
    failed = subprocess.run([*base, "--rounds", "2", *train, "--clip-eps", "-1"], capture_output=True, text=True,
                            timeout=600)  # fmt: skip
    assert failed.returncode == 1, failed.stdout + failed.stderr
    assert "round 1: morph-train failed (exit 1)" in failed.stderr and "clip_eps must be > 0" in failed.stderr
    assert "the same command continues" in failed.stderr
    assert (out / "bags" / "round_001" / "metadata.yaml").exists() and not (out / "rounds.csv").exists()

    done = subprocess.run([*base, "--rounds", "2", *train], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "round 1: recording" not in done.stdout  # the kept bag was trained on, not recorded again
    assert "round 2: recording" in done.stdout
    rows = _rows(out / "rounds.csv")
    assert [r["round"] for r in rows] == ["1", "2"]
    assert [int(r["sim_steps"]) for r in rows] == [60, 120]
    for r in rows:
        assert 0 < int(r["steps"]) <= 60 and int(r["lost_steps"]) == 60 - int(r["steps"])
        # Recorded by the policy the trainer starts its update from: on-policy, weights 1.
        assert float(r["stale_frac"]) == 0.0 and abs(float(r["is_weight_mean"]) - 1.0) < 1e-5
    assert int(rows[1]["env_steps"]) == int(rows[0]["steps"]) + int(rows[1]["steps"])
    assert rows[0]["checkpoint"] == "init/policy.safetensors"
    assert rows[1]["checkpoint"] == f"train/checkpoints/policy_{int(rows[0]['steps']):08d}.safetensors"
    state = run_state(out / "train")
    assert state["data_round"] == 2 and state["iteration"] == 2 and state["env_steps"] == int(rows[1]["env_steps"])

    table = _rows(out / "comparison.csv")
    assert [t["round"] for t in table] == ["1", "2"]
    assert all(int(t["simulator_runs"]) >= 1 and t["simulator_return_mean"] != "" for t in table)
    assert (out / "comparison.png").stat().st_size > 0
    assert "| 2 | 120 |" in done.stdout


@pytest.mark.timeout(900)
def test_rounds_of_centipedes_learn_from_whole_bags_at_the_walkers_settings(tmp_path, namespace):
    """``--bodies centipede:2``: the sim draws centipedes, the first policy reads their 12 global features, each
    round trains one pass over its whole bag (its short, fallen episodes may fill more than a batch) at the
    walkers' PPO settings, and counts the steps its bag holds (a walker's episodes end at falls)."""
    import json

    out = tmp_path / "rounds"
    cmd = [sys.executable, "-m", "trainer.bags.rounds", "--out", str(out), "--namespace", namespace, "--rounds", "2",
           "--bodies", "centipede:2", "--episodes-per-round", "8", "--episode-steps", "200", "--record-timeout", "300",
           "--compare-with", str(tmp_path / "none*"), "--",
           "--compile", "false", "--update-epochs", "1", "--tensorboard", "false", "--num-steps", "64"]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=800)
    assert done.returncode == 0, done.stdout + done.stderr
    rows = _rows(out / "rounds.csv")
    assert [r["round"] for r in rows] == ["1", "2"]
    for r in rows:
        assert int(r["lost_steps"]) == 0 and int(r["episodes"]) >= 7  # every episode counted, fallen or not
    assert [int(r["sim_steps"]) for r in rows] == [int(rows[0]["steps"]), int(rows[1]["env_steps"])]
    # One pass: every step of round 1's bag was learned from (6 envs x 64 steps a batch: several updates).
    assert int(rows[0]["steps"]) > 384
    assert rows[1]["checkpoint"] == f"train/checkpoints/policy_{int(rows[0]['steps']):08d}.safetensors"
    config = json.loads(RunDir(out / "train").config.read_text())
    assert (config["learning_rate"], config["gamma"], config["gae_lambda"]) == (0.0003, 0.99, 0.95)
    assert config["policy"]["global_features"] == 12
