"""``morph-keys``: the signing keys that decide who may change a robot's policy (``morph_core.protocol.trust``).

    morph-keys new KEY                         # KEY (private, 0600) and KEY.pub (names its fingerprint)
    morph-keys sign CHECKPOINT --key KEY       # sign a checkpoint file, e.g. one trained in simulation
    morph-keys check CHECKPOINT [--trusted KEY.pub ...]   # unsigned, or signed by which key; altered?

The trainer signs with the private key (``morph-train --live --signing-key KEY``);
each policy node is started with the public key (``-p trusted_keys:=[KEY.pub]``)
and then adopts only weights that key signed. Keys are OpenSSH's, so
``ssh-keygen -t ed25519 -N ''`` makes usable ones and ``ssh-keygen -lf KEY.pub``
prints the same fingerprint as the nodes' logs.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

from morph_core.msgs.policy_weights import weights_header
from morph_core.policy.weights import CheckpointError, SignedWeights, load_checkpoint, write_checkpoint
from morph_core.protocol.policy_updates import checkpoint_trust
from morph_core.protocol.trust import KeyFileError, load_signing_key, load_trusted_keys, write_key_pair
from morph_core.util.config_cli import BoolAction, CommandLineParser


def build_parser() -> CommandLineParser:
    parser = CommandLineParser(prog="morph-keys", description=__doc__,
                               formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    sub = parser.add_subparsers(dest="command", required=True)
    new = sub.add_parser("new", help="make an Ed25519 key pair: KEY (private, mode 0600) and KEY.pub")
    new.add_argument("key", type=Path)
    new.add_argument("--comment", default="morph-policy-signing", help="one word, written in KEY.pub")
    new.add_argument("--force", action=BoolAction, default=False, help="replace an existing key pair")
    sign = sub.add_parser("sign", help="sign a checkpoint (.safetensors, its .json beside it) with a private key")
    sign.add_argument("checkpoint", type=Path)
    sign.add_argument("--key", type=Path, required=True)
    sign.add_argument("--version", type=int, default=None,
                      help="the weights version to sign it as (default: its metadata's, else 0)")  # fmt: skip
    check = sub.add_parser("check", help="say whether a checkpoint is signed, by which key, and if it still matches")
    check.add_argument("checkpoint", type=Path)
    check.add_argument("--trusted", type=Path, nargs="*", default=[], help="public keys to check the signature with")
    return parser


def _new(args) -> int:
    signer = write_key_pair(args.key, comment=args.comment, overwrite=args.force)
    print(f"wrote {args.key} (private, mode 600) and {args.key}.pub: {signer.fingerprint}")
    print(f"  trainer:      morph-train --live --signing-key {args.key} ...")
    print(f"  policy nodes: --ros-args -p trusted_keys:=[{args.key}.pub]")
    return 0


def _sign(args) -> int:
    weights = load_checkpoint(args.checkpoint)
    signer = load_signing_key(args.key)
    version = args.version if args.version is not None else weights.metadata.get("version", 0)
    if isinstance(version, bool) or not isinstance(version, int) or version < 0:
        raise ValueError(f"version must be an integer >= 0, got {version!r}")
    config = dataclasses.asdict(weights.config)
    header = weights_header(version, config, {**weights.metadata, "signed_as": "checkpoint"}, time.time_ns())
    signed = SignedWeights(header, signer.sign(header, weights.data_sha256).label)
    # The same bytes, so the signature over their digest holds; the .json gains the signature.
    write_checkpoint(args.checkpoint, args.checkpoint.read_bytes(), config, weights.metadata, signed)
    print(f"signed {args.checkpoint} as version {version} with {signer.fingerprint}")
    return 0


def _check(args) -> int:
    keys, errors = load_trusted_keys([str(p) for p in args.trusted])
    if errors:
        raise errors[0]
    print(f"{args.checkpoint}: {checkpoint_trust(load_checkpoint(args.checkpoint), keys).description}")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    command = {"new": _new, "sign": _sign, "check": _check}[args.command]
    try:
        return command(args)
    except (CheckpointError, KeyFileError, FileExistsError, ValueError, OSError) as err:
        print(f"morph-keys: error: {err}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
