"""Env speed: MorphSwimmerEnv.step/s beside raw MuJoCo mj_step/s / frame_skip, same run, same core.

    python bench/bench_env.py [--seconds 2]

The ratio says how much the env adds on top of physics (target: >= 80%). Then the vector env as training
steps it (6 swimmers of the 2..10 mix, padded observations out) against the same swimmers' raw physics and
against Gymnasium's ``step`` + ``pad_observations`` (how the vector env stepped them before ``advance``),
the three measured in turns.
"""

from __future__ import annotations

import argparse
import time

import mujoco
import numpy as np

from morph_core.env.model import swimmer_model
from morph_core.env.reward import applied_action
from morph_core.env.swimmer_env import MorphSwimmerEnv
from morph_core.env.vec_env import SwimmerVecEnv
from morph_core.policy.chains import pad_observations


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


def vector_rates(num_envs: int, joint_range: tuple[int, int], seconds: float, rounds: int = 5) -> dict[str, float]:
    """Env-steps/s of one vector step of ``num_envs`` swimmers three ways, best of ``rounds`` turns each."""
    vec = SwimmerVecEnv(num_envs, joint_range, seed=0, max_episode_steps=10**9)
    plain = [MorphSwimmerEnv(num_joints=env.num_joints) for env in vec.envs]
    for i, env in enumerate(plain):
        env.reset(seed=i)
    actions = np.random.default_rng(0).uniform(-1, 1, (num_envs, joint_range[1])).astype(np.float32)

    def gymnasium_step():
        obs = [env.step(applied_action(actions[i, : env.num_joints]))[0] for i, env in enumerate(plain)]
        pad_observations(obs, joint_range[1])

    def raw_physics():
        for env in vec.envs:
            mujoco.mj_step(env.model, env.data, nstep=env.frame_skip)

    ways = {"vector env (advance, rows in place)": lambda: vec.step(actions),
            "Gymnasium step, then pad": gymnasium_step,
            "raw physics": raw_physics}  # fmt: skip
    best = dict.fromkeys(ways, 0.0)
    for _ in range(rounds):
        for name, fn in ways.items():
            best[name] = max(best[name], num_envs * rate(fn, seconds / rounds))
    vec.close()
    return best


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
    rates = vector_rates(6, (2, 10), 3 * args.seconds)
    print("\n| 6 swimmers, 2..10 joints | env-steps/s | share of raw physics |\n|---|---:|---:|")
    for name, r in rates.items():
        print(f"| {name} | {r:,.0f} | {r / rates['raw physics']:.0%} |")


if __name__ == "__main__":
    main()
