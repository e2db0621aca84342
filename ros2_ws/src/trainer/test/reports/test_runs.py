"""Run directories as data, and the table of trust-region rules reaching the CLI, the plots and the
summary: a rule registered in the table (here a temporary one) shows up everywhere without another edit."""

import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from morph_core.algo.run_dir import RunDir
from morph_core.algo.train import TrainConfig, log_columns
from morph_core.algo.trust_region import ClippedRatio, register, unregister
from trainer.cli import eval as eval_cli
from trainer.cli import train as train_cli
from trainer.reports import plots, summary
from trainer.reports.runs import load_run_report, load_runs, series, smooth

TEST_RULE = "eighth-root"


class EighthRootClip(ClippedRatio):
    name = TEST_RULE
    help = "clip r to 1 +- eps * d^(1/8) (exists only in this test)"

    def clip_scale(self, dim):
        return dim**0.125


@pytest.fixture
def eighth_root():
    rule = register(EighthRootClip())
    yield rule
    unregister(rule.name)


def write_run(run_dir, rule, seed, steps=(6144, 12288, 18432), scale=1.0):
    """A run directory as morph-train and morph-eval leave it, with made-up numbers (returns times ``scale``)."""
    cfg = TrainConfig(clip_mode=rule, seed=seed, total_timesteps=steps[-1], min_joints=2, max_joints=3)
    run_dir.mkdir(parents=True)
    RunDir(run_dir).config.write_text(json.dumps(cfg.to_dict()))
    columns = log_columns(cfg)
    with RunDir(run_dir).progress.open("w", newline="") as f:
        w = csv.DictWriter(f, columns)
        w.writeheader()
        for k, step in enumerate(steps):
            w.writerow({c: 0.1 * (k + 1) for c in columns} | {"global_step": step, "return_mean": 150 * k * scale})
    with RunDir(run_dir).evaluation.open("w", newline="") as f:
        w = csv.DictWriter(f, ["global_step", "num_joints", "episode", "return"])
        w.writeheader()
        for step in steps:
            for n in (2, 3, 5):
                w.writerows({"global_step": step, "num_joints": n, "episode": e,
                             "return": (step / 1000 + n + e) * scale} for e in range(2))  # fmt: skip
    return run_dir


def test_series_and_smoothing_of_progress_rows():
    rows = [{"global_step": "1", "x": "1.0"}, {"global_step": "2", "x": ""}, {"global_step": "3", "x": "3.0"}]
    steps, y = series(rows, "x")
    assert steps.tolist() == [1, 2, 3] and y[0] == 1.0 and math.isnan(y[1])
    assert smooth(y, 2).tolist() == [1.0, 1.0, 3.0]  # trailing mean of the finite values in the window
    assert math.isnan(series(rows, "absent")[1][0])


def test_a_run_of_a_rule_the_table_does_not_know_is_an_error(tmp_path):
    run = write_run(tmp_path / "r", "fixed", 1)
    cfg = json.loads(RunDir(run).config.read_text())
    RunDir(run).config.write_text(json.dumps({**cfg, "clip_mode": "adaptive"}))
    with pytest.raises(ValueError, match="'adaptive' is not a rule"):
        load_run_report(run)
    with pytest.raises(ValueError, match="not a training run"):
        load_run_report(tmp_path / "nowhere")


def edit_config(run_dir, **changes):
    cfg = json.loads(RunDir(run_dir).config.read_text())
    RunDir(run_dir).config.write_text(json.dumps({**cfg, **changes}))


def test_runs_of_one_rule_trained_differently_are_not_pooled(tmp_path, capsys):
    runs = [write_run(tmp_path / f"fixed-s{s}", "fixed", s) for s in (1, 2, 3)]
    edit_config(runs[1], processes=2, torch_threads=2, compile=False)  # how it ran, not what it learned
    cfg = json.loads(RunDir(runs[2]).config.read_text())
    del cfg["kl_target"]  # an older run's config, from before the key existed: its default applied
    RunDir(runs[2]).config.write_text(json.dumps(cfg))
    assert [r.dir for r in load_runs(runs)["fixed"]] == runs

    edit_config(runs[2], anneal_lr=True, gamma=0.99)
    with pytest.raises(ValueError, match=r"runs of fixed were trained differently \(anneal_lr, gamma\)"):
        load_runs(runs)
    with pytest.raises(SystemExit):
        summary.main(["--run", *map(str, runs)])
    assert "anneal_lr=True, gamma=0.99" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # refused before evaluating, not after
        eval_cli.main(["--run", *map(str, runs), "--plots", str(tmp_path / "fig")])
    assert "trained differently" in capsys.readouterr().err and not (tmp_path / "fig").exists()
    edit_config(runs[2], kl_target=0.02, anneal_lr=False, gamma=TrainConfig().gamma)
    with pytest.raises(ValueError, match=r"\(kl_target\)"):
        load_runs(runs)


def test_a_registered_rule_reaches_the_cli_the_plots_and_the_summary(tmp_path, eighth_root, capsys):
    parser = train_cli.build_parser()
    args = parser.parse_args(["--out", "x", "--clip-mode", TEST_RULE])
    assert args.clip_mode == TEST_RULE and TEST_RULE in parser.format_help()

    runs = [write_run(tmp_path / f"{rule}-s{s}", rule, s) for rule in (TEST_RULE, "fixed") for s in (1, 2)]
    groups = load_runs(runs)
    assert list(groups) == ["fixed", TEST_RULE]  # the table's order, only rules with runs
    assert [r.dir.name for r in groups[TEST_RULE]] == [f"{TEST_RULE}-s1", f"{TEST_RULE}-s2"]

    written = plots.plot_all(runs, tmp_path / "fig")
    for name in ("training_returns.png", "clip_fraction_per_dim.png", "eval_return_per_length.png"):
        assert (tmp_path / "fig" / name) in written
    table = (tmp_path / "fig" / "final_eval_table.md").read_text()
    assert table.splitlines()[0] == f"| joints | fixed (2 seeds) | {TEST_RULE} (2 seeds) |"
    # last checkpoint 18432: returns 18.432 + n + {0, 1}, mean over episodes 18.932 + n, same for both seeds
    assert f"| 5 | {18.932 + 5:.1f} ± 0.0 | {18.932 + 5:.1f} ± 0.0 |" in table

    summary.main(["--run", *map(str, runs)])
    out = capsys.readouterr().out
    assert f"clip fraction per dimension, {TEST_RULE} (2 runs): 2:0.20 3:0.20" in out
    assert f"| {TEST_RULE}-s1 | 18k | never | 150 |" in out  # trailing means 0, 75, 150


def test_summary_ranks_the_rules_claim_by_claim_and_reports_zero_shot(tmp_path, capsys):
    # kl-stop's returns are twice fixed's: it ranks first on every claim, ties (none collapsed) share rank 1.
    runs = [write_run(tmp_path / f"fixed-s{s}", "fixed", s) for s in (1, 2)]
    runs.append(write_run(tmp_path / "kl-stop-s1", "kl-stop", 1, scale=2.0))
    summary.main(["--run", *map(str, runs)])
    out = capsys.readouterr().out
    # late = checkpoints from 9216 on (12288, 18432): mean return 15.36 + n + 0.5 over episodes 0, 1
    assert "| fixed | 2 | 18 ± 0 | 21 ± 0 |" in out  # trained 2..3: 18.36; unseen 5: 20.86
    assert "| kl-stop | 1 | 37 ± 0 | 42 ± 0 |" in out
    assert "| last 10 updates | collapsed runs | late eval, trained lengths | late eval, 5 joints (unseen) |" in out
    assert "| fixed | never (2) | 150 (2) | 0 (1) | 18 (2) | 21 (2) |" in out  # trailing means 0, 75, 150
    assert "| kl-stop | 18k (1) | 300 (1) | 0 (1) | 37 (1) | 42 (1) |" in out  # 0, 150, 300: 200 at 18432
    assert "KL per dimension, fixed: 2:0.2000 3:0.2000" in out
    assert "| fixed | 0 of 2 | 18k | never | 150 [150..150] | 150 |" in out  # the per-rule training marks
    assert "| kl-stop | 1 of 1 | 12k | 18k | 300 [300..300] | 300 |" in out
    assert f"epochs per update, kl-stop: 0.2 of {TrainConfig().update_epochs}" in out  # the made-up 0.1..0.3
    assert "KL penalty beta at the end, kl-stop: 0.3" in out


@pytest.mark.slow
def test_ship_needs_an_explicit_destination(tmp_path):
    run = write_run(tmp_path / "fixed-s1", "fixed", 1)
    out = subprocess.run(
        [sys.executable, "-m", "trainer.reports.ship", "--run", str(run)], capture_output=True, text=True
    )
    assert out.returncode != 0 and "--dest" in out.stderr
    # The best evaluated checkpoint's file is gone (a run kept as data only): the error says how to get it back.
    dest = tmp_path / "model.safetensors"
    out = subprocess.run([sys.executable, "-m", "trainer.reports.ship", "--run", str(run), "--dest", str(dest)],
                         capture_output=True, text=True)  # fmt: skip
    assert out.returncode == 2 and not dest.exists()
    assert "best evaluated checkpoint is fixed-s1 at step 18432" in out.stderr
    assert "morph-train --clip-mode fixed --seed 1 " in out.stderr and "Traceback" not in out.stderr
    assert np.isfinite(float(load_run_report(run).progress[0]["return_mean"]))


def test_the_body_tables_give_episode_lengths_and_distances_where_the_evaluation_recorded_them(tmp_path):
    runs = []
    for seed, distance in ((1, 1.0), (2, 3.0)):
        run = write_run(tmp_path / f"c{seed}", "compensated", seed)
        with RunDir(run).evaluation.open() as f:
            chains = list(csv.DictReader(f))
        with RunDir(run).evaluation.open("w", newline="") as f:
            w = csv.DictWriter(f, ["global_step", "num_joints", "episode", "return", "body", "steps", "distance"])
            w.writeheader()
            w.writerows(chains)
            for body, n in (("centipede-10", 40), ("centipede-2", 8)):  # late checkpoints only: 12288 and 18432
                w.writerows({"global_step": s, "num_joints": n, "episode": 0, "return": 900.0 + n, "body": body,
                             "steps": 1000 - n, "distance": distance * n} for s in (12288, 18432))  # fmt: skip
        runs.append(run)
    old = write_run(tmp_path / "f1", "fixed", 1)  # an evaluation from before lengths and distances
    with RunDir(old).evaluation.open("w", newline="") as f:
        csv.writer(f).writerows(
            [["global_step", "num_joints", "episode", "return", "body"], [18432, 8, 0, 700, "centipede-2"]]
        )
    table = summary.tree_table(load_runs([*runs, old]))
    assert "| rule | runs | centipede-2 | centipede-10 |" in table  # 10 after 2
    assert "| compensated | 2 | 908 ± 0 | 940 ± 0 |" in table and "| fixed | 1 | 700 ± 0 | – |" in table
    assert "| rule: episode length | runs | centipede-2 | centipede-10 |" in table
    assert "| compensated | 2 | 992 ± 0 | 960 ± 0 |" in table
    assert "| compensated | 2 | 16.00 ± 8.00 | 80.00 ± 40.00 |" in table  # the root's travel, mean ± std over runs
    assert "| fixed | 1 | – | – |" in table  # recorded no distance: no figure rather than a zero


def _tables(text: str) -> list[tuple[str, list[str], str]]:
    """(heading, table lines, the paragraph after it) of every Markdown table in ``text``."""
    out, lines, i = [], text.splitlines(), 0
    while i < len(lines):
        if lines[i].startswith("|"):
            start = i
            while i < len(lines) and lines[i].startswith("|"):
                i += 1
            heading = next((x for x in reversed(lines[:start]) if x.startswith("#")), "")
            after = next((x for x in lines[i:] if x.strip()), "")
            out.append((heading, lines[start:i], after))
        i += 1
    return out


@pytest.mark.parametrize("data", ["made_up", "centipedes"])
def test_summary_tables_have_headings_and_legends_and_no_nan(tmp_path, capsys, data):
    """Each table under a heading and followed by its legend ((1), (2): ranks; never; –); a value a run does not
    have is '–', never 'nan' (the centipede runs have no chain lengths, no action dimensions 9..11)."""
    if data == "made_up":
        runs = [write_run(tmp_path / f"fixed-s{s}", "fixed", s) for s in (1, 2)]
        runs.append(write_run(tmp_path / "kl-stop-s1", "kl-stop", 1, scale=2.0))
    else:
        runs = sorted((Path(__file__).resolve().parents[5] / "docs/results_data/centipedes").glob("*-s*"))
        assert len(runs) >= 2
    summary.main(["--run", *map(str, runs)])
    out, err = capsys.readouterr()
    assert "nan" not in out.lower() and err == ""
    tables = _tables(out)
    assert len(tables) >= 3
    for heading, rows, legend in tables:
        assert heading.startswith("### ") and rows[1].startswith("|---"), (heading, rows[:2])
        assert not legend.startswith(("|", "#")) and legend.endswith("."), (heading, legend)
    ranking = next(t for t in tables if t[0] == "### The rules ranked claim by claim")
    assert "(1) the best" in ranking[2] and all("(1)" in r or "(2)" in r for r in ranking[1][2:])
    if data == "centipedes":
        assert "late eval, no joints" not in out and "| – | " not in ranking[1][2]  # unmeasured claims left out


def test_the_marks_of_the_per_run_table_are_chosen(tmp_path, capsys):
    # returns 0, 1500, 3000 at steps 6144, 12288, 18432 (scale 10): trailing means 0, 750, 1500
    write_run(tmp_path / "walker", "compensated", 1, scale=10.0)
    summary.main(["--run", str(tmp_path / "walker"), "--marks", "700", "1000", "2000"])
    out = capsys.readouterr().out
    assert "| run | >= 700 | >= 1000 | >= 2000 | mean of the last 10 updates |" in out
    assert "| walker | 12k | 18k | never | 1500 |" in out
    summary.main(["--run", str(tmp_path / "walker")])  # the swimmers' marks by default
    assert "| run | >= 100 | >= 200 |" in capsys.readouterr().out
