"""``--rule``, the trust-region rule's one name, and ``--clip-mode``, its deprecated alias: both reach the config,
the old one with a warning, the two given with different rules refused in one line (morph-train and a tool whose
options are generated from TrainConfig alone)."""

import json

import pytest

from morph_core.algo.run_dir import RunDir
from morph_core.algo.train import TrainConfig
from morph_core.util.config_cli import overrides_from_args
from trainer.cli import train as train_cli
from trainer.live import in_process as live_in_process


def test_rule_and_its_deprecated_alias_reach_the_config(capsys):
    parser = train_cli.build_parser()
    new = parser.parse_args(["--out", "x", "--rule", "fixed"])
    assert overrides_from_args(new, TrainConfig) == {"rule": "fixed"} and capsys.readouterr().err == ""
    old = parser.parse_args(["--out", "x", "--clip-mode", "kl-stop"])
    assert overrides_from_args(old, TrainConfig) == {"rule": "kl-stop"}
    assert capsys.readouterr().err == "morph-train: warning: --clip-mode is deprecated: write --rule\n"
    with pytest.raises(SystemExit) as end:
        train_cli.main(["--out", "x", "--rule", "fixed", "--clip-mode", "compensated"])
    assert end.value.code == 2
    err = capsys.readouterr().err.splitlines()
    assert err[-2] == "morph-train: error: --clip-mode is the old name of --rule: give the new one alone"


def test_a_generated_cli_keeps_the_old_option(tmp_path, capsys):
    tiny = ["--num-envs", "1", "--num-steps", "128", "--minibatch-size", "64", "--update-epochs", "1",
            "--total-timesteps", "128", "--min-joints", "2", "--max-joints", "3", "--compile", "false",
            "--tensorboard", "false", "--episode-steps", "64"]  # fmt: skip
    assert live_in_process.main(["--out", str(tmp_path / "run"), *tiny, "--clip-mode", "fixed"]) == 0
    assert "--clip-mode is deprecated: write --rule" in capsys.readouterr().err
    cfg = TrainConfig.from_dict(json.loads(RunDir(tmp_path / "run").config.read_text()))
    assert cfg.rule == "fixed"
