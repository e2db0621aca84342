"""The one place tests take a small run from (``morph_core.algo.small_runs``): its options are morph-train's own
names, so a field renamed in the config cannot leave the tests' command lines behind."""

import pytest

from morph_core.algo.small_runs import SMALL, options_of, sets_of, small, small_config
from morph_core.algo.train import TrainConfig
from morph_core.util.config_cli import overrides_from_args
from trainer.sweep.spec import load_spec
from trainer.train_options import build_parser

OVERRIDES = [{}, {"num_envs": 1, "checkpoint_interval": 32, "seed": 4},
             {"bodies": "centipede:2-3", "anneal_lr": True, "learning_rate": 3e-4}]  # fmt: skip


@pytest.mark.parametrize("overrides", OVERRIDES)
def test_the_options_parse_back_to_the_same_config(overrides):
    args = build_parser().parse_args(["--out", "unused", *options_of(small(**overrides))])
    parsed = TrainConfig.from_dict(overrides_from_args(args, TrainConfig))
    assert parsed == small_config(**overrides)
    assert parsed != TrainConfig()  # the small sizes did reach it


def test_a_sweeps_sets_are_the_same_fields():
    (trial,) = load_spec(None, sets=sets_of(small(seed=7))).expand()
    assert trial.train_config() == small_config(seed=7)


def test_quiet_switches_are_off_and_overrides_win():
    assert not any(SMALL[k] for k in ("tensorboard", "progress_bar", "compile"))
    assert small(num_envs=5)["num_envs"] == 5 and SMALL["num_envs"] != 5
