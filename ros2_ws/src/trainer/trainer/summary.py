"""Summary tables of training runs, as quoted in docs/results.md.

    python -m trainer.summary --run docs/results_data/*

Prints, from each run's own files: the first step at which the training
return (trailing mean over 5 updates) reached 100 and 200 and the mean of
the last 10 updates; per trust-region rule the clip fraction per action dimension
averaged over all updates and seeds; and per rule the late-training
(>= half the steps) deterministic eval return averaged over the training
chain lengths; and per run, whether the longest evaluated (unseen) chain
scores above every trained length, late in training and per checkpoint.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from trainer.runs import eval_means, load_runs, series, smooth


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m trainer.summary", description=__doc__)
    parser.add_argument("--run", type=Path, nargs="+", required=True)
    args = parser.parse_args(argv)
    groups = load_runs(args.run)

    print("| run | >= 100 | >= 200 | mean of the last 10 updates |\n|---|---:|---:|---:|")
    for runs in groups.values():
        for run in runs:
            steps, ret = series(run.progress, "return_mean")
            smoothed = smooth(ret, 5)
            first = [
                next((f"{s // 1000}k" for s, v in zip(steps, smoothed, strict=True) if v >= t), "never")
                for t in (100, 200)
            ]
            print(f"| {run.dir.name} | {first[0]} | {first[1]} | {np.nanmean(ret[-10:]):.0f} |")

    for rule, runs in groups.items():
        dims = runs[0].trained_lengths
        fracs = [np.mean([np.nanmean(series(r.progress, f"clip_frac_d{d}")[1]) for r in runs]) for d in dims]
        print(f"\nclip fraction per dimension, {rule} ({len(runs)} runs): "
              + " ".join(f"{d}:{f:.2f}" for d, f in zip(dims, fracs, strict=True)))  # fmt: skip
        late = []
        for run in runs:
            means = eval_means(run)
            half = 0.5 * run.config["total_timesteps"]
            late.append(np.mean([np.mean([r for s, r in means[n].items() if s >= half]) for n in dims if n in means]))
        if all(np.isfinite(late)):
            print(f"late eval return, mean over {dims.start}..{dims.stop - 1} joints, {rule}: {np.mean(late):.1f}")

    print("\n| run | unseen n | late mean, unseen | late mean, best trained (n) | unseen on top at checkpoints |")
    print("|---|---:|---:|---:|---:|")
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
            half = 0.5 * cfg["total_timesteps"]
            late = {n: np.mean([r for s, r in means[n].items() if s >= half]) for n in [*trained, unseen]}
            best = max(trained, key=late.get)
            steps = sorted(means[unseen])
            on_top = sum(means[unseen][s] > max(means[n][s] for n in trained) for s in steps)
            print(f"| {run.dir.name} | {unseen} | {late[unseen]:.0f} | {late[best]:.0f} ({best}) "
                  f"| {on_top} of {len(steps)} |")  # fmt: skip


if __name__ == "__main__":
    main()
