"""A signal asks the loop to stop; the ROS context stays valid until the loop has cleaned up.

With rclpy's own handlers a SIGINT shut the context down under a running ``spin_once``, which then raised
``RCLError`` (context invalid), and the deferred ``KeyboardInterrupt`` landed in the cleanup after it: the
live trainer printed two tracebacks on a Ctrl-C to the bringup (CI, tests/test_live.py).
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

CHILD = textwrap.dedent(
    """
    import os, signal, sys
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from morph_ros_util.stop_signals import init_stopping_on_signals

    stop = init_stopping_on_signals()
    node = rclpy.create_node("stop_signals_probe")
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    node.create_timer(0.01, lambda: os.kill(os.getpid(), getattr(signal, sys.argv[1])))
    spins = 0
    while not stop.is_set():
        executor.spin_once(timeout_sec=0.1)
        spins += 1
    print("context ok after the signal:", rclpy.ok(), "spins:", spins, flush=True)
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()
    """
)


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_a_signal_sets_the_stop_event_and_leaves_the_context_valid(sig):
    out = subprocess.run([sys.executable, "-c", CHILD, sig], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "context ok after the signal: True" in out.stdout, out.stdout + out.stderr[-2000:]
    assert "Traceback" not in out.stderr, out.stderr[-2000:]
