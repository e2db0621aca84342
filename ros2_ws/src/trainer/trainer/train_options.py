"""``morph-train``'s options, and what it refuses before anything starts: the one parser, which the command
(``cli.train``) and the bring-ups that compose its command line (``live.bringup``) both read, so a bring-up
refuses exactly what its trainer would, with the trainer's own one-line error.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from morph_core.algo.ppo_config import family_defaults
from morph_core.algo.run_dir import RunDir
from morph_core.algo.train import TrainConfig
from morph_core.algo.trust_region import RULES
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.util.config_cli import (
    BoolAction,
    CommandLineParser,
    DeprecatedAlias,
    add_dataclass_options,
    overrides_from_args,
    replace_nested,
)
from trainer.bags.options import BagOptions
from trainer.live.learner import LIVE_LEARNING_RATE, LiveOptions, live_train_config
from trainer.train_session import (
    ResumedConfig,
    finished_message,
)


def build_parser(description: str | None = None) -> CommandLineParser:
    """``morph-train``'s parser; ``description`` its help's text (the command's page)."""
    parser = CommandLineParser(
        prog="morph-train", description=description, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, required=True, help="run directory")
    parser.add_argument(
        "--resume", action=BoolAction, default=False, help="continue the run in --out from its last checkpoint"
    )
    # Each source's options come from its config (BagOptions, LiveOptions); --live only chooses the source, and
    # --init, a field of both, is one option, in the bags' group as it always was.
    add_dataclass_options(parser.add_argument_group("training from recorded bags"), BagOptions)
    live = parser.add_argument_group("live training from sim+policy pairs over DDS (trainer.live.trainer_node)")
    live.add_argument("--live", action=BoolAction, default=False,
                      help="learn from running pairs, push weights back (a new run's --learning-rate defaults to "
                      f"{LIVE_LEARNING_RATE} here: stale samples; walkers' to theirs, as in every source)")  # fmt: skip
    add_dataclass_options(live, LiveOptions, skip=("out", "resume", "init"))
    groups = add_dataclass_options(parser, TrainConfig, skip=("rule",))  # the help grouped by concern
    # The rule's choices and their help come from the table of trust-region rules.
    rules = "; ".join(f"{name}: {rule.help}" for name, rule in RULES.items())
    groups["PPO"].add_argument(
        "--rule", dest="rule", choices=list(RULES), default=None, help=f"trust-region rule ({rules}) (default: "
        f"{TrainConfig.rule})"
    )  # fmt: skip
    parser.add_argument("--clip-mode", dest="clip_mode", choices=list(RULES), default=None, action=DeprecatedAlias,
                        new="--rule", help=argparse.SUPPRESS)  # fmt: skip
    groups["simulator"].add_argument("--ray-address", default=None, metavar="ADDRESS",
                                     help="with --rollout-workers > 1: the Ray cluster to run the workers on (as ray "
                                     "start --head printed it); default: a local Ray on this machine")  # fmt: skip
    return parser


def bag_options(args) -> BagOptions:
    """The bag source's config from the command line (``ValueError``: a value it refuses)."""
    return BagOptions(**overrides_from_args(args, BagOptions))


def init_error(args) -> str | None:
    """Why ``--init`` cannot start this run (every data source: bags, the simulator, live), or None."""
    if args.init is None:
        return None
    if args.resume:
        return "--init starts a new run; --resume continues the run in --out from its own state"
    try:
        GraphActorCritic.load(args.init)
    except Exception as err:  # a missing file, no .json beside it, not safetensors, other weights
        return f"--init {args.init}: not a policy checkpoint ({type(err).__name__}: {err})"
    return None


def new_run_config(base: TrainConfig, overrides: dict, say: bool = True) -> TrainConfig:
    """A new run's config: ``base`` (the simulator's and the bags' ``TrainConfig()``, the live trainer's own),
    then, for bodies with legs, the centipede results' PPO settings where no option sets them (said in one
    line), then the options given. Every source takes them, so a centipede learns at one learning rate from
    the simulator, from bags and live."""
    legged = family_defaults(overrides.get("bodies", ""), overrides)
    cfg = replace_nested(base, {**legged, **overrides})
    if legged and say:
        given = " ".join(f"--{k.replace('_', '-')} {v:g}" for k, v in legged.items())
        print(f"morph-train: bodies with legs: {given} (the centipede results' settings; give an option to "
              "set it otherwise)", flush=True)  # fmt: skip
    return cfg


def descriptions_error(cfg, init) -> str | None:
    """Why a run from the topics (bags, live) cannot train the policy ``cfg`` or ``init`` describes, or None: one
    that reads joint descriptions (``joint_features``), which the transitions rebuilt from the topics do not carry
    yet (the policy node reads them off robot_description; the simulator trainer carries them)."""
    width = (GraphActorCritic.load(init).config if init is not None else cfg.policy).joint_features
    if not width:
        return None
    return (
        f"the policy reads joint descriptions (joint_features {width}) and training from the topics (--from-bags, "
        "--live) does not carry them yet: train it in the simulator (--bodies), or with joint_features 0"
    )


def live_config(args, parser, say: bool = True) -> tuple[TrainConfig, LiveOptions, ResumedConfig | None]:
    """The live run's config, options and (on ``--resume``) what changes in its config.json; ``parser.error``
    for what the trainer refuses before it starts ROS, and a finished run resumed is said and exits 0."""
    if not args.namespaces:
        parser.error("--live needs --namespaces NS [NS ...]")
    if args.from_bags is not None:
        parser.error("--live and --from-bags are two data sources: choose one")
    overrides = overrides_from_args(args, TrainConfig)
    if (error := init_error(args)) is not None:  # fine-tuning live: the checks of the other sources
        parser.error(error)
    try:
        if args.resume:
            if not (state := RunDir(args.out).state).exists():
                parser.error(f"--resume: no live run to resume in {args.out} ({state.name} missing)")
            resumed = ResumedConfig(args.out, overrides)
            cfg = resumed.cfg
        else:
            if RunDir(args.out).state.exists():
                parser.error(f"{args.out} already holds a run; pass --resume to continue it or choose another --out")
            cfg, resumed = new_run_config(live_train_config(), overrides, say), None
        options = LiveOptions(**overrides_from_args(args, LiveOptions))  # with --out, --resume and --init
    except (OSError, TypeError, ValueError) as err:
        parser.error(str(err))
    if (error := descriptions_error(cfg, args.init)) is not None:
        parser.error(error)
    if resumed and not args.max_updates and (done := finished_message(args.out, cfg)):
        print(f"morph-train: {done}")
        parser.exit(0)
    return cfg, options, resumed


def check_live(argv: list[str]) -> None:
    """Refuse ``morph-train --live`` arguments (``argv``, without the program) as the trainer would, with its
    one-line error and exit code 2, before anything starts: a bring-up checks its trainer's command first."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not args.live:
        parser.error("check_live: a command without --live")
    live_config(args, parser, say=False)  # the trainer says it when it starts
