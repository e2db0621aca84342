"""The trainer against damaged files and a full disk: a hand-edited config.json, a state or checkpoint file
truncated or corrupted on disk (``--resume`` names it and falls back to the previous state), and a disk that
fills up during a checkpoint (a small tmpfs in a private mount namespace: ``unshare -rm``)."""

import json
import shutil
import subprocess
import sys

import pytest
import torch

from morph_core.algo.checkpoint import check_training_state, previous_state_path
from morph_core.algo.run_dir import RunDir
from morph_core.algo.small_runs import options_of, small
from morph_core.algo.train import TrainConfig, train
from morph_core.policy.weights import load_checkpoint

pytestmark = pytest.mark.slow  # every test here starts processes, trains or compiles

SMALL = small(checkpoint_interval=128, min_joints=2, max_joints=3)
CLI = [sys.executable, "-m", "trainer.cli.train"]
CLI_SMALL = options_of(small(min_joints=2, max_joints=3, seed=4))


def _cli(*args, out):
    return subprocess.run([*CLI, "--out", str(out), *CLI_SMALL, *args], capture_output=True, text=True, timeout=600)


def _same_state(a, b):
    ta, ma = check_training_state(a)
    tb, mb = check_training_state(b)
    assert ma["counters"] == mb["counters"]
    assert ta.keys() == tb.keys() and all(torch.equal(ta[k], tb[k]) for k in ta)


# -- config.json ------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "edit, words",
    [
        ({"learning_rate": "3e-4"}, "learning_rate must be float, got str"),
        ({"num_envs": 2.5}, "num_envs must be int"),
        ({"anneal_lr": "yes"}, "anneal_lr must be bool"),
        ({"clip_eps": None}, "clip_eps must be float"),
        ({"learning_rte": 0.001}, "unknown train config fields: ['learning_rte']"),
        ({"policy": {"conv1_channels": 24, "wings": 2}}, "unknown policy config fields: ['wings']"),
        ({"policy": "big"}, "policy"),
    ],
)
def test_a_hand_edited_config_is_refused_before_anything_runs(tmp_path, edit, words):
    run = tmp_path / "run"
    run.mkdir()
    config = {**TrainConfig(**SMALL).to_dict(), **edit}
    RunDir(run).config.write_text(json.dumps(config))
    result = _cli("--resume", out=run)
    assert result.returncode == 1
    assert words in result.stderr and RunDir(run).config.name in result.stderr, result.stderr
    assert "Traceback" not in result.stderr
    assert sorted(p.name for p in run.iterdir()) == [RunDir(run).config.name]  # nothing ran, nothing written


def test_config_json_that_is_not_json_is_refused(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    RunDir(run).config.write_text('{"seed": 1,')
    result = _cli("--resume", out=run)
    assert result.returncode == 1 and RunDir(run).config.name in result.stderr and "Traceback" not in result.stderr


# -- damaged state and checkpoints --------------------------------------------------------------------------
def _truncate(path):
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 3])


def _flip_a_weight_byte(path):
    data = bytearray(path.read_bytes())
    data[-100] ^= 0xFF  # in the tensor bytes: safetensors still parses it, only the checksum tells
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("damage", [_truncate, _flip_a_weight_byte])
def test_resume_skips_a_damaged_state_and_continues_from_the_previous_one(tmp_path, damage):
    straight = train(TrainConfig(total_timesteps=512, seed=4, **SMALL), tmp_path / "straight")
    run = train(TrainConfig(total_timesteps=384, seed=4, **SMALL), tmp_path / "run")
    state = RunDir(run).state
    assert check_training_state(previous_state_path(state))[1]["counters"]["global_step"] == 256  # the last two
    damage(state)
    result = _cli("--resume", "--total-timesteps", "512", out=run)
    assert result.returncode == 0, result.stderr
    assert f"skipped {state}" in result.stderr and f"resuming from {previous_state_path(state)} (step 256)" in (
        result.stderr
    )
    _same_state(state, RunDir(straight).state)  # the fall-back lost nothing but time


def test_resume_with_both_states_damaged_is_a_clear_error(tmp_path):
    run = train(TrainConfig(total_timesteps=256, seed=4, **SMALL), tmp_path / "run")
    _truncate(RunDir(run).state)
    _flip_a_weight_byte(previous_state_path(RunDir(run).state))
    result = _cli("--resume", "--total-timesteps", "512", out=run)
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert "no usable training state" in result.stderr
    assert RunDir(run).state.name in result.stderr and "checksum" in result.stderr


def test_resume_names_a_damaged_policy_checkpoint_and_rewrites_the_resumed_steps(tmp_path):
    run = train(TrainConfig(total_timesteps=384, seed=4, **SMALL), tmp_path / "run")
    old, last = (
        RunDir(run).checkpoints / "policy_00000128.safetensors",
        RunDir(run).checkpoints / "policy_00000384.safetensors",
    )
    _truncate(old)
    _truncate(last)
    result = _cli("--resume", "--total-timesteps", "512", out=run)
    assert result.returncode == 0, result.stderr
    assert str(old) in result.stderr and str(last) in result.stderr and "written again" in result.stderr
    load_checkpoint(last)  # remade from the resumed state (the same weights)


# -- a full disk --------------------------------------------------------------------------------------------
def _unshare_works() -> bool:
    probe = subprocess.run(["unshare", "-rm", "true"], capture_output=True)
    return probe.returncode == 0


@pytest.mark.skipif(shutil.which("unshare") is None or not _unshare_works(), reason="needs unshare -rm")
@pytest.mark.timeout(600)
def test_a_disk_that_fills_up_stops_the_run_and_keeps_the_last_checkpoint(tmp_path):
    disk, saved = tmp_path / "disk", tmp_path / "saved"
    disk.mkdir()
    args = [*CLI, "--out", str(disk / "run"), *CLI_SMALL, "--total-timesteps", "100000", "--checkpoint-interval", "64"]
    # The tmpfs lives only in the child's mount namespace: copy the run out before the namespace ends.
    script = f'mount -t tmpfs -o size=1200k tmpfs "{disk}" && "$@"; rc=$?; cp -a "{disk}/run" "{saved}"; exit $rc'
    result = subprocess.run(["unshare", "-rm", "sh", "-c", script, "sh", *args], capture_output=True, text=True,
                            timeout=600)  # fmt: skip
    assert result.returncode == 1, result.stderr
    assert "No space left on device" in result.stderr and "last complete checkpoint is kept" in result.stderr
    assert "Traceback" not in result.stderr
    state = RunDir(saved).state
    _, meta = check_training_state(state)
    step = meta["counters"]["global_step"]
    assert 64 <= step < 100000
    check_training_state(previous_state_path(state))
    ckpts = [path for _, path in RunDir(saved).saved_checkpoints()]
    assert ckpts and all(load_checkpoint(p) for p in ckpts)  # every one complete; a half-written one never appears
    assert not list(saved.rglob("*.tmp")), "a temporary file was left behind"
    # On a disk with room again the run resumes from that checkpoint.
    result = _cli("--resume", "--total-timesteps", str(step + 128), "--checkpoint-interval", "64", out=saved)
    assert result.returncode == 0, result.stderr
    assert check_training_state(state)[1]["counters"]["global_step"] == step + 128
