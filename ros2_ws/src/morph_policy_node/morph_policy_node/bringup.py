"""Bring up sim + policy as two processes, run a fixed stretch of sim time, print the swim speed.

    python -m morph_policy_node.bringup [--joints 6 | --bodies SPEC | --model-file PATH] [--sim-seconds 30]
                                        [--checkpoint PATH]

What ``ros2 launch morph_policy_node swimmer_policy.launch.py`` does on a Jazzy
install, for machines without ``launch``: the sim runs in lockstep as fast as
possible (a deterministic closed loop), the policy uses the shipped model (or
``--checkpoint``), and this process watches ``odom`` until the sim clock has
run ``--sim-seconds``, then stops both nodes with SIGINT.

The body: a chain of ``--joints``, or a swimmer drawn from ``--bodies`` (a body
spec of ``morph_core.env.bodies``, e.g. ``y:2x2``: the sim's ``topology``;
one body for the whole run, the sim draws again only at a reset), or your own
robot, ``--model-file`` (an MJCF of actuated hinges: the sim's ``model_file``,
docs/your_robot.md). Without ``--checkpoint``, a chain or a robot is driven by
the shipped chain model, bodies with a tree among them by the shipped
tree-trained model (``models/swimmer_trees_gnn.safetensors``, trained on
chains and random trees: ``models/README.md``), and centipedes
(``--bodies centipede:5``) by the shipped centipede model
(``models/centipede_gnn.safetensors``); a robot is driven zero-shot.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time

from morph_policy_node import FASTDDS_PROFILE


def _start(module: str, params: dict) -> subprocess.Popen:
    args = [sys.executable, "-m", module, "--ros-args"]
    for k, v in params.items():
        # A string goes quoted (JSON is YAML): a spec such as "6" or a path must stay a string.
        text = ("true" if v else "false") if isinstance(v, bool) else json.dumps(v) if isinstance(v, str) else v
        args += ["-p", f"{k}:={text}"]
    return subprocess.Popen(args)


def _stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    for p in procs:
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def run(
    joints: int,
    sim_seconds: float,
    checkpoint: str | None,
    startup_timeout: float,
    bodies: str | None = None,
    model_file: str | None = None,
) -> dict:
    # Nodes started together must find each other quickly: fast initial announcements.
    os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(FASTDDS_PROFILE))
    import rclpy
    from nav_msgs.msg import Odometry
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState

    body = {"topology": bodies} if bodies else {"model_file": model_file} if model_file else {"num_joints": joints}
    sim_params = {**body, "lockstep": True, "real_time_factor": 0.0, "effort_timeout": 2.0}
    policy_params = {} if checkpoint is None else {"checkpoint": checkpoint}
    rclpy.init()
    node = rclpy.create_node("bringup")
    first, last, loop_start, joint_counts = [], [], [], set()

    def on_odom(msg: Odometry) -> None:
        t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        sample = (t, msg.pose.pose.position.x, msg.pose.pose.position.y)
        if not first:
            first.append(sample)
        if t > 0 and not loop_start:  # the loop runs: the policy has answered the reset state
            loop_start.append((time.monotonic(), t))
        last[:] = [sample]

    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(Odometry, "odom", on_odom, qos)
    # A joint_states listener makes the lockstep sim publish its reset state before the policy is up.
    node.create_subscription(JointState, "joint_states", lambda msg: joint_counts.add(len(msg.name)), qos)
    procs = [_start("swimmer_sim_node.sim_node", sim_params)]
    try:
        # Start the policy only once the reset state has reached us, so the measurement
        # surely starts from the swimmer's reset pose.
        t_start = time.monotonic()
        while not first:
            if procs[0].poll() is not None or time.monotonic() - t_start > startup_timeout:
                raise RuntimeError("the sim node did not come up (exited, or DDS discovery failed)")
            rclpy.spin_once(node, timeout_sec=0.05)
        procs.append(_start("morph_policy_node.policy_node", policy_params))
        while not (last and last[0][0] >= sim_seconds):
            if any(p.poll() is not None for p in procs):
                raise RuntimeError("a node exited early; see its output above")
            if not first and time.monotonic() - t_start > startup_timeout:
                raise RuntimeError(f"no odometry within {startup_timeout} s: DDS discovery failed?")
            rclpy.spin_once(node, timeout_sec=0.1)
        rate = (last[0][0] - loop_start[0][1]) / (time.monotonic() - loop_start[0][0])
    finally:
        _stop(procs)
        node.destroy_node()
        rclpy.try_shutdown()
    (t0, x0, y0), (t1, x1, y1) = first[0], last[0]
    if t0 > 0:
        raise RuntimeError(f"missed the start of the run (first odometry at t={t0:.2f} s)")
    return {
        "sim_seconds": t1 - t0,
        "dx": x1 - x0,
        "dy": y1 - y0,
        "speed": (x1 - x0) / (t1 - t0),
        "rate": rate,
        "joints": "/".join(map(str, sorted(joint_counts))),
    }


TREE_MODEL = "swimmer_trees_gnn.safetensors"
"""the shipped tree-trained policy, beside the chain one"""
CENTIPEDE_MODEL = "centipede_gnn.safetensors"
"""the shipped centipede policy (trained on 2..4 leg pairs; it walks on 3..6: models/README.md)"""


def _family(spec: str | None) -> str:
    """What a body spec draws: ``chains``, ``trees`` or ``centipedes`` (which picks the shipped model). A bad
    spec reads as chains here: it is the sim node's to refuse, with its reason."""
    from morph_core.env.bodies import parse_bodies

    try:
        mix = parse_bodies(spec) if spec else None
    except ValueError:
        return "chains"
    if mix is None or mix.chains_only:
        return "chains"
    return "centipedes" if mix.has_centipedes else "trees"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    body = ap.add_mutually_exclusive_group()
    body.add_argument("--joints", type=int, default=6, help="chain length of the simulated swimmer")
    body.add_argument("--bodies", default=None, help="body spec of the swimmer (the sim's topology), e.g. y:2x2")
    body.add_argument("--model-file", default=None, help="MJCF of your own robot (the sim's model_file)")
    ap.add_argument("--sim-seconds", type=float, default=30.0, help="sim time to run")
    ap.add_argument(
        "--checkpoint", default=None, help="policy .safetensors (default: the shipped model; trees, centipedes: theirs)"
    )
    ap.add_argument("--startup-timeout", type=float, default=60.0, help="wall seconds to wait for the nodes")
    args = ap.parse_args(argv)
    from morph_policy_node.policy_node import SHIPPED_MODEL

    family = _family(args.bodies)
    if args.checkpoint is None:
        shipped = SHIPPED_MODEL
        if family != "chains":
            shipped = SHIPPED_MODEL.with_name(CENTIPEDE_MODEL if family == "centipedes" else TREE_MODEL)
            args.checkpoint = str(shipped)
        if not shipped.is_file():
            print(f"bringup: no shipped policy at {shipped}: give --checkpoint", flush=True)
            return 2
    try:
        r = run(args.joints, args.sim_seconds, args.checkpoint, args.startup_timeout, args.bodies, args.model_file)
    except RuntimeError as err:  # the node said why above (a bad --bodies or --model-file, say)
        print(f"bringup: {err}", flush=True)
        return 1
    body = f"bodies {args.bodies}, " if args.bodies else f"robot {args.model_file}, " if args.model_file else ""
    gait = "walk" if family == "centipedes" else "swim"
    print(
        f"{gait} speed: {r['speed']:+.4f} m/s along x ({r['dx']:+.3f} m forward, {r['dy']:+.3f} m sideways) "
        f"over {r['sim_seconds']:.2f} s of sim time, {body}{r['joints'] or args.joints} joints; "
        f"closed loop over DDS at {r['rate']:.1f}x real time",
        flush=True,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
