"""The one PPO update on hand-made batches: clip statistics, losses and gradients against hand-computed
values for each rule, and the decoupled objective for off-policy data."""

import copy
import dataclasses
import math

import pytest
import torch

from morph_core.algo.batch import RolloutBatch
from morph_core.algo.learner import Learner
from morph_core.algo.off_policy import proximal_log_probs, with_proximal
from morph_core.algo.train import TrainConfig
from morph_core.algo.update import update
from morph_core.algo.update_config import UpdateConfig
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.chains import ChainBatch

EPS = 0.1


def _policy(seed=0):
    torch.manual_seed(seed)
    return GraphActorCritic()


def _batch(policy, num_joints, ratios, advantages, seed=0):
    """Samples whose ratio pi_theta / pi_behav is ``ratios`` for the policy as it is (behaviour log-probs
    set from the policy's own), joint states and actions random, zero beyond each chain."""
    gen = torch.Generator().manual_seed(seed)
    n = torch.tensor(num_joints)
    j = int(n.max())
    mask = torch.arange(j) < n.unsqueeze(1)
    fields = dict(
        num_joints=n,
        joint_pos=torch.randn(len(n), j, generator=gen) * mask,
        joint_vel=torch.randn(len(n), j, generator=gen) * mask,
        global_feats=torch.randn(len(n), 4, generator=gen),
        actions=0.3 * torch.randn(len(n), j, generator=gen) * mask,
        log_prob=torch.zeros(len(n)),
        values=torch.zeros(len(n)),
        advantages=torch.tensor(advantages),
        returns=torch.zeros(len(n)),
    )
    current = proximal_log_probs(policy, RolloutBatch(**fields))
    fields["log_prob"] = current - torch.tensor(ratios).log()
    return RolloutBatch(**fields)


def _config(rule, **kw):
    base = dict(rule=rule, clip_eps=EPS, update_epochs=1, minibatch_size=4096, vf_coef=0.0, ent_coef=0.0,
                max_grad_norm=1e9)  # fmt: skip
    return UpdateConfig(**{**base, **kw})


def _normalised(a):
    a = torch.tensor(a, dtype=torch.float64)
    return ((a - a.mean()) / a.std()).tolist()


def _reference_gradient(policy, batch, old_log_prob, live, coef):
    """Gradient of -(1/B) sum_{i in live} coef_i * r_i(theta) (the samples whose clip does not bind)."""
    ref = copy.deepcopy(policy)
    chains, actions = batch.minibatch(torch.arange(batch.size))
    ratio = (ref.log_prob(chains, actions) - old_log_prob).exp()
    loss = -sum(coef[i] * ratio[i] for i in live) / batch.size
    loss.backward()
    return torch.cat([(torch.zeros_like(p) if p.grad is None else p.grad).flatten() for p in ref.parameters()])


# Chains of 1 and 4 joints. eps = 0.1: fixed clips every sample at 1 +- 0.1; compensated widens the
# 4-joint samples to 1 +- 0.2, so r = 1.15 is clipped at d = 1 by both rules and at d = 4 by fixed only.
NUM_JOINTS = [1, 1, 4, 4]
RATIOS = [1.05, 1.15, 1.15, 1.05]
ADVANTAGES = [-1.0, 1.0, 2.0, 0.0]  # normalised: [-, +, +, -], so the clip binds where r > 1 + eps_i
CASES = {
    # rule: (ratio each sample's surrogate is taken at, samples whose clip binds, clip fraction d1, d4)
    "fixed": ([1.05, 1.1, 1.1, 1.05], {1, 2}, 0.5, 0.5),
    "compensated": ([1.05, 1.1, 1.15, 1.05], {1}, 0.5, 0.0),
}


@pytest.mark.parametrize("rule", list(CASES))
def test_update_clips_each_sample_at_its_rule_and_logs_it_per_dimension(rule):
    surrogate_ratio, binding, frac_d1, frac_d4 = CASES[rule]
    policy = _policy()
    batch = _batch(policy, NUM_JOINTS, RATIOS, ADVANTAGES)
    adv = _normalised(ADVANTAGES)
    expected_grad = _reference_gradient(policy, batch, batch.log_prob, [i for i in range(4) if i not in binding], adv)
    learner = Learner.create(policy, learning_rate=1e-3, adam_eps=1e-5, compile=False)
    stats = update(learner, batch, _config(rule), torch.Generator().manual_seed(0))

    assert stats.epochs == 1
    row = stats.row(range(1, 5))
    assert row["clip_frac_d1"] == frac_d1 and row["clip_frac_d4"] == frac_d4
    assert row["clip_frac"] == (frac_d1 + frac_d4) / 2
    assert "clip_frac_d2" not in row  # no sample of that dimension
    # |log 1.05| <= eps < |log 1.15| whatever the rule: the theory's in-eps fraction uses the base eps
    assert row["in_eps_frac_d1"] == row["in_eps_frac_d4"] == 0.5
    for d, r in ((1, RATIOS[:2]), (4, RATIOS[2:])):
        assert row[f"logr_mean_d{d}"] == pytest.approx(sum(math.log(x) for x in r) / 2, abs=1e-5)
    expected_loss = -sum(s * a for s, a in zip(surrogate_ratio, adv, strict=True)) / 4
    assert stats.policy_loss == pytest.approx(expected_loss, abs=1e-5)
    # The gradient comes from the samples whose clip does not bind, and only from them.
    torch.testing.assert_close(learner.params.grad, expected_grad, atol=1e-6, rtol=1e-4)
    assert expected_grad.abs().max() > 0


def test_update_with_proximal_equal_to_behaviour_is_plain_ppo_bit_for_bit():
    policy = _policy()
    batch = _batch(policy, NUM_JOINTS, RATIOS, ADVANTAGES)
    same = RolloutBatch(**{**batch.__dict__, "proximal_log_prob": batch.log_prob.clone()})
    results = []
    for b in (batch, same):
        learner = Learner.create(copy.deepcopy(policy), learning_rate=1e-2, adam_eps=1e-5, compile=False)
        stats = update(learner, b, _config("compensated", update_epochs=3, minibatch_size=2), torch.Generator())
        results.append((learner.params.theta.detach(), stats.policy_loss, stats.per_dim.kl))
    assert torch.equal(results[0][0], results[1][0])
    assert results[0][1] == results[1][1] and torch.equal(results[0][2], results[1][2])


@pytest.mark.parametrize("cap", [1.0, 3.0])
def test_decoupled_objective_clips_against_the_proximal_policy_and_weights_stale_samples(cap):
    # Sample 0 (2 joints) is stale: the behaviour policy liked its action more than the proximal one,
    # pi_prox / pi_behav = 1 / 1.3, and theta has moved away from pi_prox: pi_theta / pi_prox = 1.3.
    # Sample 1 (3 joints): pi_theta = pi_prox, but pi_prox / pi_behav = 2.
    policy = _policy(1)
    batch = _batch(policy, [2, 3], [1.0, 2.0], [1.0, -1.0])
    current = proximal_log_probs(policy, batch)
    prox = current - torch.tensor([math.log(1.3), 0.0])
    batch = RolloutBatch(**{**batch.__dict__, "proximal_log_prob": prox})
    weight = [1 / 1.3, min(2.0, cap)]  # min(pi_prox / pi_behav, c): the stale sample counts less
    adv = _normalised([1.0, -1.0])  # [+0.707, -0.707]
    # Against pi_prox, sample 0 (r = 1.3 > 1.1, A > 0) is clipped and sample 1 (r = 1) is not; against
    # pi_behav it would be the other way round (r = 1 and r = 2).
    expected_grad = _reference_gradient(policy, batch, prox, [1], [w * a for w, a in zip(weight, adv, strict=True)])
    learner = Learner.create(policy, learning_rate=1e-3, adam_eps=1e-5, compile=False)
    stats = update(learner, batch, _config("fixed", proximal_weight_cap=cap), torch.Generator())
    row = stats.row([2, 3])
    assert row["clip_frac_d2"] == 1.0 and row["clip_frac_d3"] == 0.0
    assert row["logr_mean_d2"] == pytest.approx(math.log(1.3), abs=1e-5)  # the log ratio is against pi_prox
    assert stats.policy_loss == pytest.approx(-(weight[0] * 1.1 * adv[0] + weight[1] * 1.0 * adv[1]) / 2, abs=1e-5)
    torch.testing.assert_close(learner.params.grad, expected_grad, atol=1e-6, rtol=1e-4)


def test_behaviour_objective_ignores_the_proximal_policy_bit_for_bit():
    # The stale batch of the test above: under the behaviour objective the ratio is against pi_behav and
    # nothing is weighted, exactly the update of the same batch without proximal log-probs.
    policy = _policy(1)
    batch = _batch(policy, [2, 3], [1.0, 2.0], [1.0, -1.0])
    prox = proximal_log_probs(policy, batch) - torch.tensor([math.log(1.3), 0.0])
    stale = RolloutBatch(**{**batch.__dict__, "proximal_log_prob": prox})
    results = []
    for b, objective in ((batch, "decoupled"), (stale, "behaviour"), (stale, "decoupled")):
        learner = Learner.create(copy.deepcopy(policy), learning_rate=1e-2, adam_eps=1e-5, compile=False)
        stats = update(learner, b, _config("fixed", off_policy_objective=objective), torch.Generator())
        results.append((learner.params.theta.detach(), stats.policy_loss))
    assert torch.equal(results[0][0], results[1][0]) and results[0][1] == results[1][1]
    assert not torch.equal(results[0][0], results[2][0])  # the decoupled objective does differ here


def test_behaviour_objective_refuses_rules_that_need_the_old_gaussian():
    with pytest.raises(ValueError, match="only the decoupled objective"):
        _config("kl-penalty", off_policy_objective="behaviour")
    with pytest.raises(ValueError, match="off_policy_objective must be one of"):
        _config("fixed", off_policy_objective="newest")
    with pytest.raises(ValueError, match="only the decoupled objective"):
        TrainConfig(clip_mode="kl-penalty-per-joint", off_policy_objective="behaviour")


def test_proximal_log_probs_are_the_current_policys_in_chunks():
    policy = _policy()
    batch = _batch(policy, [3, 1, 5, 2, 4], [1.0] * 5, [0.0] * 5)
    got = with_proximal(policy, batch).proximal_log_prob
    for i in range(batch.size):  # one sample at a time, its own padding width
        chains, actions = batch.minibatch(torch.tensor([i]))
        torch.testing.assert_close(got[i], policy.log_prob(chains, actions)[0])
    torch.testing.assert_close(proximal_log_probs(policy, batch, chunk=2), got)


def test_minibatches_are_cut_to_their_longest_chain():
    batch = _batch(_policy(), [3, 1, 5, 2], [1.0] * 4, [0.0] * 4)
    chains, actions = batch.minibatch(torch.tensor([1, 3]))
    assert chains.max_joints == 2 and actions.shape == (2, 2)
    torch.testing.assert_close(actions, batch.actions[[1, 3], :2])


def test_bad_batches_are_refused_with_the_field_named():
    good = _batch(_policy(), [2, 3], [1.0, 1.0], [0.0, 0.0]).__dict__
    actions = good["actions"].clone()
    actions[0, 2] = 0.5  # beyond the 2-joint chain's end
    with pytest.raises(ValueError, match="actions is not zero beyond"):
        RolloutBatch(**{**good, "actions": actions})
    with pytest.raises(ValueError, match=r"advantages must be \[2\]"):
        RolloutBatch(**{**good, "advantages": torch.zeros(3)})
    with pytest.raises(ValueError, match="returns holds NaN"):
        RolloutBatch(**{**good, "returns": torch.tensor([0.0, math.nan])})
    with pytest.raises(ValueError, match="num_joints must be in 1..3"):
        RolloutBatch(**{**good, "num_joints": torch.tensor([0, 3])})
    with pytest.raises(ValueError, match="unknown trust-region rule"):
        _config("adaptive")


def test_tree_minibatches_carry_their_parents_and_chain_parents_keep_the_chain_path():
    policy = _policy()
    chains = _batch(policy, [3, 1, 5, 2], [1.0] * 4, [0.0] * 4)
    given = torch.full((4, 5), -1, dtype=torch.int64)
    given[0, :3], given[2], given[3, :2] = (
        torch.tensor([-1, 0, 1]),
        torch.tensor([-1, 0, 1, 2, 3]),
        torch.tensor([-1, 0]),
    )
    assert dataclasses.replace(chains, parents=given).parents is None  # chains, however given: one thing
    trees = given.clone()
    trees[0, :3], trees[2] = torch.tensor([-1, 0, 0]), torch.tensor([-1, -1, 1, 1, 0])  # a Y, a branched star
    batch = dataclasses.replace(chains, parents=trees)
    got, actions = batch.minibatch(torch.tensor([2, 0, 1]))
    rows = [2, 0, 1]
    want = ChainBatch.from_padded(
        batch.joint_pos[rows], batch.joint_vel[rows], batch.global_feats[rows], batch.num_joints[rows],
        parents=trees[rows],
    )  # fmt: skip
    torch.testing.assert_close(got.parents, want.parents)
    torch.testing.assert_close(policy.log_prob(got, actions), policy.log_prob(want, actions))
    # a tree's log-probs are not its chain's: the parents reach the network
    assert not torch.allclose(
        policy.log_prob(got, actions), policy.log_prob(chains.minibatch(torch.tensor([2, 0, 1]))[0], actions)
    )
    assert batch.minibatch(torch.tensor([3, 1]))[0].parents is None  # only chains drawn: the chain path
    bad = trees.clone()
    bad[2, 3] = 3  # its own parent
    with pytest.raises(ValueError, match=r"parents\[2, 3\] = 3"):
        dataclasses.replace(chains, parents=bad)
    with pytest.raises(ValueError, match=r"parents must be \[4, 5\] int64"):
        dataclasses.replace(chains, parents=trees[:, :4])


def test_minibatch_cuts_never_leave_one_sample_alone():
    from morph_core.algo.minibatches import minibatch_cuts

    assert minibatch_cuts(6144, 256) == list(range(0, 6145, 256))  # the paper's split, unchanged
    assert minibatch_cuts(40, 16) == [0, 16, 32, 40]
    assert minibatch_cuts(33, 16) == [0, 16, 33]  # the lone 33rd sample joins the last minibatch
    with pytest.raises(ValueError, match="at least 2 samples"):
        minibatch_cuts(1, 16)


@pytest.mark.parametrize("world", [1, 2])
def test_a_parts_terms_are_the_batchs_rows_bit_for_bit(world):
    from morph_core.algo.minibatches import part_inputs, part_sizes, update_terms
    from morph_core.algo.off_policy import with_proximal

    policy = _policy()
    batch = with_proximal(policy, _batch(policy, [3, 1, 5, 2, 4, 2], [1.0, 0.5, 2.0, 0.3, 1.5, 0.7], [0.1] * 6))
    learner = Learner.create(policy, 1e-3, 1e-5, compile=False)
    cfg = TrainConfig(rule="kl-penalty-per-joint").update_config()  # every optional term: weights, old Gaussian
    terms = update_terms(learner, batch, cfg, torch.tensor(0.5))
    mb = torch.tensor([4, 0, 5, 2])
    normalized = torch.arange(4, dtype=torch.float32)
    for rank in range(world):
        got = part_inputs(terms, batch, mb, normalized, rank, world).minibatch
        lo = sum(part_sizes(4, world)[:rank])
        rows = mb if world == 1 else mb[lo : lo + part_sizes(4, world)[rank]]
        width = int(batch.num_joints[rows].max())
        want = {"old_log_prob": terms.old_log_prob[rows], "returns": batch.returns[rows],
                "clip_range": terms.clip_range[rows], "weight": terms.weight[rows],
                "old_mean": terms.old_mean[rows, :width], "actions": batch.actions[rows, :width]}  # fmt: skip
        for name, value in want.items():
            assert torch.equal(getattr(got, name), value), name
            assert getattr(got, name).is_contiguous(), name  # the compiled graph's layout is torch's
        advantages = batch.advantages[rows] if world == 1 else normalized[lo : lo + len(rows)]
        assert torch.equal(got.advantages, advantages)
