"""The NumPy forward pass as a node and a rollout call it, per call: median and p99 in microseconds.

    python bench/bench_forward.py                                   # this checkout
    python bench/bench_forward.py --checkouts BEFORE AFTER [--rounds 3]

A node answers one body per state message (``NumpyPolicy.mean``: a 7-joint chain, a 12-joint legged tree
with joint descriptions); a rollout steps six swimmers at once (``NumpyPolicy.act`` on chains of 2..10).
With ``--checkouts`` each checkout's packages (PYTHONPATH) run this same script in turn, alternating
BEFORE, AFTER, ... so that both see the same load, and the table gives AFTER / BEFORE of the medians.
The compiled update and the rollout as a whole are ``bench_checkouts.py``'s.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

PACKAGES = ("morph_core", "trainer", "morph_policy_node", "swimmer_sim_node", "morph_ros_util")
CALLS = 3000


def _times(fn, calls: int = CALLS) -> tuple[float, float]:
    """(median, p99) of ``calls`` calls of ``fn``, in microseconds, after 200 warm-up calls."""
    for _ in range(200):
        fn()
    samples = []
    for _ in range(calls):
        t = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - t)
    samples.sort()
    return 1e6 * statistics.median(samples), 1e6 * samples[int(0.99 * len(samples))]


def measure() -> dict[str, tuple[float, float]]:
    """The cases of this checkout's ``NumpyPolicy`` (imported from PYTHONPATH)."""
    from morph_core.policy.config import PolicyConfig
    from morph_core.policy.numpy_actor import NumpyPolicy
    from morph_core.policy.weights import untrained_weights

    rng = np.random.default_rng(0)
    swimmer = NumpyPolicy(untrained_weights(PolicyConfig(), seed=1))
    legged = NumpyPolicy(untrained_weights(PolicyConfig(global_features=12, joint_features=11), seed=1))
    chain = [rng.standard_normal(7).astype(np.float32) for _ in range(2)] + [rng.standard_normal(4)]
    parents = np.array([-1, 0, 1, -1, 3, 4, -1, 6, 7, -1, 9, 10])  # four legs of three joints
    tree = [rng.standard_normal(12).astype(np.float32) for _ in range(2)] + [rng.standard_normal(12)]
    desc = rng.standard_normal((12, 11)).astype(np.float32)
    n = np.array([2, 4, 6, 8, 10, 5], dtype=np.int64)
    pos, vel = rng.standard_normal((2, 6, 10)).astype(np.float32) * (np.arange(10) < n[:, None])
    glob, noise = rng.standard_normal((6, 4)).astype(np.float32), rng.standard_normal((6, 10)).astype(np.float32)
    return {
        "node: 7-joint chain": _times(lambda: swimmer.mean(*chain)),
        "node: 12-joint tree, descriptions": _times(lambda: legged.mean(*tree, parents=parents, joint_desc=desc)),
        "rollout: 6 chains of 2..10, act": _times(lambda: swimmer.act(pos, vel, glob, n, noise)),
    }


def _run_checkout(root: Path) -> dict[str, tuple[float, float]]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(str(root / "ros2_ws" / "src" / p) for p in PACKAGES)}
    out = subprocess.run([sys.executable, __file__, "--json"], env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkouts", nargs=2, type=Path, metavar=("BEFORE", "AFTER"))
    parser.add_argument("--rounds", type=int, default=3, help="runs of each checkout, alternating")
    parser.add_argument("--json", action="store_true", help=argparse.SUPPRESS)  # one checkout's figures
    args = parser.parse_args()
    if args.json:
        print(json.dumps(measure()))
        return 0
    if args.checkouts is None:
        print("| case | median µs | p99 µs |\n|---|---:|---:|")
        for case, (med, p99) in measure().items():
            print(f"| {case} | {med:.1f} | {p99:.1f} |")
        return 0
    runs: dict[str, list[dict]] = {"before": [], "after": []}
    for _ in range(args.rounds):
        for name, root in zip(("before", "after"), args.checkouts, strict=True):
            runs[name].append(_run_checkout(root.resolve()))
    print(f"{args.rounds} runs of each, alternating; medians of the runs' medians and p99s")
    print("| case | before median µs | after median µs | after/before | before p99 µs | after p99 µs |")
    print("|---|---:|---:|---:|---:|---:|")
    for case in runs["before"][0]:
        b = [statistics.median(r[case][i] for r in runs["before"]) for i in (0, 1)]
        a = [statistics.median(r[case][i] for r in runs["after"]) for i in (0, 1)]
        print(f"| {case} | {b[0]:.1f} | {a[0]:.1f} | {a[0] / b[0]:.3f} | {b[1]:.1f} | {a[1]:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
