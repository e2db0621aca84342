"""Batch-1 inference of a trained GraphActorCritic in NumPy, for controllers.

A node answers one chain at a time; for a network this small torch spends
most of a forward pass on per-operation overhead. This is the same
computation (``chain_conv``'s dense form) on NumPy arrays copied from the
torch model, tested equal to it to 1e-5. Training stays in torch.
"""

from __future__ import annotations

import numpy as np

from morph_core.policy import GraphActorCritic


def _linear(layer) -> tuple[np.ndarray, np.ndarray]:
    return layer.weight.detach().numpy().T.copy(), layer.bias.detach().numpy().copy()


def _edge_projection(conv) -> tuple[np.ndarray, int]:
    """[C_in, (E+1)*C_out]: the sender-side products [A_0 | A_1 | B] of an NNConv's linear edge network."""
    c_in, c_out = conv.in_channels, conv.out_channels
    a = conv.nn.weight.detach().numpy().reshape(c_in, c_out, -1)
    b = conv.nn.bias.detach().numpy().reshape(c_in, c_out, 1)
    return np.concatenate([a, b], axis=2).transpose(0, 2, 1).reshape(c_in, -1).copy(), c_out


class NumpyPolicy:
    """Deterministic mean action (and the log-std) of one chain."""

    def __init__(self, policy: GraphActorCritic):
        f = policy.features
        self.layers = []
        for conv in (f.conv1, f.conv2):
            fwd, c_out = _edge_projection(conv.fwd)
            bwd = _edge_projection(conv.bwd)[0] if conv.bwd is not None else None
            root = conv.fwd.lin.weight.detach().numpy().T.copy()
            self.layers.append((fwd, bwd, root, conv.fwd.bias.detach().numpy().copy(), c_out))
        self.global_mlp = [_linear(f.global_mlp[0]), _linear(f.global_mlp[2])]
        self.actor = [_linear(policy.actor_head[i]) for i in (0, 2, 4)]
        self.log_std = float(policy.log_std.detach())

    def mean(self, joint_pos: np.ndarray, joint_vel: np.ndarray, global_feats: np.ndarray) -> np.ndarray:
        """[N] mean action of a chain of N joints (torso to tail)."""
        n = joint_pos.shape[0]
        e = np.stack([joint_pos, joint_vel], axis=1).astype(np.float32)  # [N, 2]
        x = np.ones((n + 1, 1), dtype=np.float32)
        for fwd, bwd, root, bias, c_out in self.layers:
            out = x @ root + bias
            p = (x[:-1] @ fwd).reshape(n, 3, c_out)
            out[1:] += e[:, :1] * p[:, 0] + e[:, 1:] * p[:, 1] + p[:, 2]
            if bwd is not None:
                p = (x[1:] @ bwd).reshape(n, 3, c_out)
                out[:-1] += e[:, :1] * p[:, 0] + e[:, 1:] * p[:, 1] + p[:, 2]
            x = np.maximum(out, 0.0)
        (w1, b1), (w2, b2) = self.global_mlp
        g = np.maximum(np.maximum(global_feats.astype(np.float32) @ w1 + b1, 0.0) @ w2 + b2, 0.0)
        h = x[1:] + g
        (w1, b1), (w2, b2), (w3, b3) = self.actor
        h = np.tanh(h @ w1 + b1)
        h = np.tanh(h @ w2 + b2)
        return (h @ w3 + b3)[:, 0]
