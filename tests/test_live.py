"""Live training over real DDS: lockstep sim+policy pairs in namespaces, ``morph-train --live`` as its own
process, weights on the wire, faults (a sim killed with SIGKILL and restarted, the trainer killed and resumed).

Small batches (128 samples) and short episodes keep it to a minute or two on 2 cores. Runs inside a private
network namespace (``scripts/test.sh``).
"""

from __future__ import annotations

import csv
import dataclasses
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from rclpy.serialization import deserialize_message
from std_msgs.msg import Int64MultiArray, UInt8MultiArray
from trajectory_msgs.msg import JointTrajectory

from morph_core.algo.checkpoint import load_training_state
from morph_core.algo.run_dir import RunDir
from morph_core.algo.small_runs import options_of, small
from morph_core.algo.train import TrainConfig
from morph_core.msgs.episode_start import unpack_episode_start
from morph_core.msgs.policy_weights import unpack_policy_weights
from morph_core.msgs.stream_chunk import MAX_CHUNK_BYTES, unpack_stream_chunk
from morph_core.msgs.stream_chunk import TOPIC as CHUNK_TOPIC
from morph_core.protocol.transitions import TransitionAssembler
from morph_ros_util.processes import NodeProcess, node_command
from trainer.live.learner import LIVE_LEARNING_RATE
from trainer.live.trainer_node import (
    CHUNK_QOS,
    DATA_TOPICS,
    EPISODE_QOS,
    STREAM_TOPICS,
    WEIGHTS_QOS,
    WEIGHTS_TOPIC,
    chunk_message,
)

pytestmark = pytest.mark.slow  # every test here starts processes (nodes, bring-ups, installs)

STARTUP = 120.0
SMALL = [*options_of(small(num_envs=1, num_steps=128, minibatch_size=64, update_epochs=1, checkpoint_interval=128)),
         "--episode-steps", "60", "--silence-timeout", "2"]  # fmt: skip


class Proc(NodeProcess):
    """A process whose output goes to a log file (``morph_ros_util.processes``); the trainer may take a while
    to save and end."""

    def stop(self, sig=signal.SIGTERM) -> int:
        return super().stop(sig, timeout=20)


def same_record(a, b) -> bool:
    """Two records of one type with equal fields, arrays bit for bit."""
    if type(a) is not type(b):
        return False
    pairs = [(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a)]
    return all(np.array_equal(x, y) if isinstance(x, np.ndarray) else x == y for x, y in pairs)


def reads(listen: str) -> list[str]:
    """The trainer's option for where it reads the pairs' messages: their topics or their policy nodes' chunks."""
    return ["--stream-chunks", "true" if listen == "stream_chunks" else "false"]


def Trainer(namespaces: list[str], out: Path, log_path: Path, key, *extra: str, prefix: list[str] = ()) -> Proc:  # noqa: N802
    """``morph-train --live`` as a process, signing with ``key`` (conftest's ``TrainerKey``)."""
    cmd = [*prefix, sys.executable, "-m", "trainer.cli.train", "--live", "--namespaces", *namespaces,
           "--out", str(out), "--signing-key", str(key.path), *SMALL, *extra]  # fmt: skip
    return Proc(cmd, log_path)


def node(module: str, ns: str, params: dict, log_path: Path, prefix: list[str] = ()) -> Proc:
    return Proc(node_command(module, ns, params, prefix), log_path)


def start_pair(ns: str, seed: int, checkpoint: Path, tmp_path: Path, key, which=("sim", "policy"), prefix=(),
               body: dict | None = None) -> dict:  # fmt: skip
    """A lockstep sim and a sampling policy node in ``ns``; the node trusts ``key`` (conftest's ``TrainerKey``).
    ``body``: the sim's body parameters (default chains of 2..10 joints)."""
    procs = {}
    if "sim" in which:
        body = dict(min_joints=2, max_joints=10) if body is None else body
        procs["sim"] = node("swimmer_sim_node.sim_node", ns, dict(lockstep=True, real_time_factor=0.0,
                                   effort_timeout=1.0, seed=seed, **body),
                                   tmp_path / f"sim{ns.replace('/', '_')}_{seed}.log", prefix)  # fmt: skip
    if "policy" in which:
        params = dict(deterministic=False, seed=seed, checkpoint=str(checkpoint), trusted_keys=key.trusted)
        procs["policy"] = node(
            "morph_policy_node.policy_node", ns, params, tmp_path / f"policy{ns.replace('/', '_')}.log", prefix
        )
    return procs


class WeightsWatch:
    """The versions (and run ids) a subscriber of one namespace's weights topic receives."""

    def __init__(self, probe, ns: str):
        self.got: list[tuple[int, str]] = []
        probe.node.create_subscription(UInt8MultiArray, f"{ns}/{WEIGHTS_TOPIC}", self._on, WEIGHTS_QOS)

    def _on(self, msg) -> None:
        w = unpack_policy_weights([d.label for d in msg.layout.dim], [d.size for d in msg.layout.dim], msg.data)
        self.got.append((w.version, w.metadata["run"]))

    @property
    def version(self) -> int:
        return self.got[-1][0] if self.got else -1


def progress(out: Path) -> list[dict]:
    path = RunDir(out).progress
    return list(csv.DictReader(open(path))) if path.exists() else []


@pytest.mark.timeout(300)
# Two bring-ups, not three: the user's key rides with the chunks (each bring-up is ~1 min of the suite).
@pytest.mark.parametrize("listen, own_key", [("topics", False), ("stream_chunks", True)],
                         ids=["topics", "stream_chunks_users_key"])  # fmt: skip
def test_the_bringup_starts_pairs_and_trainer_and_stops_when_it_is_done(tmp_path, listen, own_key):
    """``python -m trainer.live.bringup`` (what ``scripts/live.sh`` runs): K = 2 pairs paced at real time (its
    default) and the trainer, which updates on both (reading their topics or their policy nodes' chunks) and
    ends the bring-up. With the user's key given to the trainer (``-- --signing-key KEY``) the nodes trust
    that key (they trusted the run's own alone and refused the weights once a second)."""
    from morph_core.protocol.trust import write_key_pair

    out = tmp_path / "run"
    trainer_options = [o for o in SMALL if o not in ("--episode-steps", "60")] + reads(listen)
    if own_key:
        user = write_key_pair(tmp_path / "my_key")
        trainer_options += ["--signing-key", str(tmp_path / "my_key")]
    cmd = [sys.executable, "-m", "trainer.live.bringup", "--pairs", "2", "--out", str(out), "--max-updates", "2",
           "--episode-steps", "60", "--startup-timeout", str(STARTUP), "--timeout", "200",
           "--", *trainer_options]  # fmt: skip
    bringup = Proc(cmd, tmp_path / "bringup.log")
    try:
        bringup.proc.wait(timeout=240)
    finally:
        bringup.stop()
    log = bringup.log()
    assert bringup.proc.returncode == 0 and "2 pairs running" in log and "timed out" not in log, log[-3000:]
    rows = progress(out)
    assert len(rows) == 2 and all(int(r["batch_size"]) >= 128 for r in rows), log[-3000:]
    assert max(int(r["pairs"]) for r in rows) == 2
    assert all(f"pair /swimmer{i} is running" in log for i in range(2))
    # The run's own key: the trainer signed with it, each node trusted it and took the signed versions.
    fingerprint = log.split("signing the weights with ")[1].split()[0]
    assert (fingerprint == user.fingerprint) if own_key else "my_key" not in log
    assert log.count(f"trusting weights signed by {fingerprint}") == 2
    assert log.count(f"signed by {fingerprint} received") >= 2 and "UNSIGNED" not in log


@pytest.mark.timeout(300)
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl_c", "sigterm"])
def test_stopping_the_bringup_is_quiet(tmp_path, sig):
    """Ctrl-C (or a SIGTERM to the group) reaches every process: the nodes end 0, and that is a stop, not a node
    to restart (it logged "sim_node ... ended (0): restarting it"), and no KeyboardInterrupt traceback."""
    out = tmp_path / "run"
    trainer_options = [o for o in SMALL if o not in ("--episode-steps", "60")]
    cmd = [sys.executable, "-m", "trainer.live.bringup", "--pairs", "1", "--out", str(out), "--max-updates", "50",
           "--startup-timeout", str(STARTUP), "--timeout", "250", "--", *trainer_options]  # fmt: skip
    log_path = tmp_path / "bringup.log"
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            deadline = time.monotonic() + STARTUP
            while "pair /swimmer0 is running" not in log_path.read_text(errors="replace"):
                assert proc.poll() is None and time.monotonic() < deadline, log_path.read_text(errors="replace")
                time.sleep(0.5)
            os.killpg(proc.pid, sig)  # the terminal's Ctrl-C: the whole process group
            proc.wait(timeout=60)
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    text = log_path.read_text(errors="replace")
    assert "restarting it" not in text and "Traceback" not in text, text[-3000:]


@pytest.mark.timeout(400)
@pytest.mark.parametrize("listen", ["topics", "stream_chunks"])
def test_trainer_on_another_host_over_a_veth_link(
    two_hosts, namespace, tmp_path, untrained_checkpoint, trainer_key, listen
):
    """A pair on one host, the trainer on the other: the veth link is the only path between them. The trainer
    can only update on samples that crossed it: on the pair's topics, or only in its policy node's chunks."""
    import time

    pair_host, trainer_host = two_hosts
    p0 = f"{namespace}/p0"
    out = tmp_path / "run"
    procs = [Trainer([p0], out, tmp_path / "trainer.log", trainer_key, "--max-updates", "2", *reads(listen),
                     prefix=trainer_host)]  # fmt: skip
    pair = start_pair(p0, 0, untrained_checkpoint, tmp_path, trainer_key, prefix=pair_host)
    procs += pair.values()
    try:
        deadline = time.monotonic() + STARTUP
        while procs[0].alive() and time.monotonic() < deadline:
            time.sleep(0.5)
        assert procs[0].proc.returncode == 0, procs[0].log()[-3000:]
        rows = progress(out)
        assert len(rows) == 2 and all(int(r["batch_size"]) >= 128 for r in rows)
        # No --learning-rate given: the live trainer's own default, not the paper's (stale samples).
        assert {float(r["learning_rate"]) for r in rows} == {LIVE_LEARNING_RATE} != {TrainConfig().learning_rate}
        assert f"pair {p0} is running" in procs[0].log()
        links = subprocess.run([*trainer_host, "ip", "-o", "link"], capture_output=True, text=True).stdout
        assert "vB" in links and "vA" not in links
    finally:
        for p in procs:
            p.stop()


@pytest.mark.timeout(300)
def test_a_policy_node_streams_its_messages_in_chunks(probe, namespace, tmp_path, untrained_checkpoint, trainer_key):
    """stream_chunks: what the policy node received and sent, in its order, within one datagram per chunk; the
    trainer's decoders and assembler make whole transitions of it."""
    p0 = f"{namespace}/p0"
    chunks = probe.collect(UInt8MultiArray, f"{p0}/{CHUNK_TOPIC}", CHUNK_QOS)
    infos = probe.collect(JointTrajectory, f"{p0}/policy_info")
    pair = start_pair(p0, 0, untrained_checkpoint, tmp_path, trainer_key)
    try:
        probe.spin_until(lambda: len(chunks) >= 20, STARTUP, "20 stream chunks")
        probe.spin_for(0.5)  # the topic's own messages of the last chunk
    finally:
        for p in pair.values():
            p.stop()
    unpacked = [unpack_stream_chunk(c.data) for c in chunks]
    sequences = [seq for seq, _ in unpacked]
    assert sequences == list(range(sequences[0], sequences[0] + len(chunks)))
    assert all(len(c.data) <= MAX_CHUNK_BYTES for c in chunks)
    entries = [e for _, es in unpacked for e in es]
    assert {e.topic for e in entries} >= set(DATA_TOPICS)
    decoders = STREAM_TOPICS
    # Decoded as the trainer decodes chunks, and as rclpy decodes the topics: the same records.
    records = [decoders[e.topic][1](chunk_message(e), e.log_ns) for e in entries]
    by_rclpy = [decoders[e.topic][1](deserialize_message(e.data, decoders[e.topic][0]), e.log_ns) for e in entries]
    assert all(same_record(a, b) for a, b in zip(records, by_rclpy, strict=True))
    assembler = TransitionAssembler()
    transitions = assembler.push_many(records) + assembler.flush()
    assert len(transitions) >= 50 and all(t.has_policy_info for t in transitions)
    assert assembler.skips.steps_skipped == 0 and assembler.stats.boundaries_stamp_gap == 0
    # The very messages that went out on policy_info (CDR padding may differ), each after the state it answers.
    direct = [repr(m) for m in infos]
    streamed = [repr(deserialize_message(e.data, JointTrajectory)) for e in entries if e.topic == "policy_info"]
    assert streamed and set(streamed) <= set(direct), (len(streamed), len(set(streamed) - set(direct)), len(direct))
    seen_states = set()
    for e, r in zip(entries, records, strict=True):
        if e.topic == "joint_states":
            seen_states.add(r.stamp_ns)
        elif e.topic == "policy_info":
            assert r.stamp_ns in seen_states


@pytest.mark.timeout(600)
@pytest.mark.parametrize("listen", ["topics", "stream_chunks"])
def test_live_training_survives_a_killed_sim_and_a_killed_trainer(
    probe, namespace, tmp_path, untrained_checkpoint, trainer_key, listen
):
    p0, p1 = f"{namespace}/p0", f"{namespace}/p1"
    out = tmp_path / "run"
    weights = WeightsWatch(probe, p0)
    starts = []
    probe.node.create_subscription(Int64MultiArray, f"{p0}/episode_start", starts.append, EPISODE_QOS)
    trainer = Trainer([p0, p1], out, tmp_path / "trainer.log", trainer_key, *reads(listen))
    pairs = [start_pair(p, i, untrained_checkpoint, tmp_path, trainer_key) for i, p in enumerate((p0, p1))]
    procs = [trainer, *pairs[0].values(), *pairs[1].values()]

    def waiting(what: str):  # a timeout says what was awaited and shows the (current) trainer's log then
        return lambda: f"{what}; trainer log:\n{trainer.log()[-6000:]}"

    try:
        probe.spin_until(lambda: weights.version >= 0, STARTUP, waiting("the initial weights (version 0)"))
        probe.spin_until(lambda: weights.version >= 2, STARTUP, waiting("2 updates"))
        run_id = weights.got[0][1]
        # Versions arrive in order (each again every --weights-period s); a probe that matches late (a loaded
        # machine) first gets the latched latest one, and keep-last-1 may skip a version it was too slow to take.
        got = [v for v, _ in weights.got]
        assert got == sorted(got), got
        assert {r for _, r in weights.got} == {run_id}
        rows = progress(out)
        assert [int(r["version"]) for r in rows] == list(range(1, len(rows) + 1))
        assert all(int(r["batch_size"]) >= 128 and int(r["pairs"]) in (1, 2) for r in rows), rows
        # A pair that joins after an update began (a loaded machine) counts from the next one.
        probe.spin_until(lambda: int(progress(out)[-1]["pairs"]) == 2, STARTUP, waiting("an update with both pairs"))

        # The sim of p1 dies mid-episode: its partial episode is dropped, training goes on with p0.
        # (Counted from now: a pair may also go silent and rejoin while the sims start up.)
        silent, running = trainer.log().count(f"pair {p1} silent"), trainer.log().count(f"pair {p1} is running")
        pairs[1]["sim"].proc.kill()
        noticed = waiting("the trainer noticing p1 gone")
        probe.spin_until(lambda: trainer.log().count(f"pair {p1} silent") > silent, 30, noticed)
        n = len(progress(out))
        probe.spin_until(lambda: len(progress(out)) >= n + 2, STARTUP, waiting("2 updates on p0 alone"))
        assert int(progress(out)[-1]["pairs"]) == 1, waiting("the last update on p0 alone")()
        # It comes back: taken back (episode length set, reset), training on both again.
        pairs[1]["sim"].stop()
        back = start_pair(p1, 1, untrained_checkpoint, tmp_path, trainer_key, which=("sim",))
        procs.append(back["sim"])
        taken_back = waiting("p1 taken back")
        probe.spin_until(lambda: trainer.log().count(f"pair {p1} is running") > running, STARTUP, taken_back)
        probe.spin_until(lambda: int(progress(out)[-1]["pairs"]) == 2, STARTUP, waiting("an update with both pairs"))

        # The trainer dies; the nodes keep running; --resume continues from its last state and re-publishes it.
        trainer.stop(signal.SIGKILL)
        saved = load_training_state(RunDir(out).state)[1]["counters"]
        steps = [int(r["global_step"]) for r in progress(out) if int(r["global_step"]) <= saved["global_step"]]
        saved = saved["version"]
        probe.spin_for(1.0)  # what the killed trainer sent is in
        assert all(p.alive() for pair in pairs for p in pair.values() if p is not pairs[1]["sim"])
        n = len(weights.got)
        trainer = Trainer([p0, p1], out, tmp_path / "trainer2.log", trainer_key, "--resume", *reads(listen))
        procs.append(trainer)
        probe.spin_until(lambda: len(weights.got) > n, STARTUP, waiting("the resumed trainer's weights"))
        # It resumes at the saved version, of the same run. (The probe may first hear a later one: on a
        # loaded machine it matches the new publisher after a few fast updates, and keep-last-1 latches
        # only the latest.)
        probe.spin_until(lambda: "resumed at version" in trainer.log(), STARTUP, waiting("the resume line"))
        assert f"resumed at version {saved} " in trainer.log(), trainer.log()
        assert weights.got[n][1] == run_id and weights.got[n][0] >= saved
        probe.spin_until(lambda: weights.version >= saved + 2, STARTUP, waiting("2 updates after resume"))
        after = [int(r["global_step"]) for r in progress(out)]
        assert after[: len(steps)] == steps and after == sorted(set(after)) and len(after) >= len(steps) + 2
    finally:
        for p in procs:
            p.stop()
    # The trainer drove the episodes: time-limited (episode_steps 60 set at run time), lengths redrawn.
    records = [unpack_episode_start(0, m.layout.dim[0].label, m.data) for m in starts]
    assert any(r.cause == "steps" for r in records) and any(r.cause == "reset" for r in records)
    assert len({r.num_joints for r in records}) >= 2 and all(2 <= r.num_joints <= 10 for r in records)
    assert "dropped its partial episode" in Path(tmp_path / "trainer.log").read_text()


@pytest.mark.timeout(400)
@pytest.mark.parametrize("listen", ["topics", "stream_chunks"])
def test_live_training_on_branched_swimmers_with_shuffled_joints(
    probe, namespace, tmp_path, untrained_checkpoint, trainer_key, listen
):
    """A pair whose sim draws Y and star swimmers and lists their joints in a new order every state: the
    trainer reads each state on its body's tree (robot_description, from its topic or the policy node's
    chunks) and updates on trees, and the policy node takes the new weights."""
    ns = f"{namespace}/t0"
    out = tmp_path / "run"
    weights = WeightsWatch(probe, ns)
    spec = "y:1-2x2,star:3x1-2"  # the trainer's --bodies: its log splits the returns over chains and trees
    trainer = Trainer([ns], out, tmp_path / "trainer.log", trainer_key, "--bodies", spec, *reads(listen))
    body = dict(topology=spec, shuffle_joints=True)
    procs = [trainer, *start_pair(ns, 4, untrained_checkpoint, tmp_path, trainer_key, body=body).values()]
    try:
        probe.spin_until(lambda: weights.version >= 2, STARTUP + 120, lambda: trainer.log()[-6000:])
    finally:
        for p in procs:
            p.stop()
    rows = progress(out)
    assert len(rows) >= 2 and all(int(r["batch_size"]) >= 128 for r in rows), trainer.log()[-3000:]
    assert "return_trees" in rows[0] and any(r["return_trees"] not in ("", "nan") for r in rows), rows
    assert all(r["return_chains"] in ("", "nan") for r in rows), rows  # every body a tree: no chain step


# -- the policy node's side: weights adopted, late joiners, bad weights ---------------------------------------------
def weights_msg(version: int, log_std: float, key, seed: int = 0, damage: str = ""):
    """A weights message for a fresh policy whose log-std is ``log_std`` (visible in every policy_info), signed
    with ``key`` (conftest's ``TrainerKey``) as it is, damage included."""
    import torch
    from safetensors.torch import save as torch_save
    from std_msgs.msg import MultiArrayDimension

    from morph_core.msgs.policy_weights import pack_policy_weights
    from morph_core.policy.actor_critic import GraphActorCritic

    torch.manual_seed(seed)
    policy = GraphActorCritic()
    with torch.no_grad():
        policy.log_std.fill_(log_std)
    tensors = {k: v.detach().clone().contiguous() for k, v in policy.state_dict().items()}
    dims, data = pack_policy_weights(version, dataclasses.asdict(policy.config), torch_save(tensors), {"run": "test"})
    if damage == "nan":
        first = next(iter(tensors))
        tensors[first].view(-1)[0] = float("nan")
        data = torch_save(tensors)
        dims[0] = ("safetensors", len(data), len(data))
    elif damage == "shape":
        first = next(iter(tensors))
        tensors[first] = torch.zeros(2, 2)
        data = torch_save(tensors)
        dims[0] = ("safetensors", len(data), len(data))
    elif damage == "json":
        dims[1] = ("{not json", 0, 0)
    dims = key.sign(dims, data) if damage != "json" else dims
    msg = UInt8MultiArray()
    msg.layout.dim = [MultiArrayDimension(label=label, size=size, stride=stride) for label, size, stride in dims]
    msg.data = data
    return msg


class InfoWatch:
    """(version tag, log-std) of each policy_info a namespace publishes."""

    def __init__(self, probe, ns: str):
        from trajectory_msgs.msg import JointTrajectory

        from morph_core.msgs.policy_weights import parse_policy_version

        self.got: list[tuple[int | None, float]] = []
        self._parse = parse_policy_version
        probe.node.create_subscription(JointTrajectory, f"{ns}/policy_info", self._on, 100)

    def _on(self, msg) -> None:
        self.got.append((self._parse(msg.header.frame_id), float(msg.points[0].accelerations[0])))

    def shows(self, version: int, log_std: float) -> bool:
        return bool(self.got) and self.got[-1][0] == version and abs(self.got[-1][1] - log_std) < 1e-6


class Pusher:
    """Weights on each namespace as the live trainer sends them: published now, then again every half second
    (policy nodes read best effort, so re-publication is how a late node gets them)."""

    def __init__(self, probe, spaces: list[str]):
        self.pubs = {ns: probe.node.create_publisher(UInt8MultiArray, f"{ns}/{WEIGHTS_TOPIC}", WEIGHTS_QOS)
                     for ns in spaces}  # fmt: skip
        self.latest: dict[str, UInt8MultiArray] = {}
        probe.node.create_timer(0.5, self._again)

    def push(self, ns: str, msg, keep: bool = True) -> None:
        self.pubs[ns].publish(msg)
        if keep:
            self.latest[ns] = msg

    def _again(self) -> None:
        for ns, msg in self.latest.items():
            self.pubs[ns].publish(msg)


@pytest.mark.timeout(300)
def test_weights_adopted_by_two_policy_nodes_late_joiner_and_bad_weights_kept_out(
    probe, namespace, tmp_path, untrained_checkpoint, trainer_key
):
    spaces = [f"{namespace}/p{i}" for i in range(3)]
    pusher = Pusher(probe, spaces)
    infos = [InfoWatch(probe, ns) for ns in spaces]
    procs = []
    try:
        for i, ns in enumerate(spaces[:2]):
            procs.append(start_pair(ns, i, untrained_checkpoint, tmp_path, trainer_key))
        probe.spin_until(lambda: all(w.got for w in infos[:2]), STARTUP, "both policies answering")
        assert all(w.got[-1][0] is None for w in infos[:2])  # a checkpoint file: no weights version
        # pushed: both adopt version 1 between two answers; policy_info says so
        for ns in spaces:
            pusher.push(ns, weights_msg(1, -1.25, trainer_key))
        probe.spin_until(lambda: all(w.shows(1, -1.25) for w in infos[:2]), 30, "version 1 in both policy_info")
        # a late policy node (the third pair) gets the latest weights
        procs.append(start_pair(spaces[2], 2, untrained_checkpoint, tmp_path, trainer_key))
        probe.spin_until(lambda: infos[2].shows(1, -1.25), STARTUP, "the late node running version 1")
        # malformed weights: each rejected with its reason, version 1 kept
        policy0 = procs[0]["policy"]
        for damage, reason in (("nan", "NaN or inf"), ("shape", "has shape"), ("json", "not JSON")):
            bad = weights_msg(5, -0.5, trainer_key, damage=damage)
            for _ in range(40):  # best effort: sent until the node has said why it refused it
                pusher.push(spaces[0], bad, keep=False)
                probe.spin_for(0.5)
                if reason in policy0.log():
                    break
            assert reason in policy0.log(), policy0.log()[-2000:]
        n = len(infos[0].got)
        probe.spin_until(lambda: len(infos[0].got) > n + 20, 30, "more answers")
        assert all(w == (1, -1.25) for w in infos[0].got[n:]), infos[0].got[n:][:5]
        assert "current policy kept" in policy0.log()
        # an old version of the same run is refused as a replay; the next good one is taken
        pusher.push(spaces[0], weights_msg(0, -2.0, trainer_key), keep=False)
        pusher.push(spaces[0], weights_msg(2, -0.75, trainer_key))
        probe.spin_until(lambda: infos[0].shows(2, -0.75), 30, "version 2 after the bad ones")
        assert not any(w == (0, -2.0) for w in infos[0].got)
        assert infos[1].shows(1, -1.25)  # pushed to p0 only
    finally:
        for pair in procs:
            for p in pair.values():
                p.stop()


@pytest.mark.timeout(300)
@pytest.mark.parametrize("listen", ["topics", "stream_chunks"])
def test_the_trainer_reads_branched_swimmers_on_their_described_trees(tmp_path, untrained_checkpoint, trainer_key,
                                                                       listen):  # fmt: skip
    """The live trainer's own input handlers (no pair running: the messages are the ones a tree sim and a policy
    node publish, from protocol.loopback, serialized as on the wire): robot_description taken from its topic or
    from the chunks, every state read on its tree by name, whatever order it lists the joints in."""
    import array

    import rclpy
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
    from rclpy.serialization import deserialize_message

    from morph_core.env.bodies import star_parents, swimmer_tree, y_parents
    from morph_core.msgs.stream_chunk import ChunkWriter
    from morph_core.policy.actor_critic import GraphActorCritic
    from morph_core.protocol.loopback import SamplingController, record_episodes
    from morph_core.protocol.transition_batch import TransitionBatch
    from morph_core.protocol.transitions import SkipCounts, assemble
    from trainer.codec import TYPESTORE, record_message
    from trainer.live.learner import LiveOptions, live_train_config
    from trainer.live.trainer_node import LiveTrainer

    trees = (swimmer_tree(star_parents(2, 2)), swimmer_tree(y_parents(1, 2)))
    policy = GraphActorCritic.load(untrained_checkpoint)
    records = record_episodes(SamplingController(policy, 2), ((trees[0], 30), (trees[1], 25)), describe=True,
                              shuffle_seed=3, name_efforts=True)  # fmt: skip
    wire = []  # (topic, log_ns, CDR)
    for r in records:
        topic, msg = record_message(r)
        wire.append((topic, r.log_ns, bytes(TYPESTORE.serialize_cdr(msg, msg.__msgtype__))))
    cfg = live_train_config(num_envs=1, num_steps=128, minibatch_size=64, compile=False, tensorboard=False,
                            progress_bar=False)  # fmt: skip
    options = LiveOptions(("/p",), tmp_path / "run", stream_chunks=listen == "stream_chunks")
    rclpy.init()
    node = None
    try:
        node = LiveTrainer(cfg, options, trainer_key.signer)
        pair = node.pairs["/p"]
        if listen == "stream_chunks":
            writer, chunks = ChunkWriter(), []
            for topic, log_ns, data in wire:
                chunks.append(writer.add(topic, log_ns, data))
            chunks.append(writer.take())
            on_chunk = node._chunk_handler(pair)
            for chunk in filter(None, chunks):
                on_chunk(UInt8MultiArray(data=array.array("B", chunk)))
        else:
            # Latched as the sim publishes it, and subscribed before the states (taken first when both wait).
            subs = [sub.topic_name for sub in node.subscriptions]
            assert subs.index("/p/robot_description") < subs.index("/p/joint_states")
            qos = next(sub.qos_profile for sub in node.subscriptions if sub.topic_name == "/p/robot_description")
            assert (qos.durability, qos.reliability, qos.depth) == (DurabilityPolicy.TRANSIENT_LOCAL,
                                                                    ReliabilityPolicy.RELIABLE, 1)  # fmt: skip
            for topic, log_ns, data in wire:
                msg_type, decode = STREAM_TOPICS[topic]
                node._take(pair, decode, deserialize_message(data, msg_type), log_ns)
        assert not pair.decode_errors and pair.assembler.stats.descriptions == 2
        with node._lock:
            transitions = pair.episodes.episode + pair.assembler.flush()
        assert pair.assembler.skips == SkipCounts()
    finally:
        if node is not None:
            node.close()
            node.destroy_node()
        rclpy.try_shutdown()
    got = TransitionBatch.from_transitions(transitions)
    assert np.bincount(got.episode).tolist() == [30, 25]
    for k, v in assemble(records).batch.arrays().items():
        np.testing.assert_array_equal(got.arrays()[k], v, err_msg=k)
    for t in transitions:
        assert t.names == trees[t.episode].names and t.parents.tolist() == trees[t.episode].parents.tolist()


def test_a_pair_gone_silent_at_a_body_swap_keeps_its_complete_episodes(tmp_path, untrained_checkpoint, trainer_key):
    """The trainer's own handlers and its drop (no pair running, no spinning): five 60-step episodes of five
    bodies, then a new body's first state and silence (a policy stalled at the swap). The node's assembler holds
    them all unjudged (SETTLE_STATES); the drop hands every complete episode to the pool and loses nothing."""
    import rclpy

    from morph_core.policy.actor_critic import GraphActorCritic
    from morph_core.protocol.loopback import SamplingController, record_episodes
    from trainer.codec import TYPESTORE, record_message
    from trainer.live.learner import LiveOptions, live_train_config
    from trainer.live.trainer_node import LiveTrainer

    policy = GraphActorCritic.load(untrained_checkpoint)
    bodies = ((3, 60), (5, 60), (4, 60), (6, 60), (3, 60), (5, 1))
    records = record_episodes(SamplingController(policy, 2), bodies, seed=3, describe=True)
    last_state = max(i for i, r in enumerate(records) if type(r).__name__ == "JointStateRecord")
    cfg = live_train_config(num_envs=1, num_steps=128, minibatch_size=64, compile=False, tensorboard=False,
                            progress_bar=False, min_joints=2, max_joints=10)  # fmt: skip
    rclpy.init()
    node = None
    try:
        node = LiveTrainer(cfg, LiveOptions(("/p",), tmp_path / "run"), trainer_key.signer)
        pair = node.pairs["/p"]
        for r in records[:last_state]:  # the new body's second state never comes
            topic, msg = record_message(r)
            msg_type, decode = STREAM_TOPICS[topic]
            node._take(pair, decode, deserialize_message(bytes(TYPESTORE.serialize_cdr(msg, msg.__msgtype__)),
                                                         msg_type), r.log_ns)  # fmt: skip
        assert node.learner.pool_size == 0 and pair.assembler.stats.transitions == 0  # all unjudged yet
        with node._lock:
            node._drop(pair, "silent (test)")
        assert pair.dropped_partial == 0 and pair.drops == 1
        assert node.learner.pool_size == 5 * 60 and node.learner.dropped_no_info == 0
    finally:
        if node is not None:
            node.close()
            node.destroy_node()
        rclpy.try_shutdown()
