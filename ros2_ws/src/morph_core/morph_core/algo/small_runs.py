"""Small training runs: the one place tests (and smoke runs) take a few-second configuration from.

A test states only what it is about (``small(num_envs=1, checkpoint_interval=32)``); the sizes it does not
care about and the quiet switches (no TensorBoard, no progress bar, no compile) come from ``SMALL``. The same
fields reach every way a run is started: a ``TrainConfig`` (``small_config``), ``morph-train``'s options
(``options_of``, the names ``util.config_cli`` gives the fields) and a sweep's ``key=value`` sets
(``sets_of``).
"""

from __future__ import annotations

from morph_core.algo.train import TrainConfig

QUIET = dict(tensorboard=False, progress_bar=False, compile=False)
"""what a run nobody watches turns off: TensorBoard files, the progress bar, the compile's warm-up"""
SMALL = dict(num_envs=2, num_steps=64, minibatch_size=32, update_epochs=2, **QUIET)
"""a batch of 128 steps in minibatches of 32, two epochs: an update takes well under a second"""


def small(**overrides) -> dict:
    """``SMALL`` with ``overrides`` (any ``TrainConfig`` field) on top."""
    return {**SMALL, **overrides}


def small_config(**overrides) -> TrainConfig:
    return TrainConfig(**small(**overrides))


def _text(value) -> str:
    return str(value).lower() if isinstance(value, bool) else str(value)


def options_of(fields: dict) -> list[str]:
    """``morph-train``'s options for ``fields``: ``{"num_envs": 2, "compile": False}`` gives
    ``["--num-envs", "2", "--compile", "false"]``."""
    return [text for name, value in fields.items() for text in (f"--{name.replace('_', '-')}", _text(value))]


def sets_of(fields: dict) -> list[str]:
    """A sweep's ``--set`` items for ``fields``: ``["num-envs=2", "compile=false"]``."""
    return [f"{name.replace('_', '-')}={_text(value)}" for name, value in fields.items()]
