"""Fixtures for topic-level tests: real node processes through their entry points, real DDS.

Run inside ``scripts/in_netns.sh`` (``scripts/test.sh`` does): a private
network namespace whose loopback carries multicast, so discovery works and
nothing leaves the machine. Every test puts its nodes in a namespace of its
own, so a straggler from an earlier test can never answer for a later one.
"""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

import morph_policy_node

BIN = Path(sys.executable).parent
FASTDDS_PROFILE = Path(morph_policy_node.__file__).parent / "fastdds_profile.xml"
_names = itertools.count()


@pytest.fixture(scope="session", autouse=True)
def dds_environment():
    """Fast start-up discovery for this process and the node processes; a domain of our own."""
    os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(FASTDDS_PROFILE)
    os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
    os.environ.pop("ROS_LOCALHOST_ONLY", None)
    yield


class RosProbe:
    """The test's own rclpy node, spun on demand while waiting for a condition."""

    def __init__(self, namespace: str):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(f"probe_{namespace.strip('/')}", namespace=namespace, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def spin_until(self, condition: Callable[[], bool], timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not condition():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out after {timeout} s waiting for {what}")
            self.executor.spin_once(timeout_sec=0.02)

    def spin_for(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.02)

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()


class NodeProcess:
    """A node started through its console script; output goes to a log file the test can read."""

    def __init__(self, executable: str, namespace: str, params: dict, log_path: Path):
        args = [str(BIN / executable), "--ros-args", "-r", f"__ns:={namespace}"]
        for k, v in params.items():
            args += ["-p", f"{k}:={_param_text(v)}"]
        self.log_path = log_path
        self._log = open(log_path, "wb")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen(args, stdout=self._log, stderr=subprocess.STDOUT)

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self) -> int | None:
        """SIGTERM (the nodes treat it as a normal end), then SIGKILL if it lingers. Returns the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()
        return self.proc.returncode


def _param_text(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return v if v else "''"
    return repr(v)


@pytest.fixture
def namespace() -> str:
    return f"/t{os.getpid()}_{next(_names)}"


@pytest.fixture
def probe(namespace):
    p = RosProbe(namespace)
    yield p
    p.close()


@pytest.fixture
def launch(namespace, tmp_path):
    """launch(executable, **params) -> NodeProcess in the test's namespace; all are stopped afterwards."""
    started: list[NodeProcess] = []

    def _launch(executable: str, **params) -> NodeProcess:
        proc = NodeProcess(executable, namespace, params, tmp_path / f"{executable}_{len(started)}.log")
        started.append(proc)
        return proc

    yield _launch
    for proc in reversed(started):
        proc.stop()


@pytest.fixture(scope="session")
def untrained_checkpoint(tmp_path_factory) -> Path:
    """A randomly initialised policy saved like a trained one (so tests never depend on training)."""
    import torch

    from morph_core.policy.actor_critic import GraphActorCritic

    torch.manual_seed(123)
    path = tmp_path_factory.mktemp("policy") / "untrained.safetensors"
    GraphActorCritic().save(path, metadata={"note": "untrained, for tests"})
    return path
