"""The table of trust-region rules: a rule added to it reaches the config, the theory and the update."""

import numpy as np
import pytest
import torch

from morph_core.algo import trust_region
from morph_core.algo.batch import RolloutBatch
from morph_core.algo.learner import Learner
from morph_core.algo.train import TrainConfig
from morph_core.algo.trust_region import ClippedRatio, get_rule, register, unregister
from morph_core.algo.update import update
from morph_core.algo.update_config import UpdateConfig
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.theory import clip_analysis as theory


class QuarterPowerClip(ClippedRatio):
    """A rule that exists only in this test: clip r to 1 +- eps * d^(1/4)."""

    name = "quarter-power"
    help = "test rule"

    def clip_scale(self, dim):
        return trust_region._array_module(dim).sqrt(trust_region._array_module(dim).sqrt(dim))


@pytest.fixture
def quarter_power():
    rule = register(QuarterPowerClip())
    yield rule
    unregister(rule.name)


def test_todays_rules_in_order_and_names_are_unique():
    assert trust_region.rule_names()[:2] == ("fixed", "compensated")
    with pytest.raises(ValueError, match="new name"):
        register(trust_region.FixedClip())
    with pytest.raises(ValueError, match="unknown trust-region rule 'nope'"):
        get_rule("nope")


def test_clip_ranges_in_torch_and_numpy():
    d = np.array([1.0, 4.0, 9.0])
    np.testing.assert_array_equal(get_rule("fixed").clip_range(0.2, d), [0.2, 0.2, 0.2])
    np.testing.assert_allclose(get_rule("compensated").clip_range(0.2, d), [0.2, 0.4, 0.6])
    t = get_rule("compensated").clip_range(0.2, torch.tensor([1.0, 4.0, 9.0]))
    assert isinstance(t, torch.Tensor) and t.dtype == torch.float32
    torch.testing.assert_close(t, torch.tensor([0.2, 0.4, 0.6]))


def test_a_registered_rule_reaches_config_theory_and_update(quarter_power):
    # the trainer's config accepts it (and still refuses names the table does not have)
    assert TrainConfig(clip_mode="quarter-power").update_config().rule == "quarter-power"
    with pytest.raises(ValueError, match="clip_mode must be one of"):
        TrainConfig(clip_mode="quarter-powr")
    # the theory evaluates its clip range: e = eps d^(1/4)
    dims = np.arange(1, 17)
    np.testing.assert_allclose(theory.effective_eps(dims, 0.2, "quarter-power"), 0.2 * dims**0.25)
    np.testing.assert_array_equal(
        theory.clip_probability(dims, 0.1, 0.2, "quarter-power"),
        theory.clip_probability(dims, 0.1, theory.effective_eps(dims, 0.2, "quarter-power")),
    )
    assert quarter_power in trust_region.clip_rules()
    # the update clips with it. At d = 16 its range is 1 +- 0.2 for eps = 0.1: r = 1.15 stays inside
    # (fixed would clip it), r = 1.3 is clipped (compensated, 1 +- 0.4, would not).
    torch.manual_seed(0)
    policy = GraphActorCritic()
    n = torch.tensor([16, 16])
    mask = torch.arange(16) < n.unsqueeze(1)
    fields = dict(num_joints=n, joint_pos=0.1 * mask, joint_vel=-0.2 * mask, global_feats=torch.zeros(2, 4),
                  actions=0.3 * mask, values=torch.zeros(2), advantages=torch.tensor([1.0, 2.0]),
                  returns=torch.zeros(2))  # fmt: skip
    chains, actions = RolloutBatch(**fields, log_prob=torch.zeros(2)).minibatch(torch.arange(2))
    with torch.no_grad():
        log_prob = policy.log_prob(chains, actions) - torch.tensor([1.15, 1.3]).log()
    batch = RolloutBatch(**fields, log_prob=log_prob)
    cfg = UpdateConfig("quarter-power", 0.1, 1, 2, 0.5, 0.0, 0.5)
    row = update(Learner.create(policy, 1e-3, 1e-5, compile=False), batch, cfg, torch.Generator()).row([16])
    assert row["clip_frac_d16"] == 0.5


def test_a_rule_without_a_clip_range_is_no_case_for_the_theory():
    class NoClip(trust_region.TrustRegionRule):
        name = "no-clip"

    rule = NoClip()
    assert not rule.clips_joint_ratio
    with pytest.raises(ValueError, match="no clip range"):
        theory.effective_eps(2, 0.2, rule)
