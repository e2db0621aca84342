"""A training run's directory, the one place its file names are spelled: ``RunDir``.

Every trainer writes the same layout and every tool reads it (``algo.run``, ``algo.run_log``, the trainers'
resume, ``morph-train``'s report, evaluation, plots, summaries, the sweep, the benches, the scripts, the
tests), so the names live here and the others ask for a path::

    config.json                            the config the run trains with
    init.json                              the checkpoint a fine-tuning run started from
    progress.csv, tb/                      a row per update (``run_log.RunLog``)
    checkpoints/policy_<step>.safetensors  the policy every ``checkpoint_interval`` steps and at the end
    state.safetensors                      what a resume needs (``algo.checkpoint``)
    state.prev.safetensors                 the state the last one replaced
    eval.csv                               ``morph-eval``'s rows (``trainer.reports.evaluation``)

No torch here: bench and report code read run directories without loading the learner.
"""

from __future__ import annotations

import json
import re
from pathlib import Path


def previous_state_path(path: str | Path) -> Path:
    """Where the state a new one replaced is kept: ``state.safetensors`` -> ``state.prev.safetensors``."""
    path = Path(path)
    return path.with_name(f"{path.stem}.prev{path.suffix}")


CHECKPOINT_NAME = re.compile(r"policy_(\d+)\.safetensors$")
"""a policy checkpoint's file name, its step in group 1"""


class RunDir:
    """The paths of one run directory (``path``); nothing is created or read until asked."""

    def __init__(self, path: str | Path):
        self.path = Path(path)

    def __repr__(self) -> str:
        return f"RunDir({str(self.path)!r})"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, RunDir) and other.path == self.path

    def __hash__(self) -> int:
        return hash(self.path)

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def config(self) -> Path:
        return self.path / "config.json"

    @property
    def init(self) -> Path:
        return self.path / "init.json"

    @property
    def progress(self) -> Path:
        return self.path / "progress.csv"

    @property
    def tensorboard(self) -> Path:
        return self.path / "tb"

    @property
    def checkpoints(self) -> Path:
        return self.path / "checkpoints"

    @property
    def state(self) -> Path:
        return self.path / "state.safetensors"

    @property
    def previous_state(self) -> Path:
        """where the state a new one replaced is kept (``previous_state_path`` of ``state``)"""
        return previous_state_path(self.state)

    @property
    def evaluation(self) -> Path:
        return self.path / "eval.csv"

    def checkpoint(self, step: int) -> Path:
        """The policy checkpoint of ``step``."""
        return self.checkpoints / f"policy_{step:08d}.safetensors"

    def saved_checkpoints(self) -> list[tuple[int, Path]]:
        """``(step, path)`` of every policy checkpoint on disk, by step."""
        found = []
        for path in self.checkpoints.glob("policy_*.safetensors"):
            step = checkpoint_step(path)
            if step is not None:
                found.append((step, path))
        return sorted(found)

    def read_config(self) -> dict:
        """``config.json`` as written (``OSError``, ``ValueError`` as ``json`` raises them)."""
        return json.loads(self.config.read_text())

    def has_state(self) -> bool:
        """Whether a resume has a state to start from (the current one or the one it replaced)."""
        return self.state.exists() or self.previous_state.exists()

    @staticmethod
    def of_checkpoint(path: str | Path) -> RunDir:
        """The run a policy checkpoint (``<run>/checkpoints/policy_<step>.safetensors``) belongs to."""
        return RunDir(Path(path).parent.parent)


def checkpoint_step(path: str | Path) -> int | None:
    """The step in a policy checkpoint's file name (None: not a checkpoint's name)."""
    match = CHECKPOINT_NAME.search(Path(path).name)
    return int(match.group(1)) if match else None
