"""Bring up sim + policy as two processes, run a fixed stretch of sim time, print the swim (or walk) speed.

    python -m morph_policy_node.bringup [--joints 6 | --bodies SPEC | --model-file PATH] [--seconds 30]
                                        [--checkpoint PATH]

What ``ros2 launch morph_policy_node swimmer_policy.launch.py`` does on a Jazzy
install, for machines without ``launch``: the sim runs in lockstep as fast as
possible (a deterministic closed loop), the policy uses the shipped model (or
``--checkpoint``), and this process watches ``odom`` until the sim clock has
run ``--seconds`` (``--sim-seconds``, its old name, still works and says so), then stops both nodes with SIGINT.

The body: a chain of ``--joints``, or a swimmer drawn from ``--bodies`` (a body
spec of ``morph_core.env.bodies``, e.g. ``y:2x2``: the sim's ``topology``;
one body for the whole run, the sim draws again only at a reset), or your own
robot, ``--model-file`` (an MJCF of actuated hinges: the sim's ``model_file``,
docs/your_robot.md). Without ``--checkpoint``, a chain or a planar robot is
driven by the shipped chain model, bodies with a tree among them by the shipped
tree-trained model (``models/swimmer_trees_gnn.safetensors``, trained on
chains and random trees: ``models/README.md``), centipedes
(``--bodies centipede:5``) by the shipped centipede model
(``models/centipede_gnn.safetensors``), and other walkers (``legged:`` bodies,
a robot whose MJCF root is free, such as Gymnasium's ant) by the shipped legged
generalist (``models/legged_gnn.safetensors``, which reads joint descriptions);
a robot is driven zero-shot.
"""

from __future__ import annotations

import os
import sys
import time

from morph_core.constants import MAX_JOINTS
from morph_core.util.config_cli import CommandLineParser
from morph_policy_node import FASTDDS_PROFILE
from morph_ros_util.processes import NodeProcess, start_node, stop_all, use_fastdds_profile, yaml_string


class Posture:
    """What the odometry says of the body's posture: whether it moves in 3-D (a robot on a floor, a centipede;
    a swimmer's pose is planar: z = 0, a yaw alone) and how often it fell, i.e. its root turned from upright to
    tipped over (its up axis below the horizon: the sim lets a fallen body lie, so each fall counts once)."""

    def __init__(self):
        self.in_3d, self.falls, self._down = False, 0, False

    def see(self, z: float, q) -> None:
        if z != 0.0 or q.x != 0.0 or q.y != 0.0:
            self.in_3d = True
        up_z = 1.0 - 2.0 * (q.x * q.x + q.y * q.y)  # the world z of the root's z axis
        down = up_z < 0.0
        if down and not self._down:
            self.falls += 1
        self._down = down


def run(
    joints: int,
    sim_seconds: float,
    checkpoint: str | None,
    startup_timeout: float,
    bodies: str | None = None,
    model_file: str | None = None,
) -> dict:
    # Nodes started together must find each other quickly: fast initial announcements.
    use_fastdds_profile(FASTDDS_PROFILE)
    # ROS loads after the line above has pointed Fast DDS at the profile
    import rclpy
    from nav_msgs.msg import Odometry
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState

    # Strings go quoted: a spec such as "6" or a path must stay a string.
    body = (
        {"topology": yaml_string(bodies)}
        if bodies
        else {"model_file": yaml_string(model_file)}
        if model_file
        else {"num_joints": joints}
    )
    sim_params = {**body, "lockstep": True, "real_time_factor": 0.0, "effort_timeout": 2.0}
    policy_params = {} if checkpoint is None else {"checkpoint": yaml_string(checkpoint)}
    rclpy.init()
    node = rclpy.create_node("bringup")
    first, last, loop_start, joint_counts = [], [], [], set()
    posture = Posture()

    def on_odom(msg: Odometry) -> None:
        t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        sample = (t, msg.pose.pose.position.x, msg.pose.pose.position.y)
        posture.see(msg.pose.pose.position.z, msg.pose.pose.orientation)
        if not first:
            first.append(sample)
        if t > 0 and not loop_start:  # the loop runs: the policy has answered the reset state
            loop_start.append((time.monotonic(), t))
        last[:] = [sample]

    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(Odometry, "odom", on_odom, qos)
    # A joint_states listener makes the lockstep sim publish its reset state before the policy is up.
    node.create_subscription(JointState, "joint_states", lambda msg: joint_counts.add(len(msg.name)), qos)
    procs: list[NodeProcess] = [start_node("swimmer_sim_node.sim_node", params=sim_params)]
    try:
        # Start the policy only once the reset state has reached us, so the measurement
        # surely starts from the swimmer's reset pose.
        t_start = time.monotonic()
        while not first:
            if procs[0].poll() is not None or time.monotonic() - t_start > startup_timeout:
                raise RuntimeError("the sim node did not come up (exited, or DDS discovery failed)")
            rclpy.spin_once(node, timeout_sec=0.05)
        procs.append(start_node("morph_policy_node.policy_node", params=policy_params))
        while not (last and last[0][0] >= sim_seconds):
            if any(p.poll() is not None for p in procs):
                raise RuntimeError("a node exited early; see its output above")
            if not first and time.monotonic() - t_start > startup_timeout:
                raise RuntimeError(f"no odometry within {startup_timeout} s: DDS discovery failed?")
            rclpy.spin_once(node, timeout_sec=0.1)
        rate = (last[0][0] - loop_start[0][1]) / (time.monotonic() - loop_start[0][0])
    finally:
        stop_all(procs)
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
        "in_3d": posture.in_3d,
        "falls": posture.falls,
    }


TREE_MODEL = "swimmer_trees_gnn.safetensors"
"""the shipped tree-trained policy, beside the chain one"""
CENTIPEDE_MODEL = "centipede_gnn.safetensors"
"""the shipped centipede policy (trained on 2..4 leg pairs; it walks on 3..6: models/README.md)"""
LEGGED_MODEL = "legged_gnn.safetensors"
"""the shipped legged generalist (joint descriptions; trained on the generated legged family: models/README.md)"""
FAMILY_MODELS = {"trees": TREE_MODEL, "centipedes": CENTIPEDE_MODEL, "legged": LEGGED_MODEL}
"""the shipped model of each family but chains' (the node's own default)"""


def _family(spec: str | None, model_file: str | None = None) -> str:
    """What a run drives, which picks the shipped model: ``chains`` (and a planar MJCF), ``trees`` (swimmers),
    ``centipedes`` (a spec of centipedes alone) or ``legged`` (other walkers: legged bodies, a mix, an MJCF with a
    free root). A bad spec or a model the trainer could not run reads as chains here: it is the sim node's to
    refuse, with its reason."""
    # `env` is the sim extra's: the policy node's package installs and imports without it
    from morph_core.env.bodies import CentipedeFamily, parse_bodies

    if not (spec or model_file):
        return "chains"
    try:
        mix = parse_bodies(f"mjcf:{model_file}" if model_file else spec)
        walkers = mix.has_walkers  # an MJCF is read here
    except ValueError:  # RobotModelError too
        return "chains"
    if mix.chains_only or (model_file and not walkers):
        return "chains"  # a planar robot keeps the chain model, as it always did
    if not walkers:
        return "trees"
    return "centipedes" if all(isinstance(item, CentipedeFamily) for item in mix.items) else "legged"


PROG_ENV = "MORPH_PROG"
"""the environment variable that names the program in help and errors (scripts/demo.sh sets it)"""


def main(argv=None) -> int:
    ap = CommandLineParser(prog=os.environ.get(PROG_ENV, "python -m morph_policy_node.bringup"),
                           description=__doc__.split("\n\n")[0])  # fmt: skip
    body = ap.add_mutually_exclusive_group()
    body.add_argument("--joints", type=int, default=6, help=f"chain length of the simulated swimmer (1..{MAX_JOINTS})")
    body.add_argument("--bodies", default=None, help="body spec of the swimmer (the sim's topology), e.g. y:2x2")
    body.add_argument("--model-file", default=None, help="MJCF of your own robot (the sim's model_file)")
    ap.add_argument("--seconds", type=float, default=30.0, help="sim time to run, seconds")
    ap.add_deprecated_alias("--sim-seconds", "--seconds")
    ap.add_argument(
        "--checkpoint",
        default=None,
        help="policy .safetensors (default: the shipped model; trees, centipedes, legged: theirs)",
    )
    ap.add_argument("--startup-timeout", type=float, default=60.0, help="wall seconds to wait for the nodes")
    args = ap.parse_args(argv)
    # What the sim would refuse with a traceback of its parameter's range is refused here, in one line.
    if not 1 <= args.joints <= MAX_JOINTS:
        print(f"{ap.prog}: cannot start: --joints {args.joints}: a chain has 1..{MAX_JOINTS} joints", flush=True)
        return 2
    if not args.seconds > 0:
        print(f"{ap.prog}: cannot start: --seconds {args.seconds:g}: the run needs some sim time", flush=True)
        return 2
    # the node module loads rclpy: only once the arguments are checked, so a bad one is refused without ROS
    from morph_policy_node.policy_node import SHIPPED_MODEL

    family = _family(args.bodies, args.model_file)
    if args.checkpoint is None:
        shipped = SHIPPED_MODEL
        if family != "chains":
            shipped = SHIPPED_MODEL.with_name(FAMILY_MODELS[family])
            args.checkpoint = str(shipped)
        if not shipped.is_file():
            print(f"bringup: no shipped policy at {shipped}: give --checkpoint", flush=True)
            return 2
    try:
        r = run(args.joints, args.seconds, args.checkpoint, args.startup_timeout, args.bodies, args.model_file)
    except RuntimeError as err:  # the node said why above (a bad --bodies or --model-file, say)
        print(f"bringup: {err}", flush=True)
        return 1
    body = f"bodies {args.bodies}, " if args.bodies else f"robot {args.model_file}, " if args.model_file else ""
    walks = family in ("centipedes", "legged") or r["in_3d"]  # a body on a floor walks; a swimmer's pose is planar
    falls = "" if not walks else f"; fell {r['falls']} time{'' if r['falls'] == 1 else 's'} (turned over)"
    print(
        f"{'walk' if walks else 'swim'} speed: {r['speed']:+.4f} m/s along x ({r['dx']:+.3f} m forward, "
        f"{r['dy']:+.3f} m sideways) over {r['sim_seconds']:.2f} s of sim time, {body}{r['joints'] or args.joints} "
        f"joints; closed loop over DDS at {r['rate']:.1f}x real time{falls}",
        flush=True,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
