"""Node processes, the one way the project starts and stops them: ``start_node``, ``NodeProcess``, ``stop_all``.

The demo's bring-up (``morph_policy_node.bringup``), the recording (``trainer.bags.record_bringup``, the bag
rounds), the live bring-up, the benches and the topic-level tests all start nodes as processes, as a launch
file would on a Jazzy install: the node's module (or console script) with ``--ros-args``, its namespace and
its parameters, output to the terminal or a log file. They stop them the same way: SIGTERM (a normal end for
the nodes, ``node_runner``), then SIGKILL for one that lingers. The waits on the ROS graph (a node's
parameter, its subscriptions) live here too, for the bring-ups that start a node only once another listens.

No ROS import at module level: a bring-up sets the Fast DDS profile (``use_fastdds_profile``) before rclpy
loads, and the benches and tests start nodes without an rclpy of their own.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import IO

FASTDDS_ENV = "FASTRTPS_DEFAULT_PROFILES_FILE"
"""the environment variable Fast DDS reads its XML profile from"""

STOP_TIMEOUT = 15.0
"""seconds a node has to end after SIGTERM before it is killed"""


class BringupError(RuntimeError):
    """A node of a bring-up exited or never came up: said in one line (its own error is above), no traceback."""


def use_fastdds_profile(profile: str | Path | None) -> None:
    """Nodes started from here on (and this process's rclpy, if it loads later) read ``profile``, unless the
    environment names one already (a user's own wins)."""
    if profile:
        os.environ.setdefault(FASTDDS_ENV, str(profile))


def param_text(value) -> str:
    """A parameter's value as ``-p name:=TEXT`` wants it (YAML): booleans in YAML's spelling, the empty string
    as ``''``, any other string as the caller wrote it (a YAML list, a number meant as a number), numbers as
    Python prints them. A string that must stay a string whatever it looks like: ``yaml_string``."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return value if value else "''"
    return str(value)


def yaml_string(text: str) -> str:
    """``text`` quoted, so the node reads a string even when it looks like a number or a boolean (``"6"``)."""
    return json.dumps(text)  # JSON's strings are YAML's


def ros_arguments(namespace: str = "", params: dict | None = None) -> list[str]:
    """``--ros-args`` with the namespace (``''``: the root) and each parameter."""
    args = ["--ros-args", "-r", f"__ns:={namespace or '/'}"]
    for name, value in (params or {}).items():
        args += ["-p", f"{name}:={param_text(value)}"]
    return args


def node_command(module: str, namespace: str = "", params: dict | None = None, prefix: Sequence[str] = ()) -> list[str]:
    """The command of a node: ``module`` run by this Python (``python -m module``), or, for a path, that
    executable (a console script, another venv's); ``prefix`` before it (``nsenter ...``: another host)."""
    program = [str(module)] if os.sep in str(module) else [sys.executable, "-m", module]
    return [*prefix, *program, *ros_arguments(namespace, params)]


class NodeProcess:
    """A started process (a node, or a tool beside the nodes); its output to ``output``: a file path (opened
    here, closed by ``stop``), an open binary file (shared, left open), or None (this process's terminal).
    ``echo``: the command goes first into ``output`` (a log several processes share says who started)."""

    def __init__(
        self,
        cmd: list[str],
        output: str | Path | IO[bytes] | int | None = None,
        env: dict | None = None,
        echo: bool = False,
    ):
        self.cmd = cmd
        self.log_path = Path(output) if isinstance(output, (str, Path)) else None
        self._own = open(self.log_path, "wb") if self.log_path is not None else None  # noqa: SIM115 - stop() closes
        out = self._own if self._own is not None else output
        if out is not None and echo:
            out.write(f"$ {' '.join(cmd)}\n".encode())
            out.flush()
        stderr = subprocess.STDOUT if out is not None else None
        self.proc = subprocess.Popen(cmd, stdout=out, stderr=stderr, env=env)

    @property
    def pid(self) -> int:
        return self.proc.pid

    @property
    def returncode(self) -> int | None:
        return self.proc.returncode

    def poll(self) -> int | None:
        return self.proc.poll()

    def alive(self) -> bool:
        return self.proc.poll() is None

    def log(self) -> str:
        """What the process wrote so far (its own log file only)."""
        return self.log_path.read_text(errors="replace")

    def send_signal(self, sig: int = signal.SIGTERM) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)

    def wait(self, timeout: float = STOP_TIMEOUT) -> int:
        """Its exit code; killed when it has not ended within ``timeout`` seconds."""
        try:
            self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        return self.proc.returncode

    def stop(self, sig: int = signal.SIGTERM, timeout: float = STOP_TIMEOUT) -> int:
        """``sig`` (SIGTERM: the nodes' normal end), SIGKILL after ``timeout`` s; its exit code."""
        return stop_all([self], sig, timeout)[0]

    def close(self) -> None:
        if self._own is not None:
            self._own.close()


def start_node(
    module: str,
    namespace: str = "",
    params: dict | None = None,
    output: str | Path | IO[bytes] | int | None = None,
    prefix: Sequence[str] = (),
    env: dict | None = None,
    echo: bool = False,
) -> NodeProcess:
    """A node as a process (``node_command``), its output to ``output`` (``NodeProcess``)."""
    return NodeProcess(node_command(module, namespace, params, prefix), output, env, echo)


def stop_all(procs: Iterable[NodeProcess], sig: int = signal.SIGTERM, timeout: float = STOP_TIMEOUT) -> list[int]:
    """Signal every process first, then wait for each (they end side by side); their exit codes."""
    procs = list(procs)
    for p in procs:
        p.send_signal(sig)
    codes = [p.wait(timeout) for p in procs]
    for p in procs:
        p.close()
    return codes


# -- waits on the ROS graph (the caller's rclpy node) ------------------------------------------------------
def has_parameter(node, target: str, name: str, timeout: float) -> bool:
    """Whether node ``target`` declares parameter ``name`` (asked over its parameter service)."""
    # no ROS at module level: a bring-up sets the Fast DDS profile before rclpy loads
    import rclpy
    from rcl_interfaces.srv import ListParameters

    client = node.create_client(ListParameters, f"{target}/list_parameters")
    if not client.wait_for_service(timeout_sec=timeout):
        raise BringupError(f"{target} did not come up within {timeout} s (exited, or DDS discovery failed)")
    future = client.call_async(ListParameters.Request(names=[name]))
    rclpy.spin_until_future_complete(node, future, timeout_sec=timeout)
    if future.result() is None:
        raise BringupError(f"no answer from {target}/list_parameters")
    return name in future.result().result.names


def wait_for_subscriber(node, proc: NodeProcess, alternatives: list[list[str]], name: str, timeout: float) -> None:
    """Until node ``name`` (the process ``proc``) subscribes to every topic of one of ``alternatives``, as the
    ROS graph shows it."""
    # no ROS at module level: a bring-up sets the Fast DDS profile before rclpy loads
    import rclpy

    def missing(topics: list[str]) -> list[str]:
        return [t for t in topics if not any(i.node_name == name for i in node.get_subscriptions_info_by_topic(t))]

    deadline = time.monotonic() + timeout
    while True:
        left = [missing(topics) for topics in alternatives]
        if not all(left):
            return
        said = " or ".join(str(m) for m in left)
        if proc.poll() is not None:
            raise BringupError(f"{name} exited (code {proc.returncode}) before it subscribed to {said}: see its "
                               "error above")  # fmt: skip
        if time.monotonic() > deadline:
            raise BringupError(f"{name} did not subscribe to {said} within {timeout} s (DDS discovery failed?)")
        rclpy.spin_once(node, timeout_sec=0.05)


def has_endpoint(node, topic: str, node_name: str, kind: str) -> bool:
    """Whether node ``node_name`` subscribes to (``kind`` ``sub``) or publishes (``pub``) ``topic``."""
    infos = node.get_subscriptions_info_by_topic(topic) if kind == "sub" else node.get_publishers_info_by_topic(topic)
    return any(i.node_name == node_name for i in infos)
