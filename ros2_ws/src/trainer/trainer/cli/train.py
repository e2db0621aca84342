"""``morph-train``: PPO on bodies of mixed sizes (swimmer chains and trees, centipedes), under a trust-region rule
of the table.

Bodies: chains of ``--min-joints``..``--max-joints`` joints by default, or ``--bodies SPEC`` (docs/bodies.md,
e.g. ``2-10,random:3-10``, ``centipede:2-4``). Bodies with legs (centipedes) take the centipede results' PPO
settings where no option sets them, from the simulator, from bags and live: ``--learning-rate 0.0003 --gamma
0.99 --gae-lambda 0.95`` (docs/centipedes.md); swimmers the paper's (0.01, 0.98, 0.98; live 0.003).

Every TrainConfig field is an option (``--rule``, ``--total-timesteps``,
``--policy-bidirectional`` ...; ``--clip-mode`` is the deprecated name of
``--rule``). ``--resume`` continues the run in ``--out`` from its last
checkpoint, with the config it was started with; options given again
override it (e.g. a larger ``--total-timesteps``, a new ``--learning-rate``:
the optimizer's state comes back with the rate and epsilon given) and are
written back to its config.json. A run that reached its
``--total-timesteps`` says so and does nothing.

From recorded topics instead of the simulator (``morph_core.algo.train_from_data``):

    morph-train --from-bags BAG... --out DIR [--init POLICY.safetensors] [--iterations N]
    morph-train --from-bags BAG... --out DIR --resume               after a kill: the same bags
    morph-train --from-bags NEW... --out DIR --resume --new-data    the next round, on new bags

PPO updates of up to num_envs x num_steps samples (6144 by default) on the
bags' transitions, each bag its own stream (``morph-bag info`` shows what a
bag holds). The bags must carry ``policy_info`` (the behaviour log-prob):
record with ``morph_policy_node`` ``deterministic:=false`` (scripts/record.sh
does). ``--iterations`` defaults to one pass over the data. Without
``--init`` the policy starts fresh from ``--seed``. The run directory is laid
out as for simulator training; a resume on other bags than the run trains
on is refused. The learning rate is the paper's 0.01, at which a fresh
policy's updates on bags stayed near the KL target; a trained policy given
with ``--init`` wants a lower one: the shipped policy, on a bag of its own
episodes, reached approximate KL 17.6 on its first update at 0.01 (and then
diverged), 0.19 at 0.003 and 0.05 at 0.001 (a one-off check: docs/guides/bags.md).

What it says: the progress bar shows ``ret`` (simulator: the mean return of
the last 50 episodes), ``sps`` (steps per second) and ``kl`` (the last
update's approximate KL); from bags ``kl`` and ``w``, the mean truncated
importance weight min(pi_prox / pi_behav, proximal_weight_cap) of the
update's samples (1 while the data are the policy's own, lower as it moves
away from the policy that acted). An update whose approximate KL exceeds 10
x ``--kl-target`` (0.1 by default) is warned about (the first 3; the
summary counts them all). At the end, two lines: the steps and updates, the
final training return (from bags: the recorded episodes' return) and where
the run's files are. Every file is in ``--out``: config.json (the config,
options given with ``--resume`` written back), progress.csv (a row per
update), tb/ (TensorBoard), checkpoints/policy_<step>.safetensors (the
policy) and state.safetensors (what ``--resume`` continues from).
"""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path

from morph_core.algo.checkpoint import TrainingStateError
from morph_core.algo.rollout_workers import RolloutWorkerError
from morph_core.algo.run_dir import RunDir
from morph_core.algo.train import TrainConfig, train
from morph_core.algo.train_from_data import describe_bodies, passes_cut, train_from_data
from morph_core.protocol.transition_batch import MissingPolicyInfoError
from morph_core.protocol.transitions import TransitionConfig
from morph_core.protocol.trust import load_signing_key
from morph_core.util.config_cli import (
    CommandLineParser,
    overrides_from_args,
)
from trainer import train_options
from trainer.bags.contents import no_steps, read_bags, summarize_bag
from trainer.bags.io import BagError
from trainer.bags.options import BagOptions
from trainer.cli.train_report import KL_WARN_FACTOR, ProgressFollower
from trainer.train_options import bag_options, descriptions_error, init_error, live_config, new_run_config
from trainer.train_session import (
    ResumedConfig,
    ResumeError,
    finished_data_message,
    finished_message,
    saved_counters,
)


class CliError(Exception):
    """A one-line error for the command line."""


def build_parser() -> CommandLineParser:
    return train_options.build_parser(__doc__)


def _train_from_bags(args, bags: BagOptions) -> None:
    overrides = overrides_from_args(args, TrainConfig)
    if (error := init_error(args)) is not None:
        raise CliError(error)
    source = [str(Path(b).resolve()) for b in bags.from_bags]
    resumed = None
    if args.resume:
        if not (config := RunDir(args.out).config).exists():
            raise CliError(f"--resume: no run to resume in {args.out} ({config.name} missing)")
        resumed = ResumedConfig(args.out, overrides)
        cfg = resumed.cfg
        if not bags.new_data and (done := finished_data_message(args.out, source, bags.iterations)):
            print(f"morph-train: {done}")
            return
    else:
        if RunDir(args.out).state.exists():
            raise CliError(f"{args.out} already holds a run; pass --resume to continue it or choose another --out")
        cfg = new_run_config(TrainConfig(), overrides)
    if (error := descriptions_error(cfg, bags.init)) is not None:
        raise CliError(error)
    data, warnings, skips = read_bags(bags.from_bags, bags.namespace)
    for w in warnings:
        print(f"morph-train: warning: {w}", file=sys.stderr)
    if not len(data):
        skipped = ", ".join(f"{r} {n}" for r, n in skips.steps().items() if n)
        why = skipped or "none; " + (
            no_steps(summarize_bag(bags.from_bags[0], TransitionConfig(), bags.namespace))
            if len(bags.from_bags) == 1
            else "morph-bag info BAG says why, bag by bag"
        )
        raise CliError(f"no usable steps in {', '.join(map(str, bags.from_bags))} (skipped: {why})")
    missing = int((~data.has_policy_info).sum())
    if missing == len(data):
        try:
            data.require_policy_info()
        except MissingPolicyInfoError as err:
            hint = "record with morph_policy_node deterministic:=false (scripts/record.sh does)"
            raise CliError(f"{err}; {hint}") from None
    if missing:
        print(f"morph-train: warning: {missing} of {len(data)} steps have no policy_info (lost, or another "
              "controller acted): they enter the advantages, not the updates", file=sys.stderr)  # fmt: skip
    updates = bags.iterations or passes_cut(len(data) - missing, cfg.batch_size)
    print(
        f"morph-train: {len(data)} steps ({data.num_episodes} episodes, {describe_bodies(data)}) from "
        f"{len(bags.from_bags)} bag(s); {'up to ' if args.resume else ''}{updates} "
        f"update(s) of up to {cfg.batch_size} samples into {args.out}",
        flush=True,
    )
    follower = _follower(args.out, cfg, args.resume, bags.init)
    if cfg.progress_bar:
        print(f"morph-train: progress bar: kl = the update's approximate KL (warned above {follower.kl_limit:g}), "
              "w = its samples' mean importance weight min(pi_prox / pi_behav, proximal_weight_cap): 1 on the "
              "policy's own data, lower as it moves away from the policy that acted", file=sys.stderr)  # fmt: skip
    with resumed.kept_unless_trained(RunDir(args.out).state) if resumed else contextlib.nullcontext():
        if resumed:
            resumed.write_back()
        with follower:
            train_from_data(
                cfg,
                data,
                args.out,
                iterations=bags.iterations,
                init=bags.init,
                resume=args.resume,
                new_data=bags.new_data,
                source=source,
                on_row=follower.on_row,
            )
    print("\n".join(follower.summary(args.out, data=True)), flush=True)


def _train_live(args, parser) -> int:
    from trainer.live.trainer_node import run_live  # rclpy only here

    cfg, options, resumed = live_config(args, parser)
    try:
        signer = None if args.signing_key is None else load_signing_key(args.signing_key)
    except ValueError as err:  # KeyFileError is a ValueError
        parser.error(str(err))
    follower = _follower(args.out, cfg, args.resume)
    with resumed.kept_unless_trained(RunDir(args.out).state) if resumed else contextlib.nullcontext():
        if resumed:
            resumed.write_back()
        with follower:
            code = run_live(cfg, options, signer=signer, on_row=follower.on_row)
    print("\n".join(follower.summary(args.out)), flush=True)
    return code


def _follower(out: Path, cfg: TrainConfig, resume: bool, init: Path | None = None) -> ProgressFollower:
    """The reader of the run's progress.csv that warns of high KL while it trains and sums the session up."""
    counters = saved_counters(out) if resume else None
    start = 0 if counters is None else counters["global_step"]
    hint = "a lower --learning-rate keeps it closer"
    if init is not None:
        hint += " (a trained policy given with --init: e.g. --learning-rate 0.001)"
    return ProgressFollower(out, KL_WARN_FACTOR * cfg.kl_target, start_step=start, hint=hint)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        overrides_from_args(args, TrainConfig)  # --rule and --clip-mode given with two rules: said here
    except ValueError as err:
        parser.error(str(err))
    if args.live:
        return _train_live(args, parser)
    if args.from_bags is not None:
        try:
            bags = bag_options(args)
        except ValueError as err:
            parser.error(str(err))
        if bags.new_data and not args.resume:
            parser.error("--new-data continues a run: pass --resume too")
        try:
            _train_from_bags(args, bags)
        except (CliError, BagError, ValueError, TypeError) as err:
            # ValueError: bad option values (the config's checks), data that do not fit the run
            print(f"morph-train: error: {err}", file=sys.stderr)
            return 1
        return 0
    if args.namespaces or args.signing_key:
        parser.error("--namespaces, --signing-key: only with --live")
    given = [opt for opt, v in (("--iterations", args.iterations), ("--new-data", args.new_data),
                                ("--namespace", args.namespace)) if v]  # fmt: skip
    if given:
        parser.error(f"{', '.join(given)}: only with --from-bags")
    if (error := init_error(args)) is not None:  # fine-tuning in the simulator: the checks of bags
        parser.error(error)
    overrides = overrides_from_args(args, TrainConfig)
    resumed = None
    if args.resume:
        if not (config := RunDir(args.out).config).exists():
            parser.error(f"--resume: no run to resume in {args.out} ({config.name} missing)")
        try:
            resumed = ResumedConfig(args.out, overrides)
        except ResumeError as err:
            parser.error(str(err))
        except (OSError, TypeError, ValueError) as err:  # a hand-edited config.json: said before anything runs
            print(f"morph-train: error: {RunDir(args.out).config}: {err}", file=sys.stderr)
            return 1
        cfg = resumed.cfg
        if done := finished_message(args.out, cfg):
            print(f"morph-train: {done}")
            return 0
    else:
        if RunDir(args.out).state.exists():
            parser.error(f"{args.out} already holds a run; pass --resume to continue it or choose another --out")
        try:
            cfg = new_run_config(TrainConfig(), overrides)
        except (TypeError, ValueError) as err:
            parser.error(str(err))
    pool = None
    if cfg.rollout_workers > 1:
        try:
            from trainer.sim.ray_rollouts import ray_rollout_pool  # Ray, the trainer[ray] extra, only here
        except ImportError as err:
            parser.error(f"--rollout-workers {cfg.rollout_workers} runs on Ray ({err}): install trainer[ray]")
        pool = ray_rollout_pool(args.ray_address)
    elif args.ray_address is not None:
        parser.error("--ray-address: only with --rollout-workers > 1")
    follower = _follower(args.out, cfg, args.resume)
    if cfg.progress_bar:
        print("morph-train: progress bar: ret = the mean return of the last 50 episodes, sps = steps per second, "
              f"kl = the last update's approximate KL (warned above {follower.kl_limit:g})",
              file=sys.stderr)  # fmt: skip
    try:
        with resumed.kept_unless_trained(RunDir(args.out).state) if resumed else contextlib.nullcontext():
            if resumed:
                resumed.write_back()
            with follower:
                train(cfg, args.out, resume=args.resume, on_row=follower.on_row, rollout_pool=pool, init=args.init)
    except (TrainingStateError, RolloutWorkerError, ValueError) as err:  # ValueError: bodies that refuse --init
        print(f"morph-train: error: {err}", file=sys.stderr)
        return 1
    except OSError as err:  # a full disk: every file is written atomically, so the last checkpoint is intact
        print(f"morph-train: error: {err}; the run stopped, its last complete checkpoint is kept", file=sys.stderr)
        return 1
    print("\n".join(follower.summary(args.out)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
