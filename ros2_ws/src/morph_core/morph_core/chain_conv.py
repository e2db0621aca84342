"""Edge-conditioned convolution (NNConv) on padded chains, dense and through PyTorch Geometric.

NNConv (Gilmer et al.; PyG's ``NNConv`` with ``aggr="add"``) updates node i as

    x_i' = W_root x_i + b + sum_{j -> i} x_j Theta(e_ji),   Theta(e) = reshape(W_e e + b_e, [C_in, C_out])

With the linear edge network used here, Theta is affine in e, so each
message splits into node-wise products that need no per-edge weight matrix:

    x_j Theta(e) = e_0 (x_j A_0) + e_1 (x_j A_1) + x_j B,    [A_0 | A_1 | B] from (W_e, b_e).

On a chain the neighbours of link i are links i-1 and i+1, so aggregation is
two shifted adds. ``dense_chain_conv`` computes exactly PyG's result (tested
to 1e-5) from the same parameters; ``pyg_chain_conv`` runs PyG itself and
stays the reference.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch_geometric.nn import NNConv

from morph_core.graph import NUM_EDGE_FEATURES


def make_nnconv(in_channels: int, out_channels: int) -> NNConv:
    """PyG NNConv whose edge network is one linear layer on the joint state (the paper's layer)."""
    edge_net = torch.nn.Linear(NUM_EDGE_FEATURES, in_channels * out_channels)
    return NNConv(in_channels, out_channels, nn=edge_net, aggr="add", root_weight=True, bias=True)


def dense_chain_conv(
    conv: NNConv, x: torch.Tensor, edge_attr: torch.Tensor, joint_mask: torch.Tensor, bidirectional: bool
) -> torch.Tensor:
    """NNConv over padded chains.

    x: [B, J+1, C_in] link features; edge_attr: [B, J, E] joint states;
    joint_mask: [B, J] valid joints. Returns [B, J+1, C_out].
    """
    c_in, c_out = conv.in_channels, conv.out_channels
    edge_net: torch.nn.Linear = conv.nn
    # W_e: [C_in*C_out, E] -> [C_in, C_out, E]; same (in, out) order as PyG's view(-1, C_in, C_out).
    a = edge_net.weight.view(c_in, c_out, -1)
    b = edge_net.bias.view(c_in, c_out)
    # One matmul gives every link's products with A_0, A_1 and B: [B, J+1, E+1, C_out].
    proj = torch.cat([a.permute(0, 2, 1).reshape(c_in, -1), b], dim=1)
    p = (x @ proj).view(*x.shape[:-1], -1, c_out)
    # Zeroing the padded joints' attributes and constant term silences their messages.
    keep = joint_mask.unsqueeze(-1).to(x.dtype)
    e = (edge_attr * keep).unsqueeze(-1)  # [B, J, E, 1]

    def messages(src: torch.Tensor) -> torch.Tensor:  # src: [B, J, E+1, C_out] products of the sending links
        return (e * src[:, :, :-1]).sum(dim=2) + src[:, :, -1] * keep

    # Torso-to-tail messages: link j -> link j+1 across joint j.
    agg = F.pad(messages(p[:, :-1]), (0, 0, 1, 0))
    if bidirectional:
        # Tail-to-torso messages: link j+1 -> link j across joint j.
        agg = agg + F.pad(messages(p[:, 1:]), (0, 0, 0, 1))
    return agg + conv.lin(x) + conv.bias


def chain_edge_index(joint_mask: torch.Tensor, bidirectional: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Flatten padded chains into one PyG graph.

    Returns (edge_index [2, E], link_mask [B, J+1], joint_b_j [2, J_valid]) where the
    valid links are numbered in row-major order and joint k's edges come first
    torso-to-tail, then (if bidirectional) tail-to-torso.
    """
    b, j = joint_mask.shape
    num_joints = joint_mask.sum(dim=1)
    link_mask = torch.arange(j + 1).unsqueeze(0) <= num_joints.unsqueeze(1)
    link_id = torch.cumsum(link_mask.flatten(), 0).view(b, j + 1) - 1
    bj = joint_mask.nonzero().T  # [2, J_valid]: (graph, joint)
    parent, child = link_id[bj[0], bj[1]], link_id[bj[0], bj[1] + 1]
    src, dst = [parent], [child]
    if bidirectional:
        src.append(child)
        dst.append(parent)
    return torch.stack([torch.cat(src), torch.cat(dst)]), link_mask, bj


def pyg_chain_conv(
    conv: NNConv, x: torch.Tensor, edge_attr: torch.Tensor, joint_mask: torch.Tensor, bidirectional: bool
) -> torch.Tensor:
    """The same layer computed by PyG's NNConv on the flattened graph (reference path)."""
    edge_index, link_mask, bj = chain_edge_index(joint_mask, bidirectional)
    attr = edge_attr[bj[0], bj[1]]
    if bidirectional:
        attr = torch.cat([attr, attr])
    out_flat = conv(x[link_mask], edge_index, attr)
    out = x.new_zeros(*link_mask.shape, conv.out_channels)
    out[link_mask] = out_flat
    return out
