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
import sys
from pathlib import Path

from morph_core.algo.run_dir import RunDir
from morph_core.policy.weights import CheckpointError, load_checkpoint
from morph_core.util.config_cli import (
    BoolAction,
    CommandLineParser,
    add_dataclass_options,
    overrides_from_args,
    replace_nested,
)
from trainer.reports.evaluation import (
    EvalConfig,
    checkpoint_table,
    eval_bodies,
    evaluate_run,
    has_centipedes,
    run_bodies,
    run_eval_config,
)


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
    elif has_centipedes(overrides.get("bodies", "")):
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
        if not (config := RunDir(run).config).exists():
            parser.error(f"{run} is not a training run ({config.name} missing)")
    if args.plots is not None:
        # the reports (torch) only when plots are asked
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
        # Matplotlib only when plots are asked
        from trainer.reports.plots import plot_all

        for path in plot_all(args.run, args.plots):
            print(f"wrote {path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
