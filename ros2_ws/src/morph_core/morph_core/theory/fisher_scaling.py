"""TRPO / beta-PPO update norms vs action dimension, measured on the project's GNN policy.

The paper (section III) argues that the Fisher information ``F`` of a factorised policy is a sum of
per-joint terms, so its eigenvalues grow like ``d`` (the action dimension) while the gradient's
coordinates ``alpha = Q^T g`` do not. Then, for a fixed gradient ``g``,

    |dtheta_TRPO| = sqrt(2 delta / (g^T F^-1 g)) |F^-1 g|  ~  d^-1/2,
    |dtheta_beta| = |F^-1 g| / beta                          ~  d^-1.

This module computes ``F`` exactly for :class:`~morph_core.policy.actor_critic.GraphActorCritic` on real
``MorphSwimmer-v0`` states of chains with ``d`` joints and fits ``log |dtheta|`` against ``log d``.

Fisher of the policy. ``pi(a|s) = prod_j N(a_j; mu_j(s), sigma^2)`` with one state-independent
``log sigma``. Its score is ``(J_mu(s)^T (a - mu) / sigma^2, sum_j (z_j^2 - 1))`` with
``z = (a - mu) / sigma``, so the expected Fisher over actions at a state is block diagonal,

    F(s) = [ J_mu(s)^T J_mu(s) / sigma^2     0  ]
           [ 0                              2 d ],

and ``F = mean_s F(s)``. ``J_mu`` is the Jacobian of the ``d`` means w.r.t. the mean parameters
(extractor and actor head). The test suite checks this closed form against the average of
per-sample score outer products from autograd.

Parameter space. The actor has ~10.9k parameters, but a batch of ``N`` states of a ``d``-joint
chain gives ``F`` rank at most ``N d + 1``: in the full space ``F`` is singular and ``F^-1 g`` is
decided by the damping (null-space directions get ``g / damping`` whatever ``d`` is). The default
therefore restricts the policy to a fixed ``k``-dimensional affine subspace of its actor
parameters, ``theta = theta_0 + B u`` (``B`` orthonormal, fixed across ``d``), which is a policy
in its own right with Fisher ``B^T F B``; with ``N d >> k`` this is well determined at every ``d``.
``subspace="output"`` uses the actor head's output layer (the 65 parameters that map the last
hidden layer to the mean), ``"random"`` a random ``k``-subspace of all actor parameters, ``"full"``
all of them (ill-posed, reported for completeness). ``log sigma`` is always a coordinate.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gymnasium
import numpy as np
import torch
from torch.func import functional_call, jacrev, jvp, vmap

import morph_core.env.registration  # noqa: F401  (registers MorphSwimmer-v0)
from morph_core.policy.actor_critic import GraphActorCritic, PolicyConfig
from morph_core.policy.chains import ChainBatch

SUBSPACES = ("output", "random", "full")
GRADIENTS = ("random", "policy_gradient")


@dataclass
class ScalingConfig:
    """What to measure; defaults are the ones behind docs/theory.md's figure 4."""

    dims: tuple[int, ...] = tuple(range(2, 21))
    """chain lengths d"""
    states_per_dim: int = 256
    """env states per chain length over which the Fisher is averaged"""
    warmup_steps: int = 5
    """random-action steps between two kept states"""
    states_per_episode: int = 32
    """kept states before the env is reset with a new seed (variety of initial conditions)"""
    subspace: str = "output"
    """'output' (actor output layer), 'random' (random k-subspace of all actor params) or 'full'"""
    subspace_dim: int = 32
    """k for subspace='random'"""
    gradient: str = "random"
    """'random': fixed random unit vector; 'policy_gradient': score-weighted random advantages at min(dims)"""
    gradient_rcond: float = 0.0
    """if > 0, project g onto F's eigenvectors at min(dims) with eigenvalue > rcond * lambda_max
    (drops directions a trained policy cannot move at all, e.g. saturated units)"""
    delta: float = 0.01
    """TRPO KL radius"""
    beta: float = 1.0
    """KL-penalty coefficient of beta-PPO"""
    damping: float = 1e-8
    """Tikhonov damping added to F, relative to F's largest eigenvalue at min(dims); fixed across d"""
    damping_sweep: tuple[float, ...] = (1e-10, 1e-8, 1e-6, 1e-4, 1e-3, 1e-2, 1e-1)
    """relative dampings at which the slopes are refitted (how much the conclusion depends on it)"""
    seed: int = 0
    """seed of policy init, env states, subspace and gradient"""
    checkpoint: str | None = None
    """policy .safetensors to analyse instead of a freshly initialised policy"""

    def __post_init__(self):
        if self.subspace not in SUBSPACES:
            raise ValueError(f"subspace must be one of {SUBSPACES}, got {self.subspace!r}")
        if self.gradient not in GRADIENTS:
            raise ValueError(f"gradient must be one of {GRADIENTS}, got {self.gradient!r}")
        if len(self.dims) < 2 or min(self.dims) < 1:
            raise ValueError(f"need at least two chain lengths >= 1, got {self.dims}")


# -- states ------------------------------------------------------------------------------------------


def collect_states(num_joints: int, n: int, warmup_steps: int, states_per_episode: int, seed: int) -> ChainBatch:
    """``n`` graph observations of a ``num_joints`` chain driven by uniform random actions in [-1, 1]."""
    env = gymnasium.make("MorphSwimmer-v0", num_joints=num_joints, observation_mode="graph")
    rng = np.random.default_rng([seed, num_joints])
    observations = []
    for i in range(n):
        if i % states_per_episode == 0:
            env.reset(seed=int(rng.integers(2**31)))
        for _ in range(warmup_steps):
            obs, *_ = env.step(rng.uniform(-1.0, 1.0, num_joints).astype(np.float32))
        observations.append(obs)
    env.close()
    return ChainBatch.from_observations(observations)


# -- parameter subspace and mean Jacobian ------------------------------------------------------------


def mean_parameters(policy: GraphActorCritic) -> dict[str, torch.Tensor]:
    """Actor parameters the Gaussian mean depends on (``actor_parameters()`` minus the log-std)."""
    actor = {id(p) for p in policy.actor_parameters()}
    return {name: p.detach() for name, p in policy.named_parameters() if id(p) in actor and p is not policy.log_std}


@dataclass
class Subspace:
    """Orthonormal directions ``B`` [P, k] in the flattened mean parameters (None: all of them)."""

    names: list[str]
    shapes: list[torch.Size]
    basis: torch.Tensor | None
    label: str

    @property
    def num_params(self) -> int:
        return int(sum(int(np.prod(s)) for s in self.shapes))

    @property
    def dim(self) -> int:
        return self.num_params if self.basis is None else self.basis.shape[1]

    def tangents(self) -> dict[str, torch.Tensor]:
        """The ``k`` directions as a dict of [k, *param_shape] tensors (for a vmapped jvp)."""
        assert self.basis is not None
        out, off = {}, 0
        for name, shape in zip(self.names, self.shapes, strict=True):
            size = int(np.prod(shape))
            out[name] = self.basis[off : off + size].T.reshape(-1, *shape).to(torch.float32).contiguous()
            off += size
        return out


def make_subspace(params: dict[str, torch.Tensor], kind: str, k: int, seed: int) -> Subspace:
    names = list(params)
    shapes = [params[n].shape for n in names]
    sizes = [params[n].numel() for n in names]
    total = sum(sizes)
    if kind == "full":
        return Subspace(names, shapes, None, f"all {total} mean parameters")
    if kind == "output":
        # The actor head's last Linear: the parameters that map the last hidden layer to the mean.
        out_names = [n for n in names if n.startswith("actor_head.")]
        last_layer = max(int(n.split(".")[1]) for n in out_names)
        chosen = {f"actor_head.{last_layer}.weight", f"actor_head.{last_layer}.bias"}
        cols, off = [], 0
        for n, size in zip(names, sizes, strict=True):
            if n in chosen:
                cols.extend(range(off, off + size))
            off += size
        basis = torch.zeros(total, len(cols), dtype=torch.float64)
        basis[cols, torch.arange(len(cols))] = 1.0
        return Subspace(names, shapes, basis, f"actor output layer ({len(cols)} parameters)")
    gen = torch.Generator().manual_seed(seed)
    basis, _ = torch.linalg.qr(torch.randn(total, k, generator=gen, dtype=torch.float64))
    return Subspace(names, shapes, basis, f"random {k}-dim subspace of {total} mean parameters")


def mean_jacobian(policy: GraphActorCritic, batch: ChainBatch, subspace: Subspace, chunk: int = 64) -> torch.Tensor:
    """``J[s, j, i] = d mu_j(s) / d u_i`` for the subspace coordinates ``u``: [N, d, k], float64.

    Forward mode (one jvp per direction, vmapped) when ``k`` is small; reverse mode over the
    ``d`` outputs of each chunk of states when the subspace is the full parameter space.
    """
    params = mean_parameters(policy)

    def means(p: dict[str, torch.Tensor], b: ChainBatch) -> torch.Tensor:
        return functional_call(policy, p, (b,))[0]

    if subspace.basis is not None:
        tangents = subspace.tangents()
        cols = []
        for start in range(0, subspace.dim, chunk):
            t = {n: v[start : start + chunk] for n, v in tangents.items()}
            cols.append(vmap(lambda tt: jvp(lambda p: means(p, batch), (params,), (tt,))[1])(t))
        return torch.cat(cols).permute(1, 2, 0).double()
    rows = []
    for start in range(0, batch.batch_size, 8):
        sub = batch.select(torch.arange(start, min(start + 8, batch.batch_size)))
        jac = jacrev(lambda p, b=sub: means(p, b))(params)
        rows.append(torch.cat([jac[n].reshape(sub.batch_size, sub.max_joints, -1) for n in subspace.names], dim=2))
    return torch.cat(rows).double()


# -- Fisher and the two updates ----------------------------------------------------------------------


@dataclass
class Fisher:
    """``F = G^T G`` on the mean coordinates (``G`` = stacked ``J_sj / (sigma sqrt(N))``) plus ``log_std_block``.

    Held through the thin SVD of ``G`` so that ``(F + lambda I)^-1 g`` is exact and cheap whether
    ``k`` is 65 or 10,913: ``V diag(1/(s^2 + lambda)) V^T g + (g - V V^T g) / lambda``.
    """

    singular_values: torch.Tensor  # [r]
    right_vectors: torch.Tensor  # [r, k]
    log_std_block: float  # 2 d
    dim: int  # k + 1 coordinates, log-std last

    @classmethod
    def from_jacobian(cls, jac: torch.Tensor, log_std: float) -> Fisher:
        n, d, k = jac.shape
        sigma2 = float(np.exp(2.0 * log_std))
        g = jac.reshape(n * d, k) / np.sqrt(n * sigma2)
        _, s, vh = torch.linalg.svd(g, full_matrices=False)
        return cls(s, vh, 2.0 * d, k + 1)

    def eigenvalues(self) -> np.ndarray:
        """All ``k + 1`` eigenvalues, descending (zeros where ``N d < k``)."""
        lam = np.zeros(self.dim)
        mean_eigs = (self.singular_values**2).numpy()
        lam[: len(mean_eigs)] = mean_eigs
        lam[len(mean_eigs)] = self.log_std_block
        return np.sort(lam)[::-1]

    def numerical_rank(self, rcond: float = 1e-10) -> int:
        lam = self.eigenvalues()
        return int((lam > rcond * lam[0]).sum())

    def project_to_range(self, g: torch.Tensor, rcond: float) -> torch.Tensor:
        """``g`` without its components along eigenvectors with eigenvalue <= rcond * lambda_max."""
        keep = self.singular_values**2 > rcond * float(self.eigenvalues()[0])
        v = self.right_vectors[keep]
        return torch.cat([v.T @ (v @ g[:-1]), g[-1:]])

    def solve(self, g: torch.Tensor, damping: float) -> torch.Tensor:
        """``(F + damping I)^-1 g``."""
        gm, gl = g[:-1], g[-1:]
        v = self.right_vectors
        proj = v @ gm
        x = v.T @ (proj / (self.singular_values**2 + damping))
        if damping > 0:  # with no damping this is the pseudo-inverse: null-space part of g dropped
            x = x + (gm - v.T @ proj) / damping
        return torch.cat([x, gl / (self.log_std_block + damping)])


def update_norms(fisher: Fisher, g: torch.Tensor, delta: float, beta: float, damping: float) -> tuple[float, float]:
    """``(|dtheta_TRPO|, |dtheta_beta|)`` for gradient ``g`` (paper eqs. for both updates)."""
    x = fisher.solve(g, damping)
    norm = float(x.norm())
    return float(np.sqrt(2.0 * delta / float(g @ x))) * norm, norm / beta


def fit_slope(dims: np.ndarray, values: np.ndarray) -> tuple[float, float]:
    """Least-squares ``log values = slope log dims + intercept``."""
    slope, intercept = np.polyfit(np.log(np.asarray(dims, float)), np.log(np.asarray(values, float)), 1)
    return float(slope), float(intercept)


def random_advantage_gradient(fisher_jac: torch.Tensor, log_std: float, seed: int) -> torch.Tensor:
    """A policy gradient ``mean_s score(s, a_s) A_s`` with actions from the policy and N(0, 1) advantages.

    Stands in for a real advantage-weighted gradient: it lies in the span of the policy's score
    vectors at those states, unlike a random vector.
    """
    n, d, k = fisher_jac.shape
    gen = torch.Generator().manual_seed(seed)
    z = torch.randn(n, d, generator=gen, dtype=torch.float64)
    adv = torch.randn(n, generator=gen, dtype=torch.float64)
    sigma = float(np.exp(log_std))
    g_mean = torch.einsum("sjk,sj,s->k", fisher_jac, z / sigma, adv) / n
    g_log_std = ((z**2 - 1.0).sum(dim=1) * adv).mean()
    return torch.cat([g_mean, g_log_std.reshape(1)])


# -- the study ---------------------------------------------------------------------------------------


@dataclass
class ScalingResult:
    dims: list[int]
    trpo_norms: np.ndarray
    beta_norms: np.ndarray
    eig_max: np.ndarray
    eig_min: np.ndarray
    eig_mean: np.ndarray
    rank: np.ndarray
    trpo_slope: float
    trpo_intercept: float
    beta_slope: float
    beta_intercept: float
    subspace: str
    gradient_kind: str
    damping_abs: float
    damping_sweep: dict[float, tuple[float, float]] = field(default_factory=dict)
    """relative damping -> (TRPO slope, beta slope)"""

    def csv_header(self) -> list[str]:
        return ["dim", "trpo_norm", "beta_norm", "fisher_eig_max", "fisher_eig_min", "fisher_eig_mean", "rank_1e-10"]

    def csv_rows(self) -> list[list[float]]:
        return [
            [d, float(t), float(b), float(mx), float(mn), float(me), int(r)]
            for d, t, b, mx, mn, me, r in zip(
                self.dims,
                self.trpo_norms,
                self.beta_norms,
                self.eig_max,
                self.eig_min,
                self.eig_mean,
                self.rank,
                strict=True,
            )
        ]

    def eigen_slopes(self) -> dict[str, float]:
        """Slopes of log eigenvalue statistics vs log d (the paper's assumption: all +1).

        The smallest eigenvalue's slope is left out when it is numerically zero at some d.
        """
        dims = np.asarray(self.dims)
        out = {}
        for name, values in (("max", self.eig_max), ("min", self.eig_min), ("mean", self.eig_mean)):
            if np.all(values > 1e-10 * self.eig_max):
                out[f"fisher_eig_{name}_slope"] = fit_slope(dims, values)[0]
        return out

    def summary(self) -> dict[str, float | str]:
        return {
            "fisher_subspace": self.subspace,
            "fisher_gradient": self.gradient_kind,
            "fisher_damping_abs": self.damping_abs,
            "fisher_rank_min_d": int(self.rank[0]),
            "fisher_rank_max_d": int(self.rank[-1]),
            "trpo_slope": self.trpo_slope,
            "beta_slope": self.beta_slope,
            **self.eigen_slopes(),
            **{f"trpo_slope_damping_{k:g}": v[0] for k, v in self.damping_sweep.items()},
            **{f"beta_slope_damping_{k:g}": v[1] for k, v in self.damping_sweep.items()},
        }


def load_or_init_policy(cfg: ScalingConfig) -> GraphActorCritic:
    """The checkpoint named by ``cfg`` or, without one, a fresh policy seeded with ``cfg.seed``; in eval mode."""
    if cfg.checkpoint:
        policy = GraphActorCritic.load(cfg.checkpoint)
    else:
        torch.manual_seed(cfg.seed)
        policy = GraphActorCritic(PolicyConfig())
    return policy.eval()


def update_norm_scaling(cfg: ScalingConfig, policy: GraphActorCritic | None = None) -> ScalingResult:
    """Fisher per chain length, fixed ``g``, both update norms and their fitted log-log slopes."""
    policy = policy if policy is not None else load_or_init_policy(cfg)
    params = mean_parameters(policy)
    subspace = make_subspace(params, cfg.subspace, cfg.subspace_dim, cfg.seed)
    log_std = float(policy.log_std.detach())
    dims = sorted(cfg.dims)
    if cfg.subspace != "full" and cfg.states_per_dim * dims[0] < 2 * subspace.dim:
        # Fewer Jacobian rows than ~2k leave F (nearly) singular at the smallest d and the slopes meaningless.
        raise ValueError(
            f"states_per_dim * min(dims) = {cfg.states_per_dim * dims[0]} rows for a {subspace.dim}-dim subspace: "
            f"need at least {2 * subspace.dim} (more states, a larger min d, or a smaller subspace)"
        )

    fishers, g = [], None
    for d in dims:
        batch = collect_states(d, cfg.states_per_dim, cfg.warmup_steps, cfg.states_per_episode, cfg.seed)
        jac = mean_jacobian(policy, batch, subspace).detach()
        fishers.append(Fisher.from_jacobian(jac, log_std))
        if g is None:
            if cfg.gradient == "policy_gradient":
                g = random_advantage_gradient(jac, log_std, cfg.seed + 1)
            else:
                gen = torch.Generator().manual_seed(cfg.seed + 1)
                g = torch.randn(subspace.dim + 1, generator=gen, dtype=torch.float64)
            if cfg.gradient_rcond > 0:
                g = fishers[0].project_to_range(g, cfg.gradient_rcond)
            g = g / g.norm()  # only directions matter for the slopes; unit norm keeps numbers readable

    # One absolute damping for every d, as a TRPO implementation would use (scaled to F at min d).
    scale = float(fishers[0].eigenvalues()[0])

    def norms_at(relative: float) -> np.ndarray:
        return np.array([update_norms(f, g, cfg.delta, cfg.beta, relative * scale) for f in fishers])

    norms = norms_at(cfg.damping)
    eigs = [f.eigenvalues() for f in fishers]
    trpo_fit = fit_slope(np.array(dims), norms[:, 0])
    beta_fit = fit_slope(np.array(dims), norms[:, 1])
    sweep = {}
    for relative in cfg.damping_sweep:
        swept = norms_at(relative)
        sweep[relative] = (fit_slope(np.array(dims), swept[:, 0])[0], fit_slope(np.array(dims), swept[:, 1])[0])
    return ScalingResult(
        dims=dims,
        trpo_norms=norms[:, 0],
        beta_norms=norms[:, 1],
        eig_max=np.array([e[0] for e in eigs]),
        eig_min=np.array([e[-1] for e in eigs]),
        eig_mean=np.array([e.mean() for e in eigs]),
        rank=np.array([f.numerical_rank() for f in fishers]),
        trpo_slope=trpo_fit[0],
        trpo_intercept=trpo_fit[1],
        beta_slope=beta_fit[0],
        beta_intercept=beta_fit[1],
        subspace=subspace.label,
        gradient_kind=cfg.gradient,
        damping_abs=cfg.damping * scale,
        damping_sweep=sweep,
    )
