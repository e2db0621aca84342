"""The dimension-aware rules of the table on hand-made Gaussians, ratios and log ratios: per-joint clipping
(DISC), the KL penalty with its adaptive beta, KL early stopping; and inside the update, the per-epoch
statistics, the early stop, beta's adaptation and its checkpoint."""

import copy
import math

import pytest
import torch

from morph_core.algo import trust_region
from morph_core.algo.batch import RolloutBatch
from morph_core.algo.checkpoint import load_training_state, save_training_state
from morph_core.algo.learner import Learner
from morph_core.algo.off_policy import proximal_log_probs
from morph_core.algo.run_dir import RunDir
from morph_core.algo.trust_region import LossContext, get_rule, joint_log_ratios, kl_per_joint
from morph_core.algo.update import update
from morph_core.algo.update_config import UpdateConfig

EPS = 0.2


def _ctx(rhos, advantages, eps=EPS, log_ratio=None, kl_beta=None):
    """A minibatch whose joints have the ratios ``rhos`` (a ragged list per sample), built from Gaussians:
    sigma = 1 for both policies, action 0, old mean 1 and new mean m_j with (1 - m_j^2) / 2 = log rho_j,
    so rho_j = N(0; m_j, 1) / N(0; 1, 1) exactly as given (the new means require grad)."""
    d = torch.tensor([len(r) for r in rhos])
    j = int(d.max())
    mask = torch.arange(j) < d.unsqueeze(1)
    log_rho = torch.zeros(len(rhos), j, dtype=torch.float64)
    for i, r in enumerate(rhos):
        log_rho[i, : len(r)] = torch.tensor(r, dtype=torch.float64).log()
    mean = (torch.sqrt(1 - 2 * log_rho) * mask).requires_grad_()
    zero = torch.tensor(0.0, dtype=torch.float64)
    return LossContext(
        log_ratio=log_rho.sum(1) if log_ratio is None else log_ratio,
        advantages=torch.tensor(advantages, dtype=torch.float64),
        clip_range=torch.full((len(rhos),), eps, dtype=torch.float64),
        num_joints=d,
        mean=mean,
        log_std=zero,
        actions=torch.zeros(len(rhos), j, dtype=torch.float64),
        mask=mask,
        old_mean=mask.to(torch.float64),
        old_log_std=zero,
        kl_beta=kl_beta,
    )


def test_joint_log_ratios_are_the_hand_made_ones_and_sum_to_the_joint_ratio():
    ctx = _ctx([[1.3, 0.9], [0.7, 1.0, 1.1]], [1.0, -2.0])
    expected = torch.tensor([[1.3, 0.9, 1.0], [0.7, 1.0, 1.1]], dtype=torch.float64)  # padding: log rho = 0
    torch.testing.assert_close(joint_log_ratios(ctx).exp(), expected)
    torch.testing.assert_close(joint_log_ratios(ctx).sum(1), ctx.log_ratio)


def test_per_joint_clip_clips_each_joints_ratio_on_its_own():
    # eps = 0.2. Sample 0 (A = +1): rho = 1.3 is clipped at 1.2 (its term 0.2), rho = 0.9 is not (-0.1):
    # A + 0.2 - 0.1 = 1.1. Its joint ratio 1.17 is inside 1 +- 0.2: the fixed clip would not bind at all.
    # Sample 1 (A = -2): rho = 0.7 clipped at 0.8 ((0.8 - 1)(-2) = 0.4 < 0.6), 1.0 gives 0, 1.1 is inside
    # (-0.2): A + 0.4 + 0 - 0.2 = -1.8.
    rule = get_rule("per-joint-clip")
    ctx = _ctx([[1.3, 0.9], [0.7, 1.0, 1.1]], [1.0, -2.0])
    surrogate = rule.surrogate(ctx)
    torch.testing.assert_close(surrogate, torch.tensor([1.1, -1.8], dtype=torch.float64))
    torch.testing.assert_close(rule.clip_share(ctx), torch.tensor([1 / 2, 1 / 3], dtype=torch.float64))
    fixed = get_rule("fixed").surrogate(ctx)  # the joint ratios 1.17 and 0.77, the latter clipped at 0.8
    torch.testing.assert_close(fixed, torch.tensor([1.17, -1.6], dtype=torch.float64))
    # A clipped joint gives no gradient; the others do, and the padding none.
    surrogate.sum().backward()
    grad = ctx.mean.grad
    assert grad[0, 0] == 0 and grad[0, 1] != 0 and grad[0, 2] == 0
    assert grad[1, 0] == 0 and grad[1, 1] != 0 and grad[1, 2] != 0


def test_per_joint_surrogate_summed_over_joints_has_ppos_gradient_at_the_old_policy():
    # At rho = 1 nothing is clipped and sum_j grad rho_j = grad prod_j rho_j: the per-joint surrogate takes
    # each sample's whole policy gradient, as the joint ratio does (the mean would divide it by d).
    adv = [0.5, -1.5, 2.0]
    ctx = _ctx([[1.0] * 2, [1.0] * 5, [1.0] * 9], adv)
    ctx_joint = ctx._replace(mean=ctx.mean.detach().clone().requires_grad_())
    get_rule("per-joint-clip").surrogate(ctx).sum().backward()
    joint = ctx_joint._replace(log_ratio=joint_log_ratios(ctx_joint).sum(1))
    get_rule("fixed").surrogate(joint).sum().backward()
    torch.testing.assert_close(ctx.mean.grad, ctx_joint.mean.grad)
    assert ctx.mean.grad.abs().sum() > 0


def test_kl_per_joint_by_hand_and_against_torch_distributions():
    # Two joints, sigma_old = 1, sigma_new = 2 (eta = 2), mu_old = (0, 0), mu_new = (1, 0): nu = (0.5, 0).
    # KL_j = log eta + (1/eta^2 + nu_j^2)/2 - 1/2 = ln 2 - 0.25 and ln 2 - 0.375.
    ctx = LossContext(
        None, None, None, torch.tensor([2]), torch.tensor([[1.0, 0.0, 0.0]]), torch.tensor(math.log(2.0)),
        None, torch.tensor([[True, True, False]]), torch.zeros(1, 3), torch.tensor(0.0),
    )  # fmt: skip
    kl = kl_per_joint(ctx)
    torch.testing.assert_close(kl, torch.tensor([[math.log(2) - 0.25, math.log(2) - 0.375, 0.0]]))
    old, new = torch.distributions.Normal(0.0, 1.0), torch.distributions.Normal(torch.tensor([1.0, 0.0]), 2.0)
    torch.testing.assert_close(kl[0, :2], torch.distributions.kl_divergence(old, new))


@pytest.mark.parametrize(
    "rule, kl", [("kl-penalty", 2 * math.log(2) - 0.625), ("kl-penalty-per-joint", math.log(2) - 0.3125)]
)
def test_kl_penalty_surrogate_by_hand(rule, kl):
    # The Gaussians of the test above (KL over the two joints 2 ln 2 - 0.625; per joint half of it),
    # r = 1.2 and A = 1 given directly, beta = 0.5: r A - beta KL.
    ctx = LossContext(
        torch.tensor([math.log(1.2)]), torch.tensor([1.0]), torch.tensor([EPS]), torch.tensor([2]),
        torch.tensor([[1.0, 0.0]]), torch.tensor(math.log(2.0)), torch.zeros(1, 2), torch.tensor([[True, True]]),
        torch.zeros(1, 2), torch.tensor(0.0), torch.tensor(0.5),
    )  # fmt: skip
    torch.testing.assert_close(get_rule(rule).surrogate(ctx), torch.tensor([1.2 - 0.5 * kl]))


def _cfg(rule, **kw):
    base = dict(rule=rule, clip_eps=0.1, update_epochs=1, minibatch_size=4096, vf_coef=0.0, ent_coef=0.0,
                max_grad_norm=1e9, kl_target=0.01)  # fmt: skip
    return UpdateConfig(**{**base, **kw})


@pytest.mark.parametrize(
    "kl, expected_joint, expected_per_joint",
    [
        # each sample's KL over its 3 joints; target 0.01: doubled above 0.015, halved below 0.01/1.5
        ([0.03, 0.03], 2.0, 1.0),  # joint mean 0.03; per joint 0.01, inside the band
        ([0.012, 0.012], 1.0, 0.5),  # joint 0.012 inside; per joint 0.004 < 0.00667
        ([0.003, 0.003], 0.5, 0.5),
        ([0.06, 0.0], 2.0, 2.0),  # d = (1, 3) here: per joint (0.06 / 1 + 0 / 3) / 2 = 0.03 as well
    ],
)
def test_adaptive_beta_doubles_and_halves_around_the_target(kl, expected_joint, expected_per_joint):
    d = torch.tensor([1, 3]) if kl[1] == 0.0 else torch.tensor([3, 3])
    for rule, expected in (("kl-penalty", expected_joint), ("kl-penalty-per-joint", expected_per_joint)):
        cfg = _cfg(rule)
        state = get_rule(rule).initial_state(cfg)
        assert state["kl_beta"].dtype == torch.float64 and float(state["kl_beta"]) == 1.0
        after = get_rule(rule).end_update(state, torch.tensor(kl), d, cfg)
        assert float(after["kl_beta"]) == expected, rule
        fixed_beta = get_rule(rule).end_update(state, torch.tensor(kl), d, _cfg(rule, kl_adaptive=False))
        assert float(fixed_beta["kl_beta"]) == 1.0


def test_kl_early_stopping_on_the_joint_kl_and_on_the_kl_per_joint():
    # (r - 1) - log r: r = 1.2 gives 0.2 - ln 1.2 = 0.017678, r = 0.9 gives -0.1 - ln 0.9 = 0.005361;
    # mean 0.011519 > 0.01: the joint rule stops. Per joint with d = (2, 4): 0.008839 and 0.001340,
    # mean 0.005090 < 0.01: the per-joint rule goes on (it stops at a target of 0.005).
    log_ratio = torch.tensor([1.2, 0.9]).log()
    d = torch.tensor([2, 4])
    assert get_rule("kl-stop").stop_after_epoch(log_ratio, d, _cfg("kl-stop"))
    assert not get_rule("kl-stop").stop_after_epoch(log_ratio, d, _cfg("kl-stop", kl_target=0.0116))
    assert not get_rule("kl-stop-per-joint").stop_after_epoch(log_ratio, d, _cfg("kl-stop-per-joint"))
    assert get_rule("kl-stop-per-joint").stop_after_epoch(log_ratio, d, _cfg("kl-stop-per-joint", kl_target=0.005))
    assert not get_rule("fixed").stop_after_epoch(log_ratio, d, _cfg("fixed", kl_target=1e-9))


def test_kl_settings_are_checked():
    with pytest.raises(ValueError, match="kl_target and kl_beta must be > 0"):
        _cfg("kl-penalty", kl_target=0.0)
    with pytest.raises(ValueError, match="kl_target and kl_beta must be > 0"):
        _cfg("kl-penalty", kl_beta=float("nan"))


# -- inside the update ---------------------------------------------------------------------------

NUM_JOINTS = [1, 1, 4, 4]
RATIOS = [1.05, 1.15, 1.15, 1.05]


def _setup(seed=0):
    torch.manual_seed(seed)
    from morph_core.policy.actor_critic import GraphActorCritic

    policy = GraphActorCritic()
    gen = torch.Generator().manual_seed(seed)
    n = torch.tensor(NUM_JOINTS)
    mask = torch.arange(4) < n.unsqueeze(1)
    fields = dict(
        num_joints=n, joint_pos=torch.randn(4, 4, generator=gen) * mask,
        joint_vel=torch.randn(4, 4, generator=gen) * mask, global_feats=torch.randn(4, 4, generator=gen),
        actions=0.3 * torch.randn(4, 4, generator=gen) * mask, log_prob=torch.zeros(4), values=torch.zeros(4),
        advantages=torch.tensor([-1.0, 1.0, 2.0, 0.0]), returns=torch.zeros(4),
    )  # fmt: skip
    fields["log_prob"] = proximal_log_probs(policy, RolloutBatch(**fields)) - torch.tensor(RATIOS).log()
    return policy, RolloutBatch(**fields)


def test_first_epoch_statistics_are_the_hand_made_ratios_and_the_pooled_ones_are_not():
    # One minibatch per epoch: the first epoch sees exactly the hand-made ratios; later epochs have moved.
    policy, batch = _setup()
    stats = update(Learner.create(policy, 1e-2, 1e-5, compile=False), batch, _cfg("fixed", update_epochs=3),
                   torch.Generator().manual_seed(0))  # fmt: skip
    row = stats.row(range(1, 5))
    assert stats.epochs == 3 and float(stats.per_dim.n.sum()) == 12 and float(stats.first_epoch.n.sum()) == 4
    for d, r in ((1, RATIOS[:2]), (4, RATIOS[2:])):
        assert row[f"logr_mean_first_d{d}"] == pytest.approx(sum(map(math.log, r)) / 2, abs=1e-6)
        assert row[f"in_eps_frac_first_d{d}"] == 0.5  # |log 1.05| <= 0.1 < |log 1.15|
        assert row[f"logr_mean_last_d{d}"] != pytest.approx(row[f"logr_mean_first_d{d}"], abs=1e-4)
    assert row["clip_frac_first"] == 0.5  # 1.15 leaves 1 +- 0.1, 1.05 does not
    k3 = sum((r - 1) - math.log(r) for r in RATIOS) / 4
    assert row["approx_kl_first"] == pytest.approx(k3, rel=1e-4)
    # pooled over the 3 epochs: the first epoch's sums and two more
    assert row["approx_kl"] != pytest.approx(row["approx_kl_first"], rel=1e-3)
    assert math.isnan(row["kl_beta"])
    one = update(Learner.create(copy.deepcopy(policy), 1e-2, 1e-5, compile=False), batch, _cfg("fixed"),
                 torch.Generator().manual_seed(0)).row(range(1, 5))  # fmt: skip
    for k in ("logr_std_d4", "in_eps_frac_d1", "approx_kl", "clip_frac"):  # one epoch: first = last = pooled
        assert one[k] == one[k.replace("_d", "_first_d") if "_d" in k else k + "_first"]
        assert one[k] == one[k.replace("_d", "_last_d") if "_d" in k else k + "_last"]


@pytest.mark.parametrize("target_factor, epochs", [(0.8, 1), (1000.0, 4)])
def test_kl_stop_ends_the_update_after_the_epoch_whose_kl_exceeds_the_target(target_factor, epochs):
    # The first epoch's mean approximate KL is the hand-made ratios' (r - 1) - log r, 0.00572: a target
    # below it stops the update after that epoch; far above it, all epochs run.
    policy, batch = _setup()
    k3 = sum((r - 1) - math.log(r) for r in RATIOS) / 4
    cfg = _cfg("kl-stop", update_epochs=4, kl_target=target_factor * k3)
    stats = update(Learner.create(policy, 1e-2, 1e-5, compile=False), batch, cfg, torch.Generator())
    assert stats.epochs == epochs
    row = stats.row(range(1, 5))
    assert row["epochs"] == epochs and row["approx_kl_first"] == pytest.approx(k3, rel=1e-4)
    if epochs == 1:
        assert row["approx_kl_last"] == row["approx_kl_first"] == row["approx_kl"]


def test_kl_penalty_adapts_beta_to_the_exact_kl_of_the_update_and_checkpoints_it(tmp_path):
    policy, batch = _setup()
    before = copy.deepcopy(policy)
    learner = Learner.create(policy, 3e-2, 1e-5, compile=False)
    cfg = _cfg("kl-penalty-per-joint", update_epochs=3, kl_beta=0.25)
    stats = update(learner, batch, cfg, torch.Generator())
    assert stats.kl_beta == 0.25  # the beta this update used
    # the exact KL between the policy before and after, per joint, from torch.distributions
    chains, actions = batch.minibatch(torch.arange(4))
    with torch.no_grad():
        (m0, s0, _), (m1, s1, _) = before(chains), policy(chains)
        s0, s1 = s0.detach(), s1.detach()
    kl = torch.distributions.kl_divergence(
        torch.distributions.Normal(m0, s0.exp()), torch.distributions.Normal(m1, s1.exp())
    )
    per_joint = float(((kl * chains.mask).sum(1) / chains.num_joints).mean())
    expected = 0.5 if per_joint > 0.015 else (0.125 if per_joint < 0.01 / 1.5 else 0.25)
    assert float(learner.rule_state["kl_beta"]) == expected
    # the learner state through a checkpoint, bit for bit, and into a fresh learner
    learner.rule_state["kl_beta"] = torch.tensor(0.1 * 3, dtype=torch.float64)  # not a power of two
    path = RunDir(tmp_path).state
    save_training_state(path, policy, learner.optimizer, torch.Generator(), {}, {}, {}, learner.state_tensors())
    tensors, _ = load_training_state(path)
    fresh = Learner.create(copy.deepcopy(before), 1e-2, 1e-5, compile=False)
    fresh.restore_state(tensors)
    assert torch.equal(fresh.rule_state["kl_beta"], learner.rule_state["kl_beta"])
    assert update(fresh, batch, cfg, torch.Generator()).kl_beta == 0.1 * 3  # the restored beta is used
    with pytest.raises(ValueError, match="must start with 'learner.'"):
        save_training_state(path, policy, learner.optimizer, torch.Generator(), {}, {}, {}, {"kl_beta": torch.ones(1)})


def test_rules_without_state_save_none():
    policy, batch = _setup()
    learner = Learner.create(policy, 1e-2, 1e-5, compile=False)
    update(learner, batch, _cfg("per-joint-clip"), torch.Generator())
    assert learner.state_tensors() == {}


def test_the_theory_covers_one_case_per_clip_range():
    # kl-stop clips as fixed does (the theory knows no stopping); the per-joint and KL-penalty rules
    # do not clip the joint ratio at all.
    names = [r.name for r in trust_region.clip_rules()]
    assert names[:2] == ["fixed", "compensated"] and "kl-stop" not in names and "kl-stop-per-joint" not in names
    assert get_rule("kl-stop").clips_joint_ratio and get_rule("kl-stop").clip_range(0.2, 9.0) == 0.2
    for rule in ("per-joint-clip", "kl-penalty", "kl-penalty-per-joint"):
        assert not get_rule(rule).clips_joint_ratio and get_rule(rule).uses_old_gaussian
