"""Edge-conditioned convolution (NNConv) along chains and kinematic trees, dense and through PyTorch Geometric.

NNConv (Gilmer et al.; PyG's ``NNConv`` with ``aggr="add"``) updates node i as

    x_i' = W_root x_i + b + sum_{j -> i} x_j Theta(e_ji),   Theta(e) = reshape(W_e e + b_e, [C_in, C_out])

With the linear edge network used here, Theta is affine in e, so a message
is one matrix product of an outer product, with no per-edge weight matrix:

    x_j Theta(e) = [e_0 x_j, e_1 x_j, x_j] [A_0; A_1; B],    A_k, B from (W_e, b_e).

The batch arrives as one long sequence of links cut between samples
(``chains.PackedChains``), and slot k's joint always delivers its
torso-to-tail message to link k+1, its child: that direction is one shifted
add. In a chain the joint's parent is link k, so the tail-to-torso messages
are a second shifted add; in a tree the parent is ``sender[k]``
(``index_plan``), so the sender's features are gathered by that index and the
tail-to-torso messages scatter-added to it (several children share a parent).
A cut slot sends nothing (its [e, 1] is zero). A batch of chains keeps the
shifted adds (``sender`` None): the same result as the gather and
scatter-add with ``sender = arange``, ~6-8% cheaper eagerly and as fast in the
compiled update (``bench/bench_policy.py --trees``).
``ChainConv`` computes exactly PyG's result (tested to 1e-5) from the same
parameters with ``backend="dense"``; ``backend="pyg"`` runs PyG itself on the
joints as an explicit edge list and stays the reference.

Joint descriptions (``PolicyConfig.joint_features``, ``policy.joint_description``) are more edge attributes,
after the state: e = [angle, velocity, description]. They enter where the joint's state enters because a
message across a joint is what a joint does to the link beyond it, and the description says what the joint
is (where, about which axis, how strong, how far it reaches): the linear edge network makes each message a
bilinear function of the sender's features and [state, description], so the same network can send
different messages across a hip and a knee. Each joint's own head reads its child link (the actor head's
input), which receives the message across that joint in the first layer, so the joint's description
reaches its own action from the first layer on; the link embeddings (initially 1) need no other input.
With ``joint_features`` 0 the edge is [angle, velocity], the layer is exactly the one without descriptions.

Direction: the edge network sees only the joint state, so with one network
for both directions a link could not tell the joint ahead from the joint
behind, and the policy could not express which way a travelling wave runs
(measured: it does not learn to swim). Tail-to-torso messages therefore get
their own edge network, as relation types do in R-GCN; the torso-to-tail
network with the root weight and bias is exactly the paper's layer.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile

import torch
import torch.nn.functional as F
from torch import nn
from torch_geometric.nn import NNConv

from morph_core.constants import NUM_EDGE_FEATURES
from morph_core.policy import graph_forward
from morph_core.policy.config import BACKENDS
from morph_core.policy.graph_forward import ConvWeights, Graph


def _nnconv(in_channels: int, out_channels: int, root: bool, edge_features: int = NUM_EDGE_FEATURES) -> NNConv:
    edge_net = nn.Linear(edge_features, in_channels * out_channels)
    conv = NNConv(in_channels, out_channels, nn=edge_net, aggr="add", root_weight=root, bias=root)
    _remove_generated_source(NNConv)
    return conv


def _remove_generated_source(cls: type) -> None:
    """Delete the file PyG wrote ``cls``'s generated ``propagate`` module to. The first ``NNConv`` of a process
    renders that module from a template into a file of the temp directory, imports it and never deletes
    the file, so every process that built a policy left one in /tmp (hundreds a day from test runs). The
    module lives on in memory; only its source file goes (it serves TorchScript, which nothing here uses)."""
    module = sys.modules.get(f"{cls.__module__}_{cls.__name__}_propagate")  # PyG's name for it
    path = getattr(module, "__file__", None)
    if path and os.path.dirname(path) == tempfile.gettempdir():
        with contextlib.suppress(OSError):  # already gone, or not ours to delete
            os.unlink(path)


class ChainConv(nn.Module):
    """NNConv along cut chains or trees: x [L, C_in] links, edge_attr [L-1, E] slots, slot_mask [L-1],
    sender [L-1] (trees; None: chains) -> [L, C_out]. E = ``edge_features``: a joint's angle and velocity,
    then its description when the policy reads them (``PolicyConfig.joint_features``)."""

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        bidirectional: bool,
        backend: str = "dense",
        edge_features: int = NUM_EDGE_FEATURES,
    ):
        super().__init__()
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        self.backend = backend
        self.fwd = _nnconv(in_channels, out_channels, True, edge_features)  # torso-to-tail, root weight and bias
        self.bwd = _nnconv(in_channels, out_channels, False, edge_features) if bidirectional else None

    def weights(self) -> ConvWeights:
        """This layer in message form (``graph_forward``), from its parameters: gradients flow through."""
        bwd = None if self.bwd is None else message_weights(self.bwd)
        return ConvWeights(self.fwd.lin.weight.T, self.fwd.bias, message_weights(self.fwd), bwd)

    def forward(
        self, x: torch.Tensor, edge_attr: torch.Tensor, slot_mask: torch.Tensor, sender: torch.Tensor | None = None
    ) -> torch.Tensor:
        if self.backend == "pyg":
            return self._pyg(x, edge_attr, slot_mask, sender)
        return graph_forward.conv(TORCH_OPS, self.weights(), x, slot_coefficients(edge_attr, slot_mask), sender)

    def _pyg(
        self, x: torch.Tensor, edge_attr: torch.Tensor, slot_mask: torch.Tensor, sender: torch.Tensor | None
    ) -> torch.Tensor:
        """The same layer by PyG's NNConv, with the joints as an explicit edge list (reference path)."""
        slots = slot_mask.nonzero().squeeze(1)
        parent_child = torch.stack([slots if sender is None else sender[slots], slots + 1])
        attr = edge_attr[slots]
        out = self.fwd(x, parent_child, attr)
        if self.bwd is not None:
            out = out + self.bwd(x, parent_child.flip(0), attr)
        return out


def slot_coefficients(edge_attr: torch.Tensor, slot_mask: torch.Tensor) -> torch.Tensor:
    """[L-1, E+1] ``graph_forward.Graph.coef``: [e, 1] per slot, zero at cuts."""
    keep = slot_mask.unsqueeze(1).to(edge_attr.dtype)
    return torch.cat([edge_attr * keep, keep], dim=1)


def message_weights(conv: NNConv) -> torch.Tensor:
    """[(E+1) * C_in, C_out]: [A_0; A_1; B] from the linear edge network of a PyG NNConv."""
    edge_net: nn.Linear = conv.nn
    return graph_forward.edge_blocks(TORCH_OPS, edge_net.weight, edge_net.bias, conv.in_channels, conv.out_channels)


class TorchOps:
    """``graph_forward.ArrayOps`` in torch: what the update differentiates and compiles, and ONNX traces."""

    def first_layer(self, conv: ConvWeights, coef: torch.Tensor, sender: torch.Tensor | None) -> torch.Tensor:
        # The product with the links' input 1 is kept (NumPy skips it): its gradient sums as it always did.
        slots = coef.shape[0]
        x = coef.new_ones(slots + 1 if slots else 0, 1)  # an empty batch has no link
        return graph_forward.conv(self, conv, x, coef, sender)

    @staticmethod
    def outer(coef: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        # Column by column: scaling rows of a contiguous block is ~2x faster, both ways, than one
        # broadcast product over [S, E+1, C_in].
        return torch.cat([coef[:, k : k + 1] * x for k in range(coef.shape[1])], dim=1)

    @staticmethod
    def affine(x: torch.Tensor, root: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        return torch.addmm(bias, x, root)

    @staticmethod
    def add_to_parents(out: torch.Tensor, sender: torch.Tensor | None, messages: torch.Tensor) -> torch.Tensor:
        if sender is None:
            out[:-1] += messages
            return out
        return out.index_add(0, sender, messages)

    relu = staticmethod(torch.relu)
    concat = staticmethod(torch.cat)
    permute_dims = staticmethod(torch.permute)

    @staticmethod
    def relu_mlp(layers, x: torch.Tensor) -> torch.Tensor:
        for w, b in layers:  # torch's (weight [out, in], bias)
            x = torch.relu(F.linear(x, w, b))
        return x

    @staticmethod
    def tanh_mlp(layers, x: torch.Tensor) -> torch.Tensor:
        """Through tanh(u) = 2 sigmoid(2u) - 1 (``actor_critic.TanhMLP`` says why): the factors 2 and the -1
        go into the small weights, W (2s - 1) + b = (2W) s + (b - W 1)."""
        for i, (w, b) in enumerate(layers):
            if i > 0:  # the input is s = sigmoid(2u), the layer wants tanh(u) = 2s - 1
                w, b = 2.0 * w, b - w.sum(1)
            if i < len(layers) - 1:  # a tanh follows: compute sigmoid(2u)
                x = torch.sigmoid(F.linear(x, 2.0 * w, 2.0 * b))
            else:
                x = F.linear(x, w, b)
        return x

    @staticmethod
    def mean_per_sample(z: torch.Tensor, graph: Graph) -> torch.Tensor:
        if graph.joint_sample is None:  # one sample
            return z.mean(dim=0, keepdim=True)
        num_joints = graph.pool  # [B]
        pooled = z.new_zeros(num_joints.shape[0], z.shape[1]).index_add(0, graph.joint_sample, z)
        return pooled / num_joints.unsqueeze(1)


TORCH_OPS = TorchOps()
