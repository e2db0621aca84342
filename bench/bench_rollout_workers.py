"""Rollout workers on Ray actors against the local helper processes, and gloo against shared memory for the
minibatch gradient, in one run on this machine.

    python bench/bench_rollout_workers.py [--iterations 4] [--compile] [--steps 300]

1. Training: ``morph-train`` at the paper's batch (6 swimmers x 1024 steps, minibatch 256, 10 epochs,
   chains of 2..10) with ``--processes 1``, ``--processes 2``, ``--rollout-workers 1`` and
   ``--rollout-workers 2`` (a local Ray of 2 CPUs), each in its own process, one after the other. A rate is
   env-steps/s by wall clock from the end of the first (warm-up) iteration to the end of the last, updates,
   logging and checkpoints included; with the rollout's and update's medians per iteration (on Ray workers
   the rollout is the learner's wait for their columns). Printed as ratios to ``--processes 1``.
2. Gradient peers: one minibatch step's exchange between two processes for the policy's gradient (its
   parameter count, float32), ``--steps`` times after a warm-up: gloo's ``all_reduce`` of it (what
   ``torch.distributed`` data parallelism would do per minibatch), against ``algo.data_parallel``'s path
   (the helper writes its gradient to shared memory and posts a semaphore, process 0 adds it and publishes
   the new parameters, the helper takes them after a second semaphore), both polled as training polls them.
   Medians and 90th percentiles in microseconds.
"""

from __future__ import annotations

import argparse
import csv
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from morph_core.algo.data_parallel import SharedArrays, take_spinning
from morph_core.algo.run_dir import RunDir
from morph_core.policy.actor_critic import GraphActorCritic, PolicyConfig

SETTINGS = {
    "--processes 1": ["--processes", "1"],
    "--processes 2": ["--processes", "2"],
    "--rollout-workers 1": ["--rollout-workers", "1"],
    "--rollout-workers 2": ["--rollout-workers", "2"],
}
RAY_INIT = "import ray; ray.init(num_cpus=2, include_dashboard=False, object_store_memory=200 * 1024**2)"


def train_rate(options: list[str], iterations: int, compile: bool, out: Path) -> dict:
    """Env-steps/s of one ``morph-train`` run (its own process) after its first iteration."""
    batch = 6 * 1024
    args = ["--out", str(out), "--total-timesteps", str(batch * (iterations + 1)), "--compile", str(compile).lower(),
            "--progress-bar", "false", "--tensorboard", "false", *options]  # fmt: skip
    # Ray workers: a local Ray of 2 CPUs and a small object store, started before morph-train would start its
    # own; the other settings run without Ray, as they do.
    ray = f"{RAY_INIT}; " if options[0] == "--rollout-workers" and int(options[1]) > 1 else ""
    code = f"import sys; {ray}from trainer.cli.train import main; sys.exit(main({args!r}))"
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True)
    with RunDir(out).progress.open() as f:
        rows = list(csv.DictReader(f))
    first, last = rows[0], rows[-1]
    steps = int(last["global_step"]) - int(first["global_step"])
    return {
        "rate": steps / (float(last["wall_time"]) - float(first["wall_time"])),
        "rollout": statistics.median(float(r["rollout_s"]) for r in rows[1:]),
        "update": statistics.median(float(r["update_s"]) for r in rows[1:]),
    }


def _gloo(rank: int, n: int, steps: int, port: int, out) -> None:
    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=2)
    grad, times = torch.randn(n), []
    for i in range(steps + 50):
        t = time.perf_counter()
        dist.all_reduce(grad)
        if i >= 50:
            times.append(time.perf_counter() - t)
        grad.mul_(0.5)  # keep the numbers finite
    if rank == 0:
        out.put(times)
    dist.barrier()
    dist.destroy_process_group()


def _shm_helper(name: str, layout: dict, done, go, steps: int) -> None:
    torch.set_num_threads(1)
    shared = SharedArrays(layout, name=name)
    grad, theta = torch.from_numpy(shared["grad"]), torch.from_numpy(shared["theta"])
    mine = torch.randn(len(grad))
    params = torch.empty_like(theta)
    for _ in range(steps + 50):
        grad.copy_(mine)  # its part's gradient, written where process 0 reads it
        done.release()
        take_spinning(go, lambda: None)
        params.copy_(theta)  # the new parameters, taken
    del grad, theta
    shared.close()


def shared_memory_times(n: int, steps: int) -> list[float]:
    """Process 0's wait from 'my part is done' to 'the helper's gradient is added and the parameters
    published' per step: the exchange ``algo.data_parallel`` makes once per minibatch step."""
    ctx = mp.get_context("spawn")
    layout = {"grad": ((n,), np.float32), "theta": ((n,), np.float32)}
    shared = SharedArrays(layout)
    done, go = ctx.Semaphore(0), ctx.Semaphore(0)
    proc = ctx.Process(target=_shm_helper, args=(shared.name, layout, done, go, steps))
    proc.start()
    grad_in, theta_out = torch.from_numpy(shared["grad"]), torch.from_numpy(shared["theta"])
    total, params, times = torch.zeros(n), torch.randn(n), []
    for i in range(steps + 50):
        t = time.perf_counter()
        take_spinning(done, lambda: None)
        total += grad_in
        theta_out.copy_(params)
        go.release()
        if i >= 50:
            times.append(time.perf_counter() - t)
    proc.join()
    del grad_in, theta_out
    shared.close(unlink=True)
    return times


def gloo_times(n: int, steps: int) -> list[float]:
    ctx = mp.get_context("spawn")
    out = ctx.SimpleQueue()
    port = 29500 + os.getpid() % 1000
    procs = [ctx.Process(target=_gloo, args=(rank, n, steps, port, out)) for rank in range(2)]
    for p in procs:
        p.start()
    times = out.get()
    for p in procs:
        p.join()
    return times


def _us(times: list[float]) -> str:
    return f"median {np.median(times) * 1e6:7.1f} us, p90 {np.percentile(times, 90) * 1e6:7.1f} us"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iterations", type=int, default=4, help="timed iterations per setting, after one")
    parser.add_argument("--compile", action="store_true", help="compile the update (~20 s more per setting)")
    parser.add_argument("--steps", type=int, default=300, help="timed exchanges of the gradient")
    parser.add_argument("--skip-training", action="store_true")
    args = parser.parse_args()

    n = sum(p.numel() for p in GraphActorCritic(PolicyConfig()).parameters())
    print(f"gradient: {n} float32 ({n * 4 / 1024:.0f} KiB), {args.steps} exchanges after 50")
    shm, gloo = shared_memory_times(n, args.steps), gloo_times(n, args.steps)
    print(f"  shared memory (data_parallel): {_us(shm)}")
    print(f"  gloo all_reduce              : {_us(gloo)}")
    print(f"  gloo / shared memory (medians): {np.median(gloo) / np.median(shm):.1f}x")
    if args.skip_training:
        return
    print(f"training: {args.iterations} timed iterations of 6,144 steps after one, compile={args.compile}")
    results = {}
    with tempfile.TemporaryDirectory() as d:
        for name, options in SETTINGS.items():
            out = Path(d) / name.strip("-").replace(" ", "_")
            r = results[name] = train_rate(options, args.iterations, args.compile, out)
            print(f"  {name:20s} {r['rate']:7.0f} env-steps/s  rollout {r['rollout']:.2f} s  "
                  f"update {r['update']:.2f} s", flush=True)  # fmt: skip
    base = results["--processes 1"]["rate"]
    print("ratios to --processes 1: " + ", ".join(f"{k} {v['rate'] / base:.2f}x" for k, v in results.items()))
    two = results["--rollout-workers 2"]["rate"] / results["--processes 2"]["rate"]
    print(f"--rollout-workers 2 / --processes 2: {two:.2f}x")


if __name__ == "__main__":
    main()
