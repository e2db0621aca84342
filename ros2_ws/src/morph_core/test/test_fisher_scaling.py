"""Fisher information of the GNN policy and the TRPO / beta-PPO update-norm scaling."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.func import functional_call, grad, vmap

from morph_core.policy.actor_critic import GraphActorCritic, PolicyConfig, gaussian_log_prob
from morph_core.theory import fisher_scaling as fs

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def policy() -> GraphActorCritic:
    torch.manual_seed(3)
    net = GraphActorCritic(PolicyConfig()).eval()
    with torch.no_grad():
        net.log_std.fill_(-0.4)  # sigma != 1, so the 1/sigma^2 factor is exercised
    return net


@pytest.fixture(scope="module")
def states():
    return fs.collect_states(4, 6, warmup_steps=3, states_per_episode=3, seed=11)


def test_collect_states_are_real_and_varied(states):
    assert states.batch_size == 6 and states.max_joints == 4 and bool(states.mask.all())
    # Distinct states (random actions in between), not one state repeated.
    assert torch.unique(states.joint_pos, dim=0).shape[0] == 6


def test_subspace_jacobian_by_forward_mode_equals_reverse_mode(policy, states):
    params = fs.mean_parameters(policy)
    assert "log_std" not in params and sum(p.numel() for p in params.values()) > 10_000
    full = fs.mean_jacobian(policy, states, fs.make_subspace(params, "full", 0, 0))  # [N, d, P], reverse mode
    for kind in ("random", "output"):
        sub = fs.make_subspace(params, kind, 12, seed=5)
        projected = full @ sub.basis
        fwd = fs.mean_jacobian(policy, states, sub)
        assert fwd.shape == projected.shape
        torch.testing.assert_close(fwd, projected, rtol=1e-4, atol=1e-6)
    assert fs.make_subspace(params, "output", 0, 0).dim == 65


def test_closed_form_fisher_equals_average_of_autograd_score_outer_products(policy, states):
    """F = E_s E_a[score score^T], scores by autograd through the policy, vs J^T J / sigma^2 (+) 2d."""
    params = fs.mean_parameters(policy)
    sub = fs.make_subspace(params, "output", 0, 0)
    chosen = [n for n in params if n.startswith("actor_head.4.")]  # the output layer, in basis order
    assert sum(params[n].numel() for n in chosen) == sub.dim
    analytic = fs.Fisher.from_jacobian(fs.mean_jacobian(policy, states, sub), float(policy.log_std.detach()))
    v, s = analytic.right_vectors, analytic.singular_values
    f_analytic = torch.zeros(sub.dim + 1, sub.dim + 1, dtype=torch.float64)
    f_analytic[:-1, :-1] = v.T @ torch.diag(s**2) @ v
    f_analytic[-1, -1] = analytic.log_std_block

    trainable = {n: params[n] for n in chosen} | {"log_std": policy.log_std.detach()}
    n_actions = 20_000
    gen = torch.Generator().manual_seed(0)
    f_mc = torch.zeros_like(f_analytic)
    for i in range(states.batch_size):
        one = states.select(torch.tensor([i]))

        def log_prob(p, action, one=one):
            # The policy's own forward and log-density, with the chosen parameters swapped in.
            mean, log_std, _ = functional_call(policy, p, (one,))
            return gaussian_log_prob(action[None], mean, log_std, one.mask).squeeze(0)

        with torch.no_grad():
            mean, log_std, _ = policy(one)
            actions = mean + log_std.exp() * torch.randn(n_actions, one.max_joints, generator=gen)
        scores = vmap(grad(log_prob), in_dims=(None, 0))(trainable, actions)
        flat = torch.cat([scores[n].reshape(n_actions, -1) for n in chosen] + [scores["log_std"][:, None]], 1)
        f_mc += flat.double().T @ flat.double() / n_actions
    f_mc /= states.batch_size

    rel = (f_mc - f_analytic).norm() / f_analytic.norm()
    print(f"relative Frobenius error {rel:.4f}")
    assert rel < 0.05
    assert f_mc[-1, -1].item() == pytest.approx(2 * 4, rel=0.05)  # log-std block = 2 d
    assert f_mc[-1, :-1].abs().max() < 0.1 * f_analytic[:-1, :-1].diagonal().max()  # no mean/log-std cross term


def test_fisher_solve_is_the_damped_inverse_even_when_singular():
    gen = torch.Generator().manual_seed(1)
    for rows, k in ((40, 10), (6, 10)):  # full rank, and rank-deficient (N d < k)
        jac = torch.randn(rows, 1, k, generator=gen, dtype=torch.float64)
        fisher = fs.Fisher.from_jacobian(jac, log_std=0.3)
        dense = torch.zeros(k + 1, k + 1, dtype=torch.float64)
        g_rows = jac.reshape(rows, k) / np.sqrt(rows * np.exp(0.6))
        dense[:k, :k] = g_rows.T @ g_rows
        dense[k, k] = 2.0
        np.testing.assert_allclose(
            fisher.eigenvalues(), np.sort(torch.linalg.eigvalsh(dense).numpy())[::-1], atol=1e-10
        )
        g = torch.randn(k + 1, generator=gen, dtype=torch.float64)
        for damping in (1e-3, 0.5):
            expected = torch.linalg.solve(dense + damping * torch.eye(k + 1, dtype=torch.float64), g)
            torch.testing.assert_close(fisher.solve(g, damping), expected, rtol=1e-8, atol=1e-10)
        assert fisher.numerical_rank() == min(rows, k) + 1
        # Projected onto the range, g has no null-space part, so a vanishing damping leaves the solve bounded.
        g_range = fisher.project_to_range(g, 1e-12)
        assert g_range[-1] == g[-1]
        torch.testing.assert_close(dense @ torch.linalg.pinv(dense) @ g_range, g_range)
        assert fisher.solve(g_range, 1e-12).norm() < 1e6


def test_update_norms_have_the_papers_slopes_when_fisher_is_exactly_d_times_fixed():
    gen = torch.Generator().manual_seed(2)
    base = torch.randn(50, 1, 8, generator=gen, dtype=torch.float64)
    g = torch.randn(9, generator=gen, dtype=torch.float64)
    dims = np.array([2, 3, 5, 8, 13, 20])
    norms = []
    for d in dims:
        # Rows of d identical-in-law joints: F_d = d F_1 (log-std block 2d as well).
        jac = base.repeat(1, d, 1)
        fisher = fs.Fisher.from_jacobian(jac, 0.0)
        norms.append(fs.update_norms(fisher, g, delta=0.01, beta=2.0, damping=0.0))
    norms = np.array(norms)
    assert fs.fit_slope(dims, norms[:, 0])[0] == pytest.approx(-0.5, abs=1e-9)
    assert fs.fit_slope(dims, norms[:, 1])[0] == pytest.approx(-1.0, abs=1e-9)
    # Damping that dominates F removes the dimension dependence: both slopes go to 0.
    damped = np.array(
        [fs.update_norms(fs.Fisher.from_jacobian(base.repeat(1, d, 1), 0.0), g, 0.01, 2.0, 1e6) for d in dims]
    )
    assert abs(fs.fit_slope(dims, damped[:, 0])[0]) < 1e-3 and abs(fs.fit_slope(dims, damped[:, 1])[0]) < 1e-3


def test_slopes_on_the_gnn_policy_small_config():
    cfg = fs.ScalingConfig(dims=(2, 4, 8, 16), states_per_dim=32, subspace="random", subspace_dim=8, seed=0)
    result = fs.update_norm_scaling(cfg)
    # Measured with this config: TRPO -0.72, beta -1.34 (paper: -1/2, -1); the Fisher's largest and
    # mean eigenvalues grow like d^1.00, the paper's assumption.
    assert -1.0 < result.trpo_slope < -0.3
    assert -1.8 < result.beta_slope < -0.6
    assert result.beta_slope < result.trpo_slope
    eig = result.eigen_slopes()
    assert eig["fisher_eig_max_slope"] == pytest.approx(1.0, abs=0.2)
    assert eig["fisher_eig_mean_slope"] == pytest.approx(1.0, abs=0.2)
    # Heavy damping flattens both slopes (the damping sweep is part of the result).
    trpo_damped, beta_damped = result.damping_sweep[max(result.damping_sweep)]
    assert abs(trpo_damped) < 0.2 and abs(beta_damped) < 0.3
    assert len(result.csv_rows()) == 4 and result.csv_header()[0] == "dim"


def test_too_few_states_for_the_subspace_is_refused():
    with pytest.raises(ValueError, match="rows"):
        fs.update_norm_scaling(fs.ScalingConfig(dims=(2, 4), states_per_dim=8, subspace="output"))
    with pytest.raises(ValueError, match="subspace"):
        fs.ScalingConfig(subspace="everything")
