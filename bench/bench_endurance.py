"""Endurance: the policy node fed 64-joint states at 25 Hz for minutes; RSS and answer latency per minute.

Run inside a private network namespace (DDS discovery stays on this machine):

    bash scripts/in_netns.sh .venv/bin/python bench/bench_endurance.py --minutes 10 --joints 64

The policy node (shipped model) answers synthetic states (a sine wave through the chain; the swimmer's
physics is not needed to load the node, and MuJoCo's 64-joint chain diverges, see docs/benchmarks.md);
latency is from publishing a state to receiving the effort message that answers it (tag matched).
Prints one row per minute: answers, latency p50/p99/max [ms], the node's RSS [MB] (/proc/<pid>/status).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from morph_ros_util.processes import FASTDDS_ENV, start_node


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--joints", type=int, default=64)
    parser.add_argument("--rate", type=float, default=25.0)
    args = parser.parse_args()

    import rclpy
    from nav_msgs.msg import Odometry
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    import morph_policy_node
    from morph_core.msgs.stamps import answer_tag, from_ns, parse_answer_tag

    os.environ[FASTDDS_ENV] = str(morph_policy_node.FASTDDS_PROFILE)
    ns = f"/endurance{os.getpid()}"
    proc = start_node(str(Path(sys.executable).parent / "morph_policy_node"), ns, output=subprocess.DEVNULL)
    rclpy.init()
    node = rclpy.create_node("endurance_probe", namespace=ns)
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    sent: dict[int, float] = {}
    lat: list[float] = []

    def on_efforts(msg):
        tag = parse_answer_tag(msg.layout.dim[0].label) if msg.layout.dim else None
        if tag in sent:
            lat.append(time.monotonic() - sent.pop(tag))

    node.create_subscription(Float64MultiArray, "effort_commands", on_efforts, 10)
    state_pub = node.create_publisher(JointState, "joint_states", 10)
    odom_pub = node.create_publisher(Odometry, "odom", 10)
    deadline = time.monotonic() + 60
    while state_pub.get_subscription_count() == 0 and time.monotonic() < deadline:
        ex.spin_once(timeout_sec=0.05)
    names = [f"motor{k}_rot" for k in range(1, args.joints + 1)]
    period = 1.0 / args.rate
    start = next_t = time.monotonic()
    end = start + 60 * args.minutes
    k, minute, rows = 0, 0, []
    print(f"policy node, {args.joints} joints, {args.rate} Hz, {args.minutes} min; load {os.getloadavg()}")
    print("minute  answers  p50_ms  p99_ms  max_ms  rss_MB")
    while time.monotonic() < end:
        stamp_ns = 40_000_000 * (k + 1)
        sec, nanosec = from_ns(stamp_ns)
        odom = Odometry()
        odom.header.stamp.sec, odom.header.stamp.nanosec = sec, nanosec
        odom.pose.pose.orientation.w = 1.0
        phase = 0.3 * np.sin(0.2 * k + np.arange(args.joints))
        msg = JointState(name=names, position=phase.tolist(), velocity=(0.1 * phase).tolist())
        msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
        odom_pub.publish(odom)
        sent[parse_answer_tag(answer_tag(sec, nanosec))] = time.monotonic()
        state_pub.publish(msg)
        k += 1
        next_t += period
        while time.monotonic() < next_t:
            ex.spin_once(timeout_sec=max(0.0, next_t - time.monotonic()))
        if time.monotonic() - start >= 60 * (minute + 1):
            minute += 1
            a = np.array(lat) * 1e3
            row = (minute, len(a), *np.percentile(a, [50, 99]), a.max(), rss_mb(proc.pid)) if len(a) else None
            lat.clear()
            sent.clear()  # an answer older than a minute is lost, not late
            if row:
                rows.append(row)
                print("{:6d}  {:7d}  {:6.2f}  {:6.2f}  {:6.1f}  {:6.1f}".format(*row), flush=True)
    proc.stop(timeout=10)
    ex.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()
    print(f"load at the end {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
