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

``--bodies SPEC [SPEC ...]`` adds a last setting per SPEC: the data-parallel one training on those bodies
(``env.bodies``' grammar, e.g. ``2-10,random:3-10``: chains plus random trees; ``centipede:2-4``), the cost
of a tree mix or of centipedes measured in the same run as the chains. Each row's share of raw physics is
against the raw physics of its own bodies (``raw_mix_rate``: MuJoCo alone, one core, frame skip 4 for
swimmers and 5 for centipedes, averaged over bodies drawn as the envs draw them); its ratio to the
reference is against the paper's code on its chains, the only bodies it trains. ``--joint-features 11``
runs each of those settings again with a policy that reads the joint descriptions (the legged family's
generalist, issue 51): what they cost, side by side (``--bodies legged:4-8x2-3 --joint-features 11``).

Every row's rate is the steady state: the first iteration (start-up, the compile of the update step and
its first call) is left out, and reported on its own as the warm-up (seconds from the start of the run
to its first logged iteration).

``--reference DIR``: a checkout of the paper's code (github.com/jr-robotics/MorphologicalPPO), run by
``--reference-python`` (a Python with its requirements) at its paper configuration (``agent=sb3_flex_varppo``:
compensated clipping, 6 envs, 1024 steps, minibatch 256, 10 epochs) for the same number of iterations, in a
copy of DIR. Its rate is wall clock between the first and last of its per-iteration logs, and each of our
settings is printed as a multiple of it. Machines of this kind differ 2x in speed from hour to hour, so only
such a side-by-side ratio is a claim. The reference runs first; ``--bracket`` runs it again after the
settings and prints how far the machine's speed moved between the two (on a loaded machine it can move
several-fold, and a ratio against the first alone would mislead).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import os
import shutil
import statistics
import subprocess
import tempfile
import time
from collections import deque
from pathlib import Path

import mujoco
import numpy as np
from bench_env import rate, raw_step_rate

from morph_core.algo.run_dir import RunDir
from morph_core.algo.train import TrainConfig, train
from morph_core.env.bodies import Centipede, body_label, is_walker, parse_bodies
from morph_core.env.centipede import MorphCentipedeEnv
from morph_core.env.model import body_parents, swimmer_model

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


def run(iterations: int, torch_threads: int, env_threads: int, processes: int, bodies: str = "",
        joint_features: int = 0) -> dict[str, float]:  # fmt: skip
    cfg = TrainConfig(
        bodies=bodies,
        total_timesteps=(1 + iterations) * BATCH,
        torch_threads=torch_threads,
        env_threads=env_threads,
        processes=processes,
        tensorboard=False,
        progress_bar=False,
    )
    cfg = dataclasses.replace(cfg, policy=dataclasses.replace(cfg.policy, joint_features=joint_features))
    with tempfile.TemporaryDirectory() as d:
        start = time.time()  # the wall clock progress.csv's wall_time is taken by
        train(cfg, Path(d) / "run")
        with RunDir(Path(d) / "run").progress.open() as f:
            warmup, *rows = list(csv.DictReader(f))  # the first iteration compiles and warms caches
    # Overall rate by wall clock between the first and last timed rows: whole iterations,
    # logging and the checkpoint written after every iteration included.
    steps = int(rows[-1]["global_step"]) - int(rows[0]["global_step"])
    return {
        "sps": steps / (float(rows[-1]["wall_time"]) - float(rows[0]["wall_time"])),
        "rollout_s": statistics.median(float(r["rollout_s"]) for r in rows),
        "update_s": statistics.median(float(r["update_s"]) for r in rows),
        "warmup_s": float(warmup["wall_time"]) - start,
    }


def raw_mix_rate(spec: str, seconds: float = 0.6, draws: int = 200, seed: int = 0) -> float:
    """One core's raw physics rate (control steps/s) of the bodies ``spec``: MuJoCo's step alone, ``nstep`` =
    the env's frame skip, averaged over ``draws`` bodies drawn as the envs draw them (each distinct body
    timed once). A pure chain range takes every length once instead, as the envs draw them uniformly."""
    mix = parse_bodies(spec)
    if mix.chains_only and len(mix.items) == 1:
        lo, hi = mix.joint_range
        bodies = list(range(lo, hi + 1))
    else:
        rng = np.random.default_rng(seed)
        bodies = [mix.draw(rng) for _ in range(draws)]
    per_step: dict = {}  # seconds per control step of each distinct body

    def key(body) -> tuple:
        return ("walker", body_label(body)) if is_walker(body) else body_parents(body)

    # Each distinct body timed for a share of ~9 x ``seconds`` (a chain range's nine lengths' time), at least
    # 0.05 s: a random tree family draws many shapes.
    each = max(0.05, seconds * 9 / len({key(body) for body in bodies}))
    for body in bodies:
        if key(body) in per_step:
            continue
        if is_walker(body):
            per_step[key(body)] = 1.0 / walker_step_rate(body, each)
        elif isinstance(body, int):
            per_step[key(body)] = 4.0 / raw_step_rate(body, each)
        else:
            per_step[key(body)] = 4.0 / tree_step_rate(key(body), each)
    return 1.0 / np.mean([per_step[key(body)] for body in bodies])


def tree_step_rate(parents: tuple[int, ...], seconds: float) -> float:
    """mj_step/s of a swimmer tree (``raw_step_rate``'s loop on the tree's model)."""
    model = swimmer_model(parents)
    data = mujoco.MjData(model)
    data.ctrl[:] = np.random.default_rng(0).uniform(-1, 1, model.nu)
    return rate(lambda: mujoco.mj_step(model, data), seconds)


def walker_step_rate(body, seconds: float, chunk: int = 200) -> float:
    """Control steps/s of a walker's raw physics (a centipede, a generated legged body, a user's MJCF:
    ``mj_step`` x 5, no contact forces, reward or observation): chunks of ``chunk`` steps from the env's reset
    state under gentle random controls (so that it stays up, as bench_centipede.py), best of the chunks run in
    ``seconds``."""
    env = MorphCentipedeEnv(leg_pairs=body.leg_pairs) if isinstance(body, Centipede) else MorphCentipedeEnv(body=body)
    env.reset(seed=0)
    model, data = env.model, mujoco.MjData(env.model)
    qpos, qvel = env.data.qpos.copy(), env.data.qvel.copy()
    actions = np.random.default_rng(0).uniform(-0.3, 0.3, (chunk, model.nu))
    best, t_end = float("inf"), time.perf_counter() + seconds
    while time.perf_counter() < t_end or best == float("inf"):
        mujoco.mj_resetData(model, data)
        data.qpos[:], data.qvel[:] = qpos, qvel
        mujoco.mj_forward(model, data)
        t0 = time.perf_counter()
        for a in actions:
            data.ctrl[:] = a
            mujoco.mj_step(model, data, nstep=env.frame_skip)
        best = min(best, time.perf_counter() - t0)
    return chunk / best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iterations", type=int, default=4, help="timed training iterations per setting (>= 2)")
    parser.add_argument("--reference", type=Path, default=None, metavar="DIR",
                        help="a checkout of the paper's code, measured side by side")  # fmt: skip
    parser.add_argument("--reference-python", default=None, metavar="PY",
                        help="the Python that runs it (with its requirements installed)")  # fmt: skip
    parser.add_argument("--bracket", action="store_true",
                        help="run the reference again after the settings and print how far its rate moved "
                             "(a loaded machine's speed moves within a run)")  # fmt: skip
    parser.add_argument("--settings", type=int, nargs="+", default=None, metavar="K",
                        help="run only these settings (1-based, in the table's order)")  # fmt: skip
    parser.add_argument("--bodies", default=None, metavar="SPEC", nargs="+",
                        help="also train on these bodies (e.g. 2-10,random:3-10 centipede:2-4), data-parallel, "
                             "last, one setting each")  # fmt: skip
    parser.add_argument("--joint-features", type=int, default=0, metavar="N",
                        help="run each --bodies setting again with a policy reading N joint description "
                             "features (11: policy.joint_description): their cost, beside the same bodies "
                             "without")  # fmt: skip
    args = parser.parse_args()
    if args.reference is not None:
        if not (args.reference / "train.py").is_file():
            parser.error(f"--reference {args.reference}: no train.py there (a MorphologicalPPO checkout?)")
        if args.reference_python is None:
            parser.error("--reference needs --reference-python (a Python with the reference's requirements)")
    iterations = max(2, args.iterations)
    # Physics alone for the 2..10 mix (one core): mean time per control step over the lengths.
    raw = {"2-10": raw_mix_rate("2-10")}
    for spec in args.bodies or []:
        raw[spec] = raw_mix_rate(spec)
    reference = None
    if args.reference is not None:
        reference = reference_rate(args.reference, args.reference_python, iterations)
        print(f"reference (paper's code, this run): {reference:,.0f} env-steps/s")
    print("| setting | env-steps/s overall | rollout s/iter | update s/iter | share of raw physics (one core) | "
          "vs reference | warm-up s |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---:|")
    settings = [
        ("1 core (1 env thread, 1 torch thread)", 1, 1, 1),
        ("2 cores, paper config (2 env threads, 1 torch thread)", 1, 2, 1),
        ("2 cores (2 env threads, 2 torch threads)", 2, 2, 1),
        ("2 cores, 2 processes (data-parallel)", 1, 1, 2),
    ]
    chosen = [settings[k - 1] + ("",) for k in args.settings or range(1, len(settings) + 1)]
    chosen = [c + (0,) for c in chosen]
    for spec in args.bodies or []:
        chosen.append((f"2 cores, 2 processes, bodies {spec}", 1, 1, 2, spec, 0))
        if args.joint_features:
            chosen.append((f"2 cores, 2 processes, bodies {spec}, joint descriptions ({args.joint_features})", 1, 1, 2,
                           spec, args.joint_features))  # fmt: skip
    for label, tt, et, processes, bodies, joint_features in chosen:
        r = run(iterations, tt, et, processes, bodies, joint_features)
        ratio = f"{r['sps'] / reference:.1f}x" if reference else "not run"
        print(f"| {label} | {r['sps']:,.0f} | {r['rollout_s']:.2f} | {r['update_s']:.2f} | "
              f"{r['sps'] / raw[bodies or '2-10']:.2f} | {ratio} | {r['warmup_s']:.1f} |", flush=True)  # fmt: skip
    if reference is not None and args.bracket:
        after = reference_rate(args.reference, args.reference_python, iterations)
        mean = (reference + after) / 2
        print(f"\nreference again after the settings: {after:,.0f} env-steps/s ({after / reference:.2f}x the first); "
              f"against the mean of the two ({mean:,.0f}) each ratio above is {reference / mean:.2f}x what it says"
              + ("; the machine's speed moved more than 20% within the run: the ratios are not a claim"
                 if not 0.8 <= after / reference <= 1.25 else ""))  # fmt: skip
    for spec, rate_ in raw.items():
        print(f"\nraw MuJoCo for the bodies {spec}, one core: {rate_:,.0f} env-steps/s "
              f"(a rollout of 6,144 steps needs >= {6144 / rate_:.2f} s of physics)")  # fmt: skip


if __name__ == "__main__":
    main()
