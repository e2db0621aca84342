"""``morph-bag``: what recorded bags hold for learning, and their transitions as arrays.

    morph-bag info BAG...                   topics and message counts, the robot's description (or that
                                            there is none: chains), episodes, steps per chain length and
                                            per body, steps usable for PPO, skipped steps and unused
                                            messages by reason
    morph-bag export BAG... --out FILE.npz  the transitions, one row per step
                                            (layout: ``morph_core.protocol.transition_batch``)

A BAG is a rosbag2 folder, its ``metadata.yaml`` or one storage file (MCAP or
sqlite3), read by ``trainer.bags.io``. Each bag is its own stream: an episode
never spans two bags. Records become transitions as
``morph_core.protocol.transitions`` describes (pairing by stamp, episode
boundaries, nothing guessed: every step left out is counted under its
reason). The robot is the bag's ``robot_description`` (the sim latches its
URDF before each body's first state, and ``morph-record`` records it): its
tree, the joints bound by name. States recorded before the bag's first
description (a recorder whose description reader matched after its state
reader) are read on that first one, the URDF in force when they were
published (``bag_io.first_description``). A bag without one holds chains,
each state's joints in the message's order, and ``info`` says so. The options after the
command tune the assembly (``--control-period``, ``--settle-states``, ...);
``--namespace`` picks the robot when a bag holds several.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from morph_core.algo.train_from_data import describe_bodies
from morph_core.protocol.transition_batch import MissingPolicyInfoError
from morph_core.protocol.transitions import (
    TransitionConfig,
)
from morph_core.util.config_cli import (
    BoolAction,
    CommandLineParser,
    add_dataclass_options,
    overrides_from_args,
    replace_nested,
)
from trainer.bags.contents import format_summary, summarize_bag, total
from trainer.bags.io import BagError


# -- command line ---------------------------------------------------------------------------------
def build_parser() -> CommandLineParser:
    parser = CommandLineParser(
        prog="morph-bag", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    commands = parser.add_subparsers(dest="command", required=True)
    info = commands.add_parser("info", help="what the bags hold for learning")
    export = commands.add_parser("export", help="the bags' transitions as one .npz")
    for sub in (info, export):
        sub.add_argument("bags", nargs="+", metavar="BAG", help="bag folder, metadata.yaml or storage file")
        sub.add_argument("--namespace", default=None, help="namespace of the robot's topics (default: found)")
        add_dataclass_options(sub, TransitionConfig)
    info.add_argument("--json", action=BoolAction, default=False, help="print JSON instead of text")
    export.add_argument("--out", required=True, type=Path, help="the .npz to write (replaced atomically)")
    export.add_argument(
        "--require-policy-info",
        action=BoolAction,
        default=False,
        help="refuse (write nothing) if any step lacks its behaviour log-prob, as PPO needs",
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        config = replace_nested(TransitionConfig(), overrides_from_args(args, TransitionConfig))
        summaries = [summarize_bag(bag, config, args.namespace) for bag in args.bags]
    except (BagError, ValueError) as err:
        print(f"morph-bag: error: {err}", file=sys.stderr)
        return 1
    overall = summaries[0] if len(summaries) == 1 else total(summaries)
    if args.command == "info":
        if args.json:
            doc = {"bags": [s.as_dict() for s in summaries], "total": overall.as_dict()}
            print(json.dumps(doc, indent=2))
        else:
            print("\n".join(format_summary(s) for s in summaries))
            if len(summaries) > 1:
                print(format_summary(overall))
        return 0
    print("\n".join(format_summary(s) for s in summaries))
    batch = overall.batch
    if not len(batch):
        print(f"morph-bag: error: no usable steps in {', '.join(args.bags)}: nothing written", file=sys.stderr)
        return 1
    if args.require_policy_info:
        try:
            batch.require_policy_info()
        except MissingPolicyInfoError as err:
            print(f"morph-bag: error: {err}: nothing written", file=sys.stderr)
            return 1
    batch.to_npz(args.out)
    print(
        f"wrote {len(batch)} steps ({batch.num_episodes} episodes, {describe_bodies(batch)}, "
        f"{int(batch.has_policy_info.sum())} with policy_info) to {args.out}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
