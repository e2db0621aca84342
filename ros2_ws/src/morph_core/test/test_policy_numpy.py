"""The NumPy batch-1 forward equals the torch policy's mean action."""

import numpy as np
import pytest
import torch

from morph_core.graph import ChainBatch
from morph_core.policy import GraphActorCritic, PolicyConfig
from morph_core.policy_numpy import NumpyPolicy


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
