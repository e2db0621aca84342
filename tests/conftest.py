"""Fixtures for topic-level tests: real node processes through their entry points, real DDS.

Run inside ``scripts/in_netns.sh`` (``scripts/test.sh`` does): a private
network namespace whose loopback carries multicast, so discovery works and
nothing leaves the machine. Every test puts its nodes in a namespace of its
own, so a straggler from an earlier test can never answer for a later one.
"""

from __future__ import annotations

import itertools
import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import safetensors.numpy

import morph_policy_node
from morph_ros_util import processes

BIN = Path(sys.executable).parent
FASTDDS_PROFILE = morph_policy_node.FASTDDS_PROFILE
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

    def spin_until(self, condition: Callable[[], bool], timeout: float, what: str | Callable[[], str]) -> None:
        """Spin until ``condition()``; after ``timeout`` s an AssertionError saying ``what`` was awaited
        (a callable is called then, so it can show state as of the failure, e.g. a node's log)."""
        deadline = time.monotonic() + timeout
        while not condition():
            if time.monotonic() > deadline:
                said = what() if callable(what) else what
                raise AssertionError(f"timed out after {timeout} s waiting for {said}")
            self.executor.spin_once(timeout_sec=0.02)

    def spin_for(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.02)

    def collect(self, msg_type, topic: str, qos=None) -> list:
        """Every message on ``topic`` from now on (default QoS: reliable, keep last 1000: nothing lost)."""
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        got: list = []
        qos = qos if qos is not None else QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.node.create_subscription(msg_type, topic, got.append, qos)
        return got

    def set_parameter(self, node_path: str, name: str, value, timeout: float = 60.0):
        """Set one parameter of the node at ``node_path`` through its service; returns its SetParametersResult."""
        from rcl_interfaces.srv import SetParameters
        from rclpy.parameter import Parameter

        client = self.node.create_client(SetParameters, f"{node_path}/set_parameters")
        self.spin_until(client.service_is_ready, timeout, f"{node_path}/set_parameters")
        future = client.call_async(SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()]))
        self.spin_until(future.done, 20.0, "set_parameters response")
        return future.result().results[0]

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()


class NodeProcess(processes.NodeProcess):
    """A node started through its console script (``morph_ros_util.processes``, as the bring-ups start them);
    output goes to a log file the test can read."""

    def __init__(self, executable: str, namespace: str, params: dict, log_path: Path):
        super().__init__(processes.node_command(str(BIN / executable), namespace, params), log_path)

    def rss_kb(self) -> int:
        """The process's resident memory now [kB]."""
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
        raise AssertionError("no VmRSS")


@pytest.fixture
def namespace() -> str:
    return f"/t{os.getpid()}_{next(_names)}"


@pytest.fixture
def probe(namespace):
    p = RosProbe(namespace)
    yield p
    p.close()


class Diagnostics:
    """The latest input counts a node reported on /diagnostics."""

    def __init__(self, probe, node_name: str):
        from diagnostic_msgs.msg import DiagnosticArray

        self.name = f"{node_name}: inputs"
        self.latest: dict | None = None
        self.messages: list[str] = []
        probe.node.create_subscription(DiagnosticArray, "/diagnostics", self._on, 10)

    def _on(self, msg) -> None:
        from morph_core.protocol.input_counts import from_key_values

        for status in msg.status:
            if status.name == self.name:
                self.latest = from_key_values((kv.key, kv.value) for kv in status.values)
                self.messages.append(status.message)


@pytest.fixture
def diagnostics(probe):
    """diagnostics(node_name) -> the input counts that node reports on /diagnostics, as they come."""
    return lambda node_name: Diagnostics(probe, node_name)


@pytest.fixture
def launch(namespace, tmp_path):
    """launch(executable, **params) -> NodeProcess in the test's namespace; all are stopped afterwards.
    ``executable``: a console script of this venv, or the absolute path of another venv's."""
    started: list[NodeProcess] = []

    def _launch(executable: str, **params) -> NodeProcess:
        proc = NodeProcess(executable, namespace, params, tmp_path / f"{Path(executable).name}_{len(started)}.log")
        started.append(proc)
        return proc

    yield _launch
    for proc in reversed(started):
        proc.stop()


@pytest.fixture
def two_hosts():
    """Two fresh network namespaces joined by a veth pair (10.77.0.1 and 10.77.0.2): two hosts on one link, apart
    from the tests' own namespace (which they leave untouched). Yields the command prefixes that run a process on
    each. Needs ``unshare -n``, ``nsenter`` and ``ip`` (iproute2), which work without root inside
    ``scripts/in_netns.sh``'s user namespace."""
    import shutil
    import time

    if not all(shutil.which(t) for t in ("unshare", "nsenter", "ip")):
        pytest.skip("needs unshare, nsenter and ip (util-linux, iproute2)")
    holders = [subprocess.Popen(["unshare", "-n", "sleep", "3600"]) for _ in range(2)]
    hosts = [["nsenter", "-t", str(h.pid), "-n", "--preserve-credentials"] for h in holders]

    def sh(cmd: str, prefix) -> None:
        subprocess.run([*prefix, "sh", "-c", cmd], check=True, capture_output=True)

    try:
        deadline = time.monotonic() + 10
        here = os.readlink("/proc/self/ns/net")
        while any(os.readlink(f"/proc/{h.pid}/ns/net") == here for h in holders):  # until both have their own
            assert time.monotonic() < deadline, "unshare -n did not make a network namespace"
            time.sleep(0.02)
        sh(f"ip link add vA type veth peer name vB netns {holders[1].pid}", hosts[0])
        for prefix, dev, addr in ((hosts[0], "vA", "10.77.0.1"), (hosts[1], "vB", "10.77.0.2")):
            sh(f"ip link set lo up && ip addr add {addr}/24 dev {dev} && ip link set {dev} multicast on && "
               f"ip link set {dev} up && ip route add 224.0.0.0/4 dev {dev}", prefix)  # fmt: skip
        yield hosts
    finally:
        for h in holders:
            h.kill()
            h.wait()


@pytest.fixture(scope="session")
def untrained_checkpoint(tmp_path_factory) -> Path:
    """A randomly initialised policy saved like a trained one (so tests never depend on training)."""
    import torch

    from morph_core.policy.actor_critic import GraphActorCritic

    torch.manual_seed(123)
    path = tmp_path_factory.mktemp("policy") / "untrained.safetensors"
    GraphActorCritic().save(path, metadata={"note": "untrained, for tests"})
    return path


@dataclass(frozen=True)
class TrainerKey:
    """A signing key pair as ``morph-keys new`` writes it: the trainer signs with ``signer`` / ``path``, policy
    nodes trust ``public`` (``trusted_keys``)."""

    signer: object
    path: Path
    public: Path

    @property
    def trusted(self) -> str:
        """The ``trusted_keys`` parameter's text: a YAML list of the public key file."""
        return json.dumps([str(self.public)])

    def sign(self, dims: list[tuple[str, int, int]], data: bytes) -> list[tuple[str, int, int]]:
        """A weights message's layout dims with this key's signature over its header and data, as they are
        (a trusted trainer that sends damaged weights signs them too)."""
        from morph_core.protocol.trust import sha256_hex

        return [*dims[:2], (self.signer.sign(dims[1][0], sha256_hex(bytes(data))).label, 0, 0)]


@pytest.fixture(scope="session")
def trainer_key(tmp_path_factory) -> TrainerKey:
    from morph_core.protocol.trust import public_key_path, write_key_pair

    path = tmp_path_factory.mktemp("keys") / "trainer_key"
    return TrainerKey(write_key_pair(path), path, public_key_path(path))


# -- checkpoints that must be refused ----------------------------------------------------------------
def _copy(good: Path, dest: Path) -> Path:
    shutil.copyfile(good, dest)
    shutil.copyfile(good.with_suffix(".json"), dest.with_suffix(".json"))
    return dest


def _arrays(good: Path) -> dict[str, np.ndarray]:
    return safetensors.numpy.load(good.read_bytes())


def write_bad_checkpoints(directory: Path, good: Path) -> dict[str, tuple[Path, tuple[str, ...]]]:
    directory.mkdir(parents=True, exist_ok=True)
    cases: dict[str, tuple[Path, tuple[str, ...]]] = {}

    cases["missing"] = (directory / "missing.safetensors", ("no such file",))

    p = _copy(good, directory / "truncated.safetensors")
    p.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    cases["truncated"] = (p, ("safetensors",))

    p = _copy(good, directory / "garbage.safetensors")
    p.write_bytes(b"this is not a tensor file at all" * 10)
    cases["not_safetensors"] = (p, ("safetensors",))

    p = _copy(good, directory / "pickle.safetensors")
    import torch  # only to write what torch.save writes

    torch.save({k: torch.from_numpy(v) for k, v in _arrays(good).items()}, p)
    cases["pickle"] = (p, ("pickle",))

    p = _copy(good, directory / "no_config.safetensors")
    p.with_suffix(".json").unlink()
    cases["config_missing"] = (p, ("no_config.json", "missing"))

    p = _copy(good, directory / "bad_json.safetensors")
    p.with_suffix(".json").write_text("{not json")
    cases["config_not_json"] = (p, ("JSON",))

    p = _copy(good, directory / "unknown_field.safetensors")
    meta = json.loads(good.with_suffix(".json").read_text())
    meta["policy"]["wings"] = 2
    p.with_suffix(".json").write_text(json.dumps(meta))
    cases["config_wrong"] = (p, ("wings",))

    p = _copy(good, directory / "wrong_shapes.safetensors")
    meta = json.loads(good.with_suffix(".json").read_text())
    meta["policy"]["conv1_channels"] = 8  # the file holds 24 channels
    p.with_suffix(".json").write_text(json.dumps(meta))
    cases["wrong_shapes"] = (p, ("shape",))

    p = _copy(good, directory / "nan.safetensors")
    arrays = _arrays(good)
    arrays["actor_head.2.weight"][3, 5] = np.nan
    p.write_bytes(safetensors.numpy.save(arrays))
    cases["nan_weights"] = (p, ("NaN", "actor_head.2.weight"))

    p = _copy(good, directory / "missing_tensor.safetensors")
    arrays = _arrays(good)
    del arrays["critic_head.4.bias"]
    p.write_bytes(safetensors.numpy.save(arrays))
    cases["missing_tensor"] = (p, ("critic_head.4.bias",))

    p = _copy(good, directory / "float64.safetensors")
    arrays = {k: v.astype(np.float64) for k, v in _arrays(good).items()}
    p.write_bytes(safetensors.numpy.save(arrays))
    cases["wrong_dtype"] = (p, ("float64",))

    cases["not_safetensors_suffix"] = (_copy(good, directory / "policy.pt"), (".safetensors",))
    return cases


def write_overflowing_checkpoint(path: Path, good: Path) -> Path:
    """Finite weights whose output is not: the last hidden layer saturated at tanh = 1 and the action
    layer's weights at float32's largest value, so the 64-term sum overflows to inf for every state."""
    _copy(good, path)
    arrays = _arrays(good)
    arrays["actor_head.2.weight"][:] = 0.0
    arrays["actor_head.2.bias"][:] = 100.0
    arrays["actor_head.4.weight"][:] = np.finfo(np.float32).max
    assert all(np.isfinite(v).all() for v in arrays.values())
    path.write_bytes(safetensors.numpy.save(arrays))
    return path


@pytest.fixture(scope="session")
def bad_checkpoints(tmp_path_factory, untrained_checkpoint) -> dict[str, tuple[Path, tuple[str, ...]]]:
    """{case: (path, words its refusal must contain)}, one case per way a checkpoint can be unusable."""
    return write_bad_checkpoints(tmp_path_factory.mktemp("bad_checkpoints"), untrained_checkpoint)


@pytest.fixture(scope="session")
def overflowing_checkpoint(tmp_path_factory, untrained_checkpoint) -> Path:
    path = tmp_path_factory.mktemp("overflow") / "overflow.safetensors"
    return write_overflowing_checkpoint(path, untrained_checkpoint)
