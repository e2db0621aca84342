"""``bench_train.py`` of two checkouts of this repository side by side in one run: is a change slower?

    python bench/bench_checkouts.py BEFORE AFTER [--rounds 2] [--settings 1] [--iterations 4]

Runs each checkout's own ``bench/bench_train.py`` with its own packages (PYTHONPATH), alternating
BEFORE, AFTER, BEFORE, AFTER ... so that both see the same load on a shared machine (its speed drifts
from minute to minute), and prints each run's rates and the ratio AFTER / BEFORE of the medians.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
from pathlib import Path

PACKAGES = ("morph_core", "trainer", "morph_policy_node", "swimmer_sim_node", "morph_ros_util")


def bench(root: Path, settings: list[str], iterations: int) -> list[tuple[str, float, float, float]]:
    """(setting, env-steps/s, rollout s, update s) of each setting, from bench_train.py's table."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(str(root / "ros2_ws" / "src" / p) for p in PACKAGES)}
    cmd = [sys.executable, str(root / "bench" / "bench_train.py"), "--iterations", str(iterations),
           "--settings", *settings]  # fmt: skip
    out = subprocess.run(cmd, env=env, cwd=root / "bench", capture_output=True, text=True, check=True).stdout
    rows = []
    for line in out.splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if len(cells) >= 6 and cells[1].replace(",", "").isdigit():  # 6 columns before the warm-up's, 7 since
            rows.append((cells[0], float(cells[1].replace(",", "")), float(cells[2]), float(cells[3])))
    if not rows:
        raise SystemExit(f"no table in the output of {' '.join(cmd)}:\n{out}")
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("before", type=Path)
    parser.add_argument("after", type=Path)
    parser.add_argument("--rounds", type=int, default=2, help="runs of each checkout, alternating")
    parser.add_argument("--settings", nargs="+", default=["1"], help="bench_train.py's --settings")
    parser.add_argument("--iterations", type=int, default=4)
    args = parser.parse_args()
    results: dict[str, list] = {"before": [], "after": []}
    for r in range(args.rounds):
        for name in ("before", "after"):
            rows = bench(getattr(args, name).resolve(), args.settings, args.iterations)
            results[name].append(rows)
            for setting, sps, rollout_s, update_s in rows:
                print(f"round {r + 1} {name:6s} | {setting} | {sps:,.0f} env-steps/s | rollout {rollout_s:.2f} s | "
                      f"update {update_s:.2f} s", flush=True)  # fmt: skip
    for i, (setting, *_) in enumerate(results["before"][0]):
        med = {n: [statistics.median(rows[i][k] for rows in results[n]) for k in (1, 3)] for n in results}
        print(f"{setting}: after / before: env-steps/s {med['after'][0] / med['before'][0]:.3f}, "
              f"update s {med['after'][1] / med['before'][1]:.3f} (medians of {args.rounds} runs each)")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
