"""The NumPy batch-1 forward equals the torch policy's mean action."""

import numpy as np
import pytest
import torch

from morph_core.policy.actor_critic import GraphActorCritic, PolicyConfig
from morph_core.policy.chains import ChainBatch
from morph_core.policy.numpy_actor import NumpyPolicy


@pytest.mark.parametrize("bidirectional", [True, False])
def test_numpy_mean_equals_torch(bidirectional):
    torch.manual_seed(0)
    policy = GraphActorCritic(PolicyConfig(bidirectional=bidirectional))
    with torch.no_grad():  # move away from the near-zero initial action head
        for p in policy.parameters():
            p.add_(0.3 * torch.randn_like(p))
    fast = NumpyPolicy(policy)
    rng = np.random.default_rng(1)
    for n in (1, 2, 7, 20, 64):
        pos, vel, glob = rng.normal(0, 1, n), rng.normal(0, 3, n), rng.normal(0, 1, 4)
        expected = policy(ChainBatch.from_padded(pos[None], vel[None], glob[None], [n]))[0][0].detach().numpy()
        got = fast.mean(pos, vel, glob)
        assert got.shape == (n,)
        np.testing.assert_allclose(got, expected, atol=1e-5, rtol=1e-5)
    assert fast.log_std == pytest.approx(float(policy.log_std))


@pytest.mark.parametrize("bidirectional", [True, False])
def test_numpy_batched_act_equals_torch(bidirectional):
    # The rollout path: mixed chain lengths padded to one width, sampled with given noise.
    torch.manual_seed(1)
    policy = GraphActorCritic(PolicyConfig(bidirectional=bidirectional))
    with torch.no_grad():
        for p in policy.parameters():
            p.add_(0.3 * torch.randn_like(p))
    fast = NumpyPolicy(policy)
    rng = np.random.default_rng(2)
    n = np.array([2, 10, 1, 7, 7, 3])
    pos, vel = rng.normal(0, 1, (6, 10)) * (np.arange(10) < n[:, None]), rng.normal(0, 3, (6, 10))
    glob = rng.normal(0, 1, (6, 4))
    noise = rng.normal(0, 1, (6, 10)).astype(np.float32)
    action, log_prob, value, mean = fast.act(pos, vel, glob, n, noise)

    batch = ChainBatch.from_padded(pos, vel, glob, n, trim=False)
    with torch.no_grad():
        t_mean, _, t_value = policy(batch)
        t_log_prob = policy.log_prob(batch, torch.from_numpy(action))
    mask = np.arange(10) < n[:, None]
    np.testing.assert_allclose(mean, t_mean.numpy(), atol=1e-5, rtol=1e-5)
    np.testing.assert_allclose(value, t_value.numpy(), atol=1e-5, rtol=1e-5)
    np.testing.assert_allclose(log_prob, t_log_prob.numpy(), atol=1e-4, rtol=1e-5)
    np.testing.assert_allclose(action, (t_mean.numpy() + np.exp(fast.log_std) * noise) * mask, atol=1e-5)
    assert not action[~mask].any()  # padding stays zero
    np.testing.assert_array_equal(fast.mean_actions(pos, vel, glob, n), mean)  # the evaluation's, without the critic


def test_a_policy_that_saw_other_chain_mixes_answers_as_a_fresh_one():
    # The index arrays are kept per chain mix: switching mixes (a swimmer resets to a new length) must
    # never reuse another mix's, whatever the order, the batch size or the integer type.
    policy = GraphActorCritic(PolicyConfig())
    used, rng = NumpyPolicy(policy), np.random.default_rng(3)
    mixes = [[2, 10, 5], [10, 2, 5], [5], [2, 10, 5, 1], [5, 1], [2, 10, 5]]
    for counts in mixes + [np.array([5, 1], np.int32), np.array([5], np.int32)]:
        n = np.asarray(counts)
        mask = np.arange(10) < n[:, None]
        pos, vel = rng.normal(0, 1, mask.shape) * mask, rng.normal(0, 2, mask.shape) * mask
        glob, noise = rng.normal(0, 1, (len(n), 4)), rng.normal(0, 1, mask.shape)
        got = used.act(pos, vel, glob, n, noise)
        fresh = NumpyPolicy(policy).act(pos, vel, glob, n, noise)
        for a, b in zip(got, fresh, strict=True):
            np.testing.assert_array_equal(a, b)
