"""Env speed: MorphSwimmerEnv.step/s beside raw MuJoCo mj_step/s / frame_skip, same run, same core.

    python bench/bench_env.py [--seconds 2]

The ratio says how much the env adds on top of physics (target: >= 80%).
"""

from __future__ import annotations

import argparse
import time

import mujoco
import numpy as np

from morph_core.env.model import swimmer_model
from morph_core.env.swimmer_env import MorphSwimmerEnv


def rate(fn, seconds: float) -> float:
    """Calls per second of ``fn`` over roughly ``seconds`` (best of 3 windows, to dodge noise)."""
    best = 0.0
    for _ in range(3):
        n, t0 = 0, time.perf_counter()
        while (dt := time.perf_counter() - t0) < seconds / 3:
            for _ in range(100):
                fn()
            n += 100
        best = max(best, n / dt)
    return best


def raw_step_rate(num_joints: int, seconds: float) -> float:
    model = swimmer_model(num_joints)
    data = mujoco.MjData(model)
    data.ctrl[:] = np.random.default_rng(0).uniform(-1, 1, num_joints)
    return rate(lambda: mujoco.mj_step(model, data), seconds)


def env_step_rate(num_joints: int, seconds: float) -> float:
    env = MorphSwimmerEnv(num_joints=num_joints)
    env.reset(seed=0)
    action = np.random.default_rng(0).uniform(-1, 1, num_joints)
    return rate(lambda: env.step(action), seconds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=2.0, help="measuring time per figure")
    parser.add_argument("--joints", type=int, nargs="+", default=[2, 5, 10, 20])
    args = parser.parse_args()
    frame_skip = MorphSwimmerEnv().frame_skip
    print(f"| joints | env.step/s | raw mj_step/s | raw / {frame_skip} | env / (raw / {frame_skip}) |")
    print("|---:|---:|---:|---:|---:|")
    for n in args.joints:
        raw = raw_step_rate(n, args.seconds)
        env = env_step_rate(n, args.seconds)
        print(f"| {n} | {env:,.0f} | {raw:,.0f} | {raw / frame_skip:,.0f} | {env / (raw / frame_skip):.0%} |")


if __name__ == "__main__":
    main()
