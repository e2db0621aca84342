"""The layout of ``policy_info``: what a sampling policy says about each action, for a trainer.

On the wire it is a ``trajectory_msgs/JointTrajectory`` (a standard type every
tool can record and show) stamped with the state's stamp, with the state's
joint names and one point:

    positions      sampled action a (before any clip to the motors' range)
    velocities     Gaussian mean mu
    accelerations  log-std of each joint's Gaussian
    effort         each joint's term of the log-density, log N(a_j; mu_j, sigma_j^2)

so the action's log-probability is the sum of ``effort``. Nodes only copy
these arrays into and out of the message.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from morph_core.msgs.records import PolicyInfoRecord
from morph_core.policy.gaussian import log_density_per_joint


class PolicyInfoError(ValueError):
    """A ``policy_info`` whose fields do not fit the layout; ``str(err)`` is the reason."""


def pack_policy_info(action, mean, log_std) -> dict[str, np.ndarray]:
    """The point's four float64 arrays for one action; ``log_std`` a scalar or one per joint."""
    a = np.asarray(action, dtype=np.float64)
    mu = np.asarray(mean, dtype=np.float64)
    ls = np.broadcast_to(np.asarray(log_std, dtype=np.float64), a.shape).copy()
    return {
        "positions": a,
        "velocities": mu,
        "accelerations": ls,
        "effort": log_density_per_joint((a - mu) * np.exp(-ls), ls),
    }


def unpack_policy_info(
    log_ns: int,
    stamp_ns: int,
    names: Sequence[str],
    positions: Sequence[float],
    velocities: Sequence[float],
    accelerations: Sequence[float],
    effort: Sequence[float],
) -> PolicyInfoRecord:
    """A record from the message's fields; raises ``PolicyInfoError`` on lengths that differ or NaN/inf."""
    arrays = [np.asarray(x, dtype=np.float64) for x in (positions, velocities, accelerations, effort)]
    n = len(names)
    if n == 0 or any(x.shape != (n,) for x in arrays):
        raise PolicyInfoError(f"{n} joint names but array lengths {[x.size for x in arrays]}")
    if not all(np.isfinite(x).all() for x in arrays):
        raise PolicyInfoError("NaN or inf in policy_info")
    a, mu, ls, lp = arrays
    return PolicyInfoRecord(log_ns, stamp_ns, tuple(names), a, mu, ls, lp)
