"""PPO pieces on hand-made numbers: the two clip rules, the clipped loss, GAE, per-dimension stats."""

import math
from itertools import pairwise

import pytest
import torch

from morph_core.algo.minibatches import minibatch_cuts
from morph_core.algo.ppo import PerDimensionStats, compute_gae, normalized_advantages, normalized_minibatch_advantages
from morph_core.algo.trust_region import LossContext, get_rule


def clip_range(eps, num_joints, rule):
    return get_rule(rule).clip_range(eps, num_joints.to(torch.float32))


def clipped_policy_loss(ratio, adv, eps, rule="fixed"):
    """The update's policy loss for on-policy data: minus the rule's mean surrogate."""
    n = torch.ones_like(adv, dtype=torch.int64)
    ctx = LossContext(ratio.log(), adv, eps, n, None, None, None, None)
    return -get_rule(rule).surrogate(ctx).mean()


def test_fixed_clip_range_ignores_dimension():
    n = torch.tensor([1, 4, 9, 16])
    torch.testing.assert_close(clip_range(0.2, n, "fixed"), torch.full((4,), 0.2))


def test_compensated_clip_range_grows_with_sqrt_dimension():
    n = torch.tensor([1, 4, 9, 16])
    torch.testing.assert_close(clip_range(0.2, n, "compensated"), torch.tensor([0.2, 0.4, 0.6, 0.8]))


def test_unknown_clip_mode_is_refused():
    with pytest.raises(ValueError, match="unknown trust-region rule 'adaptive'"):
        clip_range(0.2, torch.tensor([2]), "adaptive")


def test_clipped_loss_on_hand_made_ratios():
    # Same ratios and advantages; sample i has dimension d_i. eps = 0.1.
    ratio = torch.tensor([1.3, 1.3, 0.7, 0.7, 1.05])
    adv = torch.tensor([1.0, 1.0, -1.0, -1.0, 2.0])
    d = torch.tensor([1, 9, 1, 9, 4])
    # fixed: every sample clipped at 1 +- 0.1 where the clip binds (positive adv above, negative below)
    fixed = clipped_policy_loss(ratio, adv, clip_range(0.1, d, "fixed"))
    expected_fixed = -(1.1 + 1.1 + (-0.9) + (-0.9) + 2.1) / 5
    assert math.isclose(float(fixed), expected_fixed, rel_tol=1e-6)
    # compensated: d = 9 widens the range to 1 +- 0.3, so 1.3 and 0.7 are just inside
    comp = clipped_policy_loss(ratio, adv, clip_range(0.1, d, "compensated"))
    expected_comp = -(1.1 + 1.3 + (-0.9) + (-0.7) + 2.1) / 5
    assert math.isclose(float(comp), expected_comp, rel_tol=1e-6)


def test_clipped_samples_give_no_gradient_and_the_pessimistic_side_does():
    ratio = torch.tensor([1.5, 0.5], requires_grad=True)
    adv = torch.tensor([1.0, 1.0])
    loss = clipped_policy_loss(ratio, adv, torch.tensor([0.2, 0.2]))
    loss.backward()
    # r = 1.5 > 1.2 with A > 0: clipped, no push; r = 0.5 with A > 0: unclipped term is the min, pushes up
    assert ratio.grad[0] == 0 and ratio.grad[1] < 0


def test_gae_on_a_hand_computed_case():
    gamma, lam = 0.9, 0.8
    # Two envs. Env 0: step 1 terminates. Env 1: a time limit truncates step 0, whose final
    # observation is worth 3.0; a new episode starts at step 1.
    rewards = torch.tensor([[1.0, 1.0], [0.0, 0.5], [2.0, 0.0]])
    values = torch.tensor([[0.5, 0.4], [1.0, 0.3], [0.2, 0.1]])
    terminated = torch.tensor([[False, False], [True, False], [False, False]])
    truncated = torch.tensor([[False, True], [False, False], [False, False]])
    final_values = torch.tensor([[0.0, 3.0], [0.0, 0.0], [0.0, 0.0]])
    last_value = torch.tensor([0.7, -1.0])
    adv, ret = compute_gae(rewards, values, terminated, truncated, final_values, last_value, gamma, lam)
    # env 0, t=2: delta = 2 + 0.9*0.7 - 0.2 = 2.43
    # t=1: terminated, no bootstrap: delta = 0 - 1.0 = -1.0, A = -1.0
    # t=0: delta = 1 + 0.9*1.0 - 0.5 = 1.4; A = 1.4 + 0.9*0.8*(-1.0) = 0.68
    torch.testing.assert_close(adv[:, 0], torch.tensor([0.68, -1.0, 2.43]))
    # env 1, t=2: delta = 0 + 0.9*(-1.0) - 0.1 = -1.0
    # t=1: delta = 0.5 + 0.9*0.1 - 0.3 = 0.29; A = 0.29 + 0.72*(-1.0) = -0.43
    # t=0: truncated: delta = 1 + 0.9*3.0 - 0.4 = 3.3, and the trace stops there (not -0.43 carried)
    torch.testing.assert_close(adv[:, 1], torch.tensor([3.3, -0.43, -1.0]))
    torch.testing.assert_close(ret, adv + values)


def test_per_dimension_stats():
    stats = PerDimensionStats(max_dim=4)
    log_r = torch.tensor([0.0, 0.3, -0.3, 0.05])
    d = torch.tensor([2, 2, 4, 4])
    eps_i = torch.tensor([0.2, 0.2, 0.4, 0.4])
    clipped = get_rule("compensated").clipped(log_r.exp(), eps_i)
    stats.add(d, log_r, clipped, base_eps=0.2)
    s = stats.summary(range(2, 5))
    assert "clip_frac_d3" not in s  # no samples of dimension 3
    assert s["in_eps_frac_d2"] == 0.5 and s["in_eps_frac_d4"] == 0.5
    assert s["clip_frac_d2"] == 0.5  # exp(0.3) - 1 = 0.35 > 0.2
    assert s["clip_frac_d4"] == 0.0  # |exp(-0.3) - 1| = 0.26 < 0.4
    assert math.isclose(s["logr_mean_d4"], -0.125, rel_tol=1e-6)
    assert math.isclose(s["logr_std_d2"], 0.15, rel_tol=1e-6)


@pytest.mark.parametrize("size", [6144, 6000, 5121, 300])
def test_minibatch_advantages_normalised_together_equal_each_minibatch_normalised_alone(size):
    g = torch.Generator().manual_seed(size)
    for scale in (1e-3, 1.0, 1e3):
        advantages = torch.randn(size, generator=g) * scale + 2.0
        perm = torch.randperm(size, generator=g)
        cuts = minibatch_cuts(size, 256)
        alone = torch.cat([normalized_advantages(advantages[perm[a:b]]) for a, b in pairwise(cuts)])
        # bit for bit, so that the two-process update's numbers do not depend on which form computed them
        assert torch.equal(normalized_minibatch_advantages(advantages, perm, cuts), alone)
