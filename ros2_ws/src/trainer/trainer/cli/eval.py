"""``morph-eval``: evaluate every checkpoint of training runs, then plot.

For each run directory, each checkpoint in ``checkpoints/`` is evaluated
deterministically (the policy's mean action), ``--episodes`` episodes per
chain length (``--joints``, default 2..10 plus the unseen 15 and 20) and per tree of
``--bodies`` (``env.bodies``' grammar, named trees: ``--bodies y:2x2,star:3x2``),
into the run's ``eval.csv`` (a row per episode, keyed by the body's label:
``chain-N`` or the tree's, beside its joint count). Checkpoints already in ``eval.csv`` are skipped, so an
interrupted evaluation resumes. ``--stride k`` evaluates every k-th
checkpoint (the last one always); ``--from-step S`` only those from step S
on (zero-shot on long chains late in training: ``--joints 30 40
--from-step 500000``, the same checkpoints as the full pass with the same
stride). ``--processes 2`` evaluates two
checkpoints at a time, one per core (each checkpoint's results are the same
as alone). Figures comparing the clip modes go to ``--plots DIR``.

Centipedes are a family of ``--bodies`` (``--bodies centipede:2-5``: every size from 2 to 5 leg pairs,
trained or zero-shot); an episode ends when the centipede falls. With centipedes in ``--bodies`` and no
``--joints``, no swimmer chains are evaluated. A run that trained on centipedes, given neither ``--bodies``
nor ``--joints``, is evaluated on the bodies it trained on and zero-shot on 5, 6, 8 and 10 leg pairs (the
sizes docs/centipedes.md reports), not on swimmer chains. A policy trained on swimmers alone (4 global features)
cannot drive a centipede (12): refused.

``--checkpoint FILE`` instead of ``--run`` evaluates one policy file (a shipped
model, say) on the same bodies and prints a table of its returns, episode lengths and distances
(mean ± std over the episodes, per body), writing nothing.
"""

from __future__ import annotations

import argparse
import csv
import json
import multiprocessing
import re
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

from threadpoolctl import threadpool_limits

from morph_core.algo.evaluate import Body, Episodes, evaluate_episodes
from morph_core.env.bodies import body_label, chain_label, parse_bodies
from morph_core.policy.tree import KinematicTree
from morph_core.policy.weights import CheckpointError, load_checkpoint
from morph_core.util.atomic import atomic_writer
from morph_core.util.config_cli import (
    BoolAction,
    CommandLineParser,
    add_dataclass_options,
    overrides_from_args,
    replace_nested,
)

CKPT = re.compile(r"policy_(\d+)\.safetensors$")
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
        return str(json.loads((run_dir / "config.json").read_text()).get("bodies", "") or "")
    except (OSError, ValueError, AttributeError):
        return ""  # no readable config: the defaults (a run without one is refused where it is read)


def run_eval_config(run_dir: Path, cfg: EvalConfig, given: set[str]) -> EvalConfig:
    """``cfg`` for the run in ``run_dir``: a run that trained on centipedes, with neither ``lengths`` nor
    ``bodies`` in ``given`` (the options the user set), is evaluated on its own bodies and zero-shot on the
    ``CENTIPEDE_ZERO_SHOT`` sizes instead of the swimmer chains; any other run takes ``cfg`` as it is."""
    trained = run_bodies(run_dir)
    if given & {"lengths", "bodies"} or not _has_centipedes(trained):
        return cfg
    zero_shot = ",".join(f"centipede:{n}" for n in CENTIPEDE_ZERO_SHOT)
    return replace_nested(cfg, {"lengths": [], "bodies": f"{trained},{zero_shot}"})


def checkpoints(run_dir: Path) -> list[tuple[int, Path]]:
    found = []
    for p in (run_dir / "checkpoints").glob("policy_*.safetensors"):
        m = CKPT.search(p.name)
        if m:
            found.append((int(m.group(1)), p))
    return sorted(found)


def read_eval(run_dir: Path) -> list[dict]:
    path = run_dir / "eval.csv"
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
    ckpts = checkpoints(run_dir)
    if not ckpts:
        raise FileNotFoundError(f"no checkpoints in {run_dir / 'checkpoints'}")
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
        with atomic_writer(run_dir / "eval.csv") as f:
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


def _has_centipedes(spec: str) -> bool:
    try:
        return bool(spec) and parse_bodies(spec).has_walkers
    except ValueError:
        return False  # said below, where the spec is read for the bodies


def main(argv: list[str] | None = None) -> int:
    parser = CommandLineParser(
        prog="morph-eval", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--run", type=Path, nargs="+", help="training run directories")
    source.add_argument("--checkpoint", type=Path, help="one policy file: print its returns, write nothing")
    parser.add_argument("--plots", type=Path, default=None, help="write comparison figures here")
    parser.add_argument("--eval", action=BoolAction, default=True,
                        help="evaluate checkpoints not yet in eval.csv (false: only plot what it holds)")  # fmt: skip
    parser.add_deprecated_alias("--no-eval", "--eval", value=False, shown="--eval false")
    add_dataclass_options(parser, EvalConfig, skip=("lengths",))
    parser.add_deprecated_alias("--threads", "--env-threads")
    parser.add_argument("--joints", dest="lengths", type=int, nargs="*", default=None, metavar="N",
                        help="chain lengths (default: 2..10 15 20; none: trees only)")  # fmt: skip
    parser.add_deprecated_alias("--lengths", "--joints")
    args = parser.parse_args(argv)
    overrides = overrides_from_args(args, EvalConfig)
    if args.lengths is not None:
        overrides["lengths"] = args.lengths
    elif _has_centipedes(overrides.get("bodies", "")):
        overrides["lengths"] = []  # a centipede evaluation films no swimmer chains unless asked (--joints)
    cfg = replace_nested(EvalConfig(), overrides)
    bad_lengths = any(not 1 <= n <= 64 for n in cfg.lengths)
    if min(cfg.episodes, cfg.stride, cfg.processes) < 1 or cfg.from_step < 0 or bad_lengths:
        parser.error("episodes, stride and processes must be >= 1, from-step >= 0, lengths in 1..64")
    try:
        if not eval_bodies(cfg):
            parser.error("nothing to evaluate: give --joints or --bodies")
    except ValueError as e:
        parser.error(str(e))
    if args.checkpoint is not None:
        if args.plots is not None or not args.eval or cfg.stride != 1 or cfg.from_step or cfg.processes != 1:
            parser.error("--plots, --eval, --stride, --from-step and --processes are for --run: --checkpoint "
                         "evaluates one file and writes nothing")  # fmt: skip
        try:
            load_checkpoint(args.checkpoint)  # a file that is no policy is said before any episode
        except CheckpointError as err:
            print(f"morph-eval: error: {err}", file=sys.stderr)
            return 1
        print(f"morph-eval: {args.checkpoint}: {cfg.episodes} deterministic episodes (the policy's mean action) "
              f"on each of {len(eval_bodies(cfg))} bodies", file=sys.stderr, flush=True)  # fmt: skip
        print(checkpoint_table(args.checkpoint, cfg))
        return 0
    for run in args.run:
        if not (run / "config.json").exists():
            parser.error(f"{run} is not a training run (config.json missing)")
    if args.plots is not None:
        from trainer.reports.runs import load_runs

        try:  # the runs' grouping is checked before an evaluation that may take an hour
            load_runs(args.run)
        except ValueError as e:
            parser.error(str(e))
    if args.eval:
        for run in args.run:
            run_cfg = run_eval_config(run, cfg, set(overrides))
            if run_cfg is not cfg:
                print(f"morph-eval: {run} trained on {run_bodies(run)}: evaluating {run_cfg.bodies} (--bodies or "
                      "--joints to choose)", file=sys.stderr, flush=True)  # fmt: skip
            try:
                evaluate_run(run, run_cfg)
            except (CheckpointError, FileNotFoundError) as err:  # a damaged checkpoint, or a run without any
                print(f"morph-eval: error: {err}", file=sys.stderr)
                return 1
    if args.plots is not None:
        from trainer.reports.plots import plot_all

        for path in plot_all(args.run, args.plots):
            print(f"wrote {path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
