"""What PPO learns with (``PPOConfig``): the update's settings (``update_config.UpdateConfig``, which it
extends) and the batch, the optimizer and the advantages. The other concerns of a trainer's config, and the
config every trainer takes, are ``algo.config``'s.

``rule`` was called ``clip_mode`` before (it names rules that do not clip too): ``clip_mode`` is still
taken, as a keyword, a ``config.json`` key or the ``--clip-mode`` option, with a deprecation warning
(``config.TrainerConfig``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from morph_core.algo.trust_region import rule_names
from morph_core.algo.update_config import UpdateConfig
from morph_core.env.bodies import parse_bodies
from morph_core.util.config_cli import check_field_types

LEGGED_DEFAULTS = {"learning_rate": 3e-4, "gamma": 0.99, "gae_lambda": 0.95}
"""PPO settings of bodies with legs (centipedes, the legged family, a user's MJCF with a free root), in place
of the paper's swimmer ones where a run did not set them: the centipede results' (CleanRL's Ant settings;
sweeps/centipedes*.yaml, docs/centipedes.md). At the swimmer's 0.01 / 0.98 a 12-feature policy's updates
reach KL 0.1-0.3."""


def family_defaults(bodies: str, given) -> dict:
    """The fields of ``LEGGED_DEFAULTS`` not in ``given`` (field names a user set) when ``bodies`` holds
    walkers (centipedes, legged bodies, a free-rooted MJCF); {} for swimmers, whose runs keep the dataclass
    defaults (bit for bit)."""
    if not bodies or not parse_bodies(bodies).has_walkers:
        return {}
    return {k: v for k, v in LEGGED_DEFAULTS.items() if k not in given}


@dataclass
class PPOConfig(UpdateConfig):
    """PPO with per-sample clip ranges, as every trainer runs it; defaults are the paper's configuration. The
    update's settings are ``UpdateConfig``'s fields, inherited, not copied."""

    batch_size: int = 6144
    """samples per update (the simulator's is num_envs * num_steps)"""
    learning_rate: float = 0.01
    """Adam learning rate (constant unless anneal_lr)"""
    anneal_lr: bool = False
    """decay the learning rate linearly to 0 over the run (CleanRL's anneal_lr); off in the paper's configuration"""
    adam_eps: float = 1e-5
    """Adam epsilon"""
    gamma: float = 0.98
    """discount"""
    gae_lambda: float = 0.98
    """GAE lambda"""

    def __post_init__(self):
        check_field_types(self, PPOConfig)
        if self.rule not in rule_names():
            raise ValueError(f"rule must be one of {rule_names()}, got {self.rule!r}")
        for name in ("batch_size", "minibatch_size", "update_epochs"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.minibatch_size > self.batch_size:
            raise ValueError(f"minibatch_size {self.minibatch_size} exceeds the rollout size {self.batch_size}")
        if self.clip_eps <= 0:
            raise ValueError(f"clip_eps must be > 0, got {self.clip_eps}")
        UpdateConfig.__post_init__(self)  # the update's own checks: weight cap, KL settings, objective and rule

    def update_config(self) -> UpdateConfig:
        """The update's part of this config (what ``update`` and the data-parallel helpers are given)."""
        return UpdateConfig(**{f.name: getattr(self, f.name) for f in dataclasses.fields(UpdateConfig)})
