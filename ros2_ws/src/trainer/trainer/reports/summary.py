"""Summary tables of training runs, as quoted in docs/results.md.

    python -m trainer.reports.summary --run docs/results_data/*

Prints, from each run's own files: the first step at which the training
return (trailing mean over 5 updates) reached 100 and 200 and the mean of
the last 10 updates; per trust-region rule the clip fraction and the KL per action dimension
averaged over all updates and seeds, the epochs per update where a KL stop
cut them short, and the KL penalty's final beta per run; and per rule the late-training
(>= half the steps) deterministic eval return averaged over the training
chain lengths; per run, whether the longest evaluated (unseen) chain
scores above every trained length, late in training and per checkpoint;
per rule the late return on every unseen length evaluated (zero-shot);
per rule the training marks (runs that reached 200, median steps to 100 and
200, the last 10 updates, the best trailing mean); one table that ranks
the rules claim by claim; and, for runs evaluated on trees or centipedes, the
late return per body (then the episodes' length and the root's forward travel,
where the evaluation recorded them) and the last training returns on chains and
on trees.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from morph_core.env.bodies import is_chain_label
from morph_core.util.config_cli import CommandLineParser
from trainer.reports.runs import RunReport, body_eval_means, eval_means, label_order, load_runs, series, smooth

MARKS = (100.0, 200.0)
"""the training returns the swimmer tables mark (walkers earn about 1,000 by standing: ``--marks 1000 2000 3000``)"""
COLLAPSE = 0.5
"""a run has collapsed when the mean of its last 10 updates is below this share of its best trailing mean"""


def main(argv: list[str] | None = None) -> None:
    parser = CommandLineParser(prog="python -m trainer.reports.summary", description=__doc__)
    parser.add_argument("--run", type=Path, nargs="+", required=True)
    parser.add_argument(
        "--marks",
        type=float,
        nargs="+",
        default=list(MARKS),
        help="training returns whose first step each run's table gives (walkers: 1000 2000 3000)",
    )
    args = parser.parse_args(argv)
    try:
        groups = load_runs(args.run)
    except ValueError as e:
        parser.error(str(e))
    with warnings.catch_warnings():  # NumPy's "mean of empty slice": a '–' in a cell, said by the legends
        warnings.simplefilter("ignore", RuntimeWarning)
        print(report(groups, tuple(args.marks)))


def report(groups: dict[str, list[RunReport]], marks: tuple[float, ...] | None = None) -> str:
    """Every table of the runs in ``groups`` (rule -> runs), each under a heading with a legend; a table with no
    rows is left out, a value a run does not have is '–' (never 'nan'). The first table gives the first step
    at which each run's training return reached each of ``marks`` (default ``MARKS``)."""
    marks = MARKS if marks is None else marks
    names = [f"{t:g}" for t in marks]
    rows = []
    for runs in groups.values():
        for run in runs:
            got = training_marks(run, marks)
            first = ["never" if got[f"to_{n}"] == np.inf else f"{int(got[f'to_{n}']) // 1000}k" for n in names]
            rows.append(f"| {run.dir.name} | {' | '.join(first)} | {_num(got['last'])} |")
    header = (f"| run | {' | '.join(f'>= {n}' for n in names)} | mean of the last 10 updates |\n"
              f"|---|{'---:|' * len(names)}---:|")  # fmt: skip
    parts = [_section("Training return per run", header, rows,
                      f"{', '.join(f'>= {n}' for n in names)}: the first step at which the training return "
                      "(trailing mean over 5 updates) reached it (k = 1000 steps); never: not in the run")]  # fmt: skip
    parts.append(per_rule_lines(groups))
    rows = []
    for runs in groups.values():
        for run in runs:
            means = eval_means(run)
            if not means:
                continue
            cfg = run.config
            trained = [n for n in run.trained_lengths if n in means]
            unseen = max(means)
            if unseen <= cfg["max_joints"] or not trained:
                continue  # no chain longer than the training range was evaluated
            run_late = late_means(run)
            late = {n: run_late.get(n, np.nan) for n in [*trained, unseen]}
            best = max(trained, key=lambda n: late[n] if np.isfinite(late[n]) else -np.inf)
            steps = sorted(means[unseen])
            on_top = sum(means[unseen][s] > max(means[n][s] for n in trained) for s in steps)
            rows.append(f"| {run.dir.name} | {unseen} | {_num(late[unseen])} | {_num(late[best])} ({best}) "
                        f"| {on_top} of {len(steps)} |")  # fmt: skip
    parts.append(_section(
        "The longest unseen chain against the trained ones",
        "| run | unseen n | late mean, unseen | late mean, best trained (n) | unseen on top at checkpoints |\n"
        "|---|---:|---:|---:|---:|", rows,
        "late: the deterministic eval return averaged over the checkpoints from half the run's steps on; unseen n: "
        "the longest chain evaluated, never trained on; (n): the trained length that scored best late",
    ))  # fmt: skip
    parts += [training_table(groups), zero_shot_table(groups), tree_table(groups), ranking_table(groups)]
    return "\n".join(part for part in parts if part).strip()


def _num(value: float, digits: int = 0) -> str:
    """A cell's number, or '–' where there is none (NaN: not measured, not evaluated)."""
    return f"{value:.{digits}f}" if np.isfinite(value) else "–"


def _section(title: str, header: str, rows: list[str], legend: str) -> str:
    """A Markdown table under a heading, its legend below it; '' when it has no rows."""
    if not rows:
        return ""
    return f"\n### {title}\n\n{header}\n" + "\n".join(rows) + f"\n\n{legend}.\n"


def per_rule_lines(groups: dict[str, list[RunReport]]) -> str:
    """Per rule: the clip fraction and KL per trained action dimension, the epochs per update a KL stop left, the
    KL penalty's final beta, the late eval return over the trained lengths (each only where measured)."""
    lines = []
    for rule, runs in groups.items():
        dims = runs[0].trained_lengths
        fracs = per_dimension(runs, "clip_frac")
        shown = [(d, f) for d, f in zip(dims, fracs, strict=True) if np.isfinite(f)]  # dimensions no body has: none
        if shown:
            lines.append(f"clip fraction per dimension, {rule} ({len(runs)} runs): "
                         + " ".join(f"{d}:{f:.2f}" for d, f in shown))  # fmt: skip
        kls = [(d, k) for d, k in zip(dims, per_dimension(runs, "approx_kl"), strict=True) if np.isfinite(k)]
        if kls:
            lines.append(f"KL per dimension, {rule}: " + " ".join(f"{d}:{k:.4f}" for d, k in kls))
        logged = [series(r.progress, "epochs")[1] for r in runs if "epochs" in r.progress[0]]
        epochs = np.mean(np.concatenate(logged)) if logged else np.nan
        if epochs < runs[0].config["update_epochs"]:  # the KL stop cut updates short (NaN: not logged)
            lines.append(f"epochs per update, {rule}: {epochs:.1f} of {runs[0].config['update_epochs']}")
        betas = [series(r.progress, "kl_beta")[1][-1] for r in runs]
        if np.isfinite(betas).all():
            lines.append(f"KL penalty beta at the end, {rule}: " + " ".join(f"{b:g}" for b in betas))
        late = [late_trained_mean(run) for run in runs]
        if all(np.isfinite(late)):
            lines.append(
                f"late eval return, mean over {dims.start}..{dims.stop - 1} joints, {rule}: {np.mean(late):.1f}"
            )
    if not lines:
        return ""
    legend = (
        "d:value per action dimension d (joints) over all updates and runs, dimensions the runs' bodies "
        "never have left out; late: checkpoints from half the run's steps on"
    )
    return "\n### Per rule: clipping and KL per action dimension\n\n" + "\n\n".join(lines) + f"\n\n{legend}.\n"


def per_dimension(runs: list[RunReport], key: str) -> np.ndarray:
    """Progress column ``key`` per trained action dimension, averaged over all updates and runs."""
    return np.array([np.mean([np.nanmean(series(r.progress, f"{key}_d{d}")[1]) for r in runs])
                     for d in runs[0].trained_lengths])  # fmt: skip


def late_tree_means(run: RunReport, column: str = "return") -> dict[str, float]:
    """{tree label: mean eval ``column`` over the run's checkpoints from half its steps on}; chains left out."""
    half = 0.5 * run.config["total_timesteps"]
    by_body = {b: steps for b, steps in body_eval_means(run, column).items() if not is_chain_label(b)}
    late = {b: [r for s, r in steps.items() if s >= half] for b, steps in by_body.items()}
    return {b: float(np.mean(v)) for b, v in late.items() if v}


def tree_table(groups: dict[str, list[RunReport]]) -> str:
    """Late eval return per rule on every tree (or centipede) evaluated (mean +- std over runs), then the
    episodes' length and the root's forward travel where the evaluation recorded them, and the training return
    of the last 10 updates on chains and on trees for runs that trained on both."""
    trees = sorted({b for runs in groups.values() for r in runs for b in late_tree_means(r)}, key=label_order)
    parts = []
    titles = {"return": "Late eval return per body", "steps": "Late episode length per body (control steps)",
              "distance": "Late forward travel per body (m)"}  # fmt: skip
    for column, what in (("return", "rule"), ("steps", "rule: episode length"), ("distance", "rule: distance, m")):
        late = {rule: [late_tree_means(r, column) for r in runs] for rule, runs in groups.items()}
        if not trees or not any(m for means in late.values() for m in means):
            continue
        header = f"| {what} | runs | " + " | ".join(trees) + " |\n|---|---:|" + "---:|" * len(trees)
        digits = 2 if column == "distance" else 0
        rows = []
        for rule, means in late.items():
            cells = [_mean_std([m.get(b, np.nan) for m in means], digits) for b in trees]
            rows.append(f"| {rule} | {len(means)} | " + " | ".join(cells) + " |")
        parts.append(_section(titles[column], header, rows,
                              "the checkpoints from half the run's steps on, deterministic, mean ± std over the runs; "
                              "–: not evaluated (or not recorded) in every run"))  # fmt: skip
    mixed = {rule: [r for r in runs if _trains_chains_and_trees(r)] for rule, runs in groups.items()}
    rows = []
    for rule, runs in mixed.items():
        last = {k: [float(np.nanmean(series(r.progress, k)[1][-10:])) for r in runs]
                for k in ("return_chains", "return_trees")}  # fmt: skip
        if runs:
            rows.append(f"| {rule} | {len(runs)} | {_mean_std(last['return_chains'])} | "
                        f"{_mean_std(last['return_trees'])} |")  # fmt: skip
    parts.append(_section("Training return on chains and on trees",
                          "| rule | runs | training return, last 10 updates: chains | trees |\n|---|---:|---:|---:|",
                          rows, "runs that trained on both; mean ± std over the runs"))  # fmt: skip
    return "\n".join(part for part in parts if part)


def _trains_chains_and_trees(run: RunReport) -> bool:
    """A run whose progress has training returns of chains and of other bodies (centipedes alone have none of
    chains: their row would be a '–' beside a figure filed under trees)."""
    if "return_trees" not in run.progress[0]:
        return False
    return all(np.isfinite(series(run.progress, k)[1]).any() for k in ("return_chains", "return_trees"))


def late_means(run: RunReport) -> dict[int, float]:
    """{num_joints: mean eval return over the run's checkpoints from half its steps on}."""
    half = 0.5 * run.config["total_timesteps"]
    late = {n: [r for s, r in by_step.items() if s >= half] for n, by_step in eval_means(run).items()}
    return {n: float(np.mean(v)) for n, v in late.items() if v}


def late_trained_mean(run: RunReport) -> float:
    """Late eval return averaged over the trained chain lengths (NaN if they were not all evaluated)."""
    late = late_means(run)
    if not all(n in late for n in run.trained_lengths):
        return np.nan
    return float(np.mean([late[n] for n in run.trained_lengths]))


def training_marks(run: RunReport, marks: tuple[float, ...] | None = None) -> dict[str, float]:
    """First step at which the trailing mean (5 updates) of the training return reached each of ``marks``
    (``to_100``, ``to_200`` for the default ``MARKS``; inf if never), the mean of the last 10 updates, and
    whether the run collapsed (last 10 below COLLAPSE x its best)."""
    marks = MARKS if marks is None else marks
    steps, ret = series(run.progress, "return_mean")
    smoothed = smooth(ret, 5)
    last = float(np.nanmean(ret[-10:]))
    first = {t: next((float(s) for s, v in zip(steps, smoothed, strict=True) if v >= t), np.inf) for t in marks}
    best = float(np.nanmax(smoothed)) if np.isfinite(smoothed).any() else np.nan
    collapsed = float(last < COLLAPSE * best)
    return {**{f"to_{t:g}": first[t] for t in marks}, "last": last, "best": best, "collapsed": collapsed}


def training_table(groups: dict[str, list[RunReport]]) -> str:
    """Per rule: runs that reached 200, median steps to 100 and 200, the last 10 updates (mean [min..max])
    and the best trailing mean, averaged over runs."""
    header = ("| rule | reached 200 | steps to 100, median | steps to 200, median | last 10 updates, mean [min..max] "
              "| best trailing mean (5 updates), mean |\n|---|---:|---:|---:|---:|---:|")  # fmt: skip
    rows = []
    for rule, runs in groups.items():
        marks = [training_marks(r) for r in runs]
        to = {t: float(np.median([m[f"to_{t}"] for m in marks])) for t in (100, 200)}
        steps = {t: "never" if to[t] == np.inf else f"{to[t] / 1000:.0f}k" for t in to}
        last = [m["last"] for m in marks]
        reached = sum(np.isfinite(m["to_200"]) for m in marks)
        spread = f"{_num(np.mean(last))} [{_num(min(last))}..{_num(max(last))}]"
        rows.append(f"| {rule} | {reached} of {len(runs)} | {steps[100]} | {steps[200]} | {spread} "
                    f"| {_num(np.mean([m['best'] for m in marks]))} |")  # fmt: skip
    return _section("Training marks per rule", header, rows,
                    "reached 200: runs whose trailing mean (5 updates) of the training return reached 200; steps to "
                    "100, 200: the median over the runs (k = 1000 steps; never: the median run did not)")  # fmt: skip


def zero_shot_table(groups: dict[str, list[RunReport]]) -> str:
    """Late eval return per rule: the trained lengths' mean, then every unseen length (mean +- std over runs)."""
    unseen = sorted({n for runs in groups.values() for r in runs for n in late_means(r) if n > r.config["max_joints"]})
    if not unseen:
        return ""
    header = ("| rule | runs | trained (mean) | " + " | ".join(f"{n} (unseen)" for n in unseen) + " |\n"
              "|---|---:|---:|" + "---:|" * len(unseen))  # fmt: skip
    rows = []
    for rule, runs in groups.items():
        cells = [_mean_std([late_trained_mean(r) for r in runs])]
        cells += [_mean_std([late_means(r).get(n, np.nan) for r in runs]) for n in unseen]
        rows.append(f"| {rule} | {len(runs)} | " + " | ".join(cells) + " |")
    return _section("Zero-shot: chains longer than any trained on", header, rows,
                    "late deterministic eval return, mean ± std over the runs; trained: averaged over the trained "
                    "lengths; n (unseen): n joints, never trained on; –: not evaluated in every run")  # fmt: skip


def _mean_std(values: list[float], digits: int = 0) -> str:
    """Mean +- std over runs; '–' unless every run has the value."""
    v = np.array(values, dtype=float)
    return f"{v.mean():.{digits}f} ± {v.std():.{digits}f}" if v.size and np.isfinite(v).all() else "–"


def ranking_table(groups: dict[str, list[RunReport]]) -> str:
    """The rules ranked claim by claim (1 = best; means over runs, the median for steps to 200). Zero-shot is
    compared on one length for all rules: the longest evaluated late in every run, if no run trained on it."""
    runs_all = [r for runs in groups.values() for r in runs]
    common = set.intersection(*[set(late_means(r)) for r in runs_all])
    unseen = max(common, default=0)
    if unseen <= max(r.config["max_joints"] for r in runs_all):
        unseen = 0
    claims = {  # name: (per-rule value, higher is better)
        "steps to 200 (median)": (lambda runs: float(np.median([training_marks(r)["to_200"] for r in runs])), False),
        "last 10 updates": (lambda runs: float(np.mean([training_marks(r)["last"] for r in runs])), True),
        "collapsed runs": (lambda runs: float(sum(training_marks(r)["collapsed"] for r in runs)), False),
        "late eval, trained lengths": (lambda runs: float(np.mean([late_trained_mean(r) for r in runs])), True),
        f"late eval, {unseen or 'no'} joints (unseen)": (
            lambda runs: float(np.mean([late_means(r)[unseen] for r in runs])) if unseen else np.nan,
            True,
        ),
    }
    values = {claim: {rule: f(runs) for rule, runs in groups.items()} for claim, (f, _) in claims.items()}
    claims = {c: v for c, v in claims.items() if any(not np.isnan(x) for x in values[c].values())}  # measured
    header = "| rule | " + " | ".join(claims) + " |\n|---|" + "---:|" * len(claims)
    rows = []
    for rule in groups:
        cells = [_ranked(values[claim], rule, higher, steps="steps" in claim) for claim, (_, higher) in claims.items()]
        rows.append(f"| {rule} | " + " | ".join(cells) + " |")
    return _section("The rules ranked claim by claim", header, rows,
                    "value (rank): the rule's mean over its runs (steps: the median; k = 1000 steps) and, in "
                    "parentheses, its rank among the rules on that claim: (1) the best, (2) the next, ties share a "
                    "rank; never: not reached; –: not measured for this rule; unmeasured claims: left out")  # fmt: skip


def _ranked(values: dict[str, float], rule: str, higher: bool, steps: bool) -> str:
    """'value (rank)' of ``rule`` among ``values``; inf ('never') ranks last, NaN ('–') is not ranked."""
    v = values[rule]
    if np.isnan(v):
        return "–"
    rank = 1 + sum((x > v) if higher else (x < v) for x in values.values() if not np.isnan(x))
    text = "never" if v == np.inf else f"{v / 1000:.0f}k" if steps else f"{v:.0f}"
    return f"{text} ({rank})"


if __name__ == "__main__":
    main()
