"""What the run log shows in TensorBoard beyond one chart per column: per-dimension charts and histograms.

A per-dimension column ``<name>_d<d>`` (``return_d3``, ``clip_frac_d3``,
``clip_frac_last_d3``, ...) is the scalar ``<name>/d<d>``. The custom-scalars
layout (TensorBoard's "Custom Scalars" tab) draws each such family as one
multi-line chart, a line per chain length, so the return per chain length
and the clip fraction per action dimension can be read side by side rather
than from one chart per length. Each update also logs histograms of the
per-sample log-ratios log pi_new / pi_old of every action dimension
(``log_ratio_histograms``): the distribution whose mean and standard
deviation the ``logr_mean``/``logr_std`` columns summarise.
"""

from __future__ import annotations

import re
from collections.abc import Iterable

import torch

from morph_core.algo.ppo import PerDimensionStats

_PER_DIM = re.compile(r"^(?P<name>.+)_d(?P<dim>\d+)$")

# Families charted first, with their titles; any other per-dimension family follows under its own name.
_TITLES = {
    "return": "return per chain length",
    "clip_frac": "clip fraction per action dimension",
    "in_eps_frac": "fraction with |log r| <= eps per action dimension",
    "approx_kl": "approx KL per action dimension",
    "logr_mean": "mean log r per action dimension",
    "logr_std": "std of log r per action dimension",
}
_EPOCH_SUFFIXES = ("_first", "_last")  # algo.update's per-epoch statistics: their own category


def scalar_tag(column: str) -> str:
    """The TensorBoard tag of a log column: ``<name>_d<d>`` -> ``<name>/d<d>``, anything else as it is."""
    m = _PER_DIM.match(column)
    return f"{m['name']}/d{m['dim']}" if m else column


def per_dimension_families(columns: Iterable[str]) -> dict[str, list[str]]:
    """name -> the scalar tags of its per-dimension columns, in the columns' order."""
    families: dict[str, list[str]] = {}
    for column in columns:
        m = _PER_DIM.match(column)
        if m:
            families.setdefault(m["name"], []).append(scalar_tag(column))
    return families


def custom_scalars_layout(columns: Iterable[str]) -> dict[str, dict[str, list]]:
    """``SummaryWriter.add_custom_scalars``'s layout: a multi-line chart per per-dimension family.

    TensorBoard reads a chart's tags as regular expressions, so each is anchored: ``clip_frac/d2``
    alone would also draw ``clip_frac/d20``.
    """
    families = per_dimension_families(columns)
    order = [*(f for f in _TITLES if f in families), *(f for f in families if f not in _TITLES)]
    layout: dict[str, dict[str, list]] = {}
    for family in order:
        epoch = next((s for s in _EPOCH_SUFFIXES if family.endswith(s)), None)
        base = family[: -len(epoch)] if epoch else family
        title = _TITLES.get(base, f"{base} per dimension")
        category = "per dimension, one epoch" if epoch else "per chain length"
        chart = f"{title} ({epoch[1:]} epoch)" if epoch else title
        tags = [f"^{re.escape(tag)}$" for tag in families[family]]
        layout.setdefault(category, {})[chart] = ["Multiline", tags]
    return layout


def log_ratio_histograms(stats: PerDimensionStats, tag: str = "log_ratio") -> dict[str, torch.Tensor]:
    """``<tag>/d<d>`` -> the log-ratios of every sample of dimension d that ``stats`` counted (each minibatch
    step's log pi_new / pi_old: pooled over epochs, the statistics of the ``logr_*_d<d>`` columns)."""
    if not stats.samples:
        return {}
    dims = torch.cat([d for d, _ in stats.samples])
    log_ratio = torch.cat([r for _, r in stats.samples])
    return {f"{tag}/d{d}": log_ratio[dims == d] for d in torch.unique(dims).tolist()}


def update_histograms(stats) -> dict[str, torch.Tensor]:
    """An update's (``algo.update_stats.UpdateStats``) log-ratio histograms: ``log_ratio/d<d>`` pooled over its
    epochs and ``log_ratio_last/d<d>`` of its last epoch alone (the policy furthest from pi_old)."""
    out = log_ratio_histograms(stats.per_dim)
    if stats.last_epoch is not None:
        out |= log_ratio_histograms(stats.last_epoch, "log_ratio_last")
    return out
