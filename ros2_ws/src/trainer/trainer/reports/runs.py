"""Training run directories as data (``RunReport``: config, progress and eval rows), grouped by trust-region rule.

What the figures (``plots``), the tables (``summary``) and the model picker
(``ship``) read. Runs are grouped under their ``clip_mode`` in the order of
``algo.trust_region.RULES``; a run of a rule the table does not know is an
error, not a run left out, and so is a group whose runs were trained
differently (say constant and annealed learning rates): pooled, their
seeds would read as one rule's spread.
"""

from __future__ import annotations

import csv
import math
import re
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from morph_core.algo.run_dir import RunDir
from morph_core.algo.train import TrainConfig
from morph_core.algo.trust_region import rule_names
from morph_core.env.bodies import chain_label, is_chain_label

# Config keys that say how a run was executed, logged or saved, not what it learned.
HOW_RUN = frozenset({"seed", "torch_threads", "env_threads", "processes", "compile", "tensorboard",
                     "progress_bar", "checkpoint_interval"})  # fmt: skip


@dataclass
class RunReport:
    """What a report reads of one run directory (``algo.run_dir.RunDir``): its config, progress rows and eval
    rows (empty before ``morph-eval``). Not the run that trains: that is ``algo.run.Run``."""

    dir: Path
    config: dict
    progress: list[dict] = field(default_factory=list)
    eval: list[dict] = field(default_factory=list)

    @property
    def rule(self) -> str:
        return self.config["clip_mode"]

    @property
    def setup(self) -> dict:
        """What the run learned with: its config minus ``HOW_RUN``, today's defaults filled in for
        the keys that older runs' configs lack (those keys did not exist, so their defaults applied)."""
        defaults = TrainConfig().to_dict()
        # rule: the same as clip_mode, which older configs hold alone; batch_size: num_envs * num_steps
        same_as = {"rule", "batch_size"}
        return {k: self.config.get(k, v) for k, v in defaults.items() if k not in HOW_RUN | same_as}

    @property
    def trained_lengths(self) -> range:
        return range(self.config["min_joints"], self.config["max_joints"] + 1)


def load_run_report(run_dir: Path) -> RunReport:
    files = RunDir(run_dir)
    if not files.config.is_file():
        raise ValueError(f"{run_dir} is not a training run ({files.config.name} missing)")
    config = files.read_config()
    if config.get("clip_mode") not in rule_names():
        raise ValueError(f"{run_dir}: clip_mode {config.get('clip_mode')!r} is not a rule of {rule_names()}")
    with files.progress.open() as f:
        progress = list(csv.DictReader(f))
    evals = []
    if files.evaluation.exists():
        with files.evaluation.open() as f:
            evals = list(csv.DictReader(f))
    return RunReport(files.path, config, progress, evals)


def load_runs(run_dirs: list[Path]) -> dict[str, list[RunReport]]:
    """Runs grouped by trust-region rule, rules in the table's order (only rules with runs appear)."""
    groups: dict[str, list[RunReport]] = defaultdict(list)
    for d in run_dirs:
        run = load_run_report(d)
        groups[run.rule].append(run)
    for name, runs in groups.items():
        first, ours = runs[0], runs[0].setup
        for run in runs[1:]:
            theirs = run.setup
            differ = sorted(k for k in ours if ours[k] != theirs[k])
            if differ:
                a, b = (", ".join(f"{k}={setup[k]}" for k in differ) for setup in (ours, theirs))
                raise ValueError(f"runs of {name} were trained differently ({', '.join(differ)}): {first.dir} has "
                                 f"{a}, {run.dir} has {b}; pass them in separate calls")  # fmt: skip
    return {name: groups[name] for name in rule_names() if groups.get(name)}


def float_or_nan(text: str | None) -> float:
    """A CSV cell as a float; an empty cell (nothing measured) is NaN."""
    return float(text) if text not in ("", None) else math.nan


def series(rows: list[dict], key: str) -> tuple[np.ndarray, np.ndarray]:
    """(global_step, column ``key``) of progress rows, NaN where the cell is empty or absent."""
    steps = np.array([int(r["global_step"]) for r in rows])
    return steps, np.array([float_or_nan(r.get(key, "")) for r in rows])


def smooth(y: np.ndarray, window: int) -> np.ndarray:
    """Trailing mean over the last ``window`` finite values (episodes end only every ~1000 steps)."""
    out = np.full_like(y, np.nan)
    for i in range(len(y)):
        seg = y[max(0, i - window + 1) : i + 1]
        seg = seg[np.isfinite(seg)]
        if seg.size:
            out[i] = seg.mean()
    return out


def eval_means(run: RunReport) -> dict[int, dict[int, float]]:
    """{num_joints: {global_step: mean return over episodes}} of one run's chains (trees: ``body_eval_means``)."""
    acc: dict[int, dict[int, list[float]]] = defaultdict(lambda: defaultdict(list))
    for r in run.eval:
        if not r.get("body") or is_chain_label(r["body"]):  # files written before trees hold chains only
            acc[int(r["num_joints"])][int(r["global_step"])].append(float(r["return"]))
    return {n: {s: float(np.mean(v)) for s, v in by_step.items()} for n, by_step in acc.items()}


def label_order(label: str) -> list:
    """Sort key for body labels and keys: chain lengths first and by number, then named bodies with their
    numbers compared as numbers (centipede-10 after centipede-8, star-3x2 after star-3x1)."""
    return [(0, int(t), "") if t.isdigit() else (1, 0, t) for t in re.split(r"(\d+)", label)]


def body_eval_means(run: RunReport, column: str = "return") -> dict[str, dict[int, float]]:
    """{body label: {global_step: mean of ``column`` over episodes}} of one run, chains (``chain-N``) and trees.
    ``column``: ``return``, ``steps`` or ``distance`` (rows that did not record it are left out)."""
    acc: dict[str, dict[int, list[float]]] = defaultdict(lambda: defaultdict(list))
    for r in run.eval:
        if r.get(column) not in (None, ""):
            acc[r.get("body") or chain_label(int(r["num_joints"]))][int(r["global_step"])].append(float(r[column]))
    return {b: {s: float(np.mean(v)) for s, v in by_step.items()} for b, by_step in acc.items()}
