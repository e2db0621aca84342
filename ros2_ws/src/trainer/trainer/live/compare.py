"""Live training against the simulator trainer at the same env-step count: a table and the curves side by side.

    python -m trainer.live.compare runs/live-vs-sim/live-s* --simulator runs/live-vs-sim/simulator-s* \\
        --plot docs/figures/live

Reads each run's own ``progress.csv`` (``trainer.reports.runs``). The x axis is
``global_step``: the samples the updates learned from (in a live run, steps
dropped as stale or unusable are not counted; ``env_steps`` holds all
collected). A live run's updates do not fall on the same steps as the
simulator's (its batches are whole episodes), so the curves are compared on a
common grid, each run's training return (trailing mean over 5 updates, as
``trainer.reports.summary``) taken at its last update at or before each grid step.
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import numpy as np

from morph_core.util.atomic import atomic_writer
from morph_core.util.config_cli import CommandLineParser
from trainer.reports.runs import RunReport, load_run_report, series, smooth

SMOOTHING = 5  # updates, as trainer.reports.summary


def return_at(run: RunReport, steps: np.ndarray) -> np.ndarray:
    """The run's smoothed training return at each of ``steps`` (its last update at or before; NaN before any)."""
    at, ret = series(run.progress, "return_mean")
    smoothed = smooth(ret, SMOOTHING)
    idx = np.searchsorted(at, steps, side="right") - 1
    out = np.where(idx >= 0, smoothed[np.clip(idx, 0, None)], np.nan)
    return np.where(steps <= at[-1], out, np.nan) if len(at) else np.full(len(steps), np.nan)


def table(groups: dict[str, list[RunReport]], marks: list[int]) -> str:
    """Markdown: per source and seed, the return at each mark, the mean of the last 10 updates, and the steps."""
    head = " | ".join(f"at {m // 1000}k" for m in marks)
    lines = [f"| source | run | {head} | last 10 updates | steps |", "|---|---|" + "---:|" * (len(marks) + 2)]
    for source, runs in groups.items():
        rows = []
        for run in runs:
            at = return_at(run, np.array(marks))
            last = np.nanmean(series(run.progress, "return_mean")[1][-10:])
            rows.append([*at, last])
            cells = " | ".join("-" if np.isnan(v) else f"{v:.1f}" for v in at)
            lines.append(f"| {source} | {run.dir.name} | {cells} | {last:.1f} | {run.progress[-1]['global_step']} |")
        with warnings.catch_warnings():  # a mark no run reached is NaN, said as "-"
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = np.nanmean(np.array(rows), axis=0)
        cells = " | ".join("-" if np.isnan(v) else f"**{v:.1f}**" for v in mean[:-1])
        lines.append(f"| {source} | mean of {len(runs)} | {cells} | **{mean[-1]:.1f}** | |")
    return "\n".join(lines)


KL_DIVERGED = 1.0
"""an update whose approximate KL exceeds this moved the policy far outside any trust region"""


def stability_table(groups: dict[str, list[RunReport]], last: int = 5) -> str:
    """Markdown: per run, the largest approximate KL of an update, the step of the first update above
    ``KL_DIVERGED``, and 1000 x reward per step over the ``last`` updates (a measure that, unlike returns,
    does not depend on how episodes were cut; "-" for runs that do not log it)."""
    head = f"| source | run | updates | max approx. KL | first KL > {KL_DIVERGED:g} at"
    lines = [f"{head} | 1000 x reward/step, last {last} |", "|---|---|---:|---:|---:|---:|"]
    for source, runs in groups.items():
        for run in runs:
            steps, kl = series(run.progress, "approx_kl")
            over = steps[kl > KL_DIVERGED]
            rate = series(run.progress, "reward_rate")[1][-last:] if "reward_rate" in run.progress[0] else []
            cells = [
                str(len(kl)), f"{np.nanmax(kl):.3g}", f"{int(over[0])}" if len(over) else "never",
                f"{1000 * np.mean(rate):.1f}" if len(rate) else "-",
            ]  # fmt: skip
            lines.append(f"| {source} | {run.dir.name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(groups: dict[str, list[RunReport]], path: Path) -> Path:
    # Matplotlib only for the figure
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # after the backend is chosen

    end = min(int(r.progress[-1]["global_step"]) for runs in groups.values() for r in runs)
    grid = np.linspace(0, end, 200)
    fig, ax = plt.subplots(figsize=(7, 4))
    for k, (source, runs) in enumerate(groups.items()):
        color = f"C{k}"
        curves = np.array([return_at(run, grid) for run in runs])
        for c in curves:
            ax.plot(grid, c, color=color, alpha=0.3, lw=0.8)
        with warnings.catch_warnings():  # before any run's first update: NaN, not drawn
            warnings.simplefilter("ignore", RuntimeWarning)
            mean = np.nanmean(curves, 0)
        ax.plot(grid, mean, color=color, lw=2.2, label=f"{source} ({len(runs)} seeds)")
    ax.set_xlabel("environment steps learned from")
    ax.set_ylabel("training episode return (chains of 2..10)")
    ax.set_title("Live over DDS vs the simulator trainer: thin = seeds, thick = mean")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path = path.with_suffix(".png")
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_writer(path, "wb") as f:
        fig.savefig(f, format="png", dpi=120)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    ap = CommandLineParser(prog="python -m trainer.live.compare", description=__doc__,
                           formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("live", type=Path, nargs="+", help="live run directories (morph-train --live --out)")
    ap.add_argument("--simulator", type=Path, nargs="*", default=[], help="simulator run directories")
    ap.add_argument("--marks", type=int, nargs="+", default=[100_000, 200_000, 300_000], help="steps to compare at")
    ap.add_argument("--plot", type=Path, default=None, help="write the curves to this .png")
    args = ap.parse_args(argv)
    try:
        groups = {"live": [load_run_report(d) for d in args.live]}
        if args.simulator:
            groups["simulator"] = [load_run_report(d) for d in args.simulator]
    except (OSError, ValueError, KeyError) as err:
        ap.error(str(err))
    for runs in groups.values():
        for run in runs:
            if not run.progress:
                ap.error(f"{run.dir} has no update logged yet")
    print(table(groups, args.marks))
    print()
    print(stability_table(groups))
    if args.plot is not None:
        print(f"\nwrote {plot(groups, args.plot)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
