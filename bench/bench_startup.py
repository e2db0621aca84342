"""Node start-up and memory: wall time from process start to the first answer, and resident memory.

    bash scripts/in_netns.sh .venv/bin/python bench/bench_startup.py [--before REV] [--runs 3]

Each node is started as a process (``python -m <module>``) and timed until it
first answers over DDS: the sim node until this process receives its first
``joint_states``; the policy node (shipped model) until the first
``effort_commands`` answering the ``joint_states`` this process publishes.
Resident memory is read from ``/proc/<pid>/status`` once it has answered
(VmRSS) together with its peak (VmHWM). The same is measured for the code at
``--before`` (a ``git worktree`` of that revision put first on PYTHONPATH),
alternating runs so both see the same machine load; medians and the ratio
new/before are printed. Not a timed test: the figures depend on the machine.
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import tempfile
import threading
import time
from pathlib import Path

from morph_ros_util.processes import node_command

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("ros2_ws/src/morph_core", "ros2_ws/src/swimmer_sim_node", "ros2_ws/src/morph_policy_node")
PROFILE = ROOT / "ros2_ws/src/morph_policy_node/morph_policy_node/fastdds_profile.xml"
NODES = {"swimmer_sim_node": "swimmer_sim_node.sim_node", "morph_policy_node": "morph_policy_node.policy_node"}
READY_LINE = {"swimmer_sim_node": "swimmer with", "morph_policy_node": "policy loaded"}


def _memory_kb(pid: int) -> tuple[int, int]:
    fields = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        fields[key] = value
    return int(fields["VmRSS"].split()[0]), int(fields["VmHWM"].split()[0])


def measure(probe, tree: Path, node: str, index: int) -> dict:
    """One start of ``node`` from the code at ``tree``: seconds to first answer, RSS and peak in MB."""
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    namespace = f"/bench{os.getpid()}_{index}"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(str(tree / p) for p in PACKAGES))
    args = node_command(NODES[node], namespace)
    got: list[float] = []
    if node == "swimmer_sim_node":
        sub = probe.create_subscription(JointState, f"{namespace}/joint_states", lambda m: got.append(1), 10)
        pub = None
    else:
        sub = probe.create_subscription(Float64MultiArray, f"{namespace}/effort_commands", lambda m: got.append(1), 10)
        pub = probe.create_publisher(JointState, f"{namespace}/joint_states", 10)
    state = JointState(name=["a", "b", "c"], position=[0.1, 0.2, 0.3], velocity=[0.0, 0.0, 0.0])
    import rclpy

    t0 = time.monotonic()
    proc = subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    ready: list[float] = []

    def read_log() -> None:  # the node's own "ready" line: start-up before any DDS matching
        for line in proc.stdout:
            if not ready and READY_LINE[node] in line:
                ready.append(time.monotonic() - t0)

    threading.Thread(target=read_log, daemon=True).start()
    try:
        while not got:
            if proc.poll() is not None:
                raise RuntimeError(f"{node} from {tree} exited with {proc.returncode}")
            if time.monotonic() - t0 > 120:
                raise RuntimeError(f"{node} from {tree} did not answer within 120 s")
            if pub is not None:
                pub.publish(state)
            rclpy.spin_once(probe, timeout_sec=0.005)
        took = time.monotonic() - t0
        rss, peak = _memory_kb(proc.pid)
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        probe.destroy_subscription(sub)
        if pub is not None:
            probe.destroy_publisher(pub)
    ready_s = ready[0] if ready else float("nan")
    return {"ready_s": ready_s, "seconds": took, "rss_mb": rss / 1024, "peak_mb": peak / 1024}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before", default="bff97df^", help="revision to compare with (default: before issue 16)")
    ap.add_argument("--runs", type=int, default=3, help="starts per node and code version")
    args = ap.parse_args()
    os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(PROFILE))
    import rclpy

    with tempfile.TemporaryDirectory() as tmp:
        before = Path(tmp) / "before"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(before), args.before], check=True)
        try:
            rclpy.init()
            probe = rclpy.create_node("bench_startup")
            results: dict[tuple[str, str], list[dict]] = {}
            k = 0
            for _ in range(args.runs):
                for node in NODES:
                    for label, tree in (("before", before), ("now", ROOT)):
                        results.setdefault((node, label), []).append(measure(probe, tree, node, k))
                        k += 1
            probe.destroy_node()
            rclpy.try_shutdown()
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(before)], check=True)

    print(f"medians of {args.runs} starts; before = {args.before}")
    print("| node | code | start to ready line (s) | start to first answer over DDS (s) | RSS (MB) | peak RSS (MB) |")
    print("|---|---|---:|---:|---:|---:|")
    med = {key: {f: statistics.median(r[f] for r in runs) for f in runs[0]} for key, runs in results.items()}
    for node in NODES:
        for label in ("before", "now"):
            m = med[(node, label)]
            print(
                f"| {node} | {label} | {m['ready_s']:.2f} | {m['seconds']:.2f} | {m['rss_mb']:.0f} "
                f"| {m['peak_mb']:.0f} |"
            )
        b, n = med[(node, "before")], med[(node, "now")]
        print(
            f"| {node} | now/before | {n['ready_s'] / b['ready_s']:.2f} | {n['seconds'] / b['seconds']:.2f} "
            f"| {n['rss_mb'] / b['rss_mb']:.2f} "
            f"| {n['peak_mb'] / b['peak_mb']:.2f} |"
        )


if __name__ == "__main__":
    main()
