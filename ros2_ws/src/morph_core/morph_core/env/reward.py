"""Swimmer-v5's reward, the one definition: the env steps with it, the topic trainer rebuilds it from messages.

    r = forward_weight * (x' - x) / dt - ctrl_cost_weight * sum_j a_j^2

``x`` and ``x'`` are the torso's world x before and after one control period
``dt`` (0.04 s: 4 physics steps of 0.01), ``a`` the action the env was
stepped with. In training that is the policy's sample clipped to the motors'
range (``applied_action``), as Stable-Baselines3 clips it before stepping
Swimmer-v5 in the paper's setup; every data source charges that same action
(the simulator loop, and transitions rebuilt from topics, where it is the
effort the sim reports as applied). Charging the unclipped sample instead makes
the cost unbounded once the policy's mean drifts beyond the range (a live run
charged so fell to returns of -340), and the sources would learn different tasks.
"""

from __future__ import annotations

import numpy as np

FORWARD_REWARD_WEIGHT = 1.0
CTRL_COST_WEIGHT = 1e-4
CTRL_LIMIT = 1.0
"""the motors' control range is [-CTRL_LIMIT, CTRL_LIMIT] (the MJCF's ctrlrange)"""


def applied_action(action) -> np.ndarray:
    """What the motors get of an action: clipped to the control range."""
    return np.asarray(action).clip(-CTRL_LIMIT, CTRL_LIMIT)  # the method: half np.clip's cost, the same values


def forward_velocity(x_before: float, x_after: float, dt: float) -> float:
    """Mean forward (world x) velocity of the torso over one control period."""
    return (x_after - x_before) / dt


def control_cost(action, ctrl_cost_weight: float = CTRL_COST_WEIGHT) -> float:
    """``ctrl_cost_weight * |a|^2`` (per row for a matrix of actions: the same sum as each row's alone)."""
    return ctrl_cost_weight * np.square(action).sum(axis=-1)  # the method: np.sum's wrapper costs more


def swimmer_reward(
    x_before: float,
    x_after: float,
    dt: float,
    action,
    forward_reward_weight: float = FORWARD_REWARD_WEIGHT,
    ctrl_cost_weight: float = CTRL_COST_WEIGHT,
) -> float:
    """Swimmer-v5's reward for one control period (see the module docstring); for many swimmers at once
    given arrays: torso positions (n,) and actions (n, joints)."""
    return forward_reward_weight * forward_velocity(x_before, x_after, dt) - control_cost(action, ctrl_cost_weight)
