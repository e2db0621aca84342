"""Summary tables of training runs, as quoted in docs/results.md.

    python -m trainer.summary --run docs/results_data/*

Prints, from each run's own files: the first step at which the training
return (trailing mean over 5 updates) reached 100 and 200 and the mean of
the last 10 updates; per clip mode the clip fraction per action dimension
averaged over all updates and seeds; and per clip mode the late-training
(>= half the steps) deterministic eval return averaged over the training
chain lengths.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from trainer.plots import MODES, _series, _smooth, eval_means, load_runs


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m trainer.summary", description=__doc__)
    parser.add_argument("--run", type=Path, nargs="+", required=True)
    args = parser.parse_args(argv)
    groups = load_runs(args.run)

    print("| run | >= 100 | >= 200 | mean of the last 10 updates |\n|---|---:|---:|---:|")
    for mode in MODES:
        for run in groups.get(mode, []):
            steps, ret = _series(run["progress"], "return_mean")
            smooth = _smooth(ret, 5)
            first = [
                next((f"{s // 1000}k" for s, v in zip(steps, smooth, strict=True) if v >= t), "never")
                for t in (100, 200)
            ]
            print(f"| {run['dir'].name} | {first[0]} | {first[1]} | {np.nanmean(ret[-10:]):.0f} |")

    for mode in MODES:
        runs = groups.get(mode, [])
        if not runs:
            continue
        cfg = runs[0]["config"]
        dims = range(cfg["min_joints"], cfg["max_joints"] + 1)
        fracs = [np.mean([np.nanmean(_series(r["progress"], f"clip_frac_d{d}")[1]) for r in runs]) for d in dims]
        print(f"\nclip fraction per dimension, {mode} ({len(runs)} runs): "
              + " ".join(f"{d}:{f:.2f}" for d, f in zip(dims, fracs, strict=True)))  # fmt: skip
        late = []
        for run in runs:
            means = eval_means(run)
            half = 0.5 * run["config"]["total_timesteps"]
            late.append(np.mean([np.mean([r for s, r in means[n].items() if s >= half]) for n in dims if n in means]))
        if all(np.isfinite(late)):
            print(f"late eval return, mean over {dims.start}..{dims.stop - 1} joints, {mode}: {np.mean(late):.1f}")


if __name__ == "__main__":
    main()
