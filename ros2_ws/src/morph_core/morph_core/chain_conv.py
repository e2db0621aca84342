"""Edge-conditioned convolution (NNConv) along padded chains, dense and through PyTorch Geometric.

NNConv (Gilmer et al.; PyG's ``NNConv`` with ``aggr="add"``) updates node i as

    x_i' = W_root x_i + b + sum_{j -> i} x_j Theta(e_ji),   Theta(e) = reshape(W_e e + b_e, [C_in, C_out])

With the linear edge network used here, Theta is affine in e, so each
message splits into node-wise products that need no per-edge weight matrix:

    x_j Theta(e) = e_0 (x_j A_0) + e_1 (x_j A_1) + x_j B,    [A_0 | A_1 | B] from (W_e, b_e).

On a chain the neighbours of link i are links i-1 and i+1, so aggregation is
two shifted adds. ``ChainConv`` computes exactly PyG's result (tested to
1e-5) from the same parameters with ``backend="dense"``; ``backend="pyg"``
runs PyG itself and stays the reference.

Direction: the edge network sees only the joint state, so with one network
for both directions a link could not tell the joint ahead from the joint
behind, and the policy could not express which way a travelling wave runs
(measured: it does not learn to swim). Tail-to-torso messages therefore get
their own edge network, as relation types do in R-GCN; the torso-to-tail
network with the root weight and bias is exactly the paper's layer.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn
from torch_geometric.nn import NNConv

from morph_core.graph import NUM_EDGE_FEATURES

BACKENDS = ("dense", "pyg")


def _nnconv(in_channels: int, out_channels: int, root: bool) -> NNConv:
    edge_net = nn.Linear(NUM_EDGE_FEATURES, in_channels * out_channels)
    return NNConv(in_channels, out_channels, nn=edge_net, aggr="add", root_weight=root, bias=root)


class ChainConv(nn.Module):
    """NNConv over padded chains: x [B, J+1, C_in] links, edge_attr [B, J, E] joints, mask [B, J] -> [B, J+1, C_out]."""

    def __init__(self, in_channels: int, out_channels: int, bidirectional: bool, backend: str = "dense"):
        super().__init__()
        if backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
        self.backend = backend
        self.fwd = _nnconv(in_channels, out_channels, root=True)  # torso-to-tail, with root weight and bias
        self.bwd = _nnconv(in_channels, out_channels, root=False) if bidirectional else None

    def forward(self, x: torch.Tensor, edge_attr: torch.Tensor, joint_mask: torch.Tensor) -> torch.Tensor:
        if self.backend == "pyg":
            return self._pyg(x, edge_attr, joint_mask)
        keep = joint_mask.unsqueeze(-1).to(x.dtype)
        e = (edge_attr * keep).unsqueeze(-1)  # [B, J, E, 1]; padded joints send nothing
        # Link j -> link j+1 across joint j.
        agg = F.pad(self._messages(self.fwd, x[:, :-1], e, keep), (0, 0, 1, 0))
        if self.bwd is not None:
            # Link j+1 -> link j across joint j.
            agg = agg + F.pad(self._messages(self.bwd, x[:, 1:], e, keep), (0, 0, 0, 1))
        return agg + self.fwd.lin(x) + self.fwd.bias

    @staticmethod
    def _messages(conv: NNConv, src: torch.Tensor, e: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
        """sum_k e_k (x_src A_k) + x_src B for every joint, from one matmul of the senders."""
        c_in, c_out = conv.in_channels, conv.out_channels
        edge_net: nn.Linear = conv.nn
        # W_e: [C_in*C_out, E] -> [C_in, C_out, E]; the (in, out) order of PyG's view(-1, C_in, C_out).
        a = edge_net.weight.view(c_in, c_out, -1)
        proj = torch.cat([a.permute(0, 2, 1).reshape(c_in, -1), edge_net.bias.view(c_in, c_out)], dim=1)
        p = (src @ proj).view(*src.shape[:-1], -1, c_out)  # [B, J, E+1, C_out]
        return (e * p[:, :, :-1]).sum(dim=2) + p[:, :, -1] * keep

    def _pyg(self, x: torch.Tensor, edge_attr: torch.Tensor, joint_mask: torch.Tensor) -> torch.Tensor:
        """The same layer by PyG's NNConv on the flattened graph (reference path)."""
        (parent, child), link_mask, bj = chain_edges(joint_mask)
        attr = edge_attr[bj[0], bj[1]]
        x_flat = x[link_mask]
        out_flat = self.fwd(x_flat, torch.stack([parent, child]), attr)
        if self.bwd is not None:
            out_flat = out_flat + self.bwd(x_flat, torch.stack([child, parent]), attr)
        out = x.new_zeros(*link_mask.shape, self.fwd.out_channels)
        out[link_mask] = out_flat
        return out


def chain_edges(joint_mask: torch.Tensor) -> tuple[tuple[torch.Tensor, torch.Tensor], torch.Tensor, torch.Tensor]:
    """Flatten padded chains into one graph: ((parent, child) link ids per valid joint, link_mask, (graph, joint))."""
    b, j = joint_mask.shape
    num_joints = joint_mask.sum(dim=1)
    link_mask = torch.arange(j + 1).unsqueeze(0) <= num_joints.unsqueeze(1)
    link_id = torch.cumsum(link_mask.flatten(), 0).view(b, j + 1) - 1  # row-major numbering of valid links
    bj = joint_mask.nonzero().T
    return (link_id[bj[0], bj[1]], link_id[bj[0], bj[1] + 1]), link_mask, bj
