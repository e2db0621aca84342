"""Figures and tables comparing trust-region rules over several seeded runs.

Inputs are the run directories' own files (``runs``); nothing is dropped by
outcome: every run given is plotted. Rules appear in the order of
``algo.trust_region.RULES``, one colour and one panel each.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from morph_core.algo.trust_region import rule_names  # noqa: E402
from morph_core.util.atomic import atomic_writer  # noqa: E402
from trainer.reports.runs import RunReport, eval_means, load_runs, series, smooth  # noqa: E402


def rule_color(rule: str) -> str:
    """Matplotlib's colour cycle in the table's order, so a rule keeps its colour in every figure."""
    return f"C{rule_names().index(rule) % 10}"


def _panels(groups: dict[str, list[RunReport]], width: float = 5.5, per_row: int = 4):
    """One panel per rule with runs (at least one panel), ``per_row`` to a row, sharing the y axis."""
    rules = list(groups) or [""]
    cols = min(per_row, len(rules))
    rows = -(-len(rules) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(width * cols, 4 * rows), sharey=True, squeeze=False)
    for ax in axes.flat[len(rules) :]:
        ax.set_visible(False)
    return fig, list(zip(axes.flat, rules, strict=False))


def plot_training_returns(groups, path: Path) -> Path:
    fig, ax = plt.subplots(figsize=(9, 5) if len(groups) > 3 else (7, 4))  # room for many rules
    for rule, runs in groups.items():
        color = rule_color(rule)
        curves = []
        for run in runs:
            steps, y = series(run.progress, "return_mean")
            y = smooth(y, 5)
            ax.plot(steps, y, color=color, alpha=0.25, lw=0.8)
            curves.append((steps, y))
        n = min(len(s) for s, _ in curves)
        stack = np.array([y[:n] for _, y in curves])
        ax.plot(curves[0][0][:n], np.nanmean(stack, 0), color=color, lw=2.2, label=f"{rule} ({len(runs)} seeds)")
        ax.fill_between(curves[0][0][:n], np.nanmin(stack, 0), np.nanmax(stack, 0), color=color, alpha=0.12)
    ax.set_xlabel("environment steps")
    ax.set_ylabel("training episode return (chains of 2..10)")
    ax.set_title("Training return: thin = seeds, thick = mean, band = min..max")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_clip_fractions(groups, path: Path, key: str = "clip_frac", ylabel: str = "clip fraction") -> Path:
    fig, panels = _panels(groups)
    for ax, rule in panels:
        runs = groups.get(rule, [])
        ax.set_title(f"{rule}: {ylabel} per action dimension")
        if not runs:
            continue
        dims = runs[0].trained_lengths
        cmap = plt.get_cmap("viridis")
        for i, d in enumerate(dims):
            ys = []
            for run in runs:
                steps, y = series(run.progress, f"{key}_d{d}")
                ys.append(y)
            n = min(len(y) for y in ys)
            with warnings.catch_warnings():  # an iteration may hold no sample of dimension d: NaN there
                warnings.simplefilter("ignore", RuntimeWarning)
                mean = smooth(np.nanmean(np.array([y[:n] for y in ys]), 0), 5)
            ax.plot(steps[:n], mean, color=cmap(i / max(1, len(dims) - 1)), lw=0.6 + 0.3 * i, label=f"d={d}")
        ax.set_xlabel("environment steps")
        ax.grid(alpha=0.3)
    for ax, _ in panels:
        if ax.get_subplotspec().is_first_col():
            ax.set_ylabel(f"{ylabel} (mean over seeds)")
    panels[-1][0].legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_eval_per_length(groups, path: Path) -> Path | None:
    if not any(run.eval for runs in groups.values() for run in runs):
        return None
    fig, panels = _panels(groups)
    cmap = plt.get_cmap("viridis")
    for ax, rule in panels:
        ax.set_title(f"{rule}: deterministic eval return per chain length")
        runs = [r for r in groups.get(rule, []) if r.eval]
        if not runs:
            continue
        per_run = [eval_means(r) for r in runs]
        lengths = sorted(set().union(*[m.keys() for m in per_run]))
        train_hi = runs[0].config["max_joints"]
        for n in lengths:
            steps = sorted(set.intersection(*[set(m.get(n, {})) for m in per_run]))
            if not steps:
                continue
            y = [np.mean([m[n][s] for m in per_run]) for s in steps]
            unseen = n > train_hi
            ax.plot(steps, y, ls="--" if unseen else "-", lw=2.2 if unseen else 0.5 + 0.2 * n,
                    color="crimson" if n == max(lengths) else cmap(min(n, train_hi) / train_hi),
                    alpha=1.0 if unseen else 0.7, label=f"{n} joints" + (" (unseen)" if unseen else ""))  # fmt: skip
        ax.set_xlabel("environment steps")
        ax.grid(alpha=0.3)
    for ax, _ in panels:
        if ax.get_subplotspec().is_first_col():
            ax.set_ylabel("return over 1000 steps (mean of seeds)")
    panels[-1][0].legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def eval_table(groups, late_fraction: float | None = None) -> str:
    """Markdown: eval return per chain length, mean +- std over seeds, per rule.

    ``late_fraction=None``: each run's final checkpoint. Otherwise each run's
    mean over its evaluated checkpoints at or beyond that fraction of its
    training steps (less sensitive to one unlucky last update).
    """
    lengths: set[int] = set()
    per_rule: dict[str, list[dict[int, float]]] = {}
    for rule, runs in groups.items():
        per_rule[rule] = []
        for run in runs:
            means = eval_means(run)
            if not means:
                continue
            steps = sorted({s for by_step in means.values() for s in by_step})
            if late_fraction is None:
                chosen = [steps[-1]]
            else:
                chosen = [s for s in steps if s >= late_fraction * run.config["total_timesteps"]] or [steps[-1]]
            per_rule[rule].append(
                {n: float(np.mean([by_step[s] for s in chosen if s in by_step])) for n, by_step in means.items()}
            )
            lengths |= set(per_rule[rule][-1])
    if not lengths:
        return ""
    head = "| joints | " + " | ".join(f"{m} ({len(per_rule[m])} seeds)" for m in per_rule) + " |"
    lines = [head, "|---:|" + "---:|" * len(per_rule)]
    for n in sorted(lengths):
        cells = []
        for m in per_rule:
            vals = [f[n] for f in per_rule[m] if n in f and np.isfinite(f[n])]
            cells.append(f"{np.mean(vals):.1f} ± {np.std(vals):.1f}" if vals else "–")
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot_all(run_dirs: list[Path], out: Path) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    groups = load_runs(run_dirs)
    written = [
        plot_training_returns(groups, out / "training_returns.png"),
        plot_clip_fractions(groups, out / "clip_fraction_per_dim.png"),
        plot_clip_fractions(groups, out / "in_eps_fraction_per_dim.png", "in_eps_frac", "fraction |log r| <= eps"),
    ]
    eval_fig = plot_eval_per_length(groups, out / "eval_return_per_length.png")
    if eval_fig is not None:
        written.append(eval_fig)
    for name, late in (("final_eval_table.md", None), ("late_eval_table.md", 0.5)):
        table = eval_table(groups, late)
        if table:
            with atomic_writer(out / name) as f:
                f.write(table)
            written.append(out / name)
    return written
