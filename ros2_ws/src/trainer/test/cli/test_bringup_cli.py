"""The bring-ups (``scripts/live.sh``, ``scripts/record.sh``) refuse what their trainer or recorder would
refuse before starting anything: one line, the tool's own error, no traceback blaming DDS. No DDS here: each
is refused before a node starts (a subprocess with a timeout, so a bring-up that started nodes would fail)."""

import hashlib
import subprocess
import sys
from pathlib import Path

import pytest

from morph_core.algo.run_dir import RunDir

LIVE = [sys.executable, "-m", "trainer.live.bringup"]
ROOT = Path(__file__).resolve().parents[5]


def _set_up() -> bool:
    """Whether scripts/setup.sh has nothing to do (the wrappers run it first: not a reinstall in a test)."""
    stamp = ROOT / ".venv" / ".installed"
    files = [ROOT / "constraints.txt", ROOT / "requirements-dev.txt", *sorted(ROOT.glob("ros2_ws/src/*/setup.py"))]
    files.append(ROOT / "scripts" / "install_nodes.sh")  # setup.sh's stamp covers these files, in this order
    want = hashlib.sha256(b"".join(f.read_bytes() for f in files)).hexdigest()
    return stamp.is_file() and stamp.read_text().strip() == want


needs_setup = pytest.mark.skipif(not _set_up(), reason="the project venv is not set up (bash scripts/setup.sh)")


def _refused(cmd, cwd) -> list[str]:
    done = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr and done.stdout == ""
    return done.stderr.splitlines()


@pytest.mark.slow
def test_live_on_a_run_without_resume_says_the_trainer_s_one_line(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    RunDir(run).state.write_bytes(b"")  # what the trainer looks for
    assert _refused([*LIVE, "--out", str(run)], tmp_path) == [
        f"morph-train: error: {run} already holds a run; pass --resume to continue it or choose another --out",
        "see morph-train --help",
    ]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]
    assert sorted(p.name for p in run.iterdir()) == [RunDir(run).state.name]


@pytest.mark.slow
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


@pytest.mark.slow
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


@needs_setup
@pytest.mark.parametrize("script", ["live.sh", "record.sh"])
def test_the_wrappers_help_names_the_script_and_shows_defaults(tmp_path, script):
    wrapper = ROOT / "scripts" / script
    done = subprocess.run(["bash", str(wrapper), "--help"], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith(f"usage: bash scripts/{script} [-h]")
    assert "bring-up" not in done.stdout.splitlines()[0] and "(default: 10)" in done.stdout
    text = " ".join(done.stdout.split())  # the epilog wrapped
    policy = "--init" if script == "live.sh" else "--checkpoint"  # the policy a run starts from / nodes run
    assert f"A relative --out or {policy} is taken from the folder the command runs in." in text
    if script == "live.sh":
        assert "[-- MORPH-TRAIN OPTIONS]" in done.stdout and "Everything after -- goes to the trainer" in text
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
@needs_setup
def test_the_wrappers_take_a_relative_out_from_the_caller_s_folder(tmp_path):
    (tmp_path / "rel").mkdir()
    RunDir(tmp_path / "rel").state.write_bytes(b"")
    live = subprocess.run(["bash", str(ROOT / "scripts" / "live.sh"), "--out", "rel"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert live.returncode == 2
    assert live.stderr.splitlines()[0] == (
        "morph-train: error: rel already holds a run; pass --resume to continue it or choose another --out"
    )
    record = subprocess.run(["bash", str(ROOT / "scripts" / "record.sh"), "--out", "rel"], cwd=tmp_path,
                            capture_output=True, text=True, timeout=120)  # fmt: skip
    assert record.returncode == 1 and "rel exists already" in record.stderr
    assert not (ROOT / "rel").exists()


SCRIPTS = sorted(p.name for p in (ROOT / "scripts").glob("*.sh") if p.name != "help.sh")


def test_every_script_is_covered():
    assert set(SCRIPTS) >= {"demo.sh", "setup.sh", "in_netns.sh", "test.sh", "live_results.sh", "fuzz_nodes.sh",
                            "record.sh", "live.sh", "bag_rounds.sh"}  # fmt: skip


@needs_setup
@pytest.mark.parametrize("script", SCRIPTS)
@pytest.mark.parametrize("flag", ["--help", "-h"])
def test_every_script_answers_help_with_its_own_name_and_usage_and_does_nothing_else(tmp_path, script, flag):
    """Not bringup.py's usage, not bash's exec help, not a count of --help, not ruff then pytest's help."""
    done = subprocess.run(["bash", str(ROOT / "scripts" / script), flag], cwd=tmp_path, capture_output=True,
                          text=True, timeout=120)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith(f"usage: bash scripts/{script}"), done.stdout[:300]
    assert len(done.stdout.splitlines()) > 2 and done.stderr == ""  # a description too; no setup, no ruff
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("script, args", [("fuzz_nodes.sh", ["many"]), ("live_results.sh", ["3", "--help2"]),
                                          ("setup.sh", ["--force"]), ("in_netns.sh", [])])  # fmt: skip
def test_scripts_refuse_arguments_they_do_not_take_in_one_line(tmp_path, script, args):
    done = subprocess.run(["bash", str(ROOT / "scripts" / script), *args], cwd=tmp_path, capture_output=True,
                          text=True, timeout=120)  # fmt: skip
    assert done.returncode == 2 and len(done.stderr.splitlines()) == 1 and script in done.stderr, done.stderr
    assert list(tmp_path.iterdir()) == []


def test_live_bodies_go_to_the_sims_and_the_trainer():
    """``--bodies`` (centipedes included): each sim draws from the spec, the trainer's policy reads its width."""
    import argparse

    from trainer.live.bringup import pair_params, trainer_arguments

    sim, _ = pair_params(0, 2, 10, None, bodies="centipede:2-3")
    assert sim["topology"] == "centipede:2-3" and "min_joints" not in sim
    args = argparse.Namespace(out=Path("run"), bodies="centipede:2-3", episode_steps=100, max_updates=1, resume=False)
    assert trainer_arguments(["/swimmer0"], args, [])[-6:-4] == ["--bodies", "centipede:2-3"]


def test_a_signing_key_for_the_trainer_is_the_bring_up_s_key():
    from trainer.live.bringup import split_signing_key

    assert split_signing_key(["--seed", "3", "--signing-key", "k", "--num-steps", "64"]) == (
        ["--seed", "3", "--num-steps", "64"], Path("k"))  # fmt: skip
    assert split_signing_key(["--signing-key=a/k"]) == ([], Path("a/k"))
    assert split_signing_key(["--seed", "3"]) == (["--seed", "3"], None)


@pytest.mark.slow
def test_live_refuses_a_signing_key_it_cannot_use_in_one_line_before_anything_runs(tmp_path):
    from morph_core.protocol.trust import write_key_pair

    done = subprocess.run([*LIVE, "--out", str(tmp_path / "run"), "--", "--signing-key", str(tmp_path / "none")],
                          cwd=tmp_path, capture_output=True, text=True, timeout=120)  # fmt: skip
    assert done.returncode == 1 and len(done.stderr.splitlines()) == 1, done.stderr
    assert "--signing-key" in done.stderr and "morph-keys new KEY" in done.stderr
    write_key_pair(tmp_path / "a")
    write_key_pair(tmp_path / "b")
    (tmp_path / "b.pub").replace(tmp_path / "a.pub")  # a public key of another pair
    done = subprocess.run([*LIVE, "--out", str(tmp_path / "run"), "--signing-key", str(tmp_path / "a")],
                          cwd=tmp_path, capture_output=True, text=True, timeout=120)  # fmt: skip
    assert done.returncode == 1 and "is not the public half of" in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_live_init_starts_the_trainer_and_the_nodes_from_one_policy(tmp_path):
    # --init (or the trainer's -- --init, or the deprecated --checkpoint) is the run's starting policy: the
    # trainer's first weights and what the nodes run until they arrive. A bad one is refused before anything runs.
    import argparse

    from trainer.live.bringup import pair_params, split_option, trainer_arguments

    args = argparse.Namespace(out=Path("run"), bodies="", episode_steps=100, max_updates=1, resume=False,
                              init=Path("/p/start.safetensors"))  # fmt: skip
    assert trainer_arguments(["/swimmer0"], args, [])[-2:] == ["--init", "/p/start.safetensors"]
    _, policy = pair_params(0, 2, 10, "/p/start.safetensors")
    assert policy["checkpoint"] == "/p/start.safetensors" and "allow_untrained" not in policy
    _, untrained = pair_params(0, 2, 10, "")
    assert untrained["allow_untrained"] == "true"
    assert split_option(["--seed", "3", "--init=a/p"], "--init") == (["--seed", "3"], Path("a/p"))
    for given in (["--init", "none.safetensors"], ["--checkpoint", "none.safetensors"],
                  ["--", "--init", "none.safetensors"]):  # fmt: skip
        done = subprocess.run([*LIVE, "--out", str(tmp_path / "run"), *given], cwd=tmp_path, capture_output=True,
                              text=True, timeout=120)  # fmt: skip
        assert done.returncode == 2 and "--init" in done.stderr and "not a policy checkpoint" in done.stderr, given
        assert "Traceback" not in done.stderr and not (tmp_path / "run").exists()
    twice = subprocess.run([*LIVE, "--out", str(tmp_path / "run"), "--init", "a", "--", "--init", "b"],
                           cwd=tmp_path, capture_output=True, text=True, timeout=120)  # fmt: skip
    assert twice.returncode == 2 and "--init is given twice" in twice.stderr
