"""``morph-sweep``: the spec (parsed, validated, fuzzed), and real Ray Tune sweeps of tiny trials on this machine:
a 2x2 grid read by the existing tools, a trial whose process dies and resumes bit for bit, a sweep stopped as
a whole and resumed with the same command."""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from safetensors.numpy import load_file

from morph_core.algo.run_dir import RunDir
from morph_core.algo.small_runs import sets_of, small
from morph_core.algo.trust_region import rule_names
from trainer.sweep.cli import main
from trainer.sweep.spec import SpecError, load_spec

TINY_SIZES = dict(num_steps=128, minibatch_size=64, update_epochs=1)
TINY = sets_of(small(total_timesteps=512, **TINY_SIZES))
EVAL = ["lengths=2", "episodes=1"]
WALL_CLOCK = ("wall_time", "sps", "rollout_s", "update_s")


def sweep_command(out: Path, grids: list[str], sets=TINY, cpus: int = 2) -> list[str]:
    cmd = [sys.executable, "-m", "trainer.sweep", "--out", str(out), "--cpus", str(cpus)]
    for g in grids:
        cmd += ["--grid", g]
    for s in sets:
        cmd += ["--set", s]
    for e in EVAL:
        cmd += ["--eval", e]
    return cmd


def run_sweep(cmd: list[str], env=None, timeout=80) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env={**os.environ, **(env or {})})


def progress(run_dir: Path) -> list[dict]:
    with open(RunDir(run_dir).progress) as f:
        return [{k: v for k, v in r.items() if k not in WALL_CLOCK} for r in csv.DictReader(f)]


# --- the spec -----------------------------------------------------------------------------------------------


def test_a_spec_file_and_the_command_line_make_named_trials(tmp_path):
    spec = tmp_path / "s.yaml"
    spec.write_text(
        "set: {total-timesteps: 512, learning_rate: '3e-3'}\n"
        "grid: {seed: [1, 2]}\n"
        "trials:\n  - {gamma: 0.98}\n  - {gamma: 0.999, policy-bidirectional: false, eval: {lengths: [2]}}\n"
        "eval: {stride: 24}\n"
    )
    trials = load_spec(spec, sets=["num_envs=2"], grids=["clip-mode=fixed,compensated"]).expand()
    names = [t.name for t in trials]
    assert names[:2] == ["gamma=0.98,seed=1,clip_mode=fixed", "gamma=0.98,seed=1,clip_mode=compensated"]
    assert len(names) == len(set(names)) == 8
    last = trials[-1]
    assert last.name == "gamma=0.999,policy.bidirectional=false,seed=2,clip_mode=compensated"
    cfg = last.train_config()
    assert (cfg.total_timesteps, cfg.learning_rate, cfg.num_envs, cfg.gamma) == (512, 0.003, 2, 0.999)
    assert cfg.policy.bidirectional is False and cfg.clip_mode == "compensated" and cfg.seed == 2
    ev = last.eval_config(cfg.total_timesteps)
    assert (ev.lengths, ev.stride, ev.from_step) == ([2], 24, 256)  # the late checkpoints by default
    assert trials[0].eval_config(512).lengths == [*range(2, 11), 15, 20]
    # JSON too, and a spec of the command line alone.
    js = tmp_path / "s.json"
    js.write_text(json.dumps({"grid": {"seed": [3]}}))
    assert [t.name for t in load_spec(js).expand()] == ["seed=3"]
    assert [t.name for t in load_spec(None, sets=["seed=4"]).expand()] == ["trial"]


def test_the_results_sweeps_make_the_runs_of_docs_results():
    """sweeps/*.yaml: the configs the results scripts ran, so that their figures stay reproducible."""
    sweeps = Path(__file__).resolve().parents[5] / "sweeps"
    trials = {p.stem: load_spec(p).expand() for p in sorted(sweeps.glob("*.yaml"))}
    assert {k: len(v) for k, v in trials.items()} == {
        "centipedes": 10, "centipedes_long": 3, "families": 2, "rules": 70, "train": 10, "trees": 10, "two_joint": 8
    }  # fmt: skip
    rules = {(t.train_config().rule, t.train_config().anneal_lr) for t in trials["rules"]}
    assert {rule for rule, _ in rules} == set(rule_names())  # a new rule joins the comparison here
    assert len(rules) == 14 and all(t.train_config().total_timesteps == 1_000_000 for t in trials["rules"])
    assert {t.train_config().bodies for t in trials["trees"]} == {"2-10,random:3-10"}
    two = {
        (c.gamma, c.min_joints, c.max_joints, c.total_timesteps)
        for c in (t.train_config() for t in trials["two_joint"])
    }
    assert two == {(0.98, 2, 2, 500_000), (0.999, 2, 2, 500_000), (0.9999, 2, 2, 500_000), (0.9999, 2, 10, 500_000)}
    assert trials["train"][0].eval_config(1_000_000).from_step == 0  # the curves: every 24th checkpoint
    centipedes = {(t.train_config().rule, t.train_config().bodies) for t in trials["centipedes"]}
    assert centipedes == {("fixed", "centipede:2-4"), ("compensated", "centipede:2-4")}
    long = {(c.rule, c.anneal_lr, c.total_timesteps) for c in (t.train_config() for t in trials["centipedes_long"])}
    assert long == {("fixed", False, 3_000_000), ("compensated", False, 3_000_000), ("compensated", True, 3_000_000)}
    assert trials["centipedes_long"][0].eval_config(3_000_000).from_step == 2_500_000
    assert {t.train_config().bodies for t in trials["families"]} == {"2-10,centipede:2-4", "2-10"}


@pytest.mark.parametrize(
    "text, words",
    [
        ("grid: {clip_mode: [fixed, nonsense]}", "rule must be one of"),
        ("grid: {seed: []}", "non-empty list"),
        ("grid: {seed: 3}", "non-empty list"),
        ("set: {totl_timesteps: 5}", "unknown train config fields"),
        ("set: {total_timesteps: many}", "total_timesteps: expected int"),
        ("set: {num_envs: 0}", "num_envs must be >= 1"),
        ("trials: [{seed: 1}, {seed: 1}]", "same overrides"),
        ("trials: {seed: 1}", "trials must be a list"),
        ("eval: {strides: 2}", "unknown option"),
        ("eval: {lengths: [2, 99]}", "lengths must be in 1..64"),
        ("eval: {bodies: 'random:3-5'}", "random family"),
        ("sweep: {}", "unknown key(s) sweep"),
        ("[1, 2]", "a spec is a mapping"),
        ("grid: {seed: [1, 2}", "not YAML"),
    ],
)
def test_a_bad_spec_is_one_line_naming_it(tmp_path, capsys, text, words):
    spec = tmp_path / "s.yaml"
    spec.write_text(text)
    with pytest.raises(SpecError) as err:
        load_spec(spec).expand()
    assert words in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(SystemExit) as code:
        main(["--spec", str(spec), "--out", str(tmp_path / "o"), "--dry-run"])
    lines = capsys.readouterr().err.splitlines()
    assert code.value.code == 2 and lines[0].startswith("morph-sweep: error: ") and len(lines) == 2


def test_fuzz_garbled_specs_give_a_spec_error_never_a_traceback(tmp_path):
    rng = random.Random(40)
    keys = ["set", "grid", "trials", "eval", "seed", "clip_mode", "clip-mode", "policy.hidden", "policy-x",
            "total_timesteps", "lengths", "stride", "bodies", "gamma", "", "policy", 1, None]  # fmt: skip
    leaves = [0, -1, 1, 2**70, 0.5, float("nan"), "1e-3", "fixed", "", "a/b", True, None, [], {}, [1, "x"],
              "2-10,random:3-10", "y:2x2", "compensated"]  # fmt: skip

    def value(depth: int):
        kind = rng.random()
        if depth > 3 or kind < 0.4:
            return rng.choice(leaves)
        if kind < 0.7:
            return [value(depth + 1) for _ in range(rng.randint(0, 3))]
        return {rng.choice(keys): value(depth + 1) for _ in range(rng.randint(0, 3))}

    spec = tmp_path / "s.json"
    made = refused = 0
    for i in range(400):
        if i % 4 == 0:  # bytes cut or shuffled out of a good spec: not YAML, or YAML of anything
            good = "set: {total_timesteps: 512}\ngrid: {clip_mode: [fixed, compensated], seed: [1, 2]}\n"
            cut = list(good)
            for _ in range(rng.randint(1, 6)):
                cut.insert(rng.randrange(len(cut)), rng.choice("{}[]:,-'\"\n\t #&*!|>%@`"))
            (tmp_path / "g.yaml").write_text("".join(cut))
            path = tmp_path / "g.yaml"
        else:
            spec.write_text(json.dumps({rng.choice(keys[:4]): value(0) for _ in range(rng.randint(0, 4))}))
            path = spec
        try:
            load_spec(path, grids=[rng.choice(["seed=1,2", "seed=", "x", "=1", "clip-mode=fixed"])]).expand()
            made += 1
        except SpecError as err:
            assert "\n" not in str(err) and str(err)
            refused += 1
    assert made and refused  # both kinds were drawn


# --- sweeps on Ray --------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_a_2x2_grid_makes_four_run_directories_the_tools_read(tmp_path):
    from trainer.reports.runs import load_runs

    out = tmp_path / "sweep"
    done = run_sweep(sweep_command(out, ["clip-mode=fixed,compensated", "seed=1,2"]))
    assert done.returncode == 0, done.stderr[-3000:]
    names = ["clip_mode=fixed,seed=1", "clip_mode=fixed,seed=2", "clip_mode=compensated,seed=1",
             "clip_mode=compensated,seed=2"]  # fmt: skip
    assert sorted(p.name for p in out.iterdir() if p.is_dir() and not p.name.startswith(".")) == sorted(names)
    groups = load_runs([out / n for n in names])
    assert {rule: len(runs) for rule, runs in groups.items()} == {"fixed": 2, "compensated": 2}
    for runs in groups.values():
        for run in runs:
            assert int(run.progress[-1]["global_step"]) == 512 and run.eval  # trained, then evaluated
            assert {r["global_step"] for r in run.eval} == {"512"}  # the late checkpoints: from step 256 on
    text = (out / "summary.md").read_text()
    assert all(f"| {n} |" in text for n in names) and "| rule | steps to 200 (median) |" in text
    assert text in done.stdout
    status = json.loads((out / "trials.json").read_text())
    assert all(s["done"] for s in status.values())


@pytest.mark.slow
def test_a_trial_whose_process_dies_resumes_bit_for_bit(tmp_path):
    from morph_core.algo.train import train
    from trainer.sweep.spec import load_spec

    sets = sets_of(small(total_timesteps=1024, checkpoint_interval=512, **TINY_SIZES))
    out, faults = tmp_path / "sweep", tmp_path / "faults"
    faults.mkdir()
    done = run_sweep(sweep_command(out, ["seed=3"], sets=sets, cpus=1), env={"MORPH_SWEEP_FAULT_DIR": str(faults)})
    assert done.returncode == 0, done.stderr[-3000:]
    assert (faults / "seed=3").read_text() == "killed at step 768\n"  # after the state of step 512
    assert "seed=3 failed; starts again from its run directory" in done.stdout
    # The same config, never interrupted.
    (trial,) = load_spec(None, sets=sets, grids=["seed=3"]).expand()
    alone = tmp_path / "alone"
    train(dataclasses.replace(trial.train_config(), progress_bar=False), alone)
    run = out / "seed=3"
    assert [r["global_step"] for r in progress(run)] == ["256", "512", "768", "1024"]
    assert progress(run) == progress(alone)
    ckpts = sorted(p.name for p in RunDir(alone).checkpoints.iterdir())
    assert sorted(p.name for p in RunDir(run).checkpoints.iterdir()) == ckpts
    for name in (n for n in ckpts if n.endswith(".safetensors")):
        a, b = load_file(RunDir(run).checkpoints / name), load_file(RunDir(alone).checkpoints / name)
        assert a.keys() == b.keys() and all((a[k] == b[k]).all() for k in a)


@pytest.mark.slow
def test_a_sweep_stopped_as_a_whole_resumes_with_the_same_command(tmp_path):
    out = tmp_path / "sweep"
    sets = sets_of(small(total_timesteps=3072, **TINY_SIZES))
    cmd = sweep_command(out, ["seed=1,2"], sets=sets, cpus=1)  # one trial at a time: the second waits
    first = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=os.environ)
    deadline = time.monotonic() + 60
    while not RunDir(out / "seed=1").state.exists():
        assert first.poll() is None and time.monotonic() < deadline, "the first trial never saved a state"
        time.sleep(0.05)
    first.send_signal(signal.SIGINT)  # Ctrl-C: Tune saves the experiment's state and stops
    stdout, stderr = first.communicate(timeout=60)
    assert first.returncode != 0 and not (out / "summary.md").exists(), stdout  # stopped, not finished
    again = run_sweep(cmd)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "resuming 2 trial(s)" in again.stdout
    for seed in (1, 2):
        steps = [int(r["global_step"]) for r in progress(out / f"seed={seed}")]
        assert steps == list(range(256, 3072 + 1, 256))  # each step once: resumed, not started over
    # Another spec into the same directory is refused.
    other = run_sweep(sweep_command(out, ["seed=1,3"], sets=sets, cpus=1))
    assert other.returncode == 2 and "holds another sweep" in other.stderr
