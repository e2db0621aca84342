"""Training speed at the paper configuration, beside the raw physics rate of the same chain mix and, with
``--reference``, beside the paper's own implementation, all measured in this one run.

    python bench/bench_train.py [--iterations 4] [--reference DIR --reference-python PY]

Runs the real training loop (6 envs x 1024 steps, minibatch 256, 10 epochs,
chains drawn from 2..10, the update compiled as by default) for one warm-up
iteration and a few timed ones, in four settings: one core; both cores
for the physics with the paper's single torch thread; both cores for
physics and update by threads; two processes, each with half the swimmers
and half of every minibatch (``processes=2``, ``algo.data_parallel``). It
prints overall env-steps/s by wall clock (updates, logging and checkpoints
included), the median rollout and update seconds
per iteration, and the share of the raw physics rate: MuJoCo alone
(mj_step with frame_skip 4, averaged over the chain lengths 2..10 the way
the envs draw them), a ratio that does not depend on the machine.

``--bodies SPEC`` adds a last setting: the data-parallel one training on the bodies SPEC
(``env.bodies``' grammar, e.g. ``2-10,random:3-10``: chains plus random trees), the cost of a
tree mix measured in the same run as the chains.

``--reference DIR``: a checkout of the paper's code (github.com/jr-robotics/MorphologicalPPO), run by
``--reference-python`` (a Python with its requirements) at its paper configuration (``agent=sb3_flex_varppo``:
compensated clipping, 6 envs, 1024 steps, minibatch 256, 10 epochs) for the same number of iterations, in a
copy of DIR. Its rate is wall clock between the first and last of its per-iteration logs, and each of our
settings is printed as a multiple of it. Machines of this kind differ 2x in speed from hour to hour, so only
such a side-by-side ratio is a claim.
"""

from __future__ import annotations

import argparse
import csv
import os
import shutil
import statistics
import subprocess
import tempfile
import time
from collections import deque
from pathlib import Path

import numpy as np
from bench_env import raw_step_rate

from morph_core.algo.train import TrainConfig, train

BATCH = 6 * 1024  # samples per iteration at the paper configuration


def reference_rate(ref_dir: Path, python: str, iterations: int) -> float:
    """Env-steps/s of the paper's implementation over ``iterations`` timed iterations after a first one.

    Stable-Baselines3 logs a table after each rollout whose ``total_timesteps`` row gives the steps so far;
    the rate is taken between the first and the last table by wall clock (rollouts and updates included, as
    ours)."""
    with tempfile.TemporaryDirectory() as d:
        work = Path(d) / "reference"
        shutil.copytree(ref_dir, work, ignore=shutil.ignore_patterns(".git", "logs", "outputs"))
        cmd = [python, "-u", "train.py", "agent=sb3_flex_varppo", "~callbacks",
               f"learner.total_timesteps={(1 + iterations) * BATCH}", f"log_dir={work / 'logs'}"]  # fmt: skip
        marks: list[tuple[float, int]] = []
        tail: deque[str] = deque(maxlen=20)  # the run's last lines, for the error
        # PyG writes each message-passing module it generates into the temp directory: this run's, not /tmp
        env = {**os.environ, "TMPDIR": d}
        with subprocess.Popen(cmd, cwd=work, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True) as proc:  # fmt: skip
            for line in proc.stdout:
                tail.append(line)
                cells = [c.strip() for c in line.split("|")]
                if len(cells) >= 3 and cells[1] == "total_timesteps" and cells[2].isdigit():
                    marks.append((time.perf_counter(), int(cells[2])))
        if proc.returncode != 0 or len(marks) < 2:
            raise SystemExit(f"the reference run failed (exit {proc.returncode}, {len(marks)} iterations logged):\n"
                             + "".join(tail))  # fmt: skip
    (t0, s0), (t1, s1) = marks[0], marks[-1]
    return (s1 - s0) / (t1 - t0)


def run(iterations: int, torch_threads: int, env_threads: int, processes: int, bodies: str = "") -> dict[str, float]:
    cfg = TrainConfig(
        bodies=bodies,
        total_timesteps=(1 + iterations) * BATCH,
        torch_threads=torch_threads,
        env_threads=env_threads,
        processes=processes,
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
    parser.add_argument("--reference", type=Path, default=None, metavar="DIR",
                        help="a checkout of the paper's code, measured side by side")  # fmt: skip
    parser.add_argument("--reference-python", default=None, metavar="PY",
                        help="the Python that runs it (with its requirements installed)")  # fmt: skip
    parser.add_argument("--settings", type=int, nargs="+", default=None, metavar="K",
                        help="run only these settings (1-based, in the table's order)")  # fmt: skip
    parser.add_argument("--bodies", default=None, metavar="SPEC",
                        help="also train on these bodies (e.g. 2-10,random:3-10), data-parallel, last")  # fmt: skip
    args = parser.parse_args()
    if args.reference is not None:
        if not (args.reference / "train.py").is_file():
            parser.error(f"--reference {args.reference}: no train.py there (a MorphologicalPPO checkout?)")
        if args.reference_python is None:
            parser.error("--reference needs --reference-python (a Python with the reference's requirements)")
    iterations = max(2, args.iterations)
    # Physics alone for the 2..10 mix: mean time per control step over the lengths.
    per_step = np.mean([4.0 / raw_step_rate(n, 0.6) for n in range(2, 11)])
    raw_mix = 1.0 / per_step
    reference = None
    if args.reference is not None:
        reference = reference_rate(args.reference, args.reference_python, iterations)
        print(f"reference (paper's code, this run): {reference:,.0f} env-steps/s")
    print("| setting | env-steps/s overall | rollout s/iter | update s/iter | share of raw physics | vs reference |")
    print("|---|---:|---:|---:|---:|---:|")
    settings = [
        ("1 core (1 env thread, 1 torch thread)", 1, 1, 1),
        ("2 cores, paper config (2 env threads, 1 torch thread)", 1, 2, 1),
        ("2 cores (2 env threads, 2 torch threads)", 2, 2, 1),
        ("2 cores, 2 processes (data-parallel)", 1, 1, 2),
    ]
    chosen = [settings[k - 1] + ("",) for k in args.settings or range(1, len(settings) + 1)]
    if args.bodies:
        chosen.append((f"2 cores, 2 processes, bodies {args.bodies}", 1, 1, 2, args.bodies))
    for label, tt, et, processes, bodies in chosen:
        r = run(iterations, tt, et, processes, bodies)
        ratio = f"{r['sps'] / reference:.1f}x" if reference else "not run"
        print(f"| {label} | {r['sps']:,.0f} | {r['rollout_s']:.2f} | {r['update_s']:.2f} | "
              f"{r['sps'] / raw_mix:.2f} | {ratio} |")  # fmt: skip
    print(f"\nraw MuJoCo for the same 2..10 mix, one core: {raw_mix:,.0f} env-steps/s "
          f"(a rollout of 6,144 steps needs >= {6144 / raw_mix:.2f} s of physics)")  # fmt: skip


if __name__ == "__main__":
    main()
