"""Flat parameter buffer: same network, gradients land in one vector, updates reach the module."""

import copy

import torch

from morph_core.algo.param_buffer import flatten_parameters
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.chains import ChainBatch


def _loss(policy, batch):
    mean, _, value = policy(batch)
    return (mean**2).sum() + value.sum() + policy.log_std


def test_flat_gradients_equal_per_tensor_gradients_over_steps():
    torch.manual_seed(0)
    batch = ChainBatch.from_padded(torch.randn(5, 7), torch.randn(5, 7), torch.randn(5, 4), [7, 2, 3, 7, 1])
    plain = GraphActorCritic()
    flat_policy = copy.deepcopy(plain)
    theta = flatten_parameters(flat_policy)
    assert theta.numel() == sum(p.numel() for p in plain.parameters())
    opt_plain = torch.optim.Adam(plain.parameters(), lr=0.01)
    opt_flat = torch.optim.Adam([theta], lr=0.01)
    for _ in range(3):
        opt_plain.zero_grad()
        _loss(plain, batch).backward()
        theta.grad.zero_()
        _loss(flat_policy, batch).backward()
        torch.testing.assert_close(theta.grad, torch.cat([p.grad.flatten() for p in plain.parameters()]))
        opt_plain.step()
        opt_flat.step()  # updates theta in place: the module's parameters are views of it
    for a, b in zip(plain.parameters(), flat_policy.parameters(), strict=True):
        torch.testing.assert_close(a, b)
    # state dicts load into the buffer as well
    fresh = GraphActorCritic()
    flat_policy.load_state_dict(fresh.state_dict())
    torch.testing.assert_close(theta.detach(), torch.cat([p.detach().flatten() for p in fresh.parameters()]))
