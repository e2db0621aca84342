"""A trainer's config, by concern, and the config every trainer takes (``TrainerConfig``).

The concerns, each a dataclass with its fields, their help and its own checks:

- ``RunConfig``: the run itself (its length, seed, checkpoints, threads, compilation, logs, progress bar);
- ``ppo_config.PPOConfig``: what PPO learns with, the update's settings (``update_config.UpdateConfig``) among
  them;
- ``BodiesConfig``: the bodies the run trains on (they set the log's per-dimension columns and the robots the
  bag and live trainers accept);
- ``PolicyConfig`` (``policy.actor_critic``): the policy, the one nested field (``--policy-*``);
- a source's own: ``SimConfig``, the simulator loop's; the bag trainer's ``trainer.bags.options.BagOptions``
  (the bags, their topics' namespace, the updates on them) and the live trainer's ``trainer.live``'s
  ``LiveOptions`` (the pairs, staleness, timeouts) live beside their sources, outside the core, and
  ``morph-train`` generates their options from them as from these.

``TrainerConfig`` composes the first four by inheritance, so its fields stay flat: every field name is unique
over the concerns, and the command line, a run's ``config.json``, sweeps and ``dataclasses.replace`` speak of
``--seed`` and ``seed``, never ``run.seed``. Old ``config.json`` files load unchanged and new ones are what old
readers read. ``train.TrainConfig`` adds ``SimConfig``: what ``morph-train`` takes.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass, field

from morph_core.algo.ppo_config import PPOConfig
from morph_core.env.bodies import BodyMix, fit_global_features, parse_bodies
from morph_core.policy.actor_critic import PolicyConfig
from morph_core.util.config_cli import check_field_types, renamed_fields


@dataclass
class RunConfig:
    """The run's plumbing: how long, from which seed, how often it saves, and how it runs and reports."""

    total_timesteps: int = 1_000_000
    """env steps to train for (summed over envs)"""
    seed: int = 1
    """seed of envs, action noise and minibatch shuffling"""
    checkpoint_interval: int = 6000
    """env steps between checkpoints (taken at the end of the update that crosses the mark)"""
    torch_threads: int = 1
    """torch intra-op threads in the update (rollout inference always uses 1)"""
    compile: bool = True
    """compile the minibatch loss and its backward into one Inductor graph (algo.compiled; ~1.5x faster
    update, ~15-30 s to compile once; falls back to eager mode with a warning where Inductor cannot run)"""
    tensorboard: bool = True
    """also write TensorBoard scalars"""
    progress_bar: bool = True
    """show a progress bar"""

    def __post_init__(self):
        check_field_types(self, RunConfig)
        if self.total_timesteps < 1:
            raise ValueError(f"total_timesteps must be >= 1, got {self.total_timesteps}")


@dataclass
class BodiesConfig:
    """The bodies drawn at each reset: a spec in ``env.bodies``' grammar, or chains of a joint range."""

    min_joints: int = 2
    """shortest chain drawn at a reset; with ``bodies``, the fewest joints its bodies have (set from it)"""
    max_joints: int = 10
    """longest chain drawn at a reset; with ``bodies``, the most joints its bodies have (set from it)"""
    bodies: str = ""
    """the bodies drawn at each reset, in ``env.bodies``' grammar (docs/bodies.md): chains, trees and centipedes,
    e.g. '2-10,random:3-10' (chains of 2..10 joints or random trees of 3..10) or 'centipede:2-4' (2..4 leg
    pairs, with the centipede settings ``LEGGED_DEFAULTS``); empty: chains of min_joints..max_joints"""

    def __post_init__(self):
        check_field_types(self, BodiesConfig)
        if not 1 <= self.min_joints <= self.max_joints <= 64:
            raise ValueError(f"need 1 <= min_joints <= max_joints <= 64, got {self.min_joints}, {self.max_joints}")
        if self.bodies:  # parsed here, so that a bad spec is refused before anything runs
            self._joint_range_from_bodies()

    def _joint_range_from_bodies(self) -> None:
        """min_joints..max_joints become the bodies' joint range (the action dimensions they draw), which
        every reader of a run's config takes for the trained range; a range given that disagrees is refused."""
        lo, hi = parse_bodies(self.bodies).joint_range
        defaults = tuple(f.default for f in dataclasses.fields(BodiesConfig) if f.name in ("min_joints", "max_joints"))
        if (self.min_joints, self.max_joints) not in (defaults, (lo, hi)):
            raise ValueError(f"min_joints..max_joints ({self.min_joints}..{self.max_joints}) disagree with bodies "
                             f"{self.bodies!r} ({lo}..{hi} joints): give bodies alone")  # fmt: skip
        self.min_joints, self.max_joints = lo, hi

    @property
    def body_mix(self) -> BodyMix:
        """The bodies of this run's swimmers (``bodies``, or the chains of min_joints..max_joints)."""
        return parse_bodies(self.bodies or f"{self.min_joints}-{self.max_joints}")

    @property
    def dims(self) -> range:
        """The action dimensions d the run's bodies can have: the keys of its per-dimension statistics."""
        lo, hi = self.body_mix.joint_range
        return range(lo, hi + 1)


@dataclass
class SimConfig:
    """The simulator loop's own settings."""

    num_envs: int = 6
    """swimmers stepped together"""
    num_steps: int = 1024
    """steps per swimmer per rollout (rollout = num_envs * num_steps samples); training from bags and live
    training take num_envs * num_steps as their batch too, as they did before batch_size"""
    env_threads: int = 1
    """threads stepping the swimmers (MuJoCo releases the GIL) in each process"""
    processes: int = 1
    """processes sharing the swimmers and every minibatch's gradient (algo.data_parallel); 2 uses both cores
    of a 2-core machine. The action noise's random streams depend on it, so a run keeps its count"""
    rollout_workers: int = 1
    """rollout workers (Ray actors, ``morph-train --rollout-workers``) that each step a share of the swimmers
    (``algo.rollout_workers.env_bounds``) while this process updates; 1: this process steps them all. Worker
    r draws its action noise from worker_seed(seed, r) (``algo.rollout_workers``), so the noise, like
    ``processes``', depends on the count and a run keeps it"""

    def __post_init__(self):
        for name in ("num_envs", "num_steps"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")


@renamed_fields(clip_mode="rule")
@dataclass
class TrainerConfig(RunConfig, BodiesConfig, PPOConfig):
    """What every trainer takes: the run, its bodies, PPO and the policy, flat (see the module docstring).
    The bag and live trainers read only these fields of ``train.TrainConfig``."""

    policy: PolicyConfig = field(default_factory=PolicyConfig)

    concerns = (("run", RunConfig), ("PPO", PPOConfig), ("bodies", BodiesConfig), ("policy", PolicyConfig))
    """the concerns this config composes, as the command line's help groups its options (title, class)"""

    def __post_init__(self):
        if isinstance(self.policy, dict):
            self.policy = PolicyConfig.from_dict(self.policy)
        if not isinstance(self.policy, PolicyConfig):
            raise TypeError(f"policy must be a JSON object of policy fields, got {self.policy!r}")
        check_field_types(self)
        BodiesConfig.__post_init__(self)
        self.policy = fit_global_features(self.policy, self.body_mix)  # 12 with centipedes
        RunConfig.__post_init__(self)
        PPOConfig.__post_init__(self)

    def to_dict(self) -> dict:
        # clip_mode too: readers of config.json older than ``rule`` (and tools outside this repository) read it
        return {**dataclasses.asdict(self), "clip_mode": self.rule}

    @classmethod
    def from_dict(cls, d: dict):
        """The config of a ``config.json``: today's, or an older one (``clip_mode`` for ``rule``, with a
        deprecation warning; fields it lacks take their defaults)."""
        d = dict(d)
        for old, new in cls.renamed.items():
            if old in d and new in d:  # written by to_dict: both, the same
                if d[new] != d[old]:
                    raise ValueError(f"{new} {d[new]!r} and {old} {d[old]!r} disagree: give {new} alone")
                del d[old]
            elif old in d:  # a config written before the rename
                warnings.warn(f"config key {old!r} is deprecated: read as {new!r}", DeprecationWarning, stacklevel=2)
                d[new] = d.pop(old)
        known = {f.name for f in dataclasses.fields(cls) if f.init} | set(cls.renamed) | set(cls.derived)
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown train config fields: {sorted(unknown)}")
        return cls(**d)  # a derived field given (the simulator's batch_size) must agree: ``renamed_fields``

    derived = ()
    """fields set from others (``init=False``): taken by the constructor only when they agree"""
