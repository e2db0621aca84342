"""Figures and tables comparing clip modes over several seeded runs.

Inputs are the run directories' own files (config.json, progress.csv,
eval.csv); nothing is dropped by outcome: every run given is plotted.
"""

from __future__ import annotations

import csv
import json
import math
import warnings
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from morph_core.util.atomic import atomic_writer  # noqa: E402

MODES = ("compensated", "fixed")
COLORS = {"compensated": "tab:blue", "fixed": "tab:orange"}


def _float(text: str) -> float:
    return float(text) if text not in ("", None) else math.nan


def load_runs(run_dirs: list[Path]) -> dict[str, list[dict]]:
    """Runs grouped by clip mode: each {"dir", "config", "progress": rows, "eval": rows}."""
    groups: dict[str, list[dict]] = defaultdict(list)
    for d in run_dirs:
        cfg = json.loads((d / "config.json").read_text())
        with (d / "progress.csv").open() as f:
            progress = list(csv.DictReader(f))
        evals = []
        if (d / "eval.csv").exists():
            with (d / "eval.csv").open() as f:
                evals = list(csv.DictReader(f))
        groups[cfg["clip_mode"]].append({"dir": d, "config": cfg, "progress": progress, "eval": evals})
    return groups


def _series(rows: list[dict], key: str) -> tuple[np.ndarray, np.ndarray]:
    steps = np.array([int(r["global_step"]) for r in rows])
    return steps, np.array([_float(r.get(key, "")) for r in rows])


def _smooth(y: np.ndarray, window: int) -> np.ndarray:
    """Trailing mean over the last ``window`` finite values (episodes end only every ~1000 steps)."""
    out = np.full_like(y, np.nan)
    for i in range(len(y)):
        seg = y[max(0, i - window + 1) : i + 1]
        seg = seg[np.isfinite(seg)]
        if seg.size:
            out[i] = seg.mean()
    return out


def eval_means(run: dict) -> dict[int, dict[int, float]]:
    """{num_joints: {global_step: mean return over episodes}} of one run."""
    acc: dict[int, dict[int, list[float]]] = defaultdict(lambda: defaultdict(list))
    for r in run["eval"]:
        acc[int(r["num_joints"])][int(r["global_step"])].append(float(r["return"]))
    return {n: {s: float(np.mean(v)) for s, v in by_step.items()} for n, by_step in acc.items()}


def plot_training_returns(groups, path: Path) -> Path:
    fig, ax = plt.subplots(figsize=(7, 4))
    for mode in MODES:
        runs = groups.get(mode, [])
        if not runs:
            continue
        curves = []
        for run in runs:
            steps, y = _series(run["progress"], "return_mean")
            y = _smooth(y, 5)
            ax.plot(steps, y, color=COLORS[mode], alpha=0.25, lw=0.8)
            curves.append((steps, y))
        n = min(len(s) for s, _ in curves)
        stack = np.array([y[:n] for _, y in curves])
        ax.plot(curves[0][0][:n], np.nanmean(stack, 0), color=COLORS[mode], lw=2.2, label=f"{mode} ({len(runs)} seeds)")
        ax.fill_between(curves[0][0][:n], np.nanmin(stack, 0), np.nanmax(stack, 0), color=COLORS[mode], alpha=0.12)
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
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for ax, mode in zip(axes, MODES, strict=True):
        runs = groups.get(mode, [])
        ax.set_title(f"{mode}: {ylabel} per action dimension")
        if not runs:
            continue
        dims = range(runs[0]["config"]["min_joints"], runs[0]["config"]["max_joints"] + 1)
        cmap = plt.get_cmap("viridis")
        for i, d in enumerate(dims):
            ys = []
            for run in runs:
                steps, y = _series(run["progress"], f"{key}_d{d}")
                ys.append(y)
            n = min(len(y) for y in ys)
            with warnings.catch_warnings():  # an iteration may hold no sample of dimension d: NaN there
                warnings.simplefilter("ignore", RuntimeWarning)
                mean = _smooth(np.nanmean(np.array([y[:n] for y in ys]), 0), 5)
            ax.plot(steps[:n], mean, color=cmap(i / max(1, len(dims) - 1)), lw=0.6 + 0.3 * i, label=f"d={d}")
        ax.set_xlabel("environment steps")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel(f"{ylabel} (mean over seeds)")
    axes[1].legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_eval_per_length(groups, path: Path) -> Path | None:
    if not any(run["eval"] for runs in groups.values() for run in runs):
        return None
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    cmap = plt.get_cmap("viridis")
    for ax, mode in zip(axes, MODES, strict=True):
        ax.set_title(f"{mode}: deterministic eval return per chain length")
        runs = [r for r in groups.get(mode, []) if r["eval"]]
        if not runs:
            continue
        per_run = [eval_means(r) for r in runs]
        lengths = sorted(set().union(*[m.keys() for m in per_run]))
        train_hi = runs[0]["config"]["max_joints"]
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
    axes[0].set_ylabel("return over 1000 steps (mean of seeds)")
    axes[1].legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def eval_table(groups, late_fraction: float | None = None) -> str:
    """Markdown: eval return per chain length, mean +- std over seeds, per mode.

    ``late_fraction=None``: each run's final checkpoint. Otherwise each run's
    mean over its evaluated checkpoints at or beyond that fraction of its
    training steps (less sensitive to one unlucky last update).
    """
    lengths: set[int] = set()
    per_mode: dict[str, list[dict[int, float]]] = {}
    for mode in MODES:
        per_mode[mode] = []
        for run in groups.get(mode, []):
            means = eval_means(run)
            if not means:
                continue
            steps = sorted({s for by_step in means.values() for s in by_step})
            if late_fraction is None:
                chosen = [steps[-1]]
            else:
                chosen = [s for s in steps if s >= late_fraction * run["config"]["total_timesteps"]] or [steps[-1]]
            per_mode[mode].append(
                {n: float(np.mean([by_step[s] for s in chosen if s in by_step])) for n, by_step in means.items()}
            )
            lengths |= set(per_mode[mode][-1])
    if not lengths:
        return ""
    head = "| joints | " + " | ".join(f"{m} ({len(per_mode[m])} seeds)" for m in MODES) + " |"
    lines = [head, "|---:|" + "---:|" * len(MODES)]
    for n in sorted(lengths):
        cells = []
        for m in MODES:
            vals = [f[n] for f in per_mode[m] if n in f and np.isfinite(f[n])]
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
