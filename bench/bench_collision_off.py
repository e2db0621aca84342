"""MuJoCo's step of the swimmer with collision detection on (as swimmer.xml) and off (as ``env.model`` builds it).

    python bench/bench_collision_off.py [--joints 2 5 10 20] [--rounds 8] [--steps 3000]

No geom of the swimmer can collide, so switching detection off leaves every trajectory bit for bit (checked
here too); what it saves is MuJoCo's collision stage itself. Per chain length: ``--rounds`` timings of
``--steps`` steps of each model, in turns (on first, then off first), same controls; prints the medians
(µs per ``mj_step``) and their ratio. Not a timed test.
"""

from __future__ import annotations

import argparse
import copy
import time

import mujoco
import numpy as np

from morph_core.env.model import swimmer_model

_CONTACT = int(mujoco.mjtDisableBit.mjDSBL_CONTACT)


def with_detection(num_joints: int) -> mujoco.MjModel:
    """A copy of the swimmer model with collision detection back on (the cached model stays as it is)."""
    model = copy.copy(swimmer_model(num_joints))
    model.opt.disableflags &= ~_CONTACT
    return model


def timed(model: mujoco.MjModel, controls: np.ndarray) -> tuple[float, np.ndarray]:
    """(µs per step, final qpos) of stepping ``model`` through ``controls`` from its initial state."""
    data = mujoco.MjData(model)
    start = time.perf_counter()
    for ctrl in controls:
        data.ctrl[:] = ctrl
        mujoco.mj_step(model, data)
    return (time.perf_counter() - start) / len(controls) * 1e6, data.qpos.copy()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--joints", type=int, nargs="+", default=[2, 5, 10, 20])
    ap.add_argument("--rounds", type=int, default=8)
    ap.add_argument("--steps", type=int, default=3000)
    args = ap.parse_args()
    print("| joints | detection on, µs/step | off (the model), µs/step | off / on |")
    print("|---:|---:|---:|---:|")
    for n in args.joints:
        models = {"on": with_detection(n), "off": swimmer_model(n)}
        # sinusoids reach the joint limits, so the constraint solver works as in training
        controls = np.sin(np.arange(args.steps)[:, None] * 0.05 + np.arange(n))
        times, final = {"on": [], "off": []}, {}
        for r in range(args.rounds):
            for label in ("on", "off") if r % 2 == 0 else ("off", "on"):
                us, final[label] = timed(models[label], controls)
                times[label].append(us)
        if not np.array_equal(final["on"], final["off"]):
            raise SystemExit(f"{n} joints: the trajectories differ with detection on and off")
        a, b = np.median(times["on"]), np.median(times["off"])
        print(f"| {n} | {a:.2f} | {b:.2f} | {b / a:.3f} |")


if __name__ == "__main__":
    main()
