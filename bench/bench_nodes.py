"""ROS 2 node speed: policy node latency (joint_states in -> effort_commands out) and sim node real-time factor.

    bash scripts/in_netns.sh .venv/bin/python bench/bench_nodes.py [--samples 500] [--seconds 5]

Real node processes through their console scripts, real Fast DDS on loopback
(inside the private network namespace). Latency is measured by this
process's node: publish a JointState, wait for the EffortCommands answer,
one at a time; beside it, the same policy's inference alone in-process
(validation, joint graph, the NumPy batch-1 GNN forward the node runs, and
for comparison the torch forward). The sim node's real-time factor is its
free-running sim clock over wall time at 20 joints.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from morph_core.msgs.joint_state import validate_joint_state
from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.chains import chain_batch
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_ros_util.processes import NodeProcess, start_node

BIN = Path(sys.executable).parent
PROFILE = Path(__file__).resolve().parents[1] / "ros2_ws/src/morph_policy_node/morph_policy_node/fastdds_profile.xml"
JOINTS = (2, 10, 20)


def start(executable: str, **params) -> NodeProcess:
    return start_node(str(BIN / executable), params=params, output=subprocess.DEVNULL)


def stop(proc: NodeProcess) -> None:
    proc.stop(timeout=10)


def spin_until(executor, condition, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        executor.spin_once(timeout_sec=0.001)
    return True


def inference_alone(samples: int) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
    """Per-call time [ms] of what the node does per message besides DDS (validate, graph, GNN, clip),
    with the NumPy batch-1 forward the node runs and, beside it, the torch forward."""
    torch.set_num_threads(1)
    torch.manual_seed(0)
    policy = GraphActorCritic().eval()
    fast = NumpyPolicy(policy)
    out_np, out_torch = {}, {}
    rng = np.random.default_rng(0)
    for j in JOINTS:
        names = [f"j{k}" for k in range(j)]
        pos, vel, glob = rng.normal(size=j), rng.normal(size=j), rng.normal(size=4)
        times_np, times_torch = [], []
        for i in range(samples + 50):
            t = time.perf_counter()
            p, v = validate_joint_state(names, pos, vel)
            np.clip(fast.mean(p, v, glob), -1.0, 1.0)
            t1 = time.perf_counter()
            p, v = validate_joint_state(names, pos, vel)
            action, *_ = policy.act(chain_batch(p, v, glob), deterministic=True)
            np.clip(action[0].numpy(), -1.0, 1.0)
            if i >= 50:  # warm-up excluded
                times_np.append(t1 - t)
                times_torch.append(time.perf_counter() - t1)
        out_np[j], out_torch[j] = np.array(times_np) * 1e3, np.array(times_torch) * 1e3
    return out_np, out_torch


def policy_latency(samples: int) -> dict[int, np.ndarray]:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    proc = start("morph_policy_node", checkpoint="''", allow_untrained="true")
    node = rclpy.create_node("bench_latency")
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    answers = []
    node.create_subscription(Float64MultiArray, "effort_commands", lambda m: answers.append(time.perf_counter()), 10)
    pub = node.create_publisher(JointState, "joint_states", 10)
    out = {}
    try:
        if not spin_until(
            ex, lambda: pub.get_subscription_count() > 0 and node.count_publishers("effort_commands") > 0, 60
        ):
            raise RuntimeError("policy node did not come up")
        rng = np.random.default_rng(1)
        for j in JOINTS:
            msg = JointState(name=[f"j{k}" for k in range(j)])
            times = []
            for i in range(samples + 20):
                msg.position = rng.normal(size=j).tolist()
                msg.velocity = rng.normal(size=j).tolist()
                n = len(answers)
                t = time.perf_counter()
                pub.publish(msg)
                if not spin_until(ex, lambda n=n: len(answers) > n, 2.0):
                    continue  # a lost best-effort sample: not a latency
                if i >= 20:
                    times.append(answers[n] - t)
            out[j] = np.array(times) * 1e3
    finally:
        stop(proc)
        node.destroy_node()
    return out


def sim_rtf(joints: int, seconds: float) -> float:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import qos_profile_sensor_data
    from rosgraph_msgs.msg import Clock

    proc = start("swimmer_sim_node", num_joints=joints, real_time_factor=0.0)
    node = rclpy.create_node("bench_rtf")
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    clocks = []

    def on_clock(m):
        clocks.append((time.monotonic(), m.clock.sec + m.clock.nanosec * 1e-9))

    node.create_subscription(Clock, "/clock", on_clock, qos_profile_sensor_data)
    try:
        if not spin_until(ex, lambda: len(clocks) > 10, 60):
            raise RuntimeError("sim node did not come up")
        start_wall, start_sim = clocks[-1]
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.01)
        end_wall, end_sim = clocks[-1]
    finally:
        stop(proc)
        node.destroy_node()
    return (end_sim - start_sim) / (end_wall - start_wall)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=500, help="messages per chain length")
    ap.add_argument("--seconds", type=float, default=5.0, help="wall seconds of free-running sim")
    args = ap.parse_args()
    os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(PROFILE))
    import rclpy

    alone, alone_torch = inference_alone(args.samples)
    rclpy.init()
    try:
        latency = policy_latency(args.samples)
        rtf = sim_rtf(20, args.seconds)
    finally:
        rclpy.try_shutdown()
    print(
        "| joints | node latency p50 (ms) | p99 (ms) | inference alone p50 (ms) | p99 (ms) | torch forward p50 (ms) |"
    )
    print("|---:|---:|---:|---:|---:|---:|")
    for j in JOINTS:
        lat, inf, inf_t = latency[j], alone[j], alone_torch[j]
        print(
            f"| {j} | {np.percentile(lat, 50):.3f} | {np.percentile(lat, 99):.3f} "
            f"| {np.percentile(inf, 50):.3f} | {np.percentile(inf, 99):.3f} | {np.percentile(inf_t, 50):.3f} |"
        )
    print()
    print(f"sim node, 20 joints, free-running (real_time_factor 0): {rtf:.1f}x real time")


if __name__ == "__main__":
    main()
