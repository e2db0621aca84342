"""What ``morph-train`` does around a training call: a resumed run's config written back with the options
given again, a finished run told so, and (``train_report``) what a run says while and after it trains.

A resumed run takes its ``config.json`` with the options given again (``--resume --total-timesteps 24576``);
those are written back to ``config.json`` (atomically) and named, so the file says what the run trains
with and a later ``--resume`` without them goes on with them. If the run stops before it checkpoints again
(a state it cannot resume, a config its state does not fit, Ctrl-C), the file it had is put back: it
never went on with the new options.
"""

from __future__ import annotations

import contextlib
import json
from pathlib import Path

from morph_core.algo.checkpoint import load_training_state
from morph_core.algo.run_dir import RunDir
from morph_core.algo.train import TrainConfig
from morph_core.algo.train_from_data import run_state
from morph_core.util.atomic import atomic_writer
from morph_core.util.config_cli import replace_nested


def config_changes(before: dict, after: dict, prefix: str = "") -> list[str]:
    """``field old -> new`` for every field (nested ones as ``policy.field``) whose value differs."""
    changes = []
    for key, value in after.items():
        old = before.get(key)
        if isinstance(value, dict) and isinstance(old, dict):
            changes += config_changes(old, value, f"{prefix}{key}.")
        elif old != value:
            changes.append(f"{prefix}{key} {old} -> {value}")
    return changes


class ResumeError(ValueError):
    """Options given with ``--resume`` that the resumed run would not apply."""


class ResumedConfig:
    """A resumed run's config (``cfg``: ``config.json`` with ``overrides``) and what the overrides change.
    Every option applies on resume: the optimizer's learning rate and epsilon too (``algo.run.Run.restore``
    sets them from the config after restoring its state)."""

    def __init__(self, run_dir: str | Path, overrides: dict):
        self.path = RunDir(run_dir).config
        self.text = self.path.read_text()
        stored = TrainConfig.from_dict(json.loads(self.text))  # a file without newer fields: their defaults
        self.cfg = replace_nested(stored, overrides)
        # clip_mode: the copy of rule config.json keeps for older readers, said once as rule
        changes = config_changes(stored.to_dict(), self.cfg.to_dict())
        self.changes = [c for c in changes if not c.startswith("clip_mode ")]

    def write_back(self, tool: str = "morph-train") -> None:
        """Write ``cfg`` to ``config.json`` (atomically) and say what changed; nothing when nothing did."""
        if not self.changes:
            return
        with atomic_writer(self.path) as f:
            json.dump(self.cfg.to_dict(), f, indent=2)
        print(f"{tool}: resumed with {', '.join(self.changes)} (written to {self.path})", flush=True)

    def restore(self) -> None:
        """Put the file the run had back."""
        with atomic_writer(self.path) as f:
            f.write(self.text)

    @contextlib.contextmanager
    def kept_unless_trained(self, state: Path):
        """Around training: on an exception before a new training state is written, ``restore``."""
        before = _identity(state)
        try:
            yield
        except BaseException:
            if self.changes and _identity(state) == before:
                self.restore()
            raise


def _identity(path: Path) -> tuple | None:
    try:
        st = path.stat()
    except FileNotFoundError:
        return None
    return st.st_ino, st.st_mtime_ns, st.st_size


def saved_counters(run_dir: str | Path) -> dict | None:
    """The counters of the run's newest training state (global_step, iteration, ...), None without a
    readable one (then training itself says why)."""
    try:
        _, meta = load_training_state(RunDir(run_dir).state)
        return dict(meta["counters"])
    except Exception:  # a damaged or missing state: the trainer's resume reports it
        return None


def finished_message(run_dir: str | Path, cfg: TrainConfig) -> str | None:
    """What to say instead of resuming a run that reached ``cfg.total_timesteps`` already, else None."""
    counters = saved_counters(run_dir)
    if counters is None or counters["global_step"] < cfg.total_timesteps:
        return None
    return (
        f"{run_dir} already finished at step {counters['global_step']} (total_timesteps {cfg.total_timesteps}): "
        "nothing to do; raise --total-timesteps to go on"
    )


def finished_data_message(run_dir: str | Path, sources: list[str], iterations: int | None) -> str | None:
    """What to say instead of resuming a run trained from data that did all its updates on these data already
    (``sources``: the resolved bag paths; ``iterations``: ``--iterations`` if given), else None."""
    try:
        state = run_state(run_dir)
    except Exception:  # a damaged state: the trainer's resume reports it
        return None
    if state is None or list(state["source"]) != list(sources):
        return None  # other bags: the trainer says whether they are the run's data
    target = state["iterations"] if iterations is None else iterations
    if state["done"] < target:
        return None
    return (
        f"{run_dir} already finished at update {state['done']} ({state['iterations']} updates on these bags): "
        "nothing to do; raise --iterations to go on, or train on new bags with --resume --new-data"
    )
