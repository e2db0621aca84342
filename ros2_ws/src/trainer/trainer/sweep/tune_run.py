"""The sweep on Ray Tune: one function trainable per trial, one ``Tuner`` over the trial list.

The trial's run directory, ``SWEEP_DIR/<trial name>``, is its checkpoint: ``train`` writes its state there
atomically (keeping the previous one) and ``train(..., resume=True)`` continues it bit for bit, cutting
progress.csv back to the state's step. So a trial reports its progress rows to Tune as metrics only, and a
trial that Tune starts again (``FailureConfig``: an exception, or its worker process died) or a sweep restored
(``Tuner.restore``) picks up from the run directory. Copying the state into Tune checkpoints as well would
store every state twice and make two places to resume from that can disagree (Tune's copy lags the run's when
a worker dies between writing the state and reporting it). The price: every node must see the sweep
directory at the same path (a shared filesystem), which Tune asks of a cluster's storage path anyway.
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

from trainer.sweep.spec import Trial

EXPERIMENT = ".tune"
"""Tune's own files inside the sweep directory (hidden: ``SWEEP_DIR/*/`` globs only the run directories)"""

FAULT_ENV = "MORPH_SWEEP_FAULT_DIR"
"""tests only: a directory; a trial whose marker file is not in it writes one and kills its own process on
its first progress row after its first saved state, the way a worker dies (not an exception Tune catches)"""

RAY_QUIET = {
    "RAY_USAGE_STATS_ENABLED": "0",  # no usage-stats prompt or upload
    "RAY_AIR_NEW_OUTPUT": "0",  # with verbose=0: no progress tables (the sweep prints a line per trial)
    "RAY_DEDUP_LOGS": "1",
    "RAY_memory_monitor_refresh_ms": "0",  # on a small shared machine: do not kill trials for others' memory
}
"""Ray settings for a quiet, small local cluster; set before Ray is imported, never over the user's own"""


def quiet_ray_env() -> None:
    for key, value in RAY_QUIET.items():
        os.environ.setdefault(key, value)


def numeric(row: dict) -> dict:
    """The row's numbers (Tune keeps metrics), NaN as None (an update without finished episodes)."""
    out = {}
    for k, v in row.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            continue
        out[k] = None if isinstance(v, float) and math.isnan(v) else v
    return out


def run_trial(config: dict) -> None:
    """Tune's function trainable: train the trial into its run directory (resuming what is there), evaluate
    its late checkpoints, report each progress row and, last, the evaluation."""
    # in the trial's process: Ray ships the function, and its worker imports what it runs
    import ray

    # in the trial's process, as in run_trial
    from ray import tune

    from morph_core.algo.train import train
    from trainer.reports.evaluation import evaluate_run, one_blas_thread
    from trainer.reports.summary import late_means

    trial = Trial.from_dict(config["trial"])
    run_dir = Path(config["sweep_dir"]) / trial.name
    cfg = trial.train_config()
    if "progress_bar" not in trial.overrides:  # nobody watches a trial's terminal
        cfg = dataclasses.replace(cfg, progress_bar=False)
    where = {"node_ip": ray.util.get_node_ip_address(), "netns": _netns()}
    fault_dir = os.environ.get(FAULT_ENV)
    saved_once = [False]

    def on_row(row: dict, saved: bool) -> None:
        tune.report({**numeric(row), **where, "phase": "train"})
        if fault_dir and saved_once[0]:
            marker = Path(fault_dir) / trial.name
            if not marker.exists():
                marker.write_text(f"killed at step {row['global_step']}\n")
                os._exit(3)  # no cleanup, no exception: what a dead worker leaves
        saved_once[0] = saved_once[0] or saved

    # resume=True on a fresh directory starts the run: train resumes only from a state it finds.
    train(cfg, run_dir, resume=True, on_row=on_row)
    one_blas_thread()
    eval_cfg = trial.eval_config(cfg.total_timesteps)
    evaluate_run(run_dir, eval_cfg, log=lambda _: None)  # checkpoints already in eval.csv are skipped
    from trainer.reports.runs import load_run_report

    run = load_run_report(run_dir)
    late = late_means(run)
    trained = [late[n] for n in range(cfg.min_joints, cfg.max_joints + 1) if n in late]
    final = {f"late_eval_{n}": r for n, r in late.items()}
    final["late_eval_trained"] = sum(trained) / len(trained) if trained else None
    last = run.progress[-1] if run.progress else {}
    tune.report({"global_step": int(last.get("global_step", 0)), **final, **where, "phase": "done"})


def _netns() -> str:
    try:
        return os.readlink("/proc/self/ns/net")
    except OSError:
        return ""


def trial_dirname(trial) -> str:
    return trial.config["trial"]["name"]


def make_tuner(trials: list[Trial], sweep_dir: Path, cpus_per_trial: float, max_failures: int, callbacks=()):
    """A new ``Tuner`` of ``trials`` into ``sweep_dir``, or the one stopped there (``Tuner.restore``)."""
    # in the trial's process, as in run_trial
    from ray import tune

    sweep_dir = sweep_dir.resolve()
    trainable = tune.with_resources(run_trial, {"cpu": cpus_per_trial})
    path = str(sweep_dir / EXPERIMENT)
    if tune.Tuner.can_restore(path):
        # Errored trials too: a trial that ran out of max_failures goes on from its run directory.
        return tune.Tuner.restore(path, trainable, resume_unfinished=True, resume_errored=True), True
    param_space = {"trial": tune.grid_search([t.to_dict() for t in trials]), "sweep_dir": str(sweep_dir)}
    tuner = tune.Tuner(
        trainable,
        param_space=param_space,
        tune_config=tune.TuneConfig(trial_name_creator=trial_dirname, trial_dirname_creator=trial_dirname),
        run_config=tune.RunConfig(
            name=EXPERIMENT,
            storage_path=str(sweep_dir),
            failure_config=tune.FailureConfig(max_failures=max_failures),
            verbose=0,
            callbacks=list(callbacks),
        ),
    )
    return tuner, False
