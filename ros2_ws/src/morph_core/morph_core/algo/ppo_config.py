"""What every trainer learns with (``PPOConfig``) and what the simulator loop adds (``SimConfig``).

``PPOConfig`` is the PPO of every data source, simulator, bags and live: the trust-region rule and its
parameters, the batch and its minibatches, the optimizer, advantages, the bodies the run trains on (they
set the log's per-dimension columns and the robots the bag and live trainers accept), the policy, and
when to checkpoint. ``SimConfig`` is the simulator loop's own: the swimmers stepped together, the steps
of a rollout, the threads and processes stepping them. ``train.TrainConfig`` is the two in one flat
class, what ``morph-train`` and a run's ``config.json`` hold; the bag and live trainers read only its
``PPOConfig`` fields.

``rule`` was called ``clip_mode`` before (it names rules that do not clip too): ``clip_mode`` is still
taken, as a keyword, a ``config.json`` key or the ``--clip-mode`` option, with a deprecation warning.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass, field

from morph_core.algo.trust_region import rule_names
from morph_core.algo.update_config import UpdateConfig
from morph_core.env.bodies import BodyMix, fit_global_features, parse_bodies
from morph_core.policy.actor_critic import PolicyConfig
from morph_core.util.config_cli import check_field_types, renamed_fields

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


@renamed_fields(clip_mode="rule")
@dataclass
class PPOConfig:
    """PPO with per-sample clip ranges, as every trainer runs it; defaults are the paper's configuration."""

    rule: str = "compensated"
    """trust-region rule, a name from algo.trust_region.RULES: 'fixed' clips r to 1 +- eps,
    'compensated' to 1 +- eps*sqrt(dim A) per sample"""
    clip_eps: float = 0.111
    """base clip range eps"""
    total_timesteps: int = 1_000_000
    """env steps to train for (summed over envs)"""
    seed: int = 1
    """seed of envs, action noise and minibatch shuffling"""
    batch_size: int = 6144
    """samples per update (the simulator's is num_envs * num_steps)"""
    minibatch_size: int = 256
    """samples per gradient step"""
    update_epochs: int = 10
    """passes over each rollout"""
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
    vf_coef: float = 0.5
    """value loss weight"""
    ent_coef: float = 0.0
    """entropy bonus weight"""
    max_grad_norm: float = 0.5
    """global gradient-norm clip"""
    proximal_weight_cap: float = 1.0
    """c of the truncated importance weight min(pi_prox / pi_behav, c) on off-policy samples (training from
    recorded data, algo.train_from_data); simulator rollouts are on-policy and carry no weight"""
    kl_target: float = 0.01
    """target KL of the kl-* rules: the KL penalty doubles/halves beta when the update's KL is above
    1.5x / below 1/1.5 of it, KL early stopping ends the epochs above it (per joint for the -per-joint rules)"""
    kl_beta: float = 1.0
    """initial beta of the kl-penalty rules"""
    kl_adaptive: bool = True
    """adapt the kl-penalty rules' beta to kl_target after each update; false keeps beta = kl_beta"""
    off_policy_objective: str = "decoupled"
    """how samples of an older policy (bags, live) enter the update: 'decoupled' (ratio against the policy as
    the update starts, each sample weighted by min(pi_prox / pi_behav, proximal_weight_cap)) or 'behaviour'
    (PPO's own loss, the ratio against the policy that acted); simulator rollouts are on-policy either way"""
    min_joints: int = 2
    """shortest chain drawn at a reset; with ``bodies``, the fewest joints its bodies have (set from it)"""
    max_joints: int = 10
    """longest chain drawn at a reset; with ``bodies``, the most joints its bodies have (set from it)"""
    bodies: str = ""
    """the bodies drawn at each reset, in ``env.bodies``' grammar (docs/bodies.md): chains, trees and centipedes,
    e.g. '2-10,random:3-10' (chains of 2..10 joints or random trees of 3..10) or 'centipede:2-4' (2..4 leg
    pairs, with the centipede settings ``LEGGED_DEFAULTS``); empty: chains of min_joints..max_joints"""
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
    policy: PolicyConfig = field(default_factory=PolicyConfig)

    def __post_init__(self):
        if isinstance(self.policy, dict):
            self.policy = PolicyConfig.from_dict(self.policy)
        if not isinstance(self.policy, PolicyConfig):
            raise TypeError(f"policy must be a JSON object of policy fields, got {self.policy!r}")
        check_field_types(self)
        if self.rule not in rule_names():
            raise ValueError(f"rule must be one of {rule_names()}, got {self.rule!r}")
        if not 1 <= self.min_joints <= self.max_joints <= 64:
            raise ValueError(f"need 1 <= min_joints <= max_joints <= 64, got {self.min_joints}, {self.max_joints}")
        if self.bodies:  # parsed here, so that a bad spec is refused before anything runs
            self._joint_range_from_bodies()
        self.policy = fit_global_features(self.policy, self.body_mix)  # 12 with centipedes
        for name in ("batch_size", "minibatch_size", "update_epochs", "total_timesteps"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.minibatch_size > self.batch_size:
            raise ValueError(f"minibatch_size {self.minibatch_size} exceeds the rollout size {self.batch_size}")
        if self.clip_eps <= 0:
            raise ValueError(f"clip_eps must be > 0, got {self.clip_eps}")
        self.update_config()  # the update's own checks: weight cap, KL settings, objective and rule together

    def _joint_range_from_bodies(self) -> None:
        """min_joints..max_joints become the bodies' joint range (the action dimensions they draw), which
        every reader of a run's config takes for the trained range; a range given that disagrees is refused."""
        lo, hi = parse_bodies(self.bodies).joint_range
        defaults = tuple(f.default for f in dataclasses.fields(self) if f.name in ("min_joints", "max_joints"))
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

    def update_config(self) -> UpdateConfig:
        return UpdateConfig(
            rule=self.rule,
            clip_eps=self.clip_eps,
            update_epochs=self.update_epochs,
            minibatch_size=self.minibatch_size,
            vf_coef=self.vf_coef,
            ent_coef=self.ent_coef,
            max_grad_norm=self.max_grad_norm,
            proximal_weight_cap=self.proximal_weight_cap,
            kl_target=self.kl_target,
            kl_beta=self.kl_beta,
            kl_adaptive=self.kl_adaptive,
            off_policy_objective=self.off_policy_objective,
        )

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
