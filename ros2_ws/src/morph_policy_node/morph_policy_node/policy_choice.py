"""Which policy the node runs, from its parameters; no ROS, no torch.

A checkpoint that was asked for is loaded or refused, never replaced by
something else: a node that cannot load it stops at start-up, and a running
node keeps its current policy. An untrained policy runs only when asked for
explicitly (``checkpoint`` empty and ``allow_untrained`` true), and the node
then marks every effort message (``UNTRAINED_LABEL``). What the policy answers,
and how, is ``morph_core.protocol.controller``'s.
"""

from __future__ import annotations

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
