"""Pick the best evaluated checkpoint of training runs and write it, with its provenance, to ``--dest``.

    python -m trainer.reports.ship --run runs/compensated-s* \\
        --dest ros2_ws/src/morph_policy_node/morph_policy_node/models/swimmer_gnn.safetensors

The destination is always given: the path above is where the policy node
loads its default model from (its own package's ``models/``), but which file
a trainer overwrites is the caller's decision, not a path this package
derives from where its source happens to sit.

"Best" is the evaluated checkpoint (any run, any step in its eval.csv) with
the highest mean deterministic return over the training chain lengths, and,
for a run trained on trees (``--bodies`` with a tree family), over every
tree it was evaluated on too; the unseen chain lengths are reported, not used
to choose. (At the paper's constant
learning rate of 0.01 the last checkpoint is not always the best one.) The JSON beside the weights
records the source run, its training command and the evaluation table. The
weights are copied byte for byte, and a trainer's signature goes with them
(``policy.weights.SignedWeights``), so a shipped policy still says who signed it.

A policy already at ``--dest`` is a candidate too: its recorded evaluation is
scored over the same lengths, and a run's checkpoint replaces it only if it
scores higher (``--replace`` writes the best run's checkpoint regardless). So
shipping again over new runs never swaps the shipped policy for a worse one,
and the shipped policy need not come from a run whose checkpoints are kept.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from morph_core.algo.run_dir import RunDir
from morph_core.algo.train import TrainConfig
from morph_core.env.bodies import Centipede, is_chain_label, parse_bodies
from morph_core.policy.tree import KinematicTree
from morph_core.policy.weights import CheckpointError, load_checkpoint, write_checkpoint
from morph_core.util.config_cli import BoolAction, CommandLineParser
from trainer.reports.runs import body_eval_means, label_order, load_run_report


def body_key(label: str) -> str:
    """A body's key in a shipped policy's ``eval_mean_return``: the chain length for a chain (as policies
    shipped before trees recorded it), else the tree's label."""
    return label.removeprefix("chain-") if is_chain_label(label) else label


def evaluated_checkpoints(run_dir: Path) -> dict[int, dict[str, float]]:
    """{global_step: {body key: mean return}} of every evaluated checkpoint of a run (``body_key``)."""
    by_step: dict[int, dict[str, float]] = {}
    for label, steps in body_eval_means(load_run_report(run_dir)).items():
        for step, ret in steps.items():
            by_step.setdefault(step, {})[body_key(label)] = ret
    if not by_step:
        raise ValueError(f"{run_dir} has no eval.csv yet: run morph-eval first")
    return by_step


def episodes_per_body(run_dir: Path, step: int) -> int:
    """How many episodes per body the run's evaluation of the checkpoint at ``step`` holds."""
    rows = [r for r in load_run_report(run_dir).eval if int(r["global_step"]) == step]
    return max(sum(r["body"] == b for r in rows) for b in {r["body"] for r in rows})


def scored_bodies(cfg: dict, table: dict[str, float]) -> list[str]:
    """The evaluated bodies a checkpoint is chosen by: the chain lengths it trained on, every evaluated tree
    when it trained on trees, and the centipede sizes it trained on (zero-shot sizes are reported, not
    scored, as unseen chain lengths are)."""
    spec = parse_bodies(cfg["bodies"]) if cfg.get("bodies") else None
    if spec is not None and spec.has_centipedes:
        members = spec.members() or []
        trained = {m.label for m in members if isinstance(m, Centipede)}
        chains = {str(m.num_joints) for m in members if isinstance(m, KinematicTree) and m.is_chain}
        return [k for k in table if k in trained or k in chains]
    trees = spec is not None and not spec.chains_only
    chains = [k for k in table if k.isdigit() and cfg["min_joints"] <= int(k) <= cfg["max_joints"]]
    return chains + ([k for k in table if not k.isdigit()] if trees else [])


def shipped_score(dest: Path, bodies: list[str]) -> tuple[float, str, int] | None:
    """(mean recorded return over ``bodies``, source run, step) of the policy at ``dest``; None when there is
    no usable checkpoint there, or its metadata lacks an evaluation of one of those bodies (no comparison)."""
    try:
        meta = load_checkpoint(dest).metadata
        returns = meta["eval_mean_return"]
        return float(np.mean([returns[b] for b in bodies])), str(meta["source_run"]), int(meta["global_step"])
    except (CheckpointError, KeyError, TypeError, ValueError):
        return None


def training_command(cfg: dict, run_name: str) -> str:
    """The morph-train command of a run: clip mode, seed, and every option that differs from the defaults."""
    # Through TrainConfig, so keys older configs carry that are no options any more (policy.backend) drop out.
    given, defaults = _flat(TrainConfig.from_dict(cfg).to_dict()), _flat(TrainConfig().to_dict())
    cosmetic = {"tensorboard", "progress_bar", "clip_mode", "rule", "seed", "batch_size"}  # batch: envs x steps
    changed = {k: v for k, v in given.items() if k not in cosmetic and v != defaults.get(k)}
    flags = [f"--{k.replace('_', '-')} {_text(v)}" for k, v in changed.items()]
    return " ".join(
        ["morph-train", f"--clip-mode {cfg['clip_mode']}", f"--seed {cfg['seed']}", *flags, f"--out runs/{run_name}"]
    )


def _flat(cfg: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in cfg.items():
        out.update(_flat(v, f"{prefix}{k}_") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def _text(value) -> str:
    return str(value).lower() if isinstance(value, bool) else str(value)


def main(argv: list[str] | None = None) -> None:
    parser = CommandLineParser(prog="python -m trainer.reports.ship", description=__doc__)
    parser.add_argument("--run", type=Path, nargs="+", required=True)
    parser.add_argument(
        "--dest", type=Path, required=True, help="where to write the policy (.safetensors, with its .json beside it)"
    )
    parser.add_argument(
        "--replace",
        action=BoolAction,
        default=False,
        help="write the best run's checkpoint even if the policy already at --dest scored higher",
    )
    args = parser.parse_args(argv)
    scored = []
    for run in args.run:
        cfg = RunDir(run).read_config()
        for step, table in evaluated_checkpoints(run).items():
            bodies = scored_bodies(cfg, table)
            scored.append((float(np.mean([table[b] for b in bodies])), run, cfg, step, table, bodies))
    score, run, cfg, step, table, bodies = max(scored, key=lambda s: s[0])
    shipped = shipped_score(args.dest, bodies)
    if shipped is not None and shipped[0] >= score and not args.replace:
        print(f"kept {args.dest} ({shipped[1]} step {shipped[2]}, score {shipped[0]:.1f}): the best evaluated "
              f"checkpoint of the runs, {run.name} step {step}, scores {score:.1f}")  # fmt: skip
        return
    checkpoint = RunDir(run).checkpoint(step)
    if not checkpoint.is_file():  # e.g. a run kept as data only (docs/results_data keeps no checkpoints)
        parser.error(f"the best evaluated checkpoint is {run.name} at step {step} (score {score:.1f}), but "
                     f"{checkpoint} is missing; train the run again (`{training_command(cfg, run.name)}`, "
                     "deterministic) and pass its new directory")  # fmt: skip
    source = load_checkpoint(checkpoint)  # checked; its bytes are copied as they are, so a signature still holds
    write_checkpoint(
        args.dest,
        checkpoint.read_bytes(),
        dataclasses.asdict(source.config),
        metadata={
            "source_run": run.name,
            "global_step": step,
            "clip_mode": cfg["clip_mode"],
            "seed": cfg["seed"],
            "training_command": training_command(cfg, run.name),
            "eval": f"deterministic, {episodes_per_body(run, step)} episodes of up to 1000 steps per body (morph-eval)",
            "eval_mean_return": {b: round(table[b], 2) for b in sorted(table, key=label_order)},
            "chosen_by": f"mean return over {_described(bodies)} ({score:.1f})",
        },
        signed=source.signed,
    )
    print(f"shipped {run.name} step {step} (score {score:.1f}) to {args.dest}")


def _described(bodies: list[str]) -> str:
    lengths = sorted(int(b) for b in bodies if b.isdigit())
    legged = [b for b in bodies if b.startswith("centipede-")]
    trees = [b for b in bodies if not b.isdigit() and b not in legged]
    parts = [f"chain lengths {lengths[0]}..{lengths[-1]}"] if lengths else []
    parts += [f"the trees {', '.join(trees)}"] if trees else []
    parts += [f"the centipedes {', '.join(legged)}"] if legged else []
    return " and ".join(parts) or "no body"


if __name__ == "__main__":
    main()
