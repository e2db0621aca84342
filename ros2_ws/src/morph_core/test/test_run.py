"""``algo.run.Run`` and ``algo.ppo_config``: one run lifecycle for the three trainers, old runs (a flat
``config.json`` with ``clip_mode``, a state with its trainer's part under ``env``) resumed bit for bit, other
trainers' and newer states refused, a resume that takes a new learning rate, and the row hook everywhere."""

import csv
import json

import pytest
import torch
from safetensors.torch import save as safetensors_bytes

from morph_core.algo.checkpoint import TrainingStateError, _digest, load_training_state, previous_state_path
from morph_core.algo.config import TrainerConfig
from morph_core.algo.run_dir import RunDir
from morph_core.algo.small_runs import small
from morph_core.algo.train import TrainConfig, load_run_config, train
from morph_core.algo.train_from_data import run_state, train_from_data
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.protocol.loopback import SamplingController, record_episodes
from morph_core.protocol.transitions import assemble

TINY = small(
    num_steps=128, minibatch_size=64, update_epochs=1, checkpoint_interval=256, min_joints=2, max_joints=4, seed=3
)
TIMINGS = {"wall_time", "sps", "rollout_s", "update_s", "prepare_s"}

# config.json as morph-train wrote it before issue 39: flat, the rule as clip_mode, no rule or batch_size keys
OLD_CONFIG = """{
  "clip_mode": "fixed", "clip_eps": 0.111, "total_timesteps": 256, "seed": 3, "num_envs": 2, "num_steps": 128,
  "minibatch_size": 64, "update_epochs": 1, "learning_rate": 0.01, "anneal_lr": false, "adam_eps": 1e-05,
  "gamma": 0.98, "gae_lambda": 0.98, "vf_coef": 0.5, "ent_coef": 0.0, "max_grad_norm": 0.5,
  "proximal_weight_cap": 1.0, "kl_target": 0.01, "kl_beta": 1.0, "kl_adaptive": true,
  "off_policy_objective": "decoupled", "min_joints": 2, "max_joints": 4, "bodies": "", "checkpoint_interval": 256,
  "torch_threads": 1, "env_threads": 1, "processes": 1, "compile": false, "tensorboard": false,
  "progress_bar": false,
  "policy": {"conv1_channels": 24, "embed_channels": 16, "global_hidden": 128, "head_hidden": 64,
             "bidirectional": true, "log_std_init": 0.0, "ortho_init": true}
}"""


def _rows(run) -> list[dict]:
    with RunDir(run).progress.open() as f:
        return [{k: v for k, v in r.items() if k not in TIMINGS} for r in csv.DictReader(f)]


def _as_state_before_sections(run, section: str) -> None:
    """Rewrite the run's state as the trainers wrote it before sections: the section under ``env`` (no
    version), its arrays as ``env.<key>``; the previous state removed, so that a resume has to read this one."""
    path = RunDir(run).state
    tensors, meta = load_training_state(path)
    old = meta.pop("sections")[section]
    old.pop("version")
    meta["env"] = old
    prefix = f"section.{section}."
    tensors = {(f"env.{k[len(prefix) :]}" if k.startswith(prefix) else k): v for k, v in tensors.items()}
    path.write_bytes(safetensors_bytes(tensors, metadata={"state": json.dumps(meta), "sha256": _digest(tensors)}))
    previous_state_path(path).unlink(missing_ok=True)


def test_an_old_run_config_and_state_resume_bit_for_bit(tmp_path):
    straight = train(TrainConfig(**{**TINY, "rule": "fixed", "total_timesteps": 768}), tmp_path / "straight")
    old = train(TrainConfig(**{**TINY, "rule": "fixed", "total_timesteps": 256}), tmp_path / "old")
    RunDir(old).config.write_text(OLD_CONFIG)
    _as_state_before_sections(old, "swimmers")
    with pytest.warns(DeprecationWarning, match="'clip_mode' is deprecated"):
        cfg = load_run_config(old, {"total_timesteps": 768})
    assert cfg.rule == "fixed" and cfg.batch_size == 256 and cfg.clip_mode == "fixed"
    train(cfg, old, resume=True)
    assert _rows(old) == _rows(straight) and len(_rows(old)) == 3
    (ta, ma), (tb, mb) = (load_training_state(RunDir(r).state) for r in (straight, old))
    assert ta.keys() == tb.keys() and all(torch.equal(ta[k], tb[k]) for k in ta)  # written in today's layout
    assert ma["sections"]["swimmers"]["version"] == 1 and "env" not in mb
    # and config.json keeps the old key beside the new one, for its older readers
    written = json.loads(RunDir(straight).config.read_text())
    assert written["rule"] == written["clip_mode"] == "fixed" and written["batch_size"] == 256
    assert TrainConfig.from_dict(written) == TrainConfig(**{**TINY, "rule": "fixed", "total_timesteps": 768})


def test_a_config_whose_rule_and_clip_mode_disagree_or_batch_is_off_is_refused(tmp_path):
    cfg = TrainConfig(**TINY).to_dict()
    with pytest.raises(ValueError, match="rule 'compensated' and clip_mode 'fixed' disagree"):
        TrainConfig.from_dict({**cfg, "clip_mode": "fixed"})
    with pytest.raises(ValueError, match="batch_size 6144 disagrees"):
        TrainConfig.from_dict({**cfg, "batch_size": 6144})
    with pytest.raises(ValueError, match="clip_mode is the old name of rule"):
        TrainConfig(rule="fixed", clip_mode="compensated")
    with pytest.raises(ValueError, match="batch_size 64 disagrees with the other fields, which make it 256"):
        TrainConfig(**{**TINY, "batch_size": 64})  # the simulator's batch is its rollout: num_envs * num_steps
    assert TrainConfig(**TrainConfig(**TINY).to_dict()) == TrainConfig(**TINY)  # to_dict's rule and clip_mode too


def test_another_trainers_state_and_a_newer_section_are_refused_clearly(tmp_path):
    run = train(TrainConfig(**{**TINY, "total_timesteps": 256}), tmp_path / "sim")
    data = assemble(record_episodes(SamplingController(GraphActorCritic(), seed=1), ((3, 40), (4, 30)), 0)).batch
    with pytest.raises(TrainingStateError, match=r"no 'data' section \(it holds: swimmers\): a state of another"):
        train_from_data(TrainConfig(**TINY), data, run, resume=True)
    _as_state_before_sections(run, "swimmers")  # an old state is told apart by what it holds
    with pytest.raises(TrainingStateError, match=r"no 'data' section \(it holds: swimmers\)"):
        train_from_data(TrainConfig(**TINY), data, run, resume=True)
    newer = train(TrainConfig(**{**TINY, "total_timesteps": 256}), tmp_path / "newer")
    path = RunDir(newer).state
    tensors, meta = load_training_state(path)
    meta["sections"]["swimmers"]["version"] = 2
    path.write_bytes(safetensors_bytes(tensors, metadata={"state": json.dumps(meta), "sha256": _digest(tensors)}))
    previous_state_path(path).unlink(missing_ok=True)
    with pytest.raises(TrainingStateError, match="'swimmers' section is version 2, this trainer reads up to 1"):
        train(TrainConfig(**{**TINY, "total_timesteps": 512}), newer, resume=True)


def test_a_resume_trains_with_the_learning_rate_and_epsilon_given(tmp_path):
    run = train(TrainConfig(**{**TINY, "total_timesteps": 256}), tmp_path / "run")
    train(TrainConfig(**{**TINY, "total_timesteps": 512, "learning_rate": 0.003, "adam_eps": 1e-6}), run, resume=True)
    assert [float(r["learning_rate"]) for r in _rows(run)] == [0.01, 0.003]
    groups = load_training_state(RunDir(run).state)[1]["param_groups"]
    assert [(g["lr"], g["eps"]) for g in groups] == [(0.003, 1e-6)]


def test_the_bag_trainer_takes_its_batch_from_ppo_config_hears_rows_and_resumes_an_old_state(tmp_path):
    torch.manual_seed(7)
    data = assemble(record_episodes(SamplingController(GraphActorCritic(), seed=1), ((3, 40), (4, 60)), 0)).batch
    cfg = TrainerConfig(batch_size=25, minibatch_size=16, update_epochs=1, checkpoint_interval=50, seed=2,
                    min_joints=2, max_joints=4, compile=False, progress_bar=False, tensorboard=False)  # fmt: skip
    heard = []
    straight = train_from_data(cfg, data, tmp_path / "a", iterations=6, on_row=lambda r, s: heard.append((r, s)))
    assert [(r["global_step"], r["batch_size"], s) for r, s in heard] == [
        (25, 25, False), (50, 25, True), (75, 25, False), (100, 25, True), (125, 25, False), (150, 25, True)
    ]  # fmt: skip
    assert json.loads(RunDir(straight).config.read_text())["batch_size"] == 25
    part = train_from_data(cfg, data, tmp_path / "b", iterations=3)  # mid-pass: the permutation is in the state
    _as_state_before_sections(part, "data")
    assert run_state(part)["done"] == 3
    train_from_data(cfg, data, part, iterations=6, resume=True)
    assert _rows(part) == _rows(straight)
