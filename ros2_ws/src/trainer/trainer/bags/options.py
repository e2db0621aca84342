"""The bag trainer's settings (``morph-train --from-bags``), its source's own config beside the simulator's
``SimConfig`` and the live trainer's ``LiveOptions``: ``train_options`` generates their options from the fields
and their help from the docstrings (``config_cli``). ``train_from_data`` records ``iterations``, ``init`` and
the bags (``source``) in the run's files, as it always has."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path


@dataclass(frozen=True)
class BagOptions:
    """Where the recorded steps come from and how many updates they get (``TrainConfig`` says how it learns)."""

    from_bags: list[str] | None = field(default=None, metadata={"metavar": "BAG"})
    """train on these rosbag2 bags (folder, metadata.yaml or storage file) instead of the simulator"""
    init: Path | None = None
    """start a new run from this policy checkpoint (.safetensors, its .json beside it): from bags, in the
    simulator (fine-tuning on --bodies) or --live"""
    iterations: int | None = None
    """PPO updates on these bags (default: one pass, ceil(steps / (num_envs * num_steps)))"""
    new_data: bool = False
    """with --resume: the bags are new data for the run, trained on after what it has done (policy, critic,
    optimizer and generator carry over)"""
    namespace: str | None = None
    """namespace of the robot's topics (default: found)"""

    def __post_init__(self):
        if self.iterations is not None and self.iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {self.iterations}")
        if self.from_bags is not None and not self.from_bags:
            raise ValueError("from_bags: no bag given")
