"""The diagonal Gaussian policy's density: the one definition every other module uses.

Each joint's action is ``a_j = mu_j + sigma * z_j`` with ``z_j ~ N(0, 1)``, so
its log-density is ``-z_j^2 / 2 - log sigma - log(2 pi) / 2`` and the
action's is the sum over the chain's joints. The functions take the
standardised deviation ``z`` and work unchanged on NumPy arrays and torch
tensors (plain arithmetic only), so the torch policy, its NumPy twin, the
policy node's ``policy_info`` and the theory's Monte Carlo share them.
"""

from __future__ import annotations

import math

LOG_2PI = math.log(2 * math.pi)
HALF_LOG_2PI = 0.5 * LOG_2PI


def log_density_per_joint(z, log_std):
    """Per-joint log-density ``-z^2/2 - log sigma - log(2 pi)/2`` of standardised deviations ``z``."""
    return -0.5 * (z * z) - log_std - HALF_LOG_2PI


def log_density_from_norm(squared_norm, num_joints, log_std):
    """Log-density of a whole action from ``|z|^2`` over its ``num_joints`` joints (the sum of the
    per-joint terms, in the order a sampler that knows its own noise computes it)."""
    return -0.5 * squared_norm - num_joints * (log_std + HALF_LOG_2PI)


def entropy_per_joint(log_std):
    """Entropy of one joint's Gaussian, ``(1 + log(2 pi)) / 2 + log sigma``."""
    return 0.5 * (1.0 + LOG_2PI) + log_std
