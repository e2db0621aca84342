"""The compiled minibatch loss (forward and backward by Inductor) equals eager PyTorch."""

import functools

import numpy as np
import pytest
import torch

from morph_core.algo.compiled import compiled
from morph_core.algo.ppo import ppo_loss
from morph_core.algo.trust_region import get_rule
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.chains import ChainBatch


def _minibatch(rng, size, max_joints, weighted):
    n = rng.integers(2, max_joints + 1, size)
    pos = rng.normal(0, 1, (size, max_joints)) * (np.arange(max_joints) < n[:, None])
    batch = ChainBatch.from_padded(pos, rng.normal(0, 3, (size, max_joints)), rng.normal(0, 1, (size, 4)), n)
    actions = rng.normal(0, 0.5, (size, batch.max_joints))
    old_log_prob, advantages, returns = rng.normal(-5, 1, size), rng.normal(0, 1, size), rng.normal(0, 1, size)
    tensors = [torch.as_tensor(x, dtype=torch.float32) for x in (actions, old_log_prob, advantages, returns)]
    clip_range = get_rule("compensated").clip_range(0.111, batch.num_joints.to(torch.float32))
    weight = torch.as_tensor(rng.uniform(0.2, 1.0, size), dtype=torch.float32) if weighted else None
    return batch, *tensors, clip_range, weight


@pytest.mark.parametrize("weighted", [False, True])
def test_compiled_loss_and_gradients_equal_eager(weighted):
    # Two minibatches with different chain mixes (and sizes): one compiled graph serves both.
    # Weighted: the off-policy loss, each sample's policy term weighted (algo.update).
    torch.manual_seed(0)
    policy = GraphActorCritic()
    rng = np.random.default_rng(0)
    eager_fn = functools.partial(ppo_loss, rule=get_rule("compensated"))
    fast = compiled(eager_fn)
    for size, max_joints in ((64, 10), (48, 7)):
        args = _minibatch(rng, size, max_joints, weighted)
        results = []
        for fn in (eager_fn, fast):
            policy.zero_grad()
            out = fn(policy, *args, 0.5, 0.01)
            out[0].backward()
            results.append((out, [p.grad.clone() for p in policy.parameters()]))
        (eager, eager_grads), (comp, comp_grads) = results
        for a, b in zip(eager, comp, strict=True):
            torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4)
        for a, b in zip(eager_grads, comp_grads, strict=True):
            torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4)
    assert not fast.fell_back  # it really ran compiled


@pytest.mark.parametrize("rule", ["per-joint-clip", "kl-penalty-per-joint"])
def test_compiled_loss_of_the_per_joint_rules_equals_eager(rule):
    # These rules take the proximal policy's means and log-std (and beta), and per-joint-clip returns its
    # clip share from inside the loss: all of it through the compiled graph, for two chain mixes. (It
    # stays before the test without a compiler: run after that one in the same process, it fell back.)
    torch.manual_seed(0)
    policy = GraphActorCritic()
    rng = np.random.default_rng(1)
    eager_fn = functools.partial(ppo_loss, rule=get_rule(rule))
    fast = compiled(eager_fn)
    for size, max_joints in ((64, 10), (48, 7)):
        batch, *rest = _minibatch(rng, size, max_joints, weighted=False)
        with torch.no_grad():
            old_mean = policy(batch)[0] + torch.as_tensor(rng.normal(0, 0.05, batch.mask.shape), dtype=torch.float32)
        extra = {"old_mean": old_mean * batch.mask, "old_log_std": torch.tensor(-0.6), "kl_beta": torch.tensor(0.7)}
        results = []
        for fn in (eager_fn, fast):
            policy.zero_grad()
            out = fn(policy, batch, *rest, 0.5, 0.01, **extra)
            out[0].backward()
            results.append((out, [p.grad.clone() for p in policy.parameters()]))
        (eager, eager_grads), (comp, comp_grads) = results
        assert (eager[5] is None) == (rule != "per-joint-clip")
        for a, b in zip(eager, comp, strict=True):
            torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4)
        for a, b in zip(eager_grads, comp_grads, strict=True):
            torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4)
    assert not fast.fell_back


def test_without_a_cxx_compiler_training_falls_back_to_eager():
    import torch._inductor.config as inductor_config

    def scaled_softplus(x):
        return torch.nn.functional.softplus(3.0 * x) / 3.0

    x = torch.linspace(-2, 2, 9)
    fn = compiled(scaled_softplus)
    # Inductor's own patch, not monkeypatch: undoing a monkeypatch deleted fx_graph_cache from the config,
    # and every later compile in the process then failed and fell back to eager mode unnoticed.
    no_compiler = {"cpp.cxx": ("/nonexistent/c++",), "fx_graph_cache": False}  # a cached kernel needs no compiler
    with inductor_config.patch(no_compiler), pytest.warns(UserWarning, match="eager mode"):
        y = fn(x)
    assert fn.fell_back
    torch.testing.assert_close(y, scaled_softplus(x))
    torch.testing.assert_close(fn(x + 1), scaled_softplus(x + 1))  # later calls stay eager
