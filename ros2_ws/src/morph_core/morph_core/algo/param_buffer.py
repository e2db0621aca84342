"""A module's parameters and their gradients as views into one flat vector each.

The optimizer and the gradient-norm clip then see one parameter vector
theta, as PPO is written, and cost a few operations per step instead of a few
per parameter tensor (30 of them here); for a network this small that
per-tensor overhead was about a tenth of a minibatch step. Autograd adds
into an existing ``.grad`` in place, so gradients land in the flat buffer:
clear it with ``theta.grad.zero_()``, never by setting grads to None.
"""

from __future__ import annotations

import torch
from torch import nn


def flatten_parameters(module: nn.Module) -> nn.Parameter:
    """Move ``module``'s parameters into one flat Parameter (returned); they become views of it."""
    params = list(module.parameters())
    theta = nn.Parameter(torch.cat([p.detach().flatten() for p in params]))
    theta.grad = torch.zeros_like(theta)
    offset = 0
    for p in params:
        n = p.numel()
        p.data = theta.data[offset : offset + n].view_as(p)
        p.grad = theta.grad[offset : offset + n].view_as(p)
        offset += n
    return theta
