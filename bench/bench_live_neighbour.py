"""What a CPU-bound neighbour costs K unpaced lockstep sim+policy pairs: the floor under any live trainer's cost.

    bash scripts/in_netns.sh .venv/bin/python bench/bench_live_neighbour.py [--pairs 1 2 4] [--duty 1.0 0.3]

The pairs run as in ``bench_live.py`` (the same Fast DDS profile, chains of 2..10 joints, sampling policies,
no trainer). Per K, their loop rate (env-steps/s from ``/clock``) is measured alone, then beside a neighbour
process that does nothing but compute, for each ``--duty`` (the share of each 10 ms it computes; it sleeps the
rest) and each scheduling policy: ``idle`` (Linux's SCHED_IDLE: it runs only when nothing else wants the core,
and any waking thread preempts it), ``nice19`` and ``normal``; then alone again. The cost is against the mean
of both rates alone; beside it, the CPU the neighbour got (seconds of CPU per second). A trainer is such a
neighbour with the pairs' messages to decode besides: what a neighbour of its CPU costs them, at whatever
priority, is a cost the trainer cannot get under. Prints a Markdown table. Not a timed test.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import rclpy
from bench_live import ClockCounter, _stop, start_pairs

POLICIES = ("idle", "nice19", "normal")
_NEIGHBOUR = """
import os, sys, time
policy, duty = sys.argv[1], float(sys.argv[2])
if policy == "idle":
    os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
elif policy == "nice19":
    os.nice(19)
while True:
    start = time.perf_counter()
    while time.perf_counter() - start < 0.01 * duty:
        pass
    if duty < 1:
        time.sleep(0.01 * (1 - duty))
"""


def measured(counter: ClockCounter, seconds: float, policy: str | None, duty: float) -> tuple[float, float]:
    """(loop rate, the neighbour's CPU seconds per second) over ``seconds``, beside a neighbour if ``policy``."""
    neighbour, start = None, time.monotonic()
    if policy is not None:
        neighbour = subprocess.Popen([sys.executable, "-c", _NEIGHBOUR, policy, str(duty)])
    try:
        counter.rate(1.0)  # settle
        rate = counter.rate(seconds)
    finally:
        if neighbour is not None:
            neighbour.kill()  # also when interrupted: it would compute forever
    if neighbour is None:
        return rate, 0.0
    _, _, usage = os.wait4(neighbour.pid, 0)  # reaped here, for its CPU use
    neighbour.returncode = -9
    return rate, (usage.ru_utime + usage.ru_stime) / (time.monotonic() - start)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--duty", type=float, nargs="+", default=[1.0])
    ap.add_argument("--policies", nargs="+", choices=POLICIES, default=list(POLICIES))
    ap.add_argument("--seconds", type=float, default=15.0, help="measuring window per phase")
    args = ap.parse_args()
    import morph_policy_node

    os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(morph_policy_node.FASTDDS_PROFILE))  # as bench_live
    rclpy.init()
    counter = ClockCounter()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in args.pairs:
            procs = []
            try:
                start_pairs([f"/neighbour{k}_{i}" for i in range(k)], Path(tmp), counter, procs)
                before, _ = measured(counter, args.seconds, None, 0.0)
                beside = [(p, d, *measured(counter, args.seconds, p, d)) for d in args.duty for p in args.policies]
                after, _ = measured(counter, args.seconds, None, 0.0)
            finally:
                _stop(procs)
            alone = (before + after) / 2
            for policy, duty, rate, cpu in beside:
                rows.append((k, before, after, policy, duty, cpu, rate, 1 - rate / alone))
            print(f"K = {k} done", file=sys.stderr, flush=True)
    print("| K | loop rate alone (before / after) | neighbour | duty | its CPU, s/s | loop rate beside it | cost |")
    print("|---|---:|---|---:|---:|---:|---:|")
    for k, before, after, policy, duty, cpu, rate, cost in rows:
        print(f"| {k} | {before:.0f} / {after:.0f} | {policy} | {duty:.1f} | {cpu:.2f} | {rate:.0f} | {cost:.0%} |")
    rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
