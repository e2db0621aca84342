"""Open-loop travelling-wave gait: a policy-free baseline that swims any chain."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from morph_core.env.swimmer_env import MorphSwimmerEnv


@dataclass(frozen=True)
class TravellingWave:
    """a_j(t) = amplitude * sin(2 pi frequency t - j * phase_lag), a wave running from head to tail."""

    amplitude: float = 1.0
    frequency: float = 0.5  # Hz
    phase_lag: float = 2 * np.pi / 5  # rad between neighbouring joints

    def __call__(self, t: float, num_joints: int) -> np.ndarray:
        j = np.arange(num_joints)
        return self.amplitude * np.sin(2 * np.pi * self.frequency * t - j * self.phase_lag)


def run_gait(num_joints: int, gait: TravellingWave, seconds: float, seed: int = 0) -> float:
    """Swim for ``seconds`` of sim time; return the mean forward speed of the torso (m/s)."""
    env = MorphSwimmerEnv(num_joints=num_joints)
    env.reset(seed=seed)
    x0 = float(env.data.qpos[0])
    steps = int(round(seconds / env.dt))
    for k in range(steps):
        env.step(gait(k * env.dt, num_joints))
    return (float(env.data.qpos[0]) - x0) / (steps * env.dt)
