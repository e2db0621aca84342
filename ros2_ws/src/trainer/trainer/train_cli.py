"""``morph-train``: PPO on swimmers of mixed chain lengths, under a trust-region rule of the table.

Every TrainConfig field is an option (``--clip-mode``, ``--total-timesteps``,
``--policy-bidirectional`` ...). ``--resume`` continues the run in ``--out``
from its last checkpoint, with the config it was started with (options
given again override it, e.g. a larger ``--total-timesteps``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from morph_core.algo.train import TrainConfig, load_run_config, train
from morph_core.algo.trust_region import RULES
from morph_core.util.config_cli import add_dataclass_options, overrides_from_args, replace_nested


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="morph-train", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, required=True, help="run directory")
    parser.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    # The rule's choices and their help come from the table of trust-region rules.
    rules = "; ".join(f"{name}: {rule.help}" for name, rule in RULES.items())
    parser.add_argument(
        "--clip-mode",
        dest="clip_mode",
        choices=list(RULES),
        default=None,
        help=f"trust-region rule ({rules}) (default: {TrainConfig.clip_mode})",
    )
    add_dataclass_options(parser, TrainConfig, skip=("clip_mode",))
    return parser


def main(argv: list[str] | None = None) -> None:
    parser = build_parser()
    args = parser.parse_args(argv)
    overrides = overrides_from_args(args, TrainConfig)
    if args.resume:
        if not (args.out / "config.json").exists():
            parser.error(f"--resume: no run to resume in {args.out} (config.json missing)")
        cfg = load_run_config(args.out, overrides)
    else:
        if (args.out / "state.safetensors").exists():
            parser.error(f"{args.out} already holds a run; pass --resume to continue it or choose another --out")
        try:
            cfg = replace_nested(TrainConfig(), overrides)
        except (TypeError, ValueError) as e:
            parser.error(str(e))
    train(cfg, args.out, resume=args.resume)


if __name__ == "__main__":
    main()
