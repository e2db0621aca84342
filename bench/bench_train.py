"""Training speed at the paper configuration, beside the raw physics rate of the same chain mix.

    python bench/bench_train.py [--iterations 4]

Runs the real training loop (6 envs x 1024 steps, minibatch 256, 10 epochs,
chains drawn from 2..10, torch.compile on as by default) for one warm-up
iteration and a few timed ones, in three settings: one core; both cores
for the physics with the paper's single torch thread; both cores for
physics and update. It prints overall env-steps/s by wall clock (updates,
logging and checkpoints included), and the median rollout and update
seconds per iteration. The
raw rate is MuJoCo alone: mj_step with frame_skip 4, averaged over the
chain lengths 2..10 the way the envs draw them. The reference
implementation's figure (~360 env-steps/s on this machine class) is quoted
from docs/method notes for the ratio, not re-measured here.
"""

from __future__ import annotations

import argparse
import csv
import statistics
import tempfile
from pathlib import Path

import numpy as np
from bench_env import raw_step_rate

from morph_core.algo.train import TrainConfig, train

REFERENCE_SPS = 360.0
BATCH = 6 * 1024  # samples per iteration at the paper configuration


def run(iterations: int, torch_threads: int, env_threads: int) -> dict[str, float]:
    cfg = TrainConfig(
        total_timesteps=(1 + iterations) * BATCH,
        torch_threads=torch_threads,
        env_threads=env_threads,
        tensorboard=False,
        progress_bar=False,
    )
    with tempfile.TemporaryDirectory() as d:
        train(cfg, Path(d) / "run")
        with (Path(d) / "run" / "progress.csv").open() as f:
            rows = list(csv.DictReader(f))[1:]  # the first iteration compiles and warms caches
    # Overall rate by wall clock between the first and last timed rows: whole iterations,
    # logging and the checkpoint written after every iteration included.
    steps = int(rows[-1]["global_step"]) - int(rows[0]["global_step"])
    return {
        "sps": steps / (float(rows[-1]["wall_time"]) - float(rows[0]["wall_time"])),
        "rollout_s": statistics.median(float(r["rollout_s"]) for r in rows),
        "update_s": statistics.median(float(r["update_s"]) for r in rows),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iterations", type=int, default=4, help="timed training iterations per setting (>= 2)")
    args = parser.parse_args()
    # Physics alone for the 2..10 mix: mean time per control step over the lengths.
    per_step = np.mean([4.0 / raw_step_rate(n, 0.6) for n in range(2, 11)])
    raw_mix = 1.0 / per_step
    print("| setting | env-steps/s overall | rollout s/iter | update s/iter | vs reference (360/s) |")
    print("|---|---:|---:|---:|---:|")
    settings = [
        ("1 core (1 env thread, 1 torch thread)", 1, 1),
        ("2 cores, paper config (2 env threads, 1 torch thread)", 1, 2),
        ("2 cores (2 env threads, 2 torch threads)", 2, 2),
    ]
    for label, tt, et in settings:
        r = run(max(2, args.iterations), tt, et)
        ratio = r["sps"] / REFERENCE_SPS
        print(f"| {label} | {r['sps']:,.0f} | {r['rollout_s']:.2f} | {r['update_s']:.2f} | {ratio:.1f}x |")
    print(f"\nraw MuJoCo for the same 2..10 mix, one core: {raw_mix:,.0f} env-steps/s "
          f"(a rollout of 6,144 steps needs >= {6144 / raw_mix:.2f} s of physics)")  # fmt: skip


if __name__ == "__main__":
    main()
