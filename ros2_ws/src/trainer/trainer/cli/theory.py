"""``morph-theory``: figures and CSV grids for the paper's section III, and run overlays.

    morph-theory --out docs/figures/theory
    morph-theory --out /tmp/th --run-csv runs/compensated/progress.csv --run-csv runs/fixed

Figures (PNG, with the CSV they are drawn from):

1. ``fig1_clip_probability``: exact ``P(|log r| <= eps)`` over (dim, nu0), contours of approx - exact.
2. ``fig2_compensated``: the same at ``eps sqrt(dim)``, contours of the deviation from dim = 1.
3. ``fig3_monte_carlo``: Monte Carlo from sampled Gaussian policies vs the closed forms, eta != 1 included,
   one row per trust-region rule that clips the joint ratio (``algo.trust_region``).
4. ``fig4_update_scaling``: TRPO and beta-PPO update norms vs dim on the GNN policy (log-log, fitted slopes).
5. ``fig5_run_overlay`` (with ``--run-csv``): measured in-eps fraction per dim vs the closed form.

Numbers quoted in docs/theory.md come from ``summary.json``.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import sys
import time
import types
import typing
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from morph_core.algo import trust_region
from morph_core.algo.run_dir import RunDir
from morph_core.theory import clip_analysis as theory
from morph_core.theory import fisher_scaling
from morph_core.util.config_cli import BoolAction, CommandLineParser

_FISHER = fisher_scaling.ScalingConfig()  # figure 4's defaults live with the study itself


@dataclass
class TheoryConfig:
    """Options of ``morph-theory``; the argparse parser is generated from these fields."""

    out: Path = field(default=Path("theory_out"), metadata={"help": "output directory for PNGs, CSVs, summary.json"})
    eps: float = field(default=0.2, metadata={"help": "clip threshold eps of figures 1-3 (paper: 0.2)"})
    max_dim: int = field(default=20, metadata={"help": "largest action dimension on the figure axes"})
    nu0_points: int = field(default=200, metadata={"help": "grid points of nu0 in [nu0_min, 1] for figures 1-2"})
    nu0_min: float = field(default=0.005, metadata={"help": "smallest nu0 of figures 1-2 (log-spaced grid up to 1)"})
    mc_nu0: tuple[float, ...] = field(default=(0.05, 0.2), metadata={"help": "per-joint drifts nu0 of figure 3"})
    mc_eta: tuple[float, ...] = field(default=(0.9, 1.0, 1.1), metadata={"help": "std ratios eta of figure 3"})
    mc_samples: int = field(default=20_000, metadata={"help": "Monte Carlo samples per (dim, nu0, eta) point"})
    seed: int = field(default=0, metadata={"help": "seed of the Monte Carlo and of the Fisher states/policy"})
    fisher: bool = field(default=True, metadata={"help": "compute figure 4 (Fisher of the GNN policy)"})
    fisher_dims: tuple[int, ...] = field(default=_FISHER.dims, metadata={"help": "chain lengths d of figure 4"})
    fisher_states: int = field(
        default=_FISHER.states_per_dim, metadata={"help": "env states per chain length averaged in the Fisher"}
    )
    fisher_warmup: int = field(
        default=_FISHER.warmup_steps, metadata={"help": "random-action steps between two kept states"}
    )
    fisher_subspace: str = field(
        default=_FISHER.subspace,
        metadata={"help": f"actor parameters of the Fisher, one of {fisher_scaling.SUBSPACES}"},
    )
    fisher_subspace_dim: int = field(default=_FISHER.subspace_dim, metadata={"help": "k of --fisher-subspace random"})
    fisher_gradient: str = field(
        default=_FISHER.gradient, metadata={"help": f"the fixed gradient g, one of {fisher_scaling.GRADIENTS}"}
    )
    fisher_gradient_rcond: float = field(
        default=_FISHER.gradient_rcond,
        metadata={"help": "if > 0, keep only g's components along F(min d) eigenvalues > rcond * max"},
    )
    fisher_checkpoint: str | None = field(
        default=_FISHER.checkpoint, metadata={"help": "policy .safetensors to analyse (default: fresh init)"}
    )
    trpo_delta: float = field(default=_FISHER.delta, metadata={"help": "TRPO KL radius delta"})
    beta: float = field(default=_FISHER.beta, metadata={"help": "beta of the KL-penalty PPO update"})
    damping: float = field(
        default=_FISHER.damping,
        metadata={"help": "damping of the Fisher solve, relative to its largest eigenvalue at the smallest d"},
    )
    run_csv: list[Path] = field(
        default_factory=list,
        metadata={"help": "progress.csv of a morph-train run (or its run dir); repeat for several runs"},
    )
    run_tail: float = field(default=1.0, metadata={"help": "fraction of the last CSV rows averaged in the overlay"})
    run_epoch: str = field(
        default="all",
        metadata={"help": "log-ratio statistics the overlay reads: 'all' epochs of each update pooled, or only its "
                  "'first' or 'last' epoch (columns <name>_first_d<d>, <name>_last_d<d>)"},
    )  # fmt: skip


# -- argparse from the dataclass ---------------------------------------------------------------------


def build_parser() -> CommandLineParser:
    """One argument per :class:`TheoryConfig` field, with the field's default, type and help."""
    parser = CommandLineParser(prog="morph-theory", description=__doc__.split("\n\n")[0])
    hints = typing.get_type_hints(TheoryConfig)
    defaults = TheoryConfig()
    for f in dataclasses.fields(TheoryConfig):
        flag = "--" + f.name.replace("_", "-")
        hint, default = hints[f.name], getattr(defaults, f.name)
        kwargs: dict[str, typing.Any] = {"help": f"{f.metadata['help']} (default: {default})", "dest": f.name}
        origin = typing.get_origin(hint)
        if hint is bool:
            kwargs.update(action=BoolAction, default=default)
        elif origin is tuple:
            kwargs.update(nargs="+", type=typing.get_args(hint)[0], default=default)
        elif origin is list:
            kwargs.update(action="extend", nargs="+", type=typing.get_args(hint)[0], default=None)
        elif typing.get_origin(hint) in (typing.Union, types.UnionType):  # "X | None": parse as X
            kwargs.update(type=next(t for t in typing.get_args(hint) if t is not type(None)), default=default)
        else:
            kwargs.update(type=hint, default=default)
        parser.add_argument(flag, **kwargs)
        if hint is bool:  # the tool's --no-flag form of before
            no = "--no-" + f.name.replace("_", "-")
            parser.add_deprecated_alias(no, flag, value=False, shown=f"{flag} false")
    return parser


def parse_config(argv: Sequence[str] | None = None) -> TheoryConfig:
    ns = vars(build_parser().parse_args(argv))
    hints = typing.get_type_hints(TheoryConfig)
    for f in dataclasses.fields(TheoryConfig):
        origin = typing.get_origin(hints[f.name])
        if origin is tuple:
            ns[f.name] = tuple(ns[f.name])
        elif origin is list:
            ns[f.name] = list(ns[f.name] or [])
    return TheoryConfig(**ns)


# -- small helpers -----------------------------------------------------------------------------------


def _pyplot():
    # Matplotlib only for the figures
    import matplotlib

    matplotlib.use("Agg")  # headless: figures go to files only
    import matplotlib.pyplot as plt

    return plt


def write_csv(path: Path, header: Sequence[str], rows: typing.Iterable[Sequence[typing.Any]]) -> None:
    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(header)
        for row in rows:
            writer.writerow([f"{v:.6g}" if isinstance(v, float | np.floating) else v for v in row])


def nu0_axis(cfg: TheoryConfig) -> np.ndarray:
    """Log-spaced nu0 grid up to 1: the error is concentrated at small drifts, a log axis resolves it."""
    return np.geomspace(cfg.nu0_min, 1.0, cfg.nu0_points)


# -- figure 1 ----------------------------------------------------------------------------------------


@dataclass
class ProbabilityGrid:
    dims: np.ndarray  # [D] integer action dimensions
    nu0: np.ndarray  # [N]
    exact: np.ndarray  # [N, D]
    approx: np.ndarray  # [N, D]

    @property
    def error(self) -> np.ndarray:
        """Signed approximation error ``approx - exact`` (>= 0: the approximation overestimates)."""
        return self.approx - self.exact


def probability_grid(cfg: TheoryConfig, rule: str, dims: np.ndarray | None = None) -> ProbabilityGrid:
    dims = np.arange(1, cfg.max_dim + 1) if dims is None else dims
    nu0 = nu0_axis(cfg)
    d, n = dims[None, :], nu0[:, None]
    return ProbabilityGrid(
        dims,
        nu0,
        theory.clip_probability(d, n, cfg.eps, rule),
        theory.clip_probability_approx(d, n, cfg.eps, rule),
    )


def _heatmap(ax, grid: ProbabilityGrid):
    edges = np.concatenate([grid.dims - 0.5, [grid.dims[-1] + 0.5]])
    log_nu = np.log(grid.nu0)
    half = (log_nu[1] - log_nu[0]) / 2
    nu_edges = np.exp(np.concatenate([log_nu - half, [log_nu[-1] + half]]))
    mesh = ax.pcolormesh(edges, nu_edges, grid.exact, cmap="viridis", vmin=0.0, vmax=1.0, shading="flat")
    ax.set_xlabel("action dimension dim(A)")
    ax.set_ylabel(r"per-joint normalised drift $\nu_0$")
    ax.set_xticks(grid.dims[::2] if len(grid.dims) > 10 else grid.dims)
    ax.set_yscale("log")
    ax.set_ylim(grid.nu0[0], 1.0)
    return mesh


def figure1(cfg: TheoryConfig, plt) -> dict[str, float]:
    grid = probability_grid(cfg, "fixed")
    fine = probability_grid(cfg, "fixed", dims=np.linspace(1.0, cfg.max_dim, 400))
    err = grid.error
    i = np.unravel_index(int(np.argmax(err)), err.shape)
    sup, nu_star = theory.approx_error_supremum(cfg.eps)

    fig, ax = plt.subplots(figsize=(7.0, 4.6))
    mesh = _heatmap(ax, grid)
    fig.colorbar(mesh, ax=ax, label=r"exact $P[-\epsilon \leq \log r \leq \epsilon]$")
    levels = [0.01, 0.05, 0.1, 0.15, 0.2]
    cs = ax.contour(fine.dims, fine.nu0, fine.error, levels=levels, colors="white", linewidths=0.9)
    ax.clabel(cs, fmt="%.2f", fontsize=7)
    # The error peaks on the curve |nu| = sqrt(2/pi) eps, where the capped approximation reaches 1.
    dd = np.linspace(1.0, cfg.max_dim, 200)
    ax.plot(dd, nu_star / np.sqrt(dd), "r--", lw=1.0, label=rf"$|\nu| = \sqrt{{2/\pi}}\,\epsilon$ (sup err {sup:.3f})")
    ax.plot(grid.dims[i[1]], grid.nu0[i[0]], "rx", ms=8, label=f"grid max {err[i]:.3f}")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(rf"Fig. 1: clip-free probability, $\epsilon$={cfg.eps}; contours: approx $-$ exact", fontsize=10)
    fig.tight_layout()
    fig.savefig(cfg.out / "fig1_clip_probability.png", dpi=130)
    plt.close(fig)

    rows = (
        (int(d), float(n), float(ex), float(ap), float(ap - ex))
        for n, row_ex, row_ap in zip(grid.nu0, grid.exact, grid.approx, strict=True)
        for d, ex, ap in zip(grid.dims, row_ex, row_ap, strict=True)
    )
    write_csv(cfg.out / "fig1_grid.csv", ["dim", "nu0", "exact", "approx", "approx_minus_exact"], rows)
    return {
        "fig1_max_error_grid": float(err[i]),
        "fig1_max_error_dim": int(grid.dims[i[1]]),
        "fig1_max_error_nu0": float(grid.nu0[i[0]]),
        "fig1_min_error_grid": float(err.min()),
        "approx_error_supremum": sup,
        "approx_error_supremum_nu": nu_star,
    }


# -- figure 2 ----------------------------------------------------------------------------------------


def figure2(cfg: TheoryConfig, plt) -> dict[str, float]:
    grid = probability_grid(cfg, "compensated")
    fine = probability_grid(cfg, "compensated", dims=np.linspace(1.0, cfg.max_dim, 400))
    # Deviation from the dim = 1 reference: what compensation leaves of the dimension dependence.
    deviation = grid.exact - grid.exact[:, :1]
    fine_dev = fine.exact - theory.clip_probability(1, fine.nu0, cfg.eps)[:, None]
    i = np.unravel_index(int(np.argmax(np.abs(deviation))), deviation.shape)

    fig, ax = plt.subplots(figsize=(7.0, 4.6))
    mesh = _heatmap(ax, grid)
    fig.colorbar(mesh, ax=ax, label=r"exact $P[|\log r| \leq \epsilon\sqrt{\dim}]$")
    cs = ax.contour(fine.dims, fine.nu0, fine_dev, levels=[-0.12, -0.08, -0.04, -0.01], colors="white", linewidths=0.9)
    ax.clabel(cs, fmt="%.2f", fontsize=7)
    ax.plot(grid.dims[i[1]], grid.nu0[i[0]], "rx", ms=8, label=f"max |deviation| {abs(deviation[i]):.3f}")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(r"Fig. 2: compensated ($\epsilon\sqrt{\dim}$), contours: $P(\dim) - P(1)$", fontsize=10)
    fig.tight_layout()
    fig.savefig(cfg.out / "fig2_compensated.png", dpi=130)
    plt.close(fig)

    rows = (
        (int(d), float(n), float(ex), float(dv), float(ap - ex))
        for n, row_ex, row_dv, row_ap in zip(grid.nu0, grid.exact, deviation, grid.approx, strict=True)
        for d, ex, dv, ap in zip(grid.dims, row_ex, row_dv, row_ap, strict=True)
    )
    write_csv(cfg.out / "fig2_grid.csv", ["dim", "nu0", "exact", "deviation_from_dim1", "approx_minus_exact"], rows)
    return {
        "fig2_max_abs_deviation": float(abs(deviation[i])),
        "fig2_max_abs_deviation_dim": int(grid.dims[i[1]]),
        "fig2_max_abs_deviation_nu0": float(grid.nu0[i[0]]),
        "fig2_max_approx_error": float(grid.error.max()),
    }


# -- figure 3 ----------------------------------------------------------------------------------------


def monte_carlo_table(cfg: TheoryConfig) -> list[dict[str, float]]:
    """Monte Carlo vs Gaussian closed form vs exact non-central chi2 law, per (rule, nu0, eta, dim).

    The rules are the table's rules that clip the joint ratio, in the table's order.
    """
    rng = np.random.default_rng(cfg.seed)
    rows = []
    for rule in trust_region.clip_rules():
        for nu0 in cfg.mc_nu0:
            for eta in cfg.mc_eta:
                for dim in range(1, cfg.max_dim + 1):
                    est = theory.monte_carlo_point(dim, nu0, cfg.eps, eta, cfg.mc_samples, rng, rule)
                    gauss = float(theory.clip_probability(dim, nu0, cfg.eps, rule))
                    exact_eta = float(theory.clip_probability_eta(dim, nu0, cfg.eps, eta, rule))
                    m_th, s_th = theory.log_ratio_moments(dim, nu0, eta)
                    rows.append(
                        {
                            "rule": rule.name,
                            "nu0": nu0,
                            "eta": eta,
                            "dim": dim,
                            "mc": est.probability,
                            "mc_stderr": est.stderr,
                            "closed_form_eta1": gauss,
                            "exact_eta": exact_eta,
                            "z_vs_closed_form": (est.probability - gauss) / max(est.stderr, 1.0 / cfg.mc_samples),
                            "mc_logr_mean": est.logr_mean,
                            "mc_logr_std": est.logr_std,
                            "theory_logr_mean": float(m_th),
                            "theory_logr_std": float(s_th),
                        }
                    )
    return rows


def figure3(cfg: TheoryConfig, plt) -> dict[str, float]:
    rows = monte_carlo_table(cfg)
    write_csv(cfg.out / "fig3_monte_carlo.csv", list(rows[0]), (list(r.values()) for r in rows))
    colors = {eta: f"C{k}" for k, eta in enumerate(cfg.mc_eta)}
    rules = list(dict.fromkeys(r["rule"] for r in rows))
    fig, axes = plt.subplots(
        len(rules), len(cfg.mc_nu0), figsize=(5.0 * len(cfg.mc_nu0), 3.5 * len(rules)), squeeze=False
    )
    for r_i, rule in enumerate(rules):
        for c_i, nu0 in enumerate(cfg.mc_nu0):
            ax = axes[r_i, c_i]
            sel = [r for r in rows if r["rule"] == rule and r["nu0"] == nu0]
            dims = np.array([r["dim"] for r in sel if r["eta"] == cfg.mc_eta[0]])
            ax.plot(dims, [r["closed_form_eta1"] for r in sel if r["eta"] == cfg.mc_eta[0]], "k-", lw=2,
                    label=r"closed form ($\eta$=1)")  # fmt: skip
            for eta in cfg.mc_eta:
                pts = [r for r in sel if r["eta"] == eta]
                ax.errorbar(dims, [p["mc"] for p in pts], yerr=[2 * p["mc_stderr"] for p in pts], fmt="o", ms=3,
                            color=colors[eta], capsize=2, label=rf"MC $\eta$={eta} ($\pm$2 s.e.)")  # fmt: skip
                if eta != 1.0:
                    ax.plot(dims, [p["exact_eta"] for p in pts], "--", color=colors[eta], lw=1,
                            label=rf"exact $\chi'^2$ law $\eta$={eta}")  # fmt: skip
            ax.set_title(rf"$\nu_0$={nu0}, rule {rule}, $\epsilon$={cfg.eps}", fontsize=10)
            ax.set_xlabel("action dimension")
            ax.set_ylabel(r"$P[|\log r| \leq$ clip range$]$")
            ax.set_ylim(-0.02, 1.02)
            ax.set_xticks(dims[::2] if len(dims) > 10 else dims)
            ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7, loc="lower left", framealpha=0.9)
    fig.suptitle(f"Fig. 3: Monte Carlo from sampled Gaussian policies ({cfg.mc_samples} samples/point)", fontsize=11)
    fig.tight_layout()
    fig.savefig(cfg.out / "fig3_monte_carlo.png", dpi=130)
    plt.close(fig)

    eta1 = [r for r in rows if r["eta"] == 1.0]
    other = [r for r in rows if r["eta"] != 1.0]
    summary = {"fig3_points": len(rows)}
    if eta1:
        summary["fig3_eta1_max_abs_z"] = float(max(abs(r["z_vs_closed_form"]) for r in eta1))
        summary["fig3_eta1_max_abs_diff"] = float(max(abs(r["mc"] - r["closed_form_eta1"]) for r in eta1))
    if other:
        summary["fig3_eta_ne1_max_abs_diff_vs_closed_form"] = float(
            max(abs(r["mc"] - r["closed_form_eta1"]) for r in other)
        )
        summary["fig3_eta_ne1_max_abs_diff_vs_exact_eta"] = float(max(abs(r["mc"] - r["exact_eta"]) for r in other))
    return summary


# -- figure 4 ----------------------------------------------------------------------------------------


def figure4(cfg: TheoryConfig, plt) -> dict[str, float]:
    result = fisher_scaling.update_norm_scaling(
        fisher_scaling.ScalingConfig(
            dims=cfg.fisher_dims,
            states_per_dim=cfg.fisher_states,
            warmup_steps=cfg.fisher_warmup,
            subspace=cfg.fisher_subspace,
            subspace_dim=cfg.fisher_subspace_dim,
            gradient=cfg.fisher_gradient,
            gradient_rcond=cfg.fisher_gradient_rcond,
            delta=cfg.trpo_delta,
            beta=cfg.beta,
            damping=cfg.damping,
            seed=cfg.seed,
            checkpoint=cfg.fisher_checkpoint,
        )
    )
    write_csv(cfg.out / "fig4_update_scaling.csv", result.csv_header(), result.csv_rows())
    write_csv(
        cfg.out / "fig4_damping_sweep.csv",
        ["relative_damping", "trpo_slope", "beta_slope"],
        ([k, v[0], v[1]] for k, v in result.damping_sweep.items()),
    )
    fig, (ax_n, ax_e, ax_s) = plt.subplots(1, 3, figsize=(15.0, 4.4))
    dims = np.asarray(result.dims, dtype=float)
    ref = dims / dims[0]
    for norms, slope, intercept, label, color, paper in (
        (result.trpo_norms, result.trpo_slope, result.trpo_intercept, "TRPO", "C0", -0.5),
        (result.beta_norms, result.beta_slope, result.beta_intercept, r"$\beta$-PPO", "C3", -1.0),
    ):
        ax_n.loglog(dims, norms, "o", color=color, label=f"{label}: fitted slope {slope:+.2f}")
        ax_n.loglog(dims, np.exp(intercept) * dims**slope, "-", color=color, lw=1)
        ax_n.loglog(dims, norms[0] * ref**paper, ":", color=color, label=f"paper: slope {paper:+.1f}")
    ax_n.set_xlabel("chain length d (action dimension)")
    ax_n.set_ylabel(r"$\|\Delta\theta\|$")
    ax_n.set_title(f"update norm, fixed g ({result.gradient_kind}), damping {cfg.damping:g}", fontsize=9)
    ax_n.legend(fontsize=7)
    slopes = result.eigen_slopes()
    for values, name, marker in (
        (result.eig_max, "max", "^"),
        (result.eig_mean, "mean", "o"),
        (result.eig_min, "min", "v"),
    ):
        label = f"{name} eigenvalue" + (
            f", slope {slopes[f'fisher_eig_{name}_slope']:+.2f}" if f"fisher_eig_{name}_slope" in slopes else ""
        )
        ax_e.loglog(dims, values, marker + "-", ms=4, label=label)  # fmt: skip
    ax_e.loglog(dims, result.eig_mean[0] * ref, "k:", label="slope +1 (paper's assumption)")
    ax_e.set_xlabel("chain length d")
    ax_e.set_ylabel("Fisher eigenvalue")
    ax_e.set_title(f"Fisher spectrum: {result.subspace} + log-std", fontsize=9)
    ax_e.legend(fontsize=7)
    damp = np.array(list(result.damping_sweep))
    swept = np.array(list(result.damping_sweep.values()))
    ax_s.semilogx(damp, swept[:, 0], "o-", color="C0", label="TRPO slope")
    ax_s.semilogx(damp, swept[:, 1], "s-", color="C3", label=r"$\beta$-PPO slope")
    ax_s.axhline(-0.5, color="C0", ls=":", label="paper -1/2")
    ax_s.axhline(-1.0, color="C3", ls=":", label="paper -1")
    ax_s.set_xlabel(r"damping / $\lambda_{max}(F_{d_{min}})$")
    ax_s.set_ylabel("fitted log-log slope")
    ax_s.set_title("slopes vs damping of the Fisher solve", fontsize=9)
    ax_s.legend(fontsize=7)
    ticks = [t for t in (1, 2, 3, 5, 10, 15, 20, 30, 50) if dims[0] <= t <= dims[-1]]
    for ax in (ax_n, ax_e):
        ax.set_xticks(ticks, [str(t) for t in ticks])
        ax.xaxis.set_minor_formatter(plt.NullFormatter())
    for ax in (ax_n, ax_e, ax_s):
        ax.grid(alpha=0.3, which="both")
    which = f"checkpoint {Path(cfg.fisher_checkpoint).name}" if cfg.fisher_checkpoint else "fresh init"
    fig.suptitle(
        f"Fig. 4: TRPO / beta-PPO update norms, GNN policy ({which}), {cfg.fisher_states} states per d", fontsize=11
    )
    fig.tight_layout()
    fig.savefig(cfg.out / "fig4_update_scaling.png", dpi=130)
    plt.close(fig)
    return result.summary()


# -- figure 5: training-run overlay ------------------------------------------------------------------


@dataclass
class RunData:
    name: str
    clip_eps: float
    clip_mode: str
    dims: list[int]
    columns: dict[str, np.ndarray]


RUN_COLUMNS = ("in_eps_frac", "logr_std", "logr_mean")
RUN_EPOCHS = {"all": "", "first": "_first", "last": "_last"}
"""``run_epoch`` -> the column tag of those statistics (``algo.update_stats.EPOCH_TAGS``)"""


def load_run_data(path: Path, fallback_eps: float | None = None, epoch: str = "all") -> RunData:
    """Read a run's progress log (a run directory, or the CSV itself) and its config (``algo.run_dir.RunDir``).

    ``epoch``: the statistics of all epochs pooled, or of each update's first or last epoch alone,
    returned under the pooled names (``in_eps_frac_d<d>`` ...). Raises ``ValueError`` naming the
    missing columns or file; empty cells (a dimension absent from a minibatch) become NaN.
    """
    if epoch not in RUN_EPOCHS:
        raise ValueError(f"run_epoch must be one of {list(RUN_EPOCHS)}, got {epoch!r}")
    tag = RUN_EPOCHS[epoch]
    files = RunDir(path if path.is_dir() else path.parent)
    csv_path = files.progress if path.is_dir() else path
    if not csv_path.is_file():
        raise ValueError(f"run CSV not found: {csv_path}")
    with csv_path.open(newline="") as fh:
        reader = csv.DictReader(fh)
        header = reader.fieldnames or []
        records = list(reader)
    dims = sorted(int(c.removeprefix("in_eps_frac_d")) for c in header if c.startswith("in_eps_frac_d"))
    if not dims:
        raise ValueError(f"{csv_path}: no in_eps_frac_d<d> columns (header: {', '.join(header) or 'empty'})")
    missing = [f"{k}{tag}_d{d}" for d in dims for k in RUN_COLUMNS if f"{k}{tag}_d{d}" not in header]
    if missing:
        raise ValueError(f"{csv_path}: missing columns {', '.join(missing)}")
    if not records:
        raise ValueError(f"{csv_path}: no data rows")

    def column(name: str) -> np.ndarray:
        return np.array([float(r[name]) if r.get(name, "") not in ("", None) else np.nan for r in records])

    columns = {f"{k}_d{d}": column(f"{k}{tag}_d{d}") for d in dims for k in RUN_COLUMNS}
    config_path = files.config
    if config_path.is_file():
        config = json.loads(config_path.read_text())
        if "clip_eps" not in config:
            raise ValueError(f"{config_path}: no 'clip_eps' key")
        clip_eps, clip_mode = float(config["clip_eps"]), str(config.get("clip_mode", "unknown"))
    elif fallback_eps is not None:
        print(f"morph-theory: {config_path} missing, assuming clip_eps={fallback_eps}", file=sys.stderr)
        clip_eps, clip_mode = fallback_eps, "unknown"
    else:
        raise ValueError(f"{config_path} missing (needed for clip_eps)")
    name = f"{csv_path.parent.name} ({clip_mode})" + ("" if epoch == "all" else f", {epoch} epoch")
    return RunData(name, clip_eps, clip_mode, dims, columns)


def run_overlay_rows(run: RunData, tail: float) -> list[dict[str, float]]:
    """Per dimension: measured in-eps fraction vs the closed form at the measured ``|nu| = std(log r)``.

    The in-eps fraction is measured with the base ``clip_eps`` whatever the clip mode, so the closed
    form is evaluated uncompensated. The prediction is made row by row and then averaged, as the drift
    changes during training. ``nu0 = |nu| / sqrt(d)`` tells whether the homogeneous-drift model holds.
    """
    n_rows = len(next(iter(run.columns.values())))
    start = n_rows - max(1, int(round(tail * n_rows)))
    rows = []
    for d in run.dims:
        frac = run.columns[f"in_eps_frac_d{d}"][start:]
        std = run.columns[f"logr_std_d{d}"][start:]
        mean = run.columns[f"logr_mean_d{d}"][start:]
        ok = np.isfinite(frac) & np.isfinite(std) & np.isfinite(mean)
        if not ok.any():
            continue
        pred = theory.clip_probability(1, std[ok], run.clip_eps)
        rows.append(
            {
                "dim": d,
                "n_rows": int(ok.sum()),
                "measured_in_eps": float(frac[ok].mean()),
                "measured_in_eps_sd": float(frac[ok].std()),
                "predicted_at_measured_nu": float(pred.mean()),
                "logr_std": float(std[ok].mean()),
                "logr_mean": float(mean[ok].mean()),
                "predicted_logr_mean": float((-(std[ok] ** 2) / 2).mean()),
                "nu0_estimate": float((std[ok] / np.sqrt(d)).mean()),
            }
        )
    return rows


def figure5(cfg: TheoryConfig, plt) -> dict[str, float]:
    runs = [load_run_data(p, fallback_eps=cfg.eps, epoch=cfg.run_epoch) for p in cfg.run_csv]
    fig, (ax_p, ax_m) = plt.subplots(1, 2, figsize=(11.0, 4.4))
    all_rows, summary = [], {}
    for k, run in enumerate(runs):
        rows = run_overlay_rows(run, cfg.run_tail)
        if not rows:
            raise ValueError(f"{run.name}: every row of every dimension is empty")
        color = f"C{k}"
        dims = np.array([r["dim"] for r in rows])
        ax_p.errorbar(dims, [r["measured_in_eps"] for r in rows], yerr=[r["measured_in_eps_sd"] for r in rows],
                      fmt="o", color=color, capsize=2, label=f"{run.name}: measured")  # fmt: skip
        ax_p.plot(dims, [r["predicted_at_measured_nu"] for r in rows], "x--", color=color,
                  label=rf"{run.name}: closed form at measured $|\nu|$=std(log r)")  # fmt: skip
        # Homogeneous-drift curve with nu0 fitted as the median over dims of std / sqrt(d).
        nu0_hat = float(np.median([r["nu0_estimate"] for r in rows]))
        dd = np.arange(1, max(cfg.max_dim, int(dims.max())) + 1)
        ax_p.plot(dd, theory.clip_probability(dd, nu0_hat, run.clip_eps), ":", color=color,
                  label=rf"{run.name}: closed form, homogeneous $\nu_0$={nu0_hat:.3f}")  # fmt: skip
        ax_m.plot([r["predicted_logr_mean"] for r in rows], [r["logr_mean"] for r in rows], "o", color=color,
                  label=run.name)  # fmt: skip
        for r in rows:
            all_rows.append({"run": run.name, "clip_eps": run.clip_eps, **r})
        errs = [abs(r["measured_in_eps"] - r["predicted_at_measured_nu"]) for r in rows]
        summary[f"run{k}_max_abs_in_eps_error"] = float(max(errs))
        summary[f"run{k}_nu0_estimate"] = nu0_hat
    lo = min(min(r["predicted_logr_mean"], r["logr_mean"]) for r in all_rows)
    ax_m.plot([lo, 0], [lo, 0], "k-", lw=0.8, label="identity")
    ax_m.set_xlabel(r"$-\mathrm{std}(\log r)^2 / 2$ (theory for $\eta$=1)")
    ax_m.set_ylabel(r"measured mean$(\log r)$")
    ax_m.legend(fontsize=7)
    ax_m.grid(alpha=0.3)
    ax_p.set_xlabel("action dimension")
    ax_p.set_ylabel(r"fraction with $|\log r| \leq \epsilon$")
    ax_p.set_ylim(-0.02, 1.02)
    ax_p.grid(alpha=0.3)
    ax_p.legend(fontsize=7)
    fig.suptitle("Fig. 5: training runs vs theory", fontsize=11)
    fig.tight_layout()
    fig.savefig(cfg.out / "fig5_run_overlay.png", dpi=130)
    plt.close(fig)
    write_csv(cfg.out / "fig5_run_overlay.csv", list(all_rows[0]), (list(r.values()) for r in all_rows))
    return summary


# -- entry point -------------------------------------------------------------------------------------


def check_inputs(cfg: TheoryConfig) -> None:
    """Raise ``ValueError`` for inputs the figures would fail on, before any is made: every ``--run-csv`` is
    read (columns, rows, clip_eps) and must give the overlay a dimension with data."""
    if not 0 < cfg.run_tail <= 1:
        raise ValueError(f"run_tail must be in (0, 1], got {cfg.run_tail}")
    for path in cfg.run_csv:
        run = load_run_data(path, fallback_eps=cfg.eps, epoch=cfg.run_epoch)
        if not run_overlay_rows(run, cfg.run_tail):
            raise ValueError(f"{run.name}: every row of every dimension is empty")


def run(cfg: TheoryConfig) -> dict[str, float]:
    """Make every figure of ``cfg``; returns (and writes) the summary numbers."""
    # torch only when figures are made, not for --help
    import torch

    torch.set_num_threads(1)  # the machine is shared with training runs
    cfg.out.mkdir(parents=True, exist_ok=True)
    plt = _pyplot()
    summary: dict[str, typing.Any] = {"config": {k: str(v) for k, v in dataclasses.asdict(cfg).items()}}
    steps = [("fig1", figure1), ("fig2", figure2), ("fig3", figure3)]
    if cfg.fisher:
        steps.append(("fig4", figure4))
    if cfg.run_csv:
        steps.append(("fig5", figure5))
    for name, make in steps:
        t0 = time.perf_counter()
        summary.update(make(cfg, plt))
        summary[f"{name}_seconds"] = round(time.perf_counter() - t0, 2)
    (cfg.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def main(argv: Sequence[str] | None = None) -> int:
    cfg = parse_config(argv)
    try:
        check_inputs(cfg)  # a bad --run-csv is said before minutes of figures, not after
        summary = run(cfg)
    except ValueError as exc:
        print(f"morph-theory: error: {exc}", file=sys.stderr)
        return 2
    for key, value in summary.items():
        if key != "config":
            print(f"{key}: {value:.4g}" if isinstance(value, float) else f"{key}: {value}")
    print(f"wrote figures and CSVs to {cfg.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
