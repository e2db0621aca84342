"""Live training on this machine: K lockstep sim+policy pairs in namespaces plus the live trainer.

    bash scripts/live.sh --pairs 4 --out runs/live [--max-updates N] [--resume] [-- MORPH-TRAIN OPTIONS]
    python -m trainer.live.bringup --out runs/live ...      (the same, without set-up or network namespace)

What ``trainer/launch/live_training.launch.py`` does on a Jazzy install, for
machines without ``launch``. The trainer starts first (``morph-train --live``,
its subscriptions made in advance), then each pair in ``/swimmer<i>``: the
sim (lockstep, paced at ``--real-time-factor``, real time by default; chain
length redrawn from 2..10 at each reset, seed i) and, once the trainer listens to the pair, the sampling policy
(``deterministic:=false``, seed i). The bring-up makes a key pair for the run
(``protocol.trust``, in a private temporary directory removed at the end), or
takes the user's (``--signing-key KEY``, also when given to the trainer after
``--``): the trainer signs its weights with the private key, and every policy
node trusts the public key and no other. The trainer pushes its weights to every policy
node and sets each sim's episode length. The bring-up ends when the
trainer does (``--max-updates``, or the config's total_timesteps) and stops the
pairs; the run directory is ``--out``. Options after ``--`` go to
``morph-train`` (e.g. ``-- --num-steps 256 --seed 3``).
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
import textwrap
import time
from pathlib import Path

from morph_core.msgs.stream_chunk import TOPIC as CHUNK_TOPIC
from morph_core.protocol.trust import load_public_key, load_signing_key, public_key_path, write_key_pair
from morph_core.util.config_cli import BoolAction, CommandLineParser, DefaultsHelpFormatter
from morph_ros_util.processes import (
    BringupError,
    NodeProcess,
    start_node,
    stop_all,
    use_fastdds_profile,
    wait_for_subscriber,
)
from trainer.bags.record_bringup import PROG_ENV, fastdds_profile
from trainer.codec import DATA_TOPIC_TYPES

TRAINER_NODE = "morph_live_trainer"
TRAINER_INPUTS = (tuple(DATA_TOPIC_TYPES), (CHUNK_TOPIC,))
"""what the trainer subscribes to per pair before its policy node starts: the data topics, or with
``--stream-chunks`` the policy node's chunks"""


def pair_params(
    index: int,
    min_joints: int,
    max_joints: int,
    checkpoint: str | None,
    real_time_factor: float = 1.0,
    trusted_key: str | Path | None = None,
    bodies: str | None = None,
) -> tuple[dict, dict]:
    """(sim, policy) parameters of pair ``index``; the policy node takes weights signed by ``trusted_key``. With
    ``bodies`` (a body spec: centipedes included) the sim draws from it instead of chains of the joint range."""
    sim = {
        "lockstep": "true",
        "real_time_factor": real_time_factor,
        "effort_timeout": 2.0,
        **({"min_joints": min_joints, "max_joints": max_joints} if not bodies else {"topology": bodies}),
        "seed": index,
    }
    policy = {"deterministic": "false", "seed": index}
    if trusted_key is not None:
        policy["trusted_keys"] = json.dumps([str(trusted_key)])  # a YAML list of one path
    if checkpoint is not None:
        policy["checkpoint"] = checkpoint if checkpoint else "''"
        if not checkpoint:  # the node runs an untrained policy only when asked; the trainer's weights follow
            policy["allow_untrained"] = "true"
    return sim, policy


def run_key_pair(directory: str | Path) -> Path:
    """A new signing key for this run in ``directory``; returns the private key's path (the public one: .pub)."""
    key = Path(directory) / "trainer_key"
    write_key_pair(key, comment="morph-live-run")
    return key


def user_key_pair(key: Path) -> Path:
    """``key``, a user's private signing key whose public half is ``KEY.pub`` beside it, checked before anything
    starts: the trainer signs with it, every policy node trusts ``KEY.pub``. ``BringupError`` says why not."""
    try:
        signer, public = load_signing_key(key), load_public_key(public_key_path(key))
    except ValueError as err:  # KeyFileError: missing, unreadable, readable by others, not a key
        raise BringupError(f"--signing-key: {err} (morph-keys new KEY makes a pair: KEY and KEY.pub)") from None
    if public.fingerprint != signer.fingerprint:
        raise BringupError(f"--signing-key: {public_key_path(key)} is not the public half of {key}")
    return Path(key).resolve()  # the nodes and the trainer read it whatever their folder


def split_option(extra: list[str], option: str) -> tuple[list[str], Path | None]:
    """The trainer's options without ``option VALUE`` (or ``option=VALUE``), and VALUE (None: not given)."""
    out, value, i = [], None, 0
    while i < len(extra):
        arg = extra[i]
        if arg == option and i + 1 < len(extra):
            value, i = Path(extra[i + 1]), i + 2
            continue
        if arg.startswith(option + "="):
            value = Path(arg.split("=", 1)[1])
        else:
            out.append(arg)
        i += 1
    return out, value


def split_signing_key(extra: list[str]) -> tuple[list[str], Path | None]:
    """The trainer's options without ``--signing-key KEY`` (or ``--signing-key=KEY``), and KEY: a key given to
    the trainer after ``--`` is the bring-up's ``--signing-key``, so that the nodes trust it too."""
    return split_option(extra, "--signing-key")


def trainer_arguments(namespaces: list[str], args, extra: list[str], signing_key: Path | None = None) -> list[str]:
    """``morph-train``'s arguments (without the program)."""
    cmd = ["--live", "--namespaces", *namespaces, "--out", str(args.out)]
    if signing_key is not None:
        cmd += ["--signing-key", str(signing_key)]
    if args.bodies:  # the run's bodies: its policy's width (12 with legs), its task and joint range
        cmd += ["--bodies", args.bodies]
    cmd += ["--episode-steps", str(args.episode_steps), "--max-updates", str(args.max_updates)]
    if args.resume:
        cmd.append("--resume")
    if getattr(args, "init", None) is not None:
        cmd += ["--init", str(args.init)]
    return cmd + extra


def trainer_command(namespaces: list[str], args, extra: list[str], signing_key: Path | None = None) -> list[str]:
    return [sys.executable, "-m", "trainer.cli.train", *trainer_arguments(namespaces, args, extra, signing_key)]


def run(args, extra: list[str]) -> int:
    # the training stack (torch) only to check the trainer's options
    from trainer.train_options import check_live

    namespaces = [f"/swimmer{i}" for i in range(args.pairs)]
    # What the trainer would refuse (an --out that holds a run, no run to --resume, a bad option after --) it
    # refuses here, with its own one-line error, before any process starts.
    check_live(trainer_arguments(namespaces, args, extra))
    use_fastdds_profile(fastdds_profile())
    # ROS loads after the line above has pointed Fast DDS at the profile
    import rclpy

    if args.signing_key is not None:  # the user's own key: the nodes trust its public half
        key, keys = user_key_pair(args.signing_key), None
    else:
        keys = tempfile.mkdtemp(prefix="morph-live-keys-")  # mode 0700: the private key is this run's alone
        key = run_key_pair(keys)
    rclpy.init()
    node = rclpy.create_node("live_bringup")
    trainer = NodeProcess(trainer_command(namespaces, args, extra, key))
    procs: list[NodeProcess] = []
    specs: list[tuple[str, str, dict]] = []
    interrupted = False
    try:
        for i, ns in enumerate(namespaces):
            nodes_start = "" if args.init is None else str(args.init)  # the trainer's first weights, or untrained
            sim, policy = pair_params(i, args.min_joints, args.max_joints, nodes_start, args.real_time_factor,
                                      public_key_path(key), args.bodies)  # fmt: skip
            specs.append(("swimmer_sim_node.sim_node", ns, sim))
            procs.append(start_node(*specs[-1]))
            inputs = [[f"{ns}/{t}" for t in topics] for topics in TRAINER_INPUTS]
            wait_for_subscriber(node, trainer, inputs, TRAINER_NODE, args.startup_timeout)
            specs.append(("morph_policy_node.policy_node", ns, policy))
            procs.append(start_node(*specs[-1]))
        print(f"live_bringup: {args.pairs} pairs running, trainer writing to {args.out}", flush=True)
        deadline = time.monotonic() + args.timeout
        try:
            _watch(trainer, procs, specs, deadline, args.timeout)
        except KeyboardInterrupt:  # Ctrl-C: every process of the group got it; the rest stop below
            print("live_bringup: interrupted: stopping the trainer and the pairs", flush=True)
            interrupted = True
    finally:
        trainer.stop()
        stop_all(procs)
        node.destroy_node()
        rclpy.try_shutdown()
        if keys is not None:
            shutil.rmtree(keys, ignore_errors=True)
    return 130 if interrupted else 0 if trainer.returncode in (0, None) else 1


def _watch(trainer, procs: list, specs: list, deadline: float, timeout: float) -> None:
    """Until the trainer ends: restart a node that failed; end at the deadline, or when a node ended as told to."""
    while trainer.poll() is None:
        if time.monotonic() > deadline:
            print(f"live_bringup: timed out after {timeout} s: stopping the trainer", flush=True)
            break
        ended = [k for k, proc in enumerate(procs) if proc.poll() is not None]
        if any(procs[k].returncode == 0 for k in ended):
            break  # a node ends 0 only when told to stop (Ctrl-C reaches the whole group): the run ends
        # A node that failed (killed, or stuck in the middleware and ended by its runner) comes back, as
        # a launch file's respawn would do; the trainer takes its pair back when it answers again.
        for k in ended:
            module, ns, _ = specs[k]
            print(f"live_bringup: {module} in {ns} ended ({procs[k].returncode}): restarting it", flush=True)
            procs[k] = start_node(*specs[k])
        time.sleep(0.5)


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra: list[str] = []
    if "--" in argv:
        cut = argv.index("--")
        argv, extra = argv[:cut], argv[cut + 1 :]
    ap = CommandLineParser(
        prog=os.environ.get(PROG_ENV, "python -m trainer.live.bringup"),
        usage="%(prog)s [-h] --out DIR [options] [-- MORPH-TRAIN OPTIONS]",
        description=__doc__,
        formatter_class=DefaultsHelpFormatter,
        epilog=textwrap.fill(
            "Everything after -- goes to the trainer, morph-train --live (.venv/bin/morph-train --help lists its "
            "options), e.g. -- --num-steps 256 --seed 3 --learning-rate 0.003. A relative --out or --init "
            "is taken from the folder the command runs in.",
            100,
        ),
    )
    ap.add_argument("--pairs", type=int, default=2, help="sim+policy pairs (K)")
    ap.add_argument("--out", type=Path, required=True, help="the trainer's run directory")
    ap.add_argument("--max-updates", type=int, default=0,
                    help="stop after this many updates (0: at the run's total_timesteps)")  # fmt: skip
    ap.add_deprecated_alias("--updates", "--max-updates")
    ap.add_argument("--resume", action=BoolAction, default=False, help="continue the run in --out")
    ap.add_argument(
        "--episode-steps", type=int, default=1000,
        help="control steps per episode (0.04 s each; a centipede's 0.05, ending early at a fall)",
    )  # fmt: skip
    ap.add_argument(
        "--real-time-factor",
        type=float,
        default=1.0,
        help="the sims' pace (1: real time, as robots run; 0: as fast as the loop goes). Unpaced pairs "
        "can outrun the trainer's ingest on a loaded machine, which then cuts their episodes",
    )
    ap.add_argument("--min-joints", type=int, default=2, help="shortest chain a sim draws at a reset")
    ap.add_argument("--max-joints", type=int, default=10, help="longest chain a sim draws at a reset")
    ap.add_argument("--bodies", default="", help="a body spec instead of chains (env.bodies: y:2x2, centipede:2-4, "
                    "...), drawn by the sims at each reset and given to the trainer as its --bodies")  # fmt: skip
    ap.add_argument("--init", type=Path, default=None, metavar="POLICY",
                    help="the policy the run starts from, as morph-train --init: the trainer's first weights and "
                    "what the nodes run until they arrive (default: a fresh policy from the trainer's --seed, the "
                    "nodes an untrained one; -- --init POLICY is taken as this option)")  # fmt: skip
    ap.add_deprecated_alias("--checkpoint", "--init")
    ap.add_argument("--signing-key", type=Path, default=None, metavar="KEY",
                    help="your private key (morph-keys new KEY): the trainer signs with it and the nodes trust "
                    "KEY.pub (default: a key pair made for the run and removed at its end; -- --signing-key KEY "
                    "is taken as this option)")  # fmt: skip
    ap.add_argument("--timeout", type=float, default=24 * 3600.0, help="wall seconds before stopping")
    ap.add_argument("--startup-timeout", type=float, default=60.0, help="wall seconds to wait for each node")
    args = ap.parse_args(argv)
    extra, trainer_key = split_signing_key(extra)
    extra, trainer_init = split_option(extra, "--init")
    if trainer_init is not None:
        if args.init is not None and args.init != trainer_init:
            ap.error("--init is given twice with two policies (before and after --): give it once")
        args.init = trainer_init
    if args.init is not None:
        args.init = args.init.resolve()  # the nodes and the trainer read it whatever their folder
    if trainer_key is not None:
        if args.signing_key is not None and args.signing_key != trainer_key:
            ap.error("--signing-key is given twice with two keys (before and after --): give it once")
        args.signing_key = trainer_key
    if args.pairs < 1:
        ap.error("--pairs must be >= 1")
    if not args.real_time_factor >= 0:
        ap.error("--real-time-factor must be >= 0")
    try:
        return run(args, extra)
    except BringupError as err:
        print(f"{ap.prog}: error: {err}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
