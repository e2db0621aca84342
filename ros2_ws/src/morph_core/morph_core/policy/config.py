"""The graph actor-critic's architecture, without torch.

Read by the torch policy (``actor_critic``) and by the torch-free loader a
controller uses (``weights``), so a checkpoint's JSON means the same to both.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass, fields

from morph_core.constants import NUM_EDGE_FEATURES, NUM_GLOBAL_FEATURES
from morph_core.policy.joint_description import NUM_DESCRIPTION_FEATURES

MAX_GLOBAL_FEATURES = 256
"""widest global input a config may ask for (a checkpoint's JSON comes off the network)"""
BACKENDS = ("dense", "pyg")
"""how the torch policy's chain convolutions execute (``chain_conv``); not part of the architecture"""


@dataclass
class PolicyConfig:
    """Architecture of the graph actor-critic."""

    conv1_channels: int = 24
    """channels of the first NNConv layer"""
    embed_channels: int = 16
    """channels of the second NNConv layer and of the global embedding they are added to"""
    global_hidden: int = 128
    """hidden width of the global-state MLP"""
    head_hidden: int = 64
    """width of the two tanh layers in the actor and critic heads"""
    bidirectional: bool = True
    """messages flow both ways along the chain, tail-to-torso through its own edge network;
    False is the reference's torso-to-tail only (exactly the paper's 4,376-parameter extractor)"""
    log_std_init: float = 0.0
    """initial log standard deviation of every joint's Gaussian"""
    ortho_init: bool = True
    """orthogonal init as in Stable-Baselines3 (the reference's base): gain sqrt(2) for hidden
    linear layers, 0.01 for the action output (initial means ~0), 1 for the value output"""
    global_features: int = NUM_GLOBAL_FEATURES
    """width of the global input (the global MLP's first layer): 4 for swimmers (yaw, yaw rate, vx, vy), the
    default, so checkpoints written before the field existed load as they were; a body in 3-D has more
    (``env.centipede.GLOBAL_FEATURES``)"""
    joint_features: int = 0
    """width of each joint's description (``policy.joint_description``, ``NUM_DESCRIPTION_FEATURES``) the policy
    reads beside the joint's state, as more edge attributes of every edge-conditioned convolution (``chain_conv``);
    0, the default, is the policy without descriptions, so every checkpoint written before the field existed
    loads and answers as it did"""

    @property
    def edge_features(self) -> int:
        """what each joint's edge carries: its angle and angular velocity, then its description"""
        return NUM_EDGE_FEATURES + self.joint_features

    def __post_init__(self):
        for f in ("conv1_channels", "embed_channels", "global_hidden", "head_hidden"):
            value = getattr(self, f)
            # bool is an int subclass: True would pass as a width of 1.
            if not isinstance(value, numbers.Integral) or isinstance(value, bool) or value < 1:
                raise ValueError(f"{f} must be an integer >= 1, got {value!r}")
        g = self.global_features
        if not isinstance(g, numbers.Integral) or isinstance(g, bool) or not 1 <= g <= MAX_GLOBAL_FEATURES:
            raise ValueError(f"global_features must be an integer in 1..{MAX_GLOBAL_FEATURES}, got {g!r}")
        d = self.joint_features
        if isinstance(d, bool) or d not in (0, NUM_DESCRIPTION_FEATURES):
            raise ValueError(f"joint_features must be 0 (none) or {NUM_DESCRIPTION_FEATURES} (descriptions), got {d!r}")
        for f in ("bidirectional", "ortho_init"):
            if not isinstance(getattr(self, f), bool):
                raise ValueError(f"{f} must be true or false, got {getattr(self, f)!r}")
        if isinstance(self.log_std_init, bool) or not isinstance(self.log_std_init, numbers.Real):
            raise ValueError(f"log_std_init must be a number, got {self.log_std_init!r}")

    @classmethod
    def from_dict(cls, d: dict) -> PolicyConfig:
        if not isinstance(d, dict):
            raise ValueError(f"the policy config must be a JSON object, got {type(d).__name__}")
        d = dict(d)
        # Files written before the execution backend left the architecture carry it: accept and drop it.
        legacy_backend = d.pop("backend", "dense")
        if legacy_backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {legacy_backend!r}")
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown policy config fields: {sorted(unknown)}")
        return cls(**d)
