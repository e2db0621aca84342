"""Checkpoint evaluation speed: ``morph-eval`` now, with one and two processes, beside the code at ``--before``.

    python bench/bench_eval.py --run RUN_DIR [--every 10] [--before REV]

Takes every ``--every``-th checkpoint of a training run (default 10: 17 of a
1M-step run's 163) and evaluates them as ``morph-eval`` does by default (10
episodes on each of the lengths 2..10, 15 and 20, 1,000 steps each), by:
the code at ``--before`` (a ``git worktree`` of that revision first on
PYTHONPATH; default: before the NumPy evaluation and ``--processes``), this
code with one process, and this code with two. Each runs ``python -m
trainer.cli.eval`` on its own copy of the chosen checkpoints, one after the
other on the same machine; the table gives seconds per checkpoint, the time
projected for all of the run's checkpoints (``--stride 1``) and the rate
against ``--before``. Beside it, the physics alone: MuJoCo's env steps of
one checkpoint's episodes on one core. Not a timed test.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_env import raw_step_rate

from morph_core.algo.run_dir import RunDir

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("ros2_ws/src/morph_core", "ros2_ws/src/trainer")
LENGTHS = [*range(2, 11), 15, 20]  # morph-eval's default
EPISODES, STEPS = 10, 1000


def timed_eval(tree: Path, run: Path, chosen: list[Path], work: Path, processes: int) -> float:
    """Seconds ``morph-eval`` of the code in ``tree`` takes on a copy of ``run`` holding ``chosen``."""
    copy = RunDir(work / "run")
    shutil.rmtree(copy.path, ignore_errors=True)
    copy.checkpoints.mkdir(parents=True)
    shutil.copy(RunDir(run).config, copy.config)
    for path in chosen:
        for part in (path, path.with_suffix(".json")):  # the weights and their config beside them
            if part.exists():
                shutil.copy(part, copy.checkpoints)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(str(tree / p) for p in PACKAGES))
    cmd = [sys.executable, "-m", "trainer.cli.eval", "--run", str(copy.path)]
    if processes > 1:
        cmd += ["--processes", str(processes)]
    start = time.perf_counter()
    subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - start


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", type=Path, required=True, help="a training run with its checkpoints")
    ap.add_argument("--every", type=int, default=10, help="evaluate every k-th checkpoint")
    ap.add_argument("--before", default="3f8114a", help="revision to compare with (default: the torch evaluation)")
    args = ap.parse_args()
    ckpts = [path for _, path in RunDir(args.run).saved_checkpoints()]
    if not ckpts:
        ap.error(f"no checkpoints in {RunDir(args.run).checkpoints}")
    chosen = ckpts[:: args.every]
    physics = sum(EPISODES * STEPS * 4 / raw_step_rate(n, 0.6) for n in LENGTHS)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        before = Path(tmp) / "before"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(before), args.before], check=True)
        try:
            for label, tree, processes in (
                (f"before ({args.before}), 1 process", before, 1),
                ("now, 1 process", ROOT, 1),
                ("now, 2 processes", ROOT, 2),
            ):
                seconds = timed_eval(tree, args.run, chosen, Path(tmp), processes)
                rows.append((label, seconds / len(chosen)))
                print(f"{label}: {seconds:.1f} s for {len(chosen)} checkpoints", file=sys.stderr)
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(before)], check=True)
    print(f"{len(chosen)} of the {len(ckpts)} checkpoints of {args.run}; lengths {LENGTHS}, {EPISODES} episodes each")
    print("| code | s per checkpoint | all checkpoints (--stride 1), min | rate vs before |")
    print("|---|---:|---:|---:|")
    for label, per in rows:
        print(f"| {label} | {per:.1f} | {per * len(ckpts) / 60:.1f} | {rows[0][1] / per:.2f}x |")
    total = physics * len(ckpts) / 60
    print(f"\nphysics alone (raw MuJoCo, one core) for one checkpoint's episodes: {physics:.1f} s "
          f"({total:.1f} min for all, {total / 2:.1f} min on two cores)")  # fmt: skip


if __name__ == "__main__":
    main()
