"""``algo.config``: a trainer's config by concern (run, PPO with the update's settings, bodies, policy, the
simulator), composed flat, and every ``config.json`` of the runs kept in docs/results_data read as written."""

import dataclasses
import json
import warnings
from pathlib import Path

import pytest

from morph_core.algo.config import BodiesConfig, RunConfig, SimConfig, TrainerConfig
from morph_core.algo.ppo_config import PPOConfig
from morph_core.algo.run_dir import RunDir
from morph_core.algo.train import TrainConfig
from morph_core.algo.update_config import UpdateConfig
from morph_core.policy.actor_critic import PolicyConfig
from morph_core.util.config_cli import field_docs

RESULTS = Path(__file__).resolve().parents[4] / "docs/results_data"


def _names(cls) -> set[str]:
    return {f.name for f in dataclasses.fields(cls)}


def test_the_concerns_partition_the_trainers_fields_and_each_is_one_of_them():
    concerns = [RunConfig, PPOConfig, BodiesConfig, SimConfig]
    names = [_names(c) for c in concerns]
    assert sum(map(len, names)) == len(set().union(*names))  # no field in two concerns
    assert _names(TrainConfig) == set().union(*names) | {"policy"}
    assert _names(TrainerConfig) == _names(TrainConfig) - _names(SimConfig)
    assert all(isinstance(TrainConfig(), c) for c in (*concerns, UpdateConfig, TrainerConfig))
    assert [title for title, _ in TrainConfig.concerns] == ["run", "PPO", "bodies", "policy", "simulator"]


def test_the_update_settings_are_written_once_and_handed_over_whole():
    # PPOConfig extends UpdateConfig: its fields, their defaults and their help are UpdateConfig's
    assert _names(UpdateConfig) < _names(PPOConfig)
    docs, own = field_docs(TrainConfig), field_docs(UpdateConfig)
    assert all(docs[name] == own[name] for name in _names(UpdateConfig))
    cfg = TrainConfig(rule="kl-penalty", clip_eps=0.2, update_epochs=3, minibatch_size=128, vf_coef=0.25,
                      ent_coef=0.01, max_grad_norm=1.0, proximal_weight_cap=2.0, kl_target=0.02, kl_beta=0.5,
                      kl_adaptive=False, off_policy_objective="decoupled")  # fmt: skip
    update = cfg.update_config()
    assert type(update) is UpdateConfig
    assert dataclasses.asdict(update) == {name: getattr(cfg, name) for name in _names(UpdateConfig)}
    assert update == UpdateConfig("kl-penalty", 0.2, 3, 128, 0.25, 0.01, 1.0, 2.0, 0.02, 0.5, False, "decoupled")
    assert UpdateConfig() == TrainConfig().update_config()  # one set of defaults, the paper's


def test_each_concern_checks_its_own_fields_alone_and_in_the_trainers_config():
    for make in (RunConfig, TrainConfig):
        with pytest.raises(ValueError, match="total_timesteps must be >= 1, got 0"):
            make(total_timesteps=0)
        with pytest.raises(TypeError, match="seed must be int, got str"):
            make(seed="1")
    for make in (PPOConfig, TrainerConfig):
        with pytest.raises(ValueError, match="rule must be one of"):
            make(rule="nope")
        with pytest.raises(ValueError, match="minibatch_size 512 exceeds the rollout size 256"):
            make(batch_size=256, minibatch_size=512)
        with pytest.raises(ValueError, match="kl_target and kl_beta must be > 0"):  # UpdateConfig's own check
            make(kl_target=0.0)
        with pytest.raises(TypeError, match="gamma must be float, got str"):
            make(gamma="0.9")
    for make in (BodiesConfig, TrainConfig):
        with pytest.raises(ValueError, match="need 1 <= min_joints <= max_joints <= 64"):
            make(min_joints=5, max_joints=3)
        with pytest.raises(ValueError, match="disagree with bodies"):
            make(bodies="2-4", min_joints=3, max_joints=6)
        assert (make(bodies="3-5").min_joints, make(bodies="3-5").max_joints) == (3, 5)
    assert list(BodiesConfig(bodies="2-4,y:2x2").dims) == list(TrainConfig(bodies="2-4,y:2x2").dims)
    # what spans two concerns is the composition's: centipedes' bodies widen the policy's global features
    assert TrainConfig(bodies="centipede:2-3").policy.global_features == 12 != PolicyConfig().global_features


def test_every_run_config_kept_in_the_results_loads_and_reads_every_key_as_written():
    paths = sorted(run.config for run in map(RunDir, RESULTS.glob("**/")) if run.config.exists())
    assert len(paths) > 100  # the runs behind docs/results.md: flat, of every age (clip_mode, no rule, ...)
    dropped = {"policy.backend"}  # an option removed since (``PolicyConfig.from_dict`` drops it)
    for path in paths:
        written = json.loads(path.read_text())
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)  # clip_mode of before the rule's rename
            cfg = TrainConfig.from_dict(written)
        read = _flat(cfg.to_dict())
        for key, value in _flat(written).items():
            assert key in dropped or read[key] == value, (path, key, value, read.get(key))
        assert TrainConfig.from_dict(cfg.to_dict()) == cfg  # and what it writes now is read back the same


def test_the_config_json_written_is_flat_as_before():
    written = TrainConfig(bodies="2-4").to_dict()
    nested = {k for k, v in written.items() if isinstance(v, dict)}
    assert nested == {"policy"}  # old readers (and old code) read it as ever
    assert written["clip_mode"] == written["rule"] and written["min_joints"] == 2 and written["seed"] == 1


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in d.items():
        out.update(_flat(value, f"{prefix}{key}.") if isinstance(value, dict) else {f"{prefix}{key}": value})
    return out
