"""Clip-probability analysis of PPO for variable action dimensions (paper, section III).

A factorised Gaussian policy over ``dim`` joints moves from ``pi_old`` to ``pi_new``.
Per joint, ``nu_i = (mu_new - mu_old) / sigma_new`` is the normalised mean drift and
``eta_i = sigma_new / sigma_old`` the ratio of standard deviations. With ``z_i ~ N(0, 1)``
(the old policy's sampling noise) the per-joint log ratio is the quadratic

    log r_i = (1 - eta^-2) / 2 * z_i^2 + (nu_i / eta) * z_i - log(eta) - nu_i^2 / 2.

For ``eta = 1`` it is linear in ``z`` and ``log r = sum_i log r_i ~ Normal(-|nu|^2 / 2, |nu|)``.
With a homogeneous drift ``nu_0`` per joint, ``|nu| = nu_0 sqrt(dim)``.

All public functions broadcast over numpy arrays of ``dim``, ``nu0`` and ``eps`` (and ``eta``
where present). ``rule`` is a trust-region rule that clips the joint ratio, by name or as the
object from ``algo.trust_region.RULES``: ``"fixed"`` clips at ``eps``, ``"compensated"`` at
``eps * sqrt(dim)``; the clip range is the rule's own ``clip_range``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy import stats
from scipy.special import ndtr

from morph_core.algo.trust_region import TrustRegionRule, get_rule
from morph_core.policy.gaussian import log_density_per_joint

Rule = str | TrustRegionRule

SQRT_2_OVER_PI = float(np.sqrt(2.0 / np.pi))


def drift_norm(dim: ArrayLike, nu0: ArrayLike) -> np.ndarray:
    """``|nu| = nu0 * sqrt(dim)``: norm of a homogeneous per-joint drift ``nu0``."""
    return np.asarray(nu0, dtype=float) * np.sqrt(np.asarray(dim, dtype=float))


def effective_eps(dim: ArrayLike, eps: ArrayLike, rule: Rule = "fixed") -> np.ndarray:
    """Clip range ``rule`` uses for a sample of dimension ``dim`` (``eps``, ``eps * sqrt(dim)``, ...)."""
    return get_rule(rule).clip_range(np.asarray(eps, dtype=float), np.asarray(dim, dtype=float))


def _interval_probability(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``Phi(hi) - Phi(lo)`` for ``lo <= hi``, computed on the side of the tail that keeps precision.

    When both bounds sit far in the upper tail, ``Phi(hi) - Phi(lo)`` is a difference of two
    numbers close to 1; by symmetry ``Phi(-lo) - Phi(-hi)`` is the same quantity without cancellation.
    """
    upper = lo > 0
    return np.where(upper, ndtr(-lo) - ndtr(-hi), ndtr(hi) - ndtr(lo))


def clip_probability(dim: ArrayLike, nu0: ArrayLike, eps: ArrayLike, rule: Rule = "fixed") -> np.ndarray:
    """Exact ``P(-e <= log r <= e)`` for ``log r ~ Normal(-|nu|^2/2, |nu|)`` (paper eq. "true_prob").

        P = Phi(e / |nu| + |nu| / 2) - Phi(-e / |nu| + |nu| / 2),   |nu| = nu0 sqrt(dim),

    with ``e`` the rule's clip range (``effective_eps``). For ``|nu| -> 0`` the ratio is
    identically 1 (``log r = 0``), so the probability is 1; that limit is returned without NaN.
    """
    nu = drift_norm(dim, nu0)
    e = effective_eps(dim, eps, rule)
    nu, e = np.broadcast_arrays(nu, e)
    still = nu <= 0.0
    safe_nu = np.where(still, 1.0, nu)  # placeholder where nu == 0; those entries are overwritten below
    lo = -e / safe_nu + safe_nu / 2.0
    hi = e / safe_nu + safe_nu / 2.0
    return np.where(still, 1.0, _interval_probability(lo, hi))


def clip_probability_approx(dim: ArrayLike, nu0: ArrayLike, eps: ArrayLike, rule: Rule = "fixed") -> np.ndarray:
    """The paper's approximation ``min(sqrt(2/pi) e / |nu|, 1)`` (first-order cdf, ``exp(-|nu|^2/8)`` dropped)."""
    nu = drift_norm(dim, nu0)
    e = effective_eps(dim, eps, rule)
    nu, e = np.broadcast_arrays(nu, e)
    with np.errstate(divide="ignore", invalid="ignore"):
        raw = SQRT_2_OVER_PI * e / nu
    return np.where(nu <= 0.0, 1.0, np.minimum(raw, 1.0))


def approx_error_supremum(eps: float) -> tuple[float, float]:
    """Largest ``approx - exact`` over all ``|nu| > 0`` at fixed ``eps``, and the ``|nu|`` where it occurs.

    The approximation saturates at 1 for ``|nu| <= nu* = sqrt(2/pi) eps`` while the exact value
    falls monotonically in ``|nu|``, so on that side the error grows up to the kink ``nu*``. Beyond
    the kink the error is found numerically on a fine grid (it falls off there for eps <= ~1).
    """
    nu = np.concatenate([[SQRT_2_OVER_PI * eps], np.geomspace(1e-4, 50.0, 200_001)])
    err = clip_probability_approx(1, nu, eps) - clip_probability(1, nu, eps)
    i = int(np.argmax(err))
    return float(err[i]), float(nu[i])


# -- eta != 1: the exact (non-central chi-squared) law ------------------------------------------------


@dataclass(frozen=True)
class LogRatioQuadratic:
    """Per-joint ``log r_i = a z^2 + b z + c`` for homogeneous ``(nu0, eta)``."""

    a: np.ndarray
    b: np.ndarray
    c: np.ndarray

    @classmethod
    def from_drift(cls, nu0: ArrayLike, eta: ArrayLike) -> LogRatioQuadratic:
        nu0 = np.asarray(nu0, dtype=float)
        eta = np.asarray(eta, dtype=float)
        return cls(a=(1.0 - eta**-2) / 2.0, b=nu0 / eta, c=-np.log(eta) - nu0**2 / 2.0)


def log_ratio_moments(dim: ArrayLike, nu0: ArrayLike, eta: ArrayLike = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation of ``log r`` over ``dim`` joints, for any ``eta``.

        E[log r] = dim (a + c),   Var[log r] = dim (2 a^2 + b^2)

    (``E z^2 = 1``, ``Var(a z^2 + b z) = 2 a^2 + b^2``). At ``eta = 1`` this is ``(-|nu|^2/2, |nu|)``.
    """
    q = LogRatioQuadratic.from_drift(nu0, eta)
    dim = np.asarray(dim, dtype=float)
    return dim * (q.a + q.c), np.sqrt(dim * (2.0 * q.a**2 + q.b**2))


def clip_probability_eta(
    dim: ArrayLike, nu0: ArrayLike, eps: ArrayLike, eta: ArrayLike, rule: Rule = "fixed"
) -> np.ndarray:
    """Exact ``P(-e <= log r <= e)`` without the ``eta ~ 1`` assumption.

    Completing the square, ``sum_i (a z_i^2 + b z_i + c) = a X + dim (c - b^2 / (4a))`` with
    ``X = sum_i (z_i + b / 2a)^2 ~ chi2'(df=dim, nc=dim b^2 / 4a^2)``, the non-central chi-squared
    law the paper mentions. Where ``|eta - 1| < 1e-6`` (a ~ 0) the Gaussian closed form is used.
    The non-centrality grows like ``1/(eta-1)^2``; scipy's cdf agreed with Monte Carlo (200k samples,
    within ~2.5 standard errors) for ``|eta - 1|`` down to 0.0065 at dim <= 20.
    """
    dim, nu0, eps, eta = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (dim, nu0, eps, eta)))
    out = np.asarray(clip_probability(dim, nu0, eps, rule), dtype=float).copy()
    curved = np.abs(eta - 1.0) >= 1e-6
    if not np.any(curved):
        return out
    d, n0, e, et = dim[curved], nu0[curved], effective_eps(dim, eps, rule)[curved], eta[curved]
    q = LogRatioQuadratic.from_drift(n0, et)
    shift = q.b / (2.0 * q.a)
    offset = d * (q.c - q.a * shift**2)
    # a > 0 (eta > 1): X in [(-e - offset)/a, (e - offset)/a]; a < 0 flips the bounds.
    x1, x2 = (-e - offset) / q.a, (e - offset) / q.a
    lo, hi = np.minimum(x1, x2), np.maximum(x1, x2)
    law = stats.ncx2(df=d, nc=np.maximum(d * shift**2, 1e-300))
    out[curved] = np.clip(law.cdf(np.maximum(hi, 0.0)) - law.cdf(np.maximum(lo, 0.0)), 0.0, 1.0)
    return out


# -- Monte Carlo with real Gaussian policies ---------------------------------------------------------


@dataclass(frozen=True)
class MonteCarloEstimate:
    """Fraction of samples with ``|log r| <= e`` and its binomial standard error, plus log r moments."""

    probability: float
    stderr: float
    logr_mean: float
    logr_std: float
    n_samples: int


def gaussian_log_density(a: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    """``log N(a; mean, std^2)`` elementwise: the policy's own per-joint density (``policy.gaussian``)."""
    return log_density_per_joint((a - mean) / std, np.log(std))


def _monte_carlo_point(
    dim: int, nu0: float, eps: float, eta: float, n_samples: int, rng: np.random.Generator, chunk: int
) -> MonteCarloEstimate:
    """One ``(dim, nu0, eps, eta)`` point; samples processed in chunks to bound memory."""
    hits, total, s1, s2 = 0, 0, 0.0, 0.0
    while total < n_samples:
        n = min(chunk, n_samples - total)
        # Each sample is a different "state": its own old mean and std per joint. The log ratio
        # is invariant to them, which is exactly what the sampled densities have to confirm.
        mu_old = rng.normal(0.0, 1.0, size=(n, dim))
        sigma_old = np.exp(rng.uniform(np.log(0.1), np.log(1.5), size=(n, dim)))
        sigma_new = eta * sigma_old
        mu_new = mu_old + nu0 * sigma_new  # nu_i = (mu_new - mu_old) / sigma_new = nu0
        a = rng.normal(mu_old, sigma_old)  # a ~ pi_old
        logr = (gaussian_log_density(a, mu_new, sigma_new) - gaussian_log_density(a, mu_old, sigma_old)).sum(axis=1)
        hits += int(np.count_nonzero(np.abs(logr) <= eps))
        s1 += float(logr.sum())
        s2 += float((logr**2).sum())
        total += n
    p = hits / total
    mean = s1 / total
    var = max(s2 / total - mean**2, 0.0)
    return MonteCarloEstimate(p, float(np.sqrt(p * (1.0 - p) / total)), mean, float(np.sqrt(var)), total)


def monte_carlo_clip_probability(
    dim: ArrayLike,
    nu0: ArrayLike,
    eps: ArrayLike,
    eta: ArrayLike = 1.0,
    n_samples: int = 20_000,
    rng: np.random.Generator | int | None = 0,
    rule: Rule = "fixed",
    chunk: int = 50_000,
) -> tuple[np.ndarray, np.ndarray]:
    """Monte Carlo estimate of ``P(|log r| <= e)`` from sampled factorised Gaussian policy pairs.

    Per sample and joint: ``pi_old = N(mu_old, sigma_old^2)`` with random ``mu_old`` and
    ``sigma_old``, ``pi_new = N(mu_old + nu0 sigma_new, sigma_new^2)`` with ``sigma_new = eta sigma_old``.
    Actions ``a ~ pi_old``; ``log r = sum_j [log pi_new(a_j) - log pi_old(a_j)]`` from the densities.
    ``e`` is the rule's clip range (``effective_eps``).

    Returns ``(probability, stderr)`` arrays of the broadcast shape of the inputs; the standard error
    is the binomial ``sqrt(p (1 - p) / n)`` (0 when every sample lands inside or outside).
    """
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    dim_b, nu0_b, eps_b, eta_b = np.broadcast_arrays(*(np.asarray(x) for x in (dim, nu0, eps, eta)))
    e_b = effective_eps(dim_b, eps_b, rule)
    prob = np.empty(dim_b.shape)
    err = np.empty(dim_b.shape)
    for idx in np.ndindex(dim_b.shape):
        est = _monte_carlo_point(
            int(dim_b[idx]), float(nu0_b[idx]), float(e_b[idx]), float(eta_b[idx]), int(n_samples), gen, chunk
        )
        prob[idx], err[idx] = est.probability, est.stderr
    return prob, err


def monte_carlo_point(
    dim: int,
    nu0: float,
    eps: float,
    eta: float = 1.0,
    n_samples: int = 20_000,
    rng: np.random.Generator | int | None = 0,
    rule: Rule = "fixed",
) -> MonteCarloEstimate:
    """Scalar Monte Carlo with the log-ratio moments as well (see :func:`monte_carlo_clip_probability`)."""
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    e = float(effective_eps(dim, eps, rule))
    return _monte_carlo_point(int(dim), float(nu0), e, float(eta), int(n_samples), gen, 50_000)
