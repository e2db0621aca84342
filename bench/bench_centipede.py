"""Centipede env speed: MorphCentipedeEnv.step/s beside raw MuJoCo on the same compiled model, same run.

    python bench/bench_centipede.py [--sizes 2 4 8] [--seconds 6]

Per size, three loops in turns, each an episode chunk of 200 control steps from the same reset state under
the same gentle random actions (uniform +-0.3: the body stays up, no step pays a reset):
  env    ``env.step`` with graph observations (Ant-v5's task: contact forces, reward, health, observation dict)
  raw    ``mj_step(model, data, nstep=5)`` alone: the physics of one control step (Ant-v5's frame_skip)
  raw+f  the same plus ``mj_rnePostConstraint`` (the contact forces Ant-v5's contact cost reads)
Only the steps are timed (best of the rounds); ratios are env / raw.
"""

from __future__ import annotations

import argparse
import time

import mujoco
import numpy as np

from morph_core.env.centipede import MorphCentipedeEnv
from morph_core.env.centipede_model import centipede_model

CHUNK = 200


def _timed(step, actions) -> float:
    t0 = time.perf_counter()
    for a in actions:
        step(a)
    return time.perf_counter() - t0


def bench(leg_pairs: int, seconds: float, seed: int = 0) -> dict[str, float]:
    env = MorphCentipedeEnv(leg_pairs=leg_pairs)
    model = centipede_model(leg_pairs)
    data = mujoco.MjData(model)
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-0.3, 0.3, (CHUNK, 4 * leg_pairs))
    env.reset(seed=seed)
    qpos, qvel = env.data.qpos.copy(), env.data.qvel.copy()

    def restart_env():
        env.reset(seed=seed)

    def restart_raw():
        mujoco.mj_resetData(model, data)
        data.qpos[:], data.qvel[:] = qpos, qvel
        mujoco.mj_forward(model, data)

    def raw(a):
        data.ctrl[:] = a
        mujoco.mj_step(model, data, nstep=env.frame_skip)

    def raw_forces(a):
        raw(a)
        mujoco.mj_rnePostConstraint(model, data)

    def env_step(a):
        _, _, terminated, _, _ = env.step(a)
        if terminated:
            raise RuntimeError(f"centipede-{leg_pairs} fell under the bench's actions: the timing would mix resets")

    loops = {"env": (restart_env, env_step), "raw": (restart_raw, raw), "raw+f": (restart_raw, raw_forces)}
    best = dict.fromkeys(loops, float("inf"))
    t_end = time.perf_counter() + seconds
    while time.perf_counter() < t_end:
        for name, (restart, step) in loops.items():  # in turns: the machine's speed drifts
            restart()
            best[name] = min(best[name], _timed(step, actions))
    return {name: CHUNK / t for name, t in best.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[2, 4, 8])
    parser.add_argument("--seconds", type=float, default=6.0, help="per size")
    args = parser.parse_args()
    print(f"{'leg pairs':>9} {'joints':>6} {'env steps/s':>12} {'raw steps/s':>12} {'raw+f steps/s':>14} "
          f"{'env/raw':>8} {'env/raw+f':>10}")  # fmt: skip
    for n in args.sizes:
        r = bench(n, args.seconds)
        print(f"{n:>9} {4 * n:>6} {r['env']:>12,.0f} {r['raw']:>12,.0f} {r['raw+f']:>14,.0f} "
              f"{r['env'] / r['raw']:>8.2f} {r['env'] / r['raw+f']:>10.2f}")  # fmt: skip


if __name__ == "__main__":
    main()
