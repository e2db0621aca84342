"""Record episodes of the sampling policy on the simulated swimmer into a bag: sim + policy + recorder.

    bash scripts/record.sh --out bags/run1 --episodes 10 [--joints 6] [--storage mcap]
    python -m trainer.bags.record_bringup --out bags/run1 ...      (the same, without set-up or network namespace)

What a launch file would do on a Jazzy install, for machines without
``launch``: the recorder starts first (so it sees the first episode), then the
sim (lockstep, as fast as possible) and the policy (``deterministic:=false``,
so it samples and publishes ``policy_info``). If the sim has episodes (its
``episode_steps`` parameter), the recorder stops by itself when episode
N+1 is announced; otherwise it stops after N x ``--steps-per-episode``
policy answers. Then the nodes are stopped and the bag's contents printed.
"""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path

from morph_core.util.config_cli import CommandLineParser, DefaultsHelpFormatter
from morph_ros_util.processes import (
    BringupError,
    NodeProcess,
    has_parameter,
    start_node,
    stop_all,
    use_fastdds_profile,
    wait_for_subscriber,
)


def fastdds_profile() -> str | None:
    """morph_policy_node's Fast DDS profile (quick discovery for nodes started together), if installed."""
    try:
        # optional: the profile is a speed-up, the recorder runs without the policy node's package
        import morph_policy_node
    except ImportError:
        return None
    return str(morph_policy_node.FASTDDS_PROFILE)


def _legged(spec: str | None) -> bool:
    """Whether the body spec draws centipedes (a bad spec: no; the sim refuses it, with its reason)."""
    # `env` (MuJoCo, the sim extra) only to read a --bodies spec
    from morph_core.env.bodies import parse_bodies

    try:
        return bool(spec) and parse_bodies(spec).has_centipedes
    except ValueError:
        return False


def run(args) -> int:
    use_fastdds_profile(fastdds_profile())
    # ROS loads after the line above has pointed Fast DDS at the profile
    import rclpy

    out = Path(args.out)
    if out.exists():
        print(f"record_bringup: error: {out} exists already: choose a new --out", file=sys.stderr)
        return 1
    ns = "/" + args.namespace.strip("/") if args.namespace.strip("/") else ""
    recorder_params = {"output": str(out), "storage": args.storage}
    sim_params = {
        **({"num_joints": args.joints} if args.bodies is None else {"topology": args.bodies}),
        "lockstep": "true",
        "real_time_factor": 0.0,
        "effort_timeout": 2.0,
        "episode_steps": args.steps_per_episode,  # ignored by a sim without episodes
        "seed": args.seed,
    }
    policy_params = {"deterministic": "false", "seed": args.seed}
    if args.checkpoint:
        policy_params["checkpoint"] = args.checkpoint
    elif _legged(args.bodies):
        # the node modules load rclpy: only once the profile is set (run())
        from morph_policy_node.bringup import CENTIPEDE_MODEL
        from morph_policy_node.policy_node import SHIPPED_MODEL

        policy_params["checkpoint"] = str(SHIPPED_MODEL.with_name(CENTIPEDE_MODEL))  # reads 12 global features

    rclpy.init()
    node = rclpy.create_node("record_bringup", namespace=ns or "/")
    procs: list[NodeProcess] = []
    try:
        procs.append(start_node("swimmer_sim_node.sim_node", ns, sim_params))
        episodes = has_parameter(node, f"{ns}/swimmer_sim", "episode_steps", args.startup_timeout)
        if episodes:
            recorder_params["max_episodes"] = args.episodes
            what = f"{args.episodes} episodes of {args.steps_per_episode} steps"
        else:
            recorder_params["max_messages"] = args.episodes * args.steps_per_episode
            recorder_params["count_topic"] = "policy_info"
            what = f"{args.episodes * args.steps_per_episode} steps (this sim has no episodes)"
        # The lockstep sim publishes its first state once someone listens to joint_states: the
        # recorder, started now, so the bag begins with the reset state. The policy starts once the
        # recorder listens to everything (its own topics are subscribed in advance), or the loop
        # could run many steps before the recorder hears of the policy.
        recorder = start_node("trainer.bags.record", ns, recorder_params)
        procs.insert(0, recorder)
        topics = ["joint_states", "effort_commands", "policy_info"] + (["episode_start"] if episodes else [])
        wait_for_subscriber(node, recorder, [[f"{ns}/{t}" for t in topics]], "morph_record", args.startup_timeout)
        procs.append(start_node("morph_policy_node.policy_node", ns, policy_params))
        body = f"{args.joints} joints" if args.bodies is None else f"bodies {args.bodies}"
        print(f"record_bringup: recording {what}, {body}, into {out}", flush=True)
        deadline = time.monotonic() + args.timeout
        while recorder.poll() is None:
            if any(p.poll() is not None for p in procs[1:]):
                raise BringupError("a node exited early; see its output above")
            if time.monotonic() > deadline:
                print(f"record_bringup: timed out after {args.timeout} s: closing the bag early", flush=True)
                recorder.stop(signal.SIGINT)
                break
            time.sleep(0.2)
    finally:
        stop_all(procs)
        node.destroy_node()
        rclpy.try_shutdown()
    if recorder.returncode not in (0, None):
        print(f"record_bringup: error: the recorder failed (exit {recorder.returncode})", file=sys.stderr)
        return 1
    return _summarise(out, ns)


def _summarise(out: Path, ns: str) -> int:
    # the bag reader only for the summary, after the nodes have stopped
    from morph_core.msgs.records import EpisodeStartRecord, JointStateRecord, PolicyInfoRecord
    from trainer.bags.io import BagError, BagReader

    try:
        reader = BagReader(out, required=("joint_states", "effort_commands", "policy_info"), namespace=ns)
        records = reader.read()
    except BagError as err:
        print(f"record_bringup: error: the bag is not usable: {err}", file=sys.stderr)
        return 1
    starts = sum(isinstance(r, EpisodeStartRecord) for r in records)
    counts = ", ".join(f"{k}: {v}" for k, v in sorted(reader.stats.counts.items()))
    print(f"record_bringup: bag {out}: {counts}; {starts} episode announcements", flush=True)
    first_state = min(r.stamp_ns for r in records if isinstance(r, JointStateRecord))
    first_info = min(r.stamp_ns for r in records if isinstance(r, PolicyInfoRecord))
    if first_info > first_state:
        # DDS matches each pair of nodes on its own: the sim can hear the policy before the recorder does.
        print(
            f"record_bringup: warning: policy_info recorded from t={first_info * 1e-9:.2f} s of sim time on "
            f"(states from t={first_state * 1e-9:.2f} s): the first steps have no policy data",
            flush=True,
        )
    for w in reader.stats.warnings:
        print(f"record_bringup: warning: {w}", flush=True)
    return 0


PROG_ENV = "MORPH_PROG"
"""the name a wrapper script runs a bring-up under (its help and errors name the script)"""


def main(argv=None) -> int:
    ap = CommandLineParser(
        prog=os.environ.get(PROG_ENV, "python -m trainer.bags.record_bringup"),
        description=__doc__,
        formatter_class=DefaultsHelpFormatter,
        epilog="A relative --out or --checkpoint is taken from the folder the command runs in.",
    )
    ap.add_argument("--out", required=True, help="bag folder to create (must not exist)")
    ap.add_argument("--episodes", type=int, default=10, help="episodes to record")
    ap.add_argument(
        "--steps-per-episode", type=int, default=250,
        help="control steps per episode (0.04 s each; a centipede's 0.05, ending early at a fall)",
    )  # fmt: skip
    body = ap.add_mutually_exclusive_group()
    body.add_argument("--joints", type=int, default=6, help="chain length of the simulated swimmer")
    body.add_argument("--bodies", default=None,
                      help="a body spec instead (env.bodies: y:2x2, centipede:2-4, ...): one drawn at each reset; "
                      "with centipedes the default --checkpoint is the shipped centipede policy")  # fmt: skip
    ap.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap", help="the bag's storage format")
    ap.add_argument("--checkpoint", default=None, help="policy .safetensors (default: the shipped model)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the sim's resets and the policy's sampling")
    ap.add_argument("--namespace", default="", help="ROS namespace of the three nodes ('': the root)")
    ap.add_argument("--timeout", type=float, default=3600.0, help="wall seconds before closing the bag early")
    ap.add_argument("--startup-timeout", type=float, default=60.0, help="wall seconds to wait for the sim")
    args = ap.parse_args(argv)
    if args.episodes < 1 or args.steps_per_episode < 1:
        ap.error("--episodes and --steps-per-episode must be >= 1")
    try:
        return run(args)
    except BringupError as err:
        print(f"{ap.prog}: error: {err}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
