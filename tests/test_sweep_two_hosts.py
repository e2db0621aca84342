"""``morph-sweep --address`` on a Ray cluster of two hosts: a head in one network namespace, a worker node in
the other, joined only by the veth link of ``two_hosts``; a 2x2 grid of short trials runs on both.

Run inside ``scripts/in_netns.sh`` (the namespaces need its user namespace). Every Ray process here is a child
of a ``ray start --block`` this test started in its own process group, and teardown ends those groups: never
``ray stop``, which would end every Ray process of the user on the machine, other sweeps' included.
"""

from __future__ import annotations

import json
import os
import secrets
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from morph_core.algo.run_dir import RunDir
from morph_core.algo.small_runs import sets_of, small

pytestmark = pytest.mark.slow  # every test here starts processes (nodes, bring-ups, installs)

HEAD, WORKER, PORT = "10.77.0.1", "10.77.0.2", 6379
TINY = sets_of(small(total_timesteps=512, num_steps=128, minibatch_size=64, update_epochs=1))
RAY = [str(Path(sys.executable).with_name("ray"))]


def cluster_env() -> dict:
    """Ray's token authentication, as on a real cluster: one token for every node and the driver (a client
    without one is refused); this test's own, not the one Ray keeps in ~/.ray."""
    return {**os.environ, "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": TOKEN, "RAY_USAGE_STATS_ENABLED": "0"}


TOKEN = secrets.token_hex(32)


def ray_node(prefix: list[str], args: list[str], log: Path) -> subprocess.Popen:
    """``ray start ... --block`` on one host: it stays in the foreground with the node's processes as its
    children, and ends them when it is signalled."""
    small = ["--num-cpus", "1", "--num-gpus", "0", "--object-store-memory", str(100 * 1024**2), "--block"]
    return subprocess.Popen([*prefix, *RAY, "start", *args, *small], stdout=log.open("w"), stderr=subprocess.STDOUT,
                            start_new_session=True, env=cluster_env())  # fmt: skip


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def alive_nodes(prefix: list[str]) -> int:
    code = (f"import ray; ray.init(address='{HEAD}:{PORT}', logging_level='ERROR', log_to_driver=False); "
            "print(sum(n['Alive'] for n in ray.nodes()))")  # fmt: skip
    out = subprocess.run([*prefix, sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                         env=cluster_env())  # fmt: skip
    return int(out.stdout.strip().splitlines()[-1]) if out.returncode == 0 and out.stdout.strip() else 0


@pytest.mark.timeout(240)
def test_a_sweep_runs_on_a_ray_cluster_of_two_hosts(two_hosts, tmp_path):
    head_host, worker_host = two_hosts
    # A short temp dir (Ray's socket paths must stay under 107 bytes), this test's own: other Ray users here
    # keep theirs.
    temp = tempfile.mkdtemp(prefix="ray", dir="/tmp")
    nodes = [ray_node(head_host, ["--head", "--node-ip-address", HEAD, "--port", str(PORT),
                                  "--include-dashboard", "false", "--disable-usage-stats", "--temp-dir", temp],
                      tmp_path / "head.log")]  # fmt: skip
    try:
        deadline = time.monotonic() + 90
        count = 0
        while count < 2:
            assert time.monotonic() < deadline, f"the cluster has {count} of 2 nodes: " + "\n".join(
                (tmp_path / f).read_text()[-1500:] for f in ("head.log", "worker.log") if (tmp_path / f).exists()
            )
            for n in nodes:
                assert n.poll() is None, (tmp_path / "head.log").read_text()[-3000:]
            if len(nodes) == 1 and alive_nodes(head_host) == 1:  # the head is up: the worker joins it
                nodes.append(ray_node(worker_host, ["--address", f"{HEAD}:{PORT}", "--node-ip-address", WORKER],
                                      tmp_path / "worker.log"))  # fmt: skip
            count = alive_nodes(head_host) if len(nodes) == 2 else 0
        out = tmp_path / "sweep"
        cmd = [sys.executable, "-m", "trainer.sweep", "--out", str(out), "--address", f"{HEAD}:{PORT}",
               "--grid", "clip-mode=fixed,compensated", "--grid", "seed=1,2", "--eval", "lengths=2",
               "--eval", "episodes=1"]  # fmt: skip
        for s in TINY:
            cmd += ["--set", s]
        done = subprocess.run([*head_host, *cmd], capture_output=True, text=True, timeout=150, env=cluster_env())
        assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
        status = json.loads((out / "trials.json").read_text())
        assert len(status) == 4 and all(s["done"] for s in status.values())
        # Each trial records where it ran: both hosts' addresses and network namespaces appear.
        assert {s["node_ip"] for s in status.values()} == {HEAD, WORKER}
        assert len({s["netns"] for s in status.values()}) == 2
        for name in status:
            assert RunDir(out / name).evaluation.exists()  # one run directory each, on the disk both hosts share
    finally:
        for n in reversed(nodes):
            stop(n)
        subprocess.run(["rm", "-rf", temp], check=False)
