"""``morph-export``: a policy checkpoint's deterministic actor as an ONNX graph, for C++ controllers.

    morph-export CHECKPOINT.safetensors OUT.onnx [--with-value] [--tree]

The graph takes one chain of any length N (joint_pos [N], joint_vel [N],
global [G], float32; G the policy's global features: 4 for a swimmer's, 12
for the shipped centipede policy's) and returns the mean action [N] (and, with
``--with-value``, the critic's value [1]); with ``--tree`` it takes one
kinematic tree instead, a fourth input parents [N] int64 (joint j's parent
joint, -1 for the torso). See ``morph_core.policy.onnx_export`` and
docs/onnx.md. It is checked against the torch policy with ONNX Runtime at
1..64 joints (trees: random, star and chain at each) before it is written
(atomically); an unusable checkpoint or a graph that differs is refused with
exit code 1 and nothing is written. (``--onnx CHECKPOINT OUT``, the form before,
still works for now and says it is deprecated.)
"""

from __future__ import annotations

import argparse
import sys

import torch

from morph_core.policy.onnx_export import TOLERANCE, ExportError, export_checkpoint
from morph_core.policy.weights import CheckpointError
from morph_core.util.config_cli import BoolAction, CommandLineParser


def build_parser() -> CommandLineParser:
    parser = CommandLineParser(prog="morph-export", description=__doc__,
                               formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    parser.add_argument("checkpoint", nargs="?", metavar="CHECKPOINT",
                        help="the policy checkpoint (.safetensors, its .json beside it)")  # fmt: skip
    parser.add_argument("out", nargs="?", metavar="OUT", help="the ONNX file to write (.onnx)")
    parser.add_argument("--onnx", nargs=2, metavar=("CHECKPOINT", "OUT"), default=None,
                        help="deprecated: the same as the two paths without it")  # fmt: skip
    parser.add_argument(
        "--with-value", action=BoolAction, default=False, help="add the critic's value as a second output"
    )
    parser.add_argument("--tree", action=BoolAction, default=False,
                        help="for kinematic trees: a fourth input, parents [N] int64 (-1: the torso)")  # fmt: skip
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.onnx is not None:
        if args.checkpoint is not None:
            parser.error("give CHECKPOINT OUT, or the deprecated --onnx CHECKPOINT OUT, not both")
        print("morph-export: warning: --onnx is deprecated: write morph-export CHECKPOINT OUT", file=sys.stderr)
        checkpoint, out = args.onnx
    elif args.out is None:
        parser.error("give the checkpoint and the ONNX file to write: morph-export CHECKPOINT OUT")
    else:
        checkpoint, out = args.checkpoint, args.out
    torch.set_num_threads(1)  # a network this small gains nothing from threads; the machine is shared
    try:
        result = export_checkpoint(checkpoint, out, with_value=args.with_value, tree=args.tree)
    except (CheckpointError, ExportError) as err:
        print(f"morph-export: error: {err}", file=sys.stderr)
        return 1
    outputs = "action, value" if result.with_value else "action"
    lengths = ", ".join(map(str, result.lengths_checked))
    inputs = f"joint_pos [N], joint_vel [N], global [{result.global_features}]"
    inputs += ", parents [N]" if result.tree else ""
    checked = f"{lengths} joints" + (" (random, star and chain trees)" if result.tree else "")
    print(f"wrote {result.path}: inputs {inputs} -> {outputs}; "
          f"{result.num_nodes} nodes; equal to the torch policy within {result.max_error:.2g} "
          f"(<= {TOLERANCE:g}) at {checked}")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
