"""The bring-ups (``scripts/live.sh``, ``scripts/record.sh``) refuse what their trainer or recorder would
refuse before starting anything: one line, the tool's own error, no traceback blaming DDS. No DDS here: each
is refused before a node starts (a subprocess with a timeout, so a bring-up that started nodes would fail)."""

import subprocess
import sys

LIVE = [sys.executable, "-m", "trainer.live_bringup"]


def _refused(cmd, cwd) -> list[str]:
    done = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr and done.stdout == ""
    return done.stderr.splitlines()


def test_live_on_a_run_without_resume_says_the_trainer_s_one_line(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "state.safetensors").write_bytes(b"")  # what the trainer looks for
    assert _refused([*LIVE, "--out", str(run)], tmp_path) == [
        f"morph-train: error: {run} already holds a run; pass --resume to continue it or choose another --out",
        "see morph-train --help",
    ]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]
    assert sorted(p.name for p in run.iterdir()) == ["state.safetensors"]


def test_live_resume_without_a_run_and_bad_trainer_options_are_refused_first(tmp_path):
    err = _refused([*LIVE, "--out", str(tmp_path / "none"), "--resume"], tmp_path)
    assert (
        err[0]
        == f"morph-train: error: --resume: no live run to resume in {tmp_path / 'none'} (state.safetensors missing)"
    )
    err = _refused([*LIVE, "--out", str(tmp_path / "new"), "--", "--total-timestep", "5"], tmp_path)
    assert err == ["morph-train: error: unrecognized arguments: --total-timestep 5", "see morph-train --help"]
    err = _refused([*LIVE, "--out", str(tmp_path / "new"), "--", "--learning-rate", "fast"], tmp_path)
    assert err[0] == "morph-train: error: argument --learning-rate: invalid float value: 'fast'"
    assert list(tmp_path.iterdir()) == []


def test_live_resume_of_a_finished_run_says_so_and_starts_nothing(tmp_path):
    from morph_core.algo.train import TrainConfig, train

    small = dict(num_envs=2, num_steps=64, minibatch_size=32, update_epochs=1, total_timesteps=128,
                 tensorboard=False, progress_bar=False, compile=False)  # fmt: skip
    run = train(TrainConfig(**small), tmp_path / "run")  # a training state at its total_timesteps
    files = sorted(p.name for p in run.iterdir())
    done = subprocess.run([*LIVE, "--out", str(run), "--resume"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == [
        f"morph-train: {run} already finished at step 128 (total_timesteps 128): nothing to do; "
        "raise --total-timesteps to go on"
    ]
    assert sorted(p.name for p in run.iterdir()) == files
