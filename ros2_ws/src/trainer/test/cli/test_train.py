"""Training loop end to end: CLI, logs, checkpoint/resume equality (also after a SIGKILL), learning."""

import csv
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from morph_core.algo.checkpoint import load_training_state
from morph_core.algo.run_dir import RunDir
from morph_core.algo.small_runs import small
from morph_core.algo.train import TrainConfig, train

SMALL = small(checkpoint_interval=128)


def _final_weights(run_dir):
    tensors, meta = load_training_state(RunDir(run_dir).state)
    return tensors, meta["counters"]["global_step"]


def _rows(run_dir):
    with RunDir(run_dir).progress.open() as f:
        return list(csv.DictReader(f))


@pytest.mark.slow
@pytest.mark.parametrize("compiled", [False, True])
def test_resume_continues_exactly_as_an_uninterrupted_run(tmp_path, compiled):
    small = {**SMALL, "compile": compiled}
    straight = train(TrainConfig(total_timesteps=384, seed=3, **small), tmp_path / "a")
    part = train(TrainConfig(total_timesteps=128, seed=3, **small), tmp_path / "b")
    train(TrainConfig(total_timesteps=384, seed=3, **small), part, resume=True)
    (wa, step_a), (wb, step_b) = _final_weights(straight), _final_weights(part)
    assert step_a == step_b == 384
    assert wa.keys() == wb.keys()
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k  # weights, Adam moments, RNG and env states: bit for bit
    ra, rb = _rows(straight), _rows(part)
    assert [r["global_step"] for r in ra] == [r["global_step"] for r in rb] == ["128", "256", "384"]
    assert [r["return_mean"] for r in ra] == [r["return_mean"] for r in rb]
    ckpts = sorted(p.name for p in RunDir(straight).checkpoints.glob("*.safetensors"))
    assert ckpts == ["policy_00000128.safetensors", "policy_00000256.safetensors", "policy_00000384.safetensors"]


@pytest.mark.slow
def test_cli_run_killed_at_any_moment_resumes_with_nothing_lost(tmp_path):
    args = "--num-envs 2 --num-steps 64 --minibatch-size 32 --update-epochs 2 --checkpoint-interval 128 --seed 5"
    args = [*args.split(), "--tensorboard", "false", "--progress-bar", "false", "--compile", "false"]
    cli = [sys.executable, "-m", "trainer.cli.train"]
    subprocess.run([*cli, "--out", str(tmp_path / "ref"), "--total-timesteps", "2048", *args], check=True)
    run = tmp_path / "killed"
    proc = subprocess.Popen([*cli, "--out", str(run), "--total-timesteps", "2048", *args])
    deadline = time.monotonic() + 120
    # Kill it mid-run, once it has checkpointed twice: polling files the child writes (nothing to subscribe to).
    while time.monotonic() < deadline and proc.poll() is None:
        if RunDir(run).state.exists() and len(_rows(run)) >= 2:
            break
        time.sleep(0.005)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    _, killed_at = _final_weights(run)
    assert killed_at < 2048, "the run finished before it could be killed; make it longer"
    subprocess.run([*cli, "--out", str(run), "--resume"], check=True)
    (w_ref, s_ref), (w_run, s_run) = _final_weights(tmp_path / "ref"), _final_weights(run)
    assert s_ref == s_run == 2048
    for k in w_ref:
        assert torch.equal(w_ref[k], w_run[k]), k
    assert [r["global_step"] for r in _rows(run)] == [str(128 * i) for i in range(1, 17)]


@pytest.mark.slow
def test_cli_options_come_from_the_config_and_bad_values_are_refused(tmp_path):
    cli = [sys.executable, "-m", "trainer.cli.train"]
    help_text = subprocess.run([*cli, "--help"], capture_output=True, text=True, check=True).stdout
    for opt in ("--clip-mode", "--total-timesteps", "--seed", "--resume", "--policy-bidirectional", "--gae-lambda"):
        assert opt in help_text
    bad = subprocess.run(
        [*cli, "--out", str(tmp_path / "x"), "--clip-mode", "adaptive"], capture_output=True, text=True
    )
    assert bad.returncode != 0 and "--clip-mode: invalid choice: 'adaptive'" in bad.stderr
    bad = subprocess.run([*cli, "--out", str(tmp_path / "x"), "--resume"], capture_output=True, text=True)
    assert bad.returncode != 0 and "no run to resume" in bad.stderr


@pytest.mark.slow
def test_resume_writes_the_options_given_back_and_a_finished_run_says_so(tmp_path, capsys):
    from trainer.cli.train import main

    args = "--num-envs 2 --num-steps 64 --minibatch-size 32 --update-epochs 2 --checkpoint-interval 128 --seed 5"
    args = [*args.split(), "--tensorboard", "false", "--progress-bar", "false", "--compile", "false"]
    run = tmp_path / "run"
    config = lambda: json.loads(RunDir(run).config.read_text())  # noqa: E731
    assert main(["--out", str(run), "--total-timesteps", "128", "--kl-target", "1", *args]) == 0
    assert capsys.readouterr().out.splitlines() == [  # without the progress bar, still a summary
        f"morph-train: done: step 128 (update 1); no episode finished yet; last update's approximate KL "
        f"{float(_rows(run)[-1]['approx_kl']):.3g}",
        f"morph-train: files in {run}: config.json, progress.csv, checkpoints/ (1, the last "
        "policy_00000128.safetensors), state.safetensors (for --resume)",
    ]
    rows = RunDir(run).progress.read_text()
    assert main(["--out", str(run), "--resume"]) == 0
    assert capsys.readouterr().out.splitlines()[0] == (
        f"morph-train: {run} already finished at step 128 (total_timesteps 128): nothing to do; "
        "raise --total-timesteps to go on"
    )
    assert RunDir(run).progress.read_text() == rows
    assert main(["--out", str(run), "--resume", "--total-timesteps", "256", "--processes", "2"]) == 0
    said = capsys.readouterr().out
    assert (
        f"morph-train: resumed with total_timesteps 128 -> 256, processes 1 -> 2 (written to {RunDir(run).config})"
        in said
    )
    assert config()["total_timesteps"] == 256 and config()["processes"] == 2
    assert _final_weights(run)[1] == 256
    # A plain resume goes on with what config.json says now; nothing changed, nothing said or written.
    assert main(["--out", str(run), "--resume"]) == 0
    assert "already finished at step 256 (total_timesteps 256)" in capsys.readouterr().out
    # Options given to a resume that fails before it trains (no usable state) are not kept.
    for name in (RunDir(run).state.name, RunDir(run).previous_state.name):
        (run / name).write_bytes(b"damaged")
    assert main(["--out", str(run), "--resume", "--total-timesteps", "512"]) == 1
    assert "morph-train: error:" in capsys.readouterr().err
    assert config()["total_timesteps"] == 256


def test_logs_hold_per_dimension_diagnostics(tmp_path):
    run = train(TrainConfig(total_timesteps=256, clip_mode="fixed", seed=0, **SMALL), tmp_path / "r")
    cfg = json.loads(RunDir(run).config.read_text())
    assert cfg["clip_mode"] == "fixed" and cfg["clip_eps"] == 0.111
    rows = _rows(run)
    seen = [d for d in range(2, 11) if rows[-1][f"clip_frac_d{d}"] != ""]
    assert seen, "no per-dimension clip fractions logged"
    for d in seen:
        assert 0.0 <= float(rows[-1][f"clip_frac_d{d}"]) <= 1.0
        assert 0.0 <= float(rows[-1][f"in_eps_frac_d{d}"]) <= 1.0
        assert float(rows[-1][f"logr_std_d{d}"]) >= 0.0
    assert {r["learning_rate"] for r in rows} == {"0.01"}  # the paper's constant rate


def test_annealed_learning_rate_falls_linearly_towards_zero(tmp_path):
    run = train(TrainConfig(total_timesteps=512, anneal_lr=True, learning_rate=0.004, seed=0, **SMALL), tmp_path / "a")
    rows = _rows(run)
    before = [int(r["global_step"]) - 128 for r in rows]  # steps done before each update
    assert before == [0, 128, 256, 384]
    assert [float(r["learning_rate"]) for r in rows] == pytest.approx([0.004 * (1 - b / 512) for b in before])


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_short_training_run_improves_return(tmp_path):
    # The paper configuration for 20 iterations. Early on the swimmers first learn to move at
    # all (often turning round, so returns dip), then to swim forward; by ~120k steps the
    # training return has clearly risen. Seeded, and runs are bit-reproducible.
    cfg = TrainConfig(total_timesteps=122_880, seed=1, tensorboard=False, progress_bar=False)
    rows = _rows(train(cfg, tmp_path / "learn"))
    returns = [float(r["return_mean"]) for r in rows if r["return_mean"] != ""]
    first, last = np.mean(returns[:3]), np.mean(returns[-3:])
    assert last > first + 20.0, (first, last)


# The rules beyond fixed/compensated, each end to end and resumed. A tiny kl_target makes the KL rules
# act at every update: beta doubles each time (learner state that must survive the resume), and KL
# early stopping ends every update after its first epoch.
NEW_RULES = {
    "per-joint-clip": {},
    "kl-penalty": {"kl_target": 1e-9, "kl_beta": 0.5},
    "kl-penalty-per-joint": {"kl_target": 1e-9, "kl_beta": 0.5},
    "kl-stop": {"kl_target": 1e-9},
    "kl-stop-per-joint": {"kl_target": 1e-9},
}


@pytest.mark.parametrize("rule", list(NEW_RULES))
def test_each_new_rule_trains_and_resumes_bit_for_bit(tmp_path, rule):
    small = {**SMALL, **NEW_RULES[rule], "clip_mode": rule, "seed": 4}
    straight = train(TrainConfig(total_timesteps=384, **small), tmp_path / "a")
    part = train(TrainConfig(total_timesteps=128, **small), tmp_path / "b")
    train(TrainConfig(total_timesteps=384, **small), part, resume=True)
    (wa, step_a), (wb, step_b) = _final_weights(straight), _final_weights(part)
    assert step_a == step_b == 384 and wa.keys() == wb.keys()
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k
    timing = {"wall_time", "sps", "rollout_s", "update_s"}
    ra, rb = _rows(straight), _rows(part)
    assert [{k: v for k, v in r.items() if k not in timing} for r in ra] == [
        {k: v for k, v in r.items() if k not in timing} for r in rb
    ]
    epochs = [int(r["epochs"]) for r in ra]
    if rule.startswith("kl-penalty"):
        assert [float(r["kl_beta"]) for r in ra] == [0.5, 1.0, 2.0]  # the beta each update used
        assert wa["learner.kl_beta"].dtype == torch.float64 and float(wa["learner.kl_beta"]) == 4.0
    else:
        assert {r["kl_beta"] for r in ra} == {""} and not any(k.startswith("learner.") for k in wa)
    assert epochs == ([1, 1, 1] if rule.startswith("kl-stop") else [2, 2, 2])
    for r in ra:
        assert 0.0 <= float(r["clip_frac_first"]) <= 1.0 and float(r["approx_kl_last"]) >= 0.0


def test_init_fine_tunes_a_shipped_policy_on_a_users_mjcf(tmp_path):
    """``--init`` in the simulator: the run starts from the checkpoint's weights and architecture, on
    ``--bodies mjcf:PATH`` (Gymnasium's ant.xml, a walker); a resumed run refuses ``--init``."""
    import gymnasium
    from safetensors.numpy import load_file

    from morph_core.policy.weights import load_checkpoint
    from trainer.cli.train import main

    ant = os.path.join(os.path.dirname(gymnasium.__file__), "envs", "mujoco", "assets", "ant.xml")
    init = os.path.join(os.path.dirname(__file__), "..", "..", "..", "morph_policy_node", "morph_policy_node", "models",
                        "centipede_gnn.safetensors")  # fmt: skip
    run = tmp_path / "ant"
    args = ["--out", str(run), "--bodies", f"mjcf:{ant}", "--init", init, "--total-timesteps", "256",
            "--num-envs", "2", "--num-steps", "128", "--minibatch-size", "128", "--update-epochs", "1",
            "--learning-rate", "0", "--compile", "false", "--tensorboard", "false",
            "--progress-bar", "false"]  # fmt: skip
    assert main(args) == 0
    assert json.loads(RunDir(run).init.read_text())["init"] == os.path.realpath(init)
    assert json.loads(RunDir(run).config.read_text())["policy"]["global_features"] == 12
    start = load_checkpoint(init).arrays
    (saved,) = sorted(RunDir(run).checkpoints.glob("*.safetensors"))
    after = load_file(str(saved))
    assert all(np.array_equal(after[k], start[k]) for k in start if k != "log_std")  # learning rate 0
    with pytest.raises(SystemExit):
        main([*args[:2], "--resume", "--init", init])
