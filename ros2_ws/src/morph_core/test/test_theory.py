"""Clip-probability theory (paper section III) against sampled Gaussian policies, and morph-theory."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest

from morph_core.algo.run_dir import RunDir
from morph_core.theory import clip_analysis as theory
from trainer.cli.theory import TheoryConfig, load_run_data, main, parse_config


def phi_cdf(x: float) -> float:
    return 0.5 * (1.0 + math.erf(x / math.sqrt(2.0)))


# -- closed form -------------------------------------------------------------------------------------


def test_closed_form_matches_erf_formula_and_broadcasts():
    dims, nu0, eps = np.arange(1, 6)[:, None], np.array([0.03, 0.2, 0.7])[None, :], 0.15
    p = theory.clip_probability(dims, nu0, eps)
    assert p.shape == (5, 3)
    for i, d in enumerate(range(1, 6)):
        for j, n0 in enumerate([0.03, 0.2, 0.7]):
            nu = n0 * math.sqrt(d)
            expected = phi_cdf(eps / nu + nu / 2) - phi_cdf(-eps / nu + nu / 2)
            assert p[i, j] == pytest.approx(expected, abs=1e-12)


def test_zero_drift_gives_probability_one_without_nan():
    with np.errstate(all="raise"):  # no division warnings either
        p = theory.clip_probability(np.arange(1, 21), 0.0, 0.2)
        q = theory.clip_probability_approx(np.arange(1, 21), 0.0, 0.2)
    assert np.all(p == 1.0) and np.all(q == 1.0)
    # Continuity: a tiny drift is essentially 1 as well.
    assert theory.clip_probability(20, 1e-9, 0.2) == pytest.approx(1.0, abs=1e-12)


def test_probability_decreases_with_dimension_and_compensation_equals_scaled_eps():
    dims = np.arange(1, 21)
    p = theory.clip_probability(dims, 0.1, 0.2)
    assert np.all(np.diff(p) < 0)
    comp = theory.clip_probability(dims, 0.1, 0.2, "compensated")
    np.testing.assert_allclose(comp, theory.clip_probability(dims, 0.1, 0.2 * np.sqrt(dims)), rtol=0, atol=1e-15)
    approx_comp = theory.clip_probability_approx(dims, 0.1, 0.2, rule="compensated")
    np.testing.assert_allclose(approx_comp, theory.clip_probability_approx(dims, 0.1, 0.2 * np.sqrt(dims)))
    # Compensation makes the approximation exactly dimension-free (eps sqrt(d) / (nu0 sqrt(d))).
    assert np.ptp(approx_comp) == 0.0
    # ... but not the exact probability: exp(-|nu|^2 / 8) still shrinks it with d.
    assert np.all(np.diff(comp) < 0)


# -- the approximation's limits ----------------------------------------------------------------------


def test_approximation_is_capped_and_never_below_exact():
    dims, nu0 = np.arange(1, 21)[None, :], np.geomspace(1e-3, 3.0, 400)[:, None]
    for eps in (0.05, 0.111, 0.2, 0.5):
        approx = theory.clip_probability_approx(dims, nu0, eps)
        exact = theory.clip_probability(dims, nu0, eps)
        assert approx.max() == 1.0 and approx.min() > 0.0
        # The density of log r is at most 1 / (|nu| sqrt(2 pi)), so the exact mass of a 2 eps
        # interval never exceeds the (capped) approximation.
        assert np.all(approx - exact >= -1e-12)


def test_approximation_relative_error_vanishes_only_for_eps_much_smaller_than_small_nu():
    # Along eps = |nu|^2 both |nu| -> 0 and eps / |nu| -> 0: first-order expansion becomes exact.
    rel = [
        float(theory.clip_probability_approx(1, nu, nu**2) / theory.clip_probability(1, nu, nu**2) - 1)
        for nu in (0.3, 0.1, 0.03, 0.01)
    ]
    assert all(a > b > 0 for a, b in zip(rel, rel[1:], strict=False))
    assert rel[-1] < 1e-3
    # At large drift the dropped factor exp(-|nu|^2 / 8) makes it overestimate by that factor.
    nu = 2.0
    ratio = float(theory.clip_probability_approx(1, nu, 0.01) / theory.clip_probability(1, nu, 0.01))
    assert ratio == pytest.approx(math.exp(nu**2 / 8), rel=1e-3)


def test_max_approximation_error_on_fig1_grid_is_at_the_cap_kink():
    eps = 0.2
    cfg = TheoryConfig(eps=eps)
    nu0 = np.geomspace(cfg.nu0_min, 1.0, cfg.nu0_points)[:, None]
    dims = np.arange(1, cfg.max_dim + 1)[None, :]
    err = theory.clip_probability_approx(dims, nu0, eps) - theory.clip_probability(dims, nu0, eps)
    # Derived: the capped approximation reaches 1 at |nu*| = sqrt(2/pi) eps (so eps/|nu*| = sqrt(pi/2)),
    # and the error there, 1 - P(nu*), is the largest: left of it approx = 1 and P falls with |nu|.
    nu_star = math.sqrt(2 / math.pi) * eps
    at_kink = 1.0 - (phi_cdf(math.sqrt(math.pi / 2) + nu_star / 2) - phi_cdf(-math.sqrt(math.pi / 2) + nu_star / 2))
    sup, where = theory.approx_error_supremum(eps)
    assert sup == pytest.approx(at_kink, abs=1e-9) and where == pytest.approx(nu_star)
    assert err.max() <= sup + 1e-12
    assert err.max() == pytest.approx(sup, abs=0.01)  # the fine log grid gets close to the supremum
    # The paper quotes 0.19; the supremum is 0.2115. Same size, not identical (grid-dependent).
    assert 0.15 < err.max() < 0.25


# -- Monte Carlo from real Gaussian densities --------------------------------------------------------


@pytest.mark.parametrize(
    ("dim", "nu0", "eps", "rule"),
    [(1, 0.1, 0.2, "fixed"), (2, 0.05, 0.111, "fixed"), (5, 0.2, 0.2, "fixed"), (12, 0.1, 0.2, "compensated"),
     (20, 0.3, 0.1, "fixed")],
)  # fmt: skip
def test_closed_form_matches_monte_carlo_at_eta_one(dim, nu0, eps, rule):
    p_mc, se = theory.monte_carlo_clip_probability(dim, nu0, eps, eta=1.0, n_samples=40_000, rng=dim, rule=rule)
    exact = theory.clip_probability(dim, nu0, eps, rule)
    assert se > 0
    assert abs(float(p_mc) - float(exact)) < 4 * float(se)


def test_monte_carlo_log_ratio_moments_follow_gaussian_theory():
    est = theory.monte_carlo_point(8, 0.15, 0.2, eta=1.0, n_samples=50_000, rng=3)
    nu = 0.15 * math.sqrt(8)
    assert est.logr_mean == pytest.approx(-(nu**2) / 2, abs=4 * nu / math.sqrt(50_000))
    assert est.logr_std == pytest.approx(nu, rel=0.02)
    mean, std = theory.log_ratio_moments(8, 0.15, 1.0)
    assert float(mean) == pytest.approx(-(nu**2) / 2) and float(std) == pytest.approx(nu)


def test_monte_carlo_broadcasts_and_is_seeded():
    p1, se1 = theory.monte_carlo_clip_probability(
        np.array([1, 4]), np.array([[0.1], [0.3]]), 0.2, n_samples=2000, rng=7
    )
    p2, _ = theory.monte_carlo_clip_probability(np.array([1, 4]), np.array([[0.1], [0.3]]), 0.2, n_samples=2000, rng=7)
    assert p1.shape == se1.shape == (2, 2)
    np.testing.assert_array_equal(p1, p2)


@pytest.mark.parametrize("eta", [0.9, 1.1])
def test_eta_not_one_breaks_the_closed_form_but_matches_the_noncentral_chi2_law(eta):
    # With no mean drift the eta = 1 theory says the ratio is exactly 1; a 10% std change alone
    # spreads log r with variance d (1 - eta^-2)^2 / 2, so the in-eps fraction falls with d.
    rows = []
    for dim in (1, 5, 20):
        p_mc, se = theory.monte_carlo_clip_probability(dim, 0.0, 0.2, eta=eta, n_samples=20_000, rng=dim)
        rows.append((float(p_mc), float(se), float(theory.clip_probability_eta(dim, 0.0, 0.2, eta))))
    for p_mc, se, exact_eta in rows:
        assert abs(p_mc - exact_eta) < 4 * max(se, 1e-3)
        assert 1.0 - p_mc > 10 * max(se, 1e-3)  # far outside the closed form's 1.0
    assert rows[0][0] > rows[1][0] > rows[2][0]
    assert rows[2][0] < 0.4
    # With drift, the breakdown is largest at small drift and shrinks when nu dominates.
    small = theory.clip_probability_eta(20, 0.05, 0.2, eta) - theory.clip_probability(20, 0.05, 0.2)
    large = theory.clip_probability_eta(20, 0.5, 0.2, eta) - theory.clip_probability(20, 0.5, 0.2)
    assert abs(small) > 5 * abs(large)


def test_eta_law_reduces_to_closed_form_near_one_and_at_one():
    dims = np.arange(1, 21)
    np.testing.assert_allclose(
        theory.clip_probability_eta(dims, 0.2, 0.2, 1.0), theory.clip_probability(dims, 0.2, 0.2), atol=1e-15
    )
    close = theory.clip_probability_eta(dims, 0.2, 0.2, 1.02)
    assert np.max(np.abs(close - theory.clip_probability(dims, 0.2, 0.2))) < 0.03


# -- morph-theory --------------------------------------------------------------------------------------


SMALL = [
    "--nu0-points", "24", "--max-dim", "8", "--mc-samples", "600", "--mc-nu0", "0.1",
    "--fisher-dims", "2", "4", "8", "--fisher-states", "32",
    "--fisher-subspace", "random", "--fisher-subspace-dim", "8",
]  # fmt: skip


def write_synthetic_run(run_dir, eps=0.111, dims=(2, 3, 5), rows=6, with_config=True, drop=None):
    """A progress.csv whose in-eps fractions are exactly the closed form at the logged std(log r)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    header = ["global_step"]
    for d in dims:
        header += [f"in_eps_frac_d{d}", f"clip_frac_d{d}", f"logr_mean_d{d}", f"logr_std_d{d}"]
    header = [h for h in header if h != drop]
    with RunDir(run_dir).progress.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, header)
        writer.writeheader()
        for r in range(rows):
            row = {"global_step": 6144 * (r + 1)}
            for d in dims:
                if r == 0 and d == dims[-1]:
                    continue  # a dimension absent from a minibatch: empty cells
                std = 0.03 * math.sqrt(d) * (1 + 0.1 * r)
                row |= {
                    f"in_eps_frac_d{d}": float(theory.clip_probability(1, std, eps)),
                    f"clip_frac_d{d}": 0.1,
                    f"logr_mean_d{d}": -(std**2) / 2,
                    f"logr_std_d{d}": std,
                }
            writer.writerow({k: v for k, v in row.items() if k in header})
    if with_config:
        RunDir(run_dir).config.write_text(json.dumps({"clip_eps": eps, "clip_mode": "fixed"}))
    return RunDir(run_dir).progress


def test_parser_is_generated_from_the_dataclass():
    assert parse_config([]) == TheoryConfig()
    cfg = parse_config(
        ["--eps", "0.1", "--mc-eta", "0.95", "1.05", "--fisher", "false", "--run-csv", "a", "--run-csv", "b"]
    )
    assert cfg.eps == 0.1 and cfg.mc_eta == (0.95, 1.05) and cfg.fisher is False
    assert [str(p) for p in cfg.run_csv] == ["a", "b"]
    assert parse_config(["--fisher"]).fisher is True


def test_the_no_flag_form_of_before_still_works_and_says_it_is_deprecated(capsys):
    assert parse_config(["--no-fisher", "--eps", "0.1"]).fisher is False
    assert capsys.readouterr().err == "morph-theory: warning: --no-fisher is deprecated: write --fisher false\n"


@pytest.mark.slow
def test_cli_end_to_end_writes_figures_csvs_and_overlay(tmp_path, capsys):
    csv_path = write_synthetic_run(tmp_path / "runA")
    out = tmp_path / "out"
    assert main([*SMALL, "--out", str(out), "--run-csv", str(csv_path), "--run-csv", str(tmp_path / "runA")]) == 0
    printed = capsys.readouterr().out
    assert "fig1_max_error_grid" in printed
    for name in ("fig1_clip_probability", "fig2_compensated", "fig3_monte_carlo", "fig4_update_scaling"):
        png = out / f"{name}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    assert (out / "fig5_run_overlay.png").is_file()
    with (out / "fig1_grid.csv").open() as fh:
        grid = list(csv.DictReader(fh))
    assert len(grid) == 24 * 8
    assert all(float(r["approx_minus_exact"]) >= -1e-9 for r in grid)
    summary = json.loads((out / "summary.json").read_text())
    # The synthetic run obeys the closed form exactly, so the overlay must reproduce it.
    assert summary["run0_max_abs_in_eps_error"] < 1e-4 and summary["run1_max_abs_in_eps_error"] < 1e-4
    assert summary["run0_nu0_estimate"] == pytest.approx(0.03 * 1.25, rel=0.1)
    assert summary["fig3_eta1_max_abs_z"] < 5
    assert summary["trpo_slope"] < 0 and summary["beta_slope"] < summary["trpo_slope"]
    with (out / "fig5_run_overlay.csv").open() as fh:
        overlay = list(csv.DictReader(fh))
    assert {int(r["dim"]) for r in overlay} == {2, 3, 5}
    assert {int(r["n_rows"]) for r in overlay if r["dim"] == "5"} == {5}  # empty cells skipped


def test_run_csv_missing_columns_is_a_clear_error(tmp_path, capsys):
    bad = write_synthetic_run(tmp_path / "bad", drop="logr_std_d3")
    good = write_synthetic_run(tmp_path / "good")
    assert (
        main(["--fisher", "false", *SMALL, "--out", str(tmp_path / "o"), "--run-csv", str(good), "--run-csv", str(bad)])
        == 2
    )
    err = capsys.readouterr().err
    assert err.startswith("morph-theory: error: ") and "missing columns logr_std_d3" in err
    assert not (tmp_path / "o").exists()  # checked before any figure is made
    assert main([*SMALL, "--out", str(tmp_path / "o"), "--run-csv", str(tmp_path / "nowhere")]) == 2
    assert capsys.readouterr().err == f"morph-theory: error: run CSV not found: {tmp_path / 'nowhere'}\n"
    assert not (tmp_path / "o").exists()
    with pytest.raises(ValueError, match="no in_eps_frac"):
        (tmp_path / "empty.csv").write_text("global_step,return_mean\n1,2\n")
        load_run_data(tmp_path / "empty.csv")
    with pytest.raises(ValueError, match="not found"):
        load_run_data(tmp_path / "nowhere.csv")


def test_run_without_config_falls_back_to_eps_with_a_warning(tmp_path, capsys):
    path = write_synthetic_run(tmp_path / "noconf", eps=0.2, with_config=False)
    run = load_run_data(path, fallback_eps=0.2)
    assert run.clip_eps == 0.2 and "assuming clip_eps=0.2" in capsys.readouterr().err
    with pytest.raises(ValueError, match=RunDir(tmp_path).config.name):
        load_run_data(path)


def test_overlay_reads_the_first_or_last_epochs_statistics_of_a_real_run(tmp_path):
    from morph_core.algo.train import TrainConfig, train

    small = dict(num_envs=2, num_steps=64, minibatch_size=32, update_epochs=3, tensorboard=False,
                 progress_bar=False, compile=False, total_timesteps=256, clip_mode="fixed", seed=0)  # fmt: skip
    run = train(TrainConfig(**small), tmp_path / "r")
    with RunDir(run).progress.open() as fh:
        rows = list(csv.DictReader(fh))
    pooled, first, last = (load_run_data(run, epoch=e) for e in ("all", "first", "last"))
    assert first.name.endswith(", first epoch") and pooled.dims == first.dims == last.dims
    for d in first.dims:
        for k in ("in_eps_frac", "logr_std", "logr_mean"):
            for data, tag in ((pooled, ""), (first, "_first"), (last, "_last")):
                logged = [float(r[f"{k}{tag}_d{d}"]) if r[f"{k}{tag}_d{d}"] else math.nan for r in rows]
                np.testing.assert_array_equal(data.columns[f"{k}_d{d}"], logged)
    # the first epoch starts at r = 1 and drifts least: its log ratios spread less than the last epoch's
    spread = [np.nanmean([np.nanmean(x.columns[f"logr_std_d{d}"]) for d in first.dims]) for x in (first, last)]
    assert spread[0] < spread[1]
    with pytest.raises(ValueError, match="run_epoch must be one of"):
        load_run_data(run, epoch="middle")
    old = write_synthetic_run(tmp_path / "old")  # a run logged before the per-epoch statistics
    with pytest.raises(ValueError, match="missing columns in_eps_frac_first_d2"):
        load_run_data(old, epoch="first")
