"""Flat parameter buffer: same network, gradients land in one vector, updates reach the module,
and a zero_grad() that would cut the gradients loose fails loudly instead of training on nothing."""

import copy

import pytest
import torch

from morph_core.algo.param_buffer import FlatGradientError, FlatParameters
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.chains import ChainBatch


def _loss(policy, batch):
    mean, _, value = policy(batch)
    return (mean**2).sum() + value.sum() + policy.log_std


def _batch():
    return ChainBatch.from_padded(torch.randn(5, 7), torch.randn(5, 7), torch.randn(5, 4), [7, 2, 3, 7, 1])


def test_flat_gradients_equal_per_tensor_gradients_over_steps():
    torch.manual_seed(0)
    batch = _batch()
    plain = GraphActorCritic()
    flat_policy = copy.deepcopy(plain)
    flat = FlatParameters(flat_policy)
    theta = flat.theta
    assert theta.numel() == sum(p.numel() for p in plain.parameters())
    opt_plain = torch.optim.Adam(plain.parameters(), lr=0.01)
    opt_flat = flat.guard(torch.optim.Adam([theta], lr=0.01))
    for _ in range(3):
        opt_plain.zero_grad()
        _loss(plain, batch).backward()
        flat.zero_grad()
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


@pytest.mark.parametrize("who", ["optimizer", "module"])
def test_zero_grad_that_sets_gradients_to_none_fails_loudly_at_the_next_step(who):
    torch.manual_seed(0)
    policy = GraphActorCritic()
    flat = FlatParameters(policy)
    optimizer = flat.guard(torch.optim.Adam([flat.theta], lr=0.01))
    before = flat.theta.detach().clone()
    (optimizer if who == "optimizer" else policy).zero_grad()  # set_to_none=True by default
    _loss(policy, _batch()).backward()
    with pytest.raises(FlatGradientError, match="flat parameter buffer"):
        optimizer.step()
    assert torch.equal(flat.theta.detach(), before)  # nothing was stepped


@pytest.mark.parametrize("scale", [1e-3, 0.1, 1.0, 30.0])
def test_the_norm_clip_gives_torchs_numbers_bit_for_bit(scale):
    torch.manual_seed(1)
    flat = FlatParameters(GraphActorCritic())
    reference = torch.nn.Parameter(flat.theta.detach().clone())
    for _ in range(5):
        grad = torch.randn(flat.theta.numel()) * scale
        flat.grad.copy_(grad)
        reference.grad = grad.clone()
        norm = flat.clip_grad_norm_(0.5)
        expected = torch.nn.utils.clip_grad_norm_(reference, 0.5)
        assert torch.equal(norm, expected)
        assert torch.equal(flat.grad, reference.grad)  # scaled (or, below the bound, left) alike
    assert flat.theta.grad is flat.grad  # in place: the gradient views still point into the buffer


def test_optimizer_step_gives_adams_numbers_bit_for_bit_without_its_step():
    torch.manual_seed(2)
    flat = FlatParameters(GraphActorCritic())
    reference = torch.nn.Parameter(flat.theta.detach().clone())
    ours = flat.guard(torch.optim.Adam([flat.theta], lr=3e-4, eps=1e-5, fused=True))
    theirs = torch.optim.Adam([reference], lr=3e-4, eps=1e-5, fused=True)
    through_step = []
    ours.register_step_pre_hook(lambda *_: through_step.append(1))
    for k in range(12):
        grad = torch.randn(flat.theta.numel()) * (10.0 if k % 3 == 0 else 0.01)
        flat.grad.copy_(grad)
        reference.grad = grad.clone()
        for group in (*ours.param_groups, *theirs.param_groups):  # as --anneal-lr changes it between updates
            group["lr"] = 3e-4 * (1 - k / 12)
        flat.optimizer_step(ours)
        theirs.step()
        assert torch.equal(flat.theta.detach(), reference.detach())
        for key in ("step", "exp_avg", "exp_avg_sq"):
            assert torch.equal(ours.state[flat.theta][key], theirs.state[reference][key]), key
    assert len(through_step) == 1  # the first step creates the state; the others called the kernel directly


def test_optimizer_step_still_refuses_gradients_cut_loose_and_other_optimizers_step_as_usual():
    torch.manual_seed(3)
    policy = GraphActorCritic()
    flat = FlatParameters(policy)
    optimizer = flat.guard(torch.optim.Adam([flat.theta], lr=0.01, fused=True))
    flat.grad.normal_()
    flat.optimizer_step(optimizer)  # creates the state
    before = flat.theta.detach().clone()
    policy.zero_grad()  # set_to_none=True: the gradients are cut loose from the buffer
    with pytest.raises(FlatGradientError, match="flat parameter buffer"):
        flat.optimizer_step(optimizer)
    assert torch.equal(flat.theta.detach(), before)
    sgd_flat = FlatParameters(GraphActorCritic())
    sgd = torch.optim.SGD([sgd_flat.theta], lr=0.1)
    sgd_flat.grad.fill_(1.0)
    start = sgd_flat.theta.detach().clone()
    sgd_flat.optimizer_step(sgd)
    sgd_flat.optimizer_step(sgd)
    assert torch.equal(sgd_flat.theta.detach(), start - 0.1 - 0.1)
