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

Ant-v5's task, the centipedes' (``env.centipede``), is at the end: ``ant_reward`` and its constants.
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


# -- Ant-v5's locomotion task: the centipedes' (``env.centipede``) ---------------------------------------------
# Gymnasium's Ant-v5 defaults, the task every centipede is paid by, per control period of
# ANT_FRAME_SKIP x 0.01 s (0.05 s):
#     r = forward_weight * vx + healthy_reward * healthy - ctrl_cost_weight * sum_i a_i^2
#         - contact_cost_weight * sum clip(cfrc_ext, lo, hi)^2
# vx: the root body's world x (its ``xpos``, as MuJoCo left it after the step) before and after, over the
# period; healthy: the state finite and the root's z in ANT_HEALTHY_Z_RANGE (an unhealthy state ends the
# episode); cfrc_ext: every body's external (contact) wrench, from mj_rnePostConstraint (the world's row is
# zero, and summed all the same, as Ant-v5 sums it: the sum's rounding is then Ant-v5's).
# The costs grow with the body (4 actuators per leg pair, 6 contact-force entries per body), as Ant-v5's
# would if it had more legs; the healthy reward does not.
ANT_FRAME_SKIP = 5
ANT_FORWARD_REWARD_WEIGHT = 1.0
ANT_CTRL_COST_WEIGHT = 0.5
ANT_CONTACT_COST_WEIGHT = 5e-4
"""Ant-v5's default (Ant-v4 had its contact forces at zero under MuJoCo >= 2, v5 counts them)"""
ANT_HEALTHY_REWARD = 1.0
ANT_HEALTHY_Z_RANGE = (0.2, 1.0)
ANT_CONTACT_FORCE_RANGE = (-1.0, 1.0)
ANT_RESET_NOISE_SCALE = 0.1


def ant_reward(
    x_velocity: float,
    healthy: bool,
    ctrl,
    cfrc_ext,
    forward_reward_weight: float = ANT_FORWARD_REWARD_WEIGHT,
    healthy_reward: float = ANT_HEALTHY_REWARD,
    ctrl_cost_weight: float = ANT_CTRL_COST_WEIGHT,
    contact_cost_weight: float = ANT_CONTACT_COST_WEIGHT,
    contact_force_range: tuple[float, float] = ANT_CONTACT_FORCE_RANGE,
) -> tuple[float, dict[str, float]]:
    """Ant-v5's reward and its terms (Ant-v5's ``reward_*`` info keys) for one control period, computed in
    Ant-v5's order of operations (so equal bit for bit given the same numbers): ``ctrl`` the actuators' controls
    in the model's actuator order (Ant-v5's action), ``cfrc_ext`` [bodies, 6], the world's row included."""
    forward = x_velocity * forward_reward_weight
    survive = healthy * healthy_reward
    ctrl_cost = ctrl_cost_weight * np.square(ctrl).sum()
    contact_cost = contact_cost_weight * np.square(np.clip(cfrc_ext, *contact_force_range)).sum()
    reward = (forward + survive) - (ctrl_cost + contact_cost)
    terms = {"reward_forward": forward, "reward_ctrl": -ctrl_cost, "reward_contact": -contact_cost,
             "reward_survive": survive}  # fmt: skip
    return reward, terms
