"""Live training's cost to the pairs and what it collects, for K = 1, 2, 4 lockstep sim+policy pairs, in one run.

    bash scripts/in_netns.sh .venv/bin/python bench/bench_live.py [--pairs 1 2 4] [--seconds 30] [--out FILE]

Per K: the pairs start (chains of 2..10 joints, sampling policies), their loop rate is measured with no trainer
(env-steps/s summed over the pairs, counted from ``/clock``, which each sim publishes once per step: a listener
on one small topic, the same in both phases), then ``morph-train --live`` starts (the paper's batch of 6,144) and
the same rate is measured again over ``--updates`` updates after ``--warmup-updates`` (the first may wait for the
update to compile, the next work off the samples that came in meanwhile; a trainer that has not made them within
20 windows, falling behind on full cores, is measured over ``--seconds`` instead) and once more alone after the
trainer stops (the cost is against the mean of both, as the machine's speed drifts), beside the rate the trainer
collects over that window (its ``progress.csv``: env_steps between updates over wall time), its update time and
the CPU it used in the window (seconds per second, all its threads; ``bench_live_neighbour.py`` measures what that
much CPU costs the pairs from a process doing nothing else). Prints a Markdown table (and writes it to ``--out``).

``--ingest-only``: the trainer gets a batch no window fills (it subscribes, decodes and assembles, but never
updates), and the loop rate with it is measured over ``--seconds`` once every pair has joined: what listening
alone costs the pairs, apart from the update's CPU.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from morph_core.algo.run_dir import RunDir
from morph_core.protocol.trust import public_key_path
from morph_ros_util.processes import NodeProcess, start_node, stop_all, use_fastdds_profile
from trainer.live.bringup import run_key_pair

ROOT = Path(__file__).resolve().parents[1]


class ClockCounter:
    """Counts ``/clock`` messages (one per sim step, from every sim)."""

    def __init__(self):
        import rclpy
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rosgraph_msgs.msg import Clock

        self.node = rclpy.create_node("bench_live_clock")
        self.count = 0
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT)
        self.node.create_subscription(Clock, "/clock", self._on, qos)

    def _on(self, _msg) -> None:
        self.count += 1

    def rate(self, seconds: float) -> float:
        import rclpy

        end = time.monotonic() + seconds
        while time.monotonic() < end:  # settle
            rclpy.spin_once(self.node, timeout_sec=0.05)
            if self.count:
                break
        c0, t0 = self.count, time.monotonic()
        while time.monotonic() < t0 + seconds:
            rclpy.spin_once(self.node, timeout_sec=0.05)
        return (self.count - c0) / (time.monotonic() - t0)


def _collected(run: Path, first: int = 1) -> tuple[float, float, int]:
    """(env-steps/s collected from the end of update ``first`` to the last one, mean seconds of the updates in
    that window, updates so far)."""
    path = RunDir(run).progress
    rows = list(csv.DictReader(open(path))) if path.exists() else []
    window = rows[first - 1 :]
    if len(window) < 2:
        return float("nan"), float("nan"), len(rows)
    steps = int(window[-1]["env_steps"]) - int(window[0]["env_steps"])
    wall = float(window[-1]["wall_time"]) - float(window[0]["wall_time"])
    upd = sum(float(r["update_s"]) + float(r["prepare_s"]) for r in window[1:]) / (len(window) - 1)
    return steps / wall, upd, len(rows)


def _cpu_seconds(pid: int) -> float:
    """CPU seconds (user + system, all threads) a live process has used so far (Linux's /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime


def _joined(log: Path, k: int) -> bool:
    return log.exists() and log.read_text(errors="replace").count("is running") >= k


def work_key(work: Path) -> Path:
    """The signing key of the benchmark's trainers (``work/trainer_key``), made on first use."""
    key = work / "trainer_key"
    return key if key.exists() else run_key_pair(work)


def start_pairs(
    namespaces: list[str], work: Path, counter: ClockCounter, procs: list, real_time_factor: float = 0.0
) -> None:
    """A lockstep sim and a sampling policy node in each namespace (appended to ``procs``, so the caller
    stops them whatever happens), then waits until every loop runs. The nodes trust ``work``'s signing key
    (made here once), as the bring-up's nodes trust the run's."""
    key = work_key(work)
    for i, ns in enumerate(namespaces):
        sim = {"lockstep": "true", "real_time_factor": real_time_factor, "effort_timeout": 2.0, "min_joints": 2,
               "max_joints": 10, "seed": i, "episode_steps": 1000}  # fmt: skip
        name = ns.strip("/")
        procs.append(start_node("swimmer_sim_node.sim_node", ns, sim, work / f"sim_{name}.log"))
        policy = {"deterministic": "false", "seed": i, "checkpoint": "''", "allow_untrained": "true",
                  "trusted_keys": json.dumps([str(public_key_path(key))])}  # fmt: skip
        procs.append(start_node("morph_policy_node.policy_node", ns, policy, work / f"policy_{name}.log"))
    # Warm-up: every policy node up and the loops running (a lockstep sim alone re-sends a state every 2 s).
    deadline = time.monotonic() + 180
    while counter.rate(2.0) < 10 * len(namespaces) and time.monotonic() < deadline:
        pass


def bench(
    k: int,
    seconds: float,
    work: Path,
    counter: ClockCounter,
    updates: int,
    warmup: int,
    ingest_only: bool = False,
    trainer_args: tuple[str, ...] = (),
    real_time_factor: float = 0.0,
) -> dict:
    namespaces = [f"/bench{k}_{i}" for i in range(k)]
    procs = []
    try:
        start_pairs(namespaces, work, counter, procs, real_time_factor)
        alone = counter.rate(seconds)
        run = work / f"run{k}"
        # The update compiled as by default: the compiling ends before the measured window.
        cmd = [sys.executable, "-m", "trainer.cli.train", "--live", "--namespaces", *namespaces, "--out", str(run),
               "--tensorboard", "false", "--progress-bar", "false", "--signing-key", str(work_key(work))]  # fmt: skip
        cmd += trainer_args
        if ingest_only:
            cmd += ["--num-envs", "1", "--num-steps", "100000000"]
        trainer = NodeProcess(cmd, work / f"trainer{k}.log")
        procs.insert(0, trainer)
        if ingest_only:
            deadline = time.monotonic() + 20 * seconds
            while not _joined(work / f"trainer{k}.log", k) and time.monotonic() < deadline:
                counter.rate(1.0)
            cpu0, t0 = _cpu_seconds(trainer.pid), time.monotonic()
            with_trainer = counter.rate(seconds)
            trainer_cpu = (_cpu_seconds(trainer.pid) - cpu0) / (time.monotonic() - t0)
            collected, update_s, updates = float("nan"), float("nan"), 0
        else:
            # The loop rate with the trainer over the same window as the collection: from the end of update
            # ``warmup`` on. The first update waits for the update to compile (~25 s from the trainer's start),
            # and the next ones work off, back to back, the samples that came in meanwhile: neither is the
            # trainer's steady state.
            deadline = time.monotonic() + 20 * seconds
            while (done := _collected(run)[2]) < warmup and time.monotonic() < deadline:
                counter.rate(1.0)
            # A trainer that falls behind (the cores full) may not get there: then a window of ``seconds``.
            end = deadline if done >= warmup else time.monotonic() + seconds
            c0, cpu0, t0 = counter.count, _cpu_seconds(trainer.pid), time.monotonic()
            while _collected(run)[2] < warmup + updates and time.monotonic() < end:
                counter.rate(1.0)
            with_trainer = (counter.count - c0) / (time.monotonic() - t0)
            trainer_cpu = (_cpu_seconds(trainer.pid) - cpu0) / (time.monotonic() - t0)
            collected, update_s, total = _collected(run, warmup)
            updates = total - done  # in the window: fewer than asked if the deadline came first
        # The rate alone once more: the machine's speed drifts within minutes, so the cost is against both.
        trainer.stop()
        counter.rate(2.0)
        after = counter.rate(seconds)
    finally:
        stop_all(procs)
    return {"K": k, "alone": alone, "with": with_trainer, "after": after, "collected": collected,
            "update_s": update_s, "updates": updates, "trainer_cpu": trainer_cpu}  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--seconds", type=float, default=30.0, help="measuring window per phase")
    ap.add_argument("--updates", type=int, default=3, help="updates to measure the trainer over")
    ap.add_argument("--warmup-updates", type=int, default=4,
                    help="updates before the window (the first may wait for compiling; the next catch up)")  # fmt: skip
    ap.add_argument("--ingest-only", action="store_true", help="a trainer that never updates (listening alone)")
    ap.add_argument("--real-time-factor", type=float, default=0.0,
                    help="pace the sims (1: real time, 25 steps/s per pair; 4: a 100 Hz loop); 0: unpaced")  # fmt: skip
    ap.add_argument("--trainer-args", default="", help='more morph-train options, e.g. "--nice 0"')
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    import rclpy

    import morph_policy_node

    use_fastdds_profile(morph_policy_node.FASTDDS_PROFILE)
    rclpy.init()
    counter = ClockCounter()
    work = Path(tempfile.mkdtemp(prefix="bench_live_"))
    results = []
    try:
        for k in args.pairs:
            trainer_args = tuple(args.trainer_args.split())
            r = bench(
                k,
                args.seconds,
                work,
                counter,
                args.updates,
                args.warmup_updates,
                args.ingest_only,
                trainer_args,
                args.real_time_factor,
            )
            results.append(r)
            print(r, flush=True)
    finally:
        rclpy.try_shutdown()
    lines = [
        f"Live training, {os.cpu_count()} cores; env-steps/s summed over the K pairs (lockstep, sampling, 2..10 "
        + (f"joints, paced at {args.real_time_factor}x real time), " if args.real_time_factor else "joints, unpaced), ")
        + (
            "a trainer that listens and never updates."
            if args.ingest_only
            else "batch 6,144, updates in the trainer's worker thread."
        )
        + (f" Trainer options: {args.trainer_args}." if args.trainer_args else ""),
        "",
        "| K | loop rate, no trainer (before / after) | loop rate, trainer listening | cost | "
        "collected by the trainer | update (prepare + PPO) | updates in the window | trainer's CPU, s/s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        alone = (r["alone"] + r["after"]) / 2
        cost = 1 - r["with"] / alone if alone else float("nan")
        lines.append(f"| {r['K']} | {r['alone']:.0f} / {r['after']:.0f} | {r['with']:.0f} | {100 * cost:.0f}% | "
                     f"{r['collected']:.0f} | {r['update_s']:.2f} s | {r['updates']} | "
                     f"{r['trainer_cpu']:.2f} |")  # fmt: skip
    table = "\n".join(lines)
    print(table)
    if args.out:
        args.out.write_text(table + "\n")
    shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
