"""Every command line of the project parses the same way (``config_cli.CommandLineParser``): an error is one
line ``tool: error: ...`` and a hint ``see tool --help`` (no usage block), exit code 2; an option is never
abbreviated (``--total-timestep`` is refused, not taken for ``--total-timesteps``)."""

from __future__ import annotations

import dataclasses
import importlib
import re

import pytest

from morph_core.algo.run_dir import RunDir

# module, prog, arguments that parse, a truncated option of the tool (with its value, if it takes one)
TOOLS = [
    ("cli.train", "morph-train", ["--out", "run"], ["--total-timestep", "5"]),
    ("cli.eval", "morph-eval", ["--checkpoint", "p.safetensors"], ["--episode", "3"]),
    ("cli.export", "morph-export", ["p.safetensors", "p.onnx"], ["--with-val"]),
    ("cli.render", "morph-render", ["--untrained", "--gif", "x.gif"], ["--second", "2"]),
    ("cli.gait", "morph-gait", [], ["--second", "2"]),
    ("cli.keys", "morph-keys", ["new", "key"], ["--forc"]),
    ("bags.cli", "morph-bag", ["info", "bag"], ["--jso"]),
    ("cli.theory", "morph-theory", ["--out", "th"], ["--run-cs", "x.csv"]),
    ("bags.record", "morph-record", [], ["--hel"]),
    ("bags.record_bringup", "python -m trainer.bags.record_bringup", ["--out", "bag"], ["--episode", "3"]),
    ("live.bringup", "python -m trainer.live.bringup", ["--out", "run"], ["--pair", "2"]),
    ("live.in_process", "python -m trainer.live.in_process", ["--out", "run"], ["--total-timestep", "5"]),
    ("live.compare", "python -m trainer.live.compare", ["run"], ["--simulato", "sim"]),
    ("bags.rounds", "python -m trainer.bags.rounds", ["--out", "rounds"], ["--round", "3"]),
    ("reports.ship", "python -m trainer.reports.ship", ["--run", "run", "--dest", "p.safetensors"], ["--replac"]),
    ("reports.summary", "python -m trainer.reports.summary", ["--run", "run"], ["--ru", "run"]),
    ("sweep.cli", "morph-sweep", ["--out", "sweep", "--dry-run"], ["--gri", "seed=1"]),
]


def _fails(module: str, argv: list[str], capsys) -> tuple[int, str]:
    main = importlib.import_module(f"trainer.{module}").main
    if module == "bags.record":  # a ROS node's main takes the whole argv, its program name first
        argv = ["morph-record", *argv]
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    out, err = capsys.readouterr()
    assert out == ""
    return exit_.value.code, err


@pytest.mark.parametrize("module, prog, good, truncated", TOOLS, ids=[t[0] for t in TOOLS])
def test_a_bad_option_is_one_line_and_a_hint(module, prog, good, truncated, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # nothing may be created: checked below
    code, err = _fails(module, [*good, "--no-such-option"], capsys)
    assert code == 2
    assert err == f"{prog}: error: unrecognized arguments: --no-such-option\nsee {prog} --help\n"
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("module, prog, good, truncated", TOOLS, ids=[t[0] for t in TOOLS])
def test_an_abbreviated_option_is_refused(module, prog, good, truncated, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, err = _fails(module, [*good, *truncated], capsys)
    assert code == 2
    assert err == f"{prog}: error: unrecognized arguments: {' '.join(truncated)}\nsee {prog} --help\n"
    assert list(tmp_path.iterdir()) == []


def test_a_missing_argument_is_one_line_too(capsys):
    code, err = _fails("cli.train", ["--total-timesteps", "5"], capsys)
    assert code == 2
    assert err == "morph-train: error: the following arguments are required: --out\nsee morph-train --help\n"
    code, err = _fails("cli.train", ["--out", "run", "--total-timesteps", "five"], capsys)
    assert err.splitlines() == [
        "morph-train: error: argument --total-timesteps: invalid int value: 'five'",
        "see morph-train --help",
    ]


def test_every_boolean_is_flag_true_or_false_and_a_bare_flag_takes_no_positional():
    from trainer.bags import cli as bag_cli
    from trainer.cli import export as export_cli
    from trainer.cli import train as train_cli

    parse = train_cli.build_parser().parse_args
    for given, compile_, resume in (([], None, False), (["--compile"], True, False),
                                    (["--compile", "FALSE", "--resume"], False, True),
                                    (["--compile", "no", "--resume", "true"], False, True)):  # fmt: skip
        args = parse(["--out", "run", *given])
        assert (args.compile, args.resume) == (compile_, resume), given
    args = export_cli.build_parser().parse_args(["--tree", "p.safetensors", "p.onnx", "--with-value", "false"])
    assert (args.tree, args.checkpoint, args.out, args.with_value) == (True, "p.safetensors", "p.onnx", False)
    args = bag_cli.build_parser().parse_args(["info", "--json", "bag"])
    assert args.json is True and args.bags == ["bag"]


def test_no_tool_declares_a_boolean_another_way():
    from pathlib import Path

    import trainer

    for path in sorted(Path(trainer.__file__).parent.glob("*.py")):
        text = path.read_text()
        for other in ('"store_true"', '"store_false"', "BooleanOptionalAction", "type=parse_bool"):
            assert other not in text, f"{path.name}: {other}; use config_cli.BoolAction (--flag [true|false])"


def test_the_no_eval_flag_of_before_still_works_and_says_it_is_deprecated(tmp_path, capsys):
    from trainer.cli.eval import main

    RunDir(tmp_path).config.write_text("{}")
    main(["--run", str(tmp_path), "--no-eval"])  # nothing to evaluate, nothing to plot
    assert capsys.readouterr().err == "morph-eval: warning: --no-eval is deprecated: write --eval false\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == [RunDir(tmp_path).config.name]


def test_renamed_options_keep_their_old_names_for_a_release(tmp_path, capsys):
    from trainer.cli import eval as eval_cli
    from trainer.live import bringup as live_bringup

    RunDir(tmp_path).config.write_text("{}")
    eval_cli.main(["--run", str(tmp_path), "--eval", "false", "--threads", "2"])  # as morph-train: --env-threads
    assert capsys.readouterr().err == "morph-eval: warning: --threads is deprecated: write --env-threads\n"
    run = tmp_path / "run"
    run.mkdir()
    RunDir(run).state.write_bytes(b"")
    with pytest.raises(SystemExit):  # refused (a run there), but --updates was read as --max-updates first
        live_bringup.main(["--out", str(run), "--updates", "3"])
    err = capsys.readouterr().err.splitlines()
    assert err[0] == "python -m trainer.live.bringup: warning: --updates is deprecated: write --max-updates"
    assert err[1].startswith("morph-train: error:")


def _help(module: str, capsys, argv=()) -> str:
    main = importlib.import_module(module).main
    with pytest.raises(SystemExit):
        main([*argv, "--help"])
    return capsys.readouterr().out


@pytest.mark.parametrize(
    "module",
    ["trainer.cli.eval", "trainer.cli.render", "trainer.cli.gait", "trainer.bags.record_bringup",
     "morph_policy_node.bringup"],
)  # fmt: skip
def test_one_name_per_idea_chain_lengths_are_joints_and_durations_seconds(module, capsys):
    """The chain length was --joints in the demo and the recorder, --lengths in eval, render and gait; the
    duration --sim-seconds in the demo, --seconds in render and gait. One name each now; the old ones hidden."""
    text = _help(module, capsys)
    assert "--joints" in text and "--lengths" not in text and "--sim-seconds" not in text
    if module in ("trainer.cli.render", "trainer.cli.gait", "morph_policy_node.bringup"):
        assert "--seconds" in text


def test_the_old_names_still_work_and_say_they_are_deprecated(tmp_path, capsys):
    from morph_policy_node import bringup
    from trainer.cli import eval as eval_cli
    from trainer.cli import render

    RunDir(tmp_path).config.write_text("{}")
    eval_cli.main(["--run", str(tmp_path), "--eval", "false", "--lengths", "3"])
    assert capsys.readouterr().err == "morph-eval: warning: --lengths is deprecated: write --joints\n"
    with pytest.raises(SystemExit):  # 0 joints: refused after the alias was read as --joints
        render.main(["--untrained", "--gif", str(tmp_path / "x.gif"), "--lengths", "0"])
    err = capsys.readouterr().err.splitlines()
    assert err[0] == "morph-render: warning: --lengths is deprecated: write --joints" and "lengths" in err[1]
    assert bringup.main(["--sim-seconds", "0"]) == 2  # read as --seconds 0: refused before any node
    out, err = capsys.readouterr()
    assert "--sim-seconds is deprecated: write --seconds" in err and "cannot start: --seconds 0" in out
    assert sorted(p.name for p in tmp_path.iterdir()) == [RunDir(tmp_path).config.name]


@pytest.mark.parametrize(
    "module, argv",
    [("trainer.cli.train", []), ("trainer.bags.cli", ["export"]), ("trainer.bags.record", ["morph-record"]),
     ("trainer.bags.record_bringup", []), ("trainer.live.bringup", []), ("trainer.bags.rounds", []),
     ("trainer.cli.theory", []), ("trainer.sweep.cli", []), ("trainer.live.in_process", [])],
)  # fmt: skip
def test_every_tool_that_writes_a_folder_or_file_names_it_out(module, argv, capsys):
    assert "--out" in _help(module, capsys, argv)


@pytest.mark.parametrize("module, prog, good, truncated", TOOLS, ids=[t[0] for t in TOOLS])
def test_help_keeps_its_examples_lines_and_says_no_deprecated_name(module, prog, good, truncated, capsys):
    """A backslash at a docstring's line end joined two example lines into one (morph-render's help);
    morph-sweep's example used clip-mode, the old name of rule."""
    argv = ["morph-record"] if module == "bags.record" else ["info"] if module == "bags.cli" else []
    text = _help(f"trainer.{module}", capsys, argv)
    assert not re.search(r"\S {5,}--[a-z]", text), re.search(r".*\S {5,}--[a-z].*", text).group(0)
    assert "clip-mode=" not in text and "--lengths" not in text


def test_every_option_of_morph_train_says_what_it_is():
    """Options of fields a base class of TrainConfig declares (--bodies, --min-joints ...) had no help text."""
    import argparse

    from trainer.cli.train import build_parser

    bare = [a.option_strings[0] for a in build_parser()._actions
            if a.help != argparse.SUPPRESS and not re.sub(r"\(default: .*\)$", "", a.help or "").strip()]  # fmt: skip
    assert bare == []


# morph-train's options as they were before its config was split by concern (issue 54): docs, scripts and sweeps
# write them, so each keeps its name and where it goes (option, dest)
MORPH_TRAIN_OPTIONS = (
    "adam-eps anneal-lr bodies checkpoint-interval clip-eps clip-mode compile ent-coef env-threads episode-steps "
    "from-bags gae-lambda gamma help init iterations kl-adaptive kl-beta kl-target learning-rate live "
    "max-grad-norm max-joints max-staleness max-updates min-joints minibatch-size namespace namespaces new-data "
    "nice num-envs num-steps off-policy-objective out policy-bidirectional policy-conv1-channels "
    "policy-embed-channels policy-global-features policy-global-hidden policy-head-hidden policy-joint-features "
    "policy-log-std-init policy-ortho-init processes progress-bar proximal-weight-cap ray-address resume "
    "rollout-workers rule seed signing-key silence-timeout stream-chunks tensorboard torch-threads "
    "total-timesteps update-epochs vf-coef weights-period"
).split()


def test_morph_train_keeps_every_option_and_groups_its_help_by_concern(capsys):
    from morph_core.algo.train import TrainConfig
    from trainer.cli.train import build_parser

    parser = build_parser()
    options = {s: a.dest for a in parser._actions for s in a.option_strings if s.startswith("--")}
    assert sorted(options) == [f"--{o}" for o in MORPH_TRAIN_OPTIONS]
    nested = ("policy-",)  # --policy-x goes to policy__x (config_cli's nested fields)
    assert all(options[f"--{o}"] == (o.replace("-", "__", 1) if o.startswith(nested) else o).replace("-", "_")
               for o in MORPH_TRAIN_OPTIONS if o != "help")  # fmt: skip
    titled = {g.title: {s for a in g._group_actions for s in a.option_strings} for g in parser._action_groups}
    for title, concern in TrainConfig.concerns:
        group = titled[f"{title} options"]
        if title == "policy":
            assert {o for o in options if o.startswith("--policy-")} == group
        else:
            assert {f"--{f.name.replace('_', '-')}" for f in dataclasses.fields(concern)} - {"--batch-size"} <= group


def test_each_source_s_options_are_its_config_s_fields_with_their_docstrings_for_help():
    """The bag and live sources' options come from their configs (BagOptions, LiveOptions) as the simulator's come
    from SimConfig: one option per field, in the source's group, its help the field's docstring; --live only
    chooses the source, and --out, --resume and --init (a field of both) are one option each."""
    from morph_core.util.config_cli import field_docs
    from trainer.bags.options import BagOptions
    from trainer.cli.train import build_parser
    from trainer.live.learner import LiveOptions

    parser = build_parser()
    titled = {g.title: g._group_actions for g in parser._action_groups}
    for title, cls, own in (
        ("training from recorded bags", BagOptions, set()),
        ("live training from sim+policy pairs over DDS (trainer.live.trainer_node)", LiveOptions, {"live"}),
    ):
        actions = {a.dest: a for a in titled[title]}
        shared = {"out", "resume", "init"} if cls is LiveOptions else set()  # morph-train's own options
        fields = {f.name for f in dataclasses.fields(cls)} - shared
        assert set(actions) == fields | own, title
        docs = field_docs(cls)
        for name in fields:
            assert actions[name].option_strings == [f"--{name.replace('_', '-')}"]
            text = actions[name].help
            assert text == docs[name] or text.startswith(f"{docs[name]} (default: "), name
    assert build_parser().parse_args(["--out", "r", "--live", "--namespaces", "/a", "/b"]).namespaces == ["/a", "/b"]
