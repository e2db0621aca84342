"""Evaluating training runs: every checkpoint of a run on chosen bodies into its ``eval.csv``, or one policy
file into a table. ``morph-eval`` (``cli.eval``) is its command line; the sweep evaluates its trials with it.

A row per episode, keyed by the body's label (``chain-N`` or the tree's) beside its joint count. Checkpoints
already in ``eval.csv`` are skipped, so an interrupted evaluation resumes; the file is rewritten atomically
after every checkpoint.
"""

from __future__ import annotations

import csv
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

from threadpoolctl import threadpool_limits

from morph_core.algo.evaluate import Body, Episodes, evaluate_episodes
from morph_core.algo.run_dir import RunDir
from morph_core.env.bodies import body_label, chain_label, parse_bodies
from morph_core.policy.tree import KinematicTree
from morph_core.policy.weights import load_checkpoint
from morph_core.util.atomic import atomic_writer
from morph_core.util.config_cli import replace_nested

EVAL_COLUMNS = ["global_step", "num_joints", "episode", "return", "body", "steps", "distance"]
"""A row per episode. ``steps``: how long it lasted; ``distance``: the root's x displacement, metres (empty in
rows written before they were recorded)."""


@dataclass
class EvalConfig:
    """Checkpoint evaluation."""

    lengths: list[int] = field(default_factory=lambda: [*range(2, 11), 15, 20])
    """chain lengths to evaluate"""
    bodies: str = ""
    """trees (and chains) to evaluate beside ``lengths``: an ``env.bodies`` spec of named families (every
    member is evaluated; random families are refused: an evaluation needs the same bodies every time)"""
    episodes: int = 10
    """deterministic episodes per chain length"""
    stride: int = 1
    """evaluate every k-th checkpoint (the last one always)"""
    from_step: int = 0
    """only checkpoints at or after this global step (of those the stride picks; the last one always)"""
    seed: int = 10_000
    """reset seed of episode 0 (episode k uses seed + k)"""
    env_threads: int = 1
    """threads stepping the swimmers of one checkpoint (morph-train's --env-threads)"""
    processes: int = 1
    """checkpoints evaluated at a time, each in its own process (2 uses both cores of a 2-core machine)"""


CENTIPEDE_ZERO_SHOT = (5, 6, 8, 10)
"""leg pairs a centipede run is evaluated on zero-shot by default: the sizes docs/centipedes.md reports"""


def run_bodies(run_dir: Path) -> str:
    """The ``bodies`` spec the run in ``run_dir`` trained on ('' for chains of min_joints..max_joints)."""
    try:
        return str(RunDir(run_dir).read_config().get("bodies", "") or "")
    except (OSError, ValueError, AttributeError):
        return ""  # no readable config: the defaults (a run without one is refused where it is read)


def run_eval_config(run_dir: Path, cfg: EvalConfig, given: set[str]) -> EvalConfig:
    """``cfg`` for the run in ``run_dir``: a run that trained on centipedes, with neither ``lengths`` nor
    ``bodies`` in ``given`` (the options the user set), is evaluated on its own bodies and zero-shot on the
    ``CENTIPEDE_ZERO_SHOT`` sizes instead of the swimmer chains; any other run takes ``cfg`` as it is."""
    trained = run_bodies(run_dir)
    if given & {"lengths", "bodies"} or not has_centipedes(trained):
        return cfg
    zero_shot = ",".join(f"centipede:{n}" for n in CENTIPEDE_ZERO_SHOT)
    return replace_nested(cfg, {"lengths": [], "bodies": f"{trained},{zero_shot}"})


def read_eval(run_dir: Path) -> list[dict]:
    path = RunDir(run_dir).evaluation
    if not path.exists():
        return []
    with path.open() as f:
        rows = [r for r in csv.DictReader(f) if None not in r.values()]
    for r in rows:  # files written before trees hold chains only
        r.setdefault("body", chain_label(int(r["num_joints"])))
    return rows


def eval_bodies(cfg: EvalConfig) -> list[Body]:
    """The bodies ``cfg`` evaluates: its chain lengths, then every member of its ``bodies`` families."""
    bodies: list[Body] = list(cfg.lengths)
    if cfg.bodies:
        members = parse_bodies(cfg.bodies).members()
        if members is None:
            raise ValueError(f"bodies {cfg.bodies!r} holds a random family: name the trees to evaluate")
        bodies += [m.num_joints if isinstance(m, KinematicTree) and m.is_chain else m for m in members]
    return list(dict.fromkeys(bodies))


def num_joints(body: Body) -> int:
    return body if isinstance(body, int) else body.num_joints


def evaluate_run(run_dir: Path, cfg: EvalConfig, log=print) -> list[dict]:
    rows = read_eval(run_dir)
    done = {(int(r["global_step"]), r["body"]) for r in rows}
    bodies = eval_bodies(cfg)
    ckpts = RunDir(run_dir).saved_checkpoints()
    if not ckpts:
        raise FileNotFoundError(f"no checkpoints in {RunDir(run_dir).checkpoints}")
    chosen = [(step, path) for step, path in ckpts[:: cfg.stride] if step >= cfg.from_step]
    if not chosen or chosen[-1] != ckpts[-1]:
        chosen.append(ckpts[-1])
    jobs = [
        (step, path, todo)
        for step, path in chosen
        if (todo := [b for b in bodies if (step, body_label(b)) not in done])
    ]
    for step, results in _evaluated(jobs, cfg):
        for body, result in results.items():  # once per body, even one given twice (evaluate_episodes)
            rows += [
                {"global_step": step, "num_joints": num_joints(body), "episode": k, "return": float(r),
                 "body": body_label(body), "steps": int(n), "distance": float(d)}
                for k, (r, n, d) in enumerate(zip(result.returns, result.steps, result.distance, strict=True))
            ]  # fmt: skip
        rows.sort(key=lambda r: (int(r["global_step"]), int(r["num_joints"]), r["body"], int(r["episode"])))
        # Rewrite the whole file atomically after every checkpoint: an interrupted run loses nothing.
        with atomic_writer(RunDir(run_dir).evaluation) as f:
            w = csv.DictWriter(f, fieldnames=EVAL_COLUMNS)
            w.writeheader()
            w.writerows(rows)
        means = " ".join(f"{body_label(body)}:{result.returns.mean():.1f}" for body, result in results.items())
        log(f"{run_dir.name} step {step}: {means}")
    return rows


def evaluate_checkpoint(path: Path, bodies: list[Body], cfg: EvalConfig) -> dict[Body, Episodes]:
    """The episodes of the checkpoint at ``path`` per body (its weights read without torch)."""
    return evaluate_episodes(load_checkpoint(path), bodies, cfg.episodes, seed=cfg.seed, num_threads=cfg.env_threads)


def one_blas_thread() -> None:
    """One BLAS thread in this evaluation process. OpenBLAS's worker threads spin while they wait, so two
    processes with two BLAS threads each on two cores fight for them: two evaluations side by side ran
    3.6x slower than with one thread each (docs/benchmarks.md)."""
    threadpool_limits(limits=1, user_api="blas")


def _evaluated(jobs: list[tuple[int, Path, list[Body]]], cfg: EvalConfig):
    """(step, results) of every job, in order, evaluated ``cfg.processes`` at a time."""
    if cfg.processes == 1 or len(jobs) < 2:
        for step, path, todo in jobs:
            yield step, evaluate_checkpoint(path, todo, cfg)
        return
    context = multiprocessing.get_context("spawn")  # a fresh interpreter: no inherited threads or locks
    with ProcessPoolExecutor(min(cfg.processes, len(jobs)), mp_context=context, initializer=one_blas_thread) as pool:
        futures = [(step, pool.submit(evaluate_checkpoint, path, todo, cfg)) for step, path, todo in jobs]
        for step, future in futures:
            yield step, future.result()


def checkpoint_table(path: Path, cfg: EvalConfig) -> str:
    """A Markdown table of the policy file at ``path`` on ``cfg``'s bodies: return, episode length and distance
    travelled, mean ± std over the episodes."""
    results = evaluate_checkpoint(path, eval_bodies(cfg), cfg)
    lines = [
        f"mean ± std over {cfg.episodes} episodes; distance: the root's forward travel",
        "",
        "| body | joints | return | steps | distance (m) |",
        "|---|---:|---:|---:|---:|",
    ]
    for body, e in results.items():
        lines.append(
            f"| {body_label(body)} | {num_joints(body)} | {e.returns.mean():.1f} ± {e.returns.std():.1f} "
            f"| {e.steps.mean():.0f} ± {e.steps.std():.0f} | {e.distance.mean():.2f} ± {e.distance.std():.2f} |"
        )
    return "\n".join(lines)


def has_centipedes(spec: str) -> bool:
    """Whether the ``bodies`` spec names walkers (centipedes, legged bodies); False for one that does not parse,
    which is said where the spec is read for the bodies."""
    try:
        return bool(spec) and parse_bodies(spec).has_walkers
    except ValueError:
        return False
