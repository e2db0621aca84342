"""Which policy the node runs, from its parameters; no ROS, no torch.

A checkpoint that was asked for is loaded or refused, never replaced by
something else: a node that cannot load it stops at start-up, and a running
node keeps its current policy. An untrained policy runs only when asked for
explicitly (``checkpoint`` empty and ``allow_untrained`` true), and the node
then marks every effort message (``UNTRAINED_LABEL``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.weights import CheckpointError, PolicyWeights, load_checkpoint, untrained_weights

UNTRAINED_LABEL = "untrained_policy"
"""label of an extra ``layout.dim`` (size 1, stride 1: the efforts as an N x 1 array) on every effort
message of an untrained policy, so a recording shows where its efforts came from"""


def choose_policy(checkpoint: str, allow_untrained: bool, seed: int) -> PolicyWeights:
    """The weights for ``checkpoint`` ('' = untrained, only with ``allow_untrained``).

    Raises ``CheckpointError`` naming the file (or the empty checkpoint) and the reason.
    """
    if checkpoint:
        return load_checkpoint(checkpoint)
    if not allow_untrained:
        raise CheckpointError(
            "''",
            "no policy file given; an untrained policy runs only with allow_untrained:=true",
        )
    return untrained_weights(seed=seed)


EFFORT_ORDERS = ("state", "description")
"""``effort_order`` values: efforts in the order of the state's names they answer, or in the description's
(depth-first) order of its actuated joints"""


class EffortOrderError(ValueError):
    """An ``effort_order`` parameter that is none of ``EFFORT_ORDERS``."""


def effort_order(value: object) -> str:
    """``value`` if it is one of ``EFFORT_ORDERS``; ``EffortOrderError`` naming the choices otherwise."""
    if value not in EFFORT_ORDERS:
        raise EffortOrderError(f"effort_order must be one of {', '.join(EFFORT_ORDERS)}; got {str(value)[:60]!r}")
    return value


class PolicyOutputError(ValueError):
    """The policy's output for a state is not finite: the state is rejected, nothing is published."""


@dataclass(frozen=True)
class Answer:
    efforts: np.ndarray
    """float64 [N], clipped to the motors' [-1, 1]"""
    action: np.ndarray | None
    """the sample before the clip (sampling only)"""
    mean: np.ndarray | None
    """the Gaussian mean (sampling only)"""


def answer(
    policy: NumpyPolicy,
    pos: np.ndarray,
    vel: np.ndarray,
    glob: np.ndarray,
    rng: np.random.Generator | None,
    parents: np.ndarray | None = None,
) -> Answer:
    """Efforts for one robot: the mean (``rng`` None) or a sample, its joints in tree order (``parents``, the
    tree's; None: a chain). Raises ``PolicyOutputError`` if the policy's output is NaN or inf (finite weights
    can still overflow float32): a clip would turn inf into a full-scale command."""
    with np.errstate(over="ignore", invalid="ignore"):  # reported below as one rejection, not a warning
        if rng is None:
            action, mean = policy.mean(pos, vel, glob, parents).astype(np.float64), None
        else:
            action, mean = policy.sample(pos, vel, glob, rng, parents)
    if not np.isfinite(action).all() or (mean is not None and not np.isfinite(mean).all()):
        raise PolicyOutputError("the policy's output for this state is not finite")
    return Answer(np.clip(action, -1.0, 1.0), None if mean is None else action, mean)
