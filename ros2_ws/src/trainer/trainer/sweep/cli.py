"""``morph-sweep``: a grid or list of training runs on Ray Tune, each an ordinary run directory, then their table.

    morph-sweep --spec sweeps/rules.yaml --out runs/rules                       # a spec file
    morph-sweep --grid rule=fixed,compensated --grid seed=1,2,3 --set total-timesteps=200000 --out runs/s
    morph-sweep --spec sweeps/rules.yaml --out runs/rules --address HEAD:6379   # on a Ray cluster

Each trial trains into ``OUT/<trial name>`` (``rule=fixed,seed=1``: the overrides that vary) as
``morph-train --out`` would, then evaluates its late checkpoints there (``eval.csv``; the spec's ``eval``:
morph-eval's options, ``from_step`` half the run's steps unless given). A trial that fails or whose process
dies is started again (``--max-failures``) and resumes from its run directory's last state, with the result
of a run never interrupted. A sweep stopped as a whole (Ctrl-C, a lost head) resumes with the same command;
another spec into the same ``--out`` is refused. At the end ``OUT/summary.md`` holds a table of the trials
(node, steps, the last 10 updates' training return, the late evaluation) and ``trainer.reports.summary``'s tables,
the rules ranked claim by claim, for each group of trials that differ only in rule and seed; it is printed.

Local by default: Ray starts here with ``--cpus`` CPUs, one trial per ``--cpus-per-trial``. ``--address``
joins a running cluster (``ray start --head`` on one machine, ``ray start --address HEAD:PORT`` on the
others; ``OUT`` must be on a filesystem every node sees at the same path). The spec's format:
``trainer.sweep.spec``.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import sys
import warnings
from pathlib import Path

from morph_core.util.atomic import atomic_writer
from morph_core.util.config_cli import BoolAction, CommandLineParser
from trainer.sweep.spec import SpecError, Trial, load_spec
from trainer.sweep.tune_run import EXPERIMENT, make_tuner, quiet_ray_env

RULE_KEYS = ("rule", "clip_mode")
"""the trust-region setting's names (``clip_mode``, the older one, an alias of ``rule``): the ranking
table compares them, so they do not split the trials into groups"""


def build_parser() -> CommandLineParser:
    parser = CommandLineParser(
        prog="morph-sweep", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, required=True, help="the sweep directory: a run directory per trial")
    parser.add_argument("--spec", type=Path, default=None, help="a sweep spec, YAML or JSON (trainer.sweep.spec)")
    parser.add_argument("--grid", action="append", default=[], metavar="KEY=V1,V2",
                        help="a TrainConfig field and its values, crossed with other grids (repeat it)")  # fmt: skip
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a TrainConfig field set in every trial (repeat it)")  # fmt: skip
    parser.add_argument("--eval", action="append", default=[], metavar="KEY=VALUE",
                        help="a morph-eval option for every trial: stride, episodes, lengths=2,3,10 ...")  # fmt: skip
    parser.add_argument("--cpus", type=int, default=None,
                        help="CPUs of the local Ray (default: this machine's); not with --address")  # fmt: skip
    parser.add_argument("--cpus-per-trial", type=float, default=1.0, help="CPUs each trial holds (default: 1)")
    parser.add_argument("--address", default=None, help="a running Ray cluster's address (HOST:PORT) to join")
    parser.add_argument("--max-failures", type=int, default=3,
                        help="restarts of a trial that fails or whose worker dies (default: 3)")  # fmt: skip
    parser.add_argument("--dry-run", action=BoolAction, default=False, help="print the trials and exit")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.cpus is not None and args.address:
        parser.error("--cpus is for the local Ray; a cluster's CPUs are its own (ray start --num-cpus)")
    if (args.cpus is not None and args.cpus < 1) or args.cpus_per_trial <= 0 or args.max_failures < 0:
        parser.error("--cpus must be >= 1, --cpus-per-trial > 0, --max-failures >= 0")
    try:
        trials = load_spec(args.spec, args.set, args.grid, args.eval).expand()
    except SpecError as err:
        parser.error(str(err))
    if args.dry_run:
        for t in trials:
            print(t.name)
        return 0
    try:
        _claim(args.out, trials)
    except SpecError as err:
        parser.error(str(err))

    quiet_ray_env()
    import ray  # Ray (the trainer[ray] extra) loads after quiet_ray_env() has set its environment

    if args.address:
        ray.init(address=args.address, logging_level="WARNING")
    else:
        ray.init(num_cpus=args.cpus or os.cpu_count(), include_dashboard=False,
                 object_store_memory=200 * 1024**2, logging_level="WARNING")  # fmt: skip
    try:
        tuner, restored = make_tuner(trials, args.out, args.cpus_per_trial, args.max_failures, [Said()])
        print(f"morph-sweep: {'resuming' if restored else 'starting'} {len(trials)} trial(s) into {args.out}",
              flush=True)  # fmt: skip
        results = tuner.fit()
    finally:
        ray.shutdown()
    status = _status(trials, results)
    with atomic_writer(args.out / "trials.json") as f:
        json.dump(status, f, indent=2)
    done = [name for name, s in status.items() if s["done"]]
    if len(done) < len(trials):
        print(f"morph-sweep: error: {len(done)} of {len(trials)} trials finished; the same command resumes the "
              "sweep", file=sys.stderr)  # fmt: skip
        return 1
    text = summary(args.out, trials, status)
    with atomic_writer(args.out / "summary.md") as f:
        f.write(text)
    print(text, end="")
    print(f"morph-sweep: {len(trials)} trials in {args.out}; this table in {args.out / 'summary.md'}")
    return 0


def _claim(out: Path, trials: list[Trial]) -> None:
    """Write the sweep's trials to ``OUT/sweep.json``, or check they are those of the sweep already there."""
    path = out / "sweep.json"
    ours = {"trials": [t.to_dict() for t in trials]}
    if path.exists():
        try:
            theirs = json.loads(path.read_text())
        except ValueError:
            theirs = None
        if theirs != json.loads(json.dumps(ours)):
            raise SpecError(f"{out} holds another sweep ({path} differs); give its own spec or another --out")
        return
    if out.exists() and any(p.name != EXPERIMENT for p in out.iterdir()):
        raise SpecError(f"{out} is not empty and holds no sweep; choose another --out")
    with atomic_writer(path) as f:
        json.dump(ours, f, indent=2)


def _said_class():
    # Ray, the trainer[ray] extra, only when a sweep runs
    from ray.tune import Callback

    class Said(Callback):
        """One line per trial that finishes, fails or starts again: the sweep's own log, Tune's output off."""

        def on_trial_complete(self, iteration, trials, trial, **info):
            print(f"morph-sweep: {trial.config['trial']['name']} finished", flush=True)

        def on_trial_recover(self, iteration, trials, trial, **info):
            print(f"morph-sweep: {trial.config['trial']['name']} failed; starts again from its run directory",
                  flush=True)  # fmt: skip

        def on_trial_error(self, iteration, trials, trial, **info):
            print(f"morph-sweep: {trial.config['trial']['name']} failed {trial.num_failures} times; given up "
                  "(the same command tries it again)", flush=True)  # fmt: skip

    return Said


def Said():  # noqa: N802  (a class made once Ray is imported: the module imports without Ray)
    return _said_class()()


def _status(trials: list[Trial], results) -> dict:
    by_name = {}
    for result in results:
        name = result.config["trial"]["name"] if result.config else None
        metrics = result.metrics or {}
        by_name[name] = {
            "done": result.error is None and metrics.get("phase") == "done",
            "node_ip": metrics.get("node_ip"),
            "netns": metrics.get("netns"),
            "global_step": metrics.get("global_step"),
            "late_eval_trained": metrics.get("late_eval_trained"),
            "error": None if result.error is None else " ".join(str(result.error).split())[:300],
        }
    empty = {"done": False, "node_ip": None, "netns": None, "global_step": None, "late_eval_trained": None,
             "error": "no result"}  # fmt: skip
    return {t.name: by_name.get(t.name, empty) for t in trials}


def groups(trials: list[Trial]) -> dict[str, list[Trial]]:
    """Trials that differ only in how they ran (seed, threads ...) and their rule, under a label of what the
    rest of their overrides says; trainer.reports.summary refuses to pool runs of one rule trained differently."""
    # the reports (torch) stay out of the driver until the trials are grouped
    from trainer.reports.runs import HOW_RUN

    out: dict[str, list[Trial]] = {}
    for t in trials:
        rest = {k: v for k, v in t.overrides.items() if k not in HOW_RUN and k not in RULE_KEYS}
        out.setdefault(",".join(f"{k}={v}" for k, v in sorted(rest.items())), []).append(t)
    return out


def summary(out: Path, trials: list[Trial], status: dict) -> str:
    """The sweep's Markdown: its trials, then trainer.reports.summary's tables for each group of trials."""
    # the reports (torch) stay out of the driver until the sweep is summed up
    from trainer.reports import summary as tables
    from trainer.reports.runs import load_run_report

    warnings.simplefilter("ignore", RuntimeWarning)  # NumPy's "mean of empty slice": a '–' in a cell
    lines = [f"# Sweep {out}\n", "## Trials\n", "| trial | node | steps | last 10 updates | late eval, trained "
             "lengths | late eval per length |", "|---|---|---:|---:|---:|---|"]  # fmt: skip
    for t in trials:
        run = load_run_report(out / t.name)
        late = tables.late_means(run)
        per_length = " ".join(f"{n}:{r:.0f}" for n, r in sorted(late.items()))
        trained = tables.late_trained_mean(run)
        lines.append(f"| {t.name} | {status[t.name]['node_ip']} | {run.progress[-1]['global_step']} | "
                     f"{tables._num(tables.training_marks(run)['last'])} | {tables._num(trained)} "
                     f"| {per_length or '–'} |")  # fmt: skip
    lines.append("\nlast 10 updates: the mean training return of the run's last 10 updates; late eval: the "
                 "deterministic eval return over the checkpoints from half the run's steps on, averaged over the "
                 "trained chain lengths, then per chain length (n:return); –: none evaluated (a run of other "
                 "bodies: their tables follow)")  # fmt: skip
    for label, members in groups(trials).items():
        lines.append(f"\n## {label or 'all trials'}: trainer.reports.summary\n")
        text, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(text), contextlib.redirect_stderr(err):
            try:
                tables.main(["--run", *(str(out / t.name) for t in members)])
            except SystemExit:  # its one-line error (runs it cannot compare), kept in the file
                pass
        lines.append((text.getvalue() + err.getvalue()).strip())
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
