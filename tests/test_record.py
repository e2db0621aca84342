"""morph-record at topic level: real sim, policy and recorder processes on real Fast DDS, the bag read back.

Runs inside a private network namespace (``scripts/test.sh``).
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, qos_profile_sensor_data
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore
from ruamel.yaml import YAML
from std_msgs.msg import Header
from trajectory_msgs.msg import JointTrajectory

from morph_core.env.urdf import swimmer_urdf
from morph_core.msgs.records import (
    DescriptionRecord,
    EffortRecord,
    EpisodeStartRecord,
    JointStateRecord,
    PolicyInfoRecord,
)
from morph_core.policy.tree import read_urdf
from morph_core.protocol.transitions import TransitionConfig
from morph_ros_util.processes import NodeProcess, ros_arguments
from trainer.bags.cli import main as bag_main
from trainer.bags.contents import summarize_bag
from trainer.bags.io import BagError, BagReader
from trainer.bags.record import KNOWN_TYPES
from trainer.bags.writer import jazzy_metadata_problems
from trainer.codec import DESCRIPTION_TOPIC

pytestmark = pytest.mark.slow  # every test here starts processes (nodes, bring-ups, installs)

STARTUP = 60.0
STEP_NS = 40_000_000
TOPICS = ["episode_start", "joint_states", "odom", "effort_commands", "policy_info", "/clock", "probe_episodes"]
JAZZY = get_typestore(Stores.ROS2_JAZZY)


def _start_loop(launch, checkpoint, joints=4):
    sim = launch("swimmer_sim_node", num_joints=joints, lockstep=True, real_time_factor=0.0, effort_timeout=2.0)
    policy = launch("morph_policy_node", checkpoint=str(checkpoint), deterministic=False)
    return sim, policy


def _read(bag, namespace):
    reader = BagReader(bag, namespace=namespace, episode_topic="probe_episodes")
    return reader.read(), reader.stats


def _check_loop(records):
    """The recorded closed loop is consistent: states on the 40 ms grid, every answer for a recorded state."""
    states = sorted({r.stamp_ns for r in records if isinstance(r, JointStateRecord)})
    assert states == list(range(states[0], states[-1] + 1, STEP_NS))  # no state missing in the middle
    answered = sorted({r.stamp_ns for r in records if isinstance(r, PolicyInfoRecord)})
    # policy_info carries the stamp of the state it answers: the same stamps over the span both cover
    # (the recorder's subscriptions match one by one, so either may start a little later)
    lo, hi = max(states[0], answered[0]), min(states[-1], answered[-1])
    assert [a for a in answered if lo <= a <= hi] == [s for s in states if lo <= s <= hi]
    # ... and their overlap is most of the shorter of the two (discovery may start either topic seconds early)
    assert hi - lo >= 0.9 * min(answered[-1] - answered[0], states[-1] - states[0])
    # Every answer within the recorded states answers one of them (at the edges an answer can be
    # recorded without its state: it may overtake the state on the way to the recorder).
    # (Untagged efforts, the policy's 'silence' zeros when a loaded machine stalls the loop, answer no state.)
    efforts = {r.answers_ns for r in records if isinstance(r, EffortRecord) and r.answers_ns is not None}
    assert {e for e in efforts if states[0] <= e <= states[-1]} <= set(states)
    return states, answered


@pytest.mark.timeout(180)
def test_records_the_closed_loop(probe, launch, untrained_checkpoint, tmp_path, namespace):
    # A best-effort publisher of a stamped type the recorder knows only from the graph: a reliable
    # subscription would never match it.
    announce = probe.node.create_publisher(Header, "probe_episodes", qos_profile_sensor_data)
    infos = probe.collect(JointTrajectory, "policy_info", qos_profile_sensor_data)
    bag = tmp_path / "bag"
    recorder = launch("morph-record", output=str(bag), topics=TOPICS, chunk_size=16384)
    probe.spin_until(lambda: announce.get_subscription_count() > 0, STARTUP, "the recorder on probe_episodes")
    _start_loop(launch, untrained_checkpoint)

    # The recorder subscribes to each topic once it sees a publisher, topic by topic as discovery goes: count
    # from when it reads all four of the loop's topics (the sim and the policy node read some of them too).
    def recorder_reads(topic: str) -> bool:
        return any(i.node_name == "morph_record" for i in probe.node.get_subscriptions_info_by_topic(topic))

    loop_topics = [f"{namespace}/{t}" for t in ("joint_states", "odom", "effort_commands", "policy_info")]
    probe.spin_until(lambda: all(map(recorder_reads, loop_topics)) and infos, STARTUP, "the recorder on the loop")
    # A reader in the graph may still wait for the writer's side of the match (the graph shows no such thing):
    # the first announcement comes 150 states later, so the state it names is recorded.
    n0 = len(infos)
    for episode in range(3):
        n = n0 + 150 + 50 * episode
        probe.spin_until(lambda n=n: len(infos) >= n, STARTUP, f"{n} policy_info")
        announce.publish(Header(stamp=infos[-1].header.stamp, frame_id=f"episode={episode} num_joints=4"))
    probe.spin_until(lambda: len(infos) >= n0 + 320, STARTUP, "320 more policy_info messages")
    assert recorder.stop() == 0, recorder.log()
    assert "closed" in recorder.log()

    info = YAML(typ="safe").load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert jazzy_metadata_problems(info) == []
    assert info["version"] == 9 and info["storage_identifier"] == "mcap" and info["ros_distro"] == "jazzy"
    topics = {t["topic_metadata"]["name"]: t for t in info["topics_with_message_count"]}
    expected = {
        f"{namespace}/joint_states": "sensor_msgs/msg/JointState",
        f"{namespace}/odom": "nav_msgs/msg/Odometry",
        f"{namespace}/effort_commands": "std_msgs/msg/Float64MultiArray",
        f"{namespace}/policy_info": "trajectory_msgs/msg/JointTrajectory",
        f"{namespace}/probe_episodes": "std_msgs/msg/Header",
        "/clock": "rosgraph_msgs/msg/Clock",
    }
    if f"{namespace}/episode_start" in topics:  # the sim announces episodes
        expected[f"{namespace}/episode_start"] = "std_msgs/msg/Int64MultiArray"
    assert {n: t["topic_metadata"]["type"] for n, t in topics.items()} == expected, recorder.log()
    for name, msgtype in expected.items():
        meta = topics[name]["topic_metadata"]
        assert meta["type_description_hash"] == JAZZY.hash_rihs01(msgtype), name
        assert meta["serialization_format"] == "cdr"
        assert meta["offered_qos_profiles"], name
    sim_qos = topics[f"{namespace}/joint_states"]["topic_metadata"]["offered_qos_profiles"]
    assert [(q["reliability"], q["durability"]) for q in sim_qos] == [("reliable", "volatile")]
    probe_qos = topics[f"{namespace}/probe_episodes"]["topic_metadata"]["offered_qos_profiles"]
    assert [q["reliability"] for q in probe_qos] == ["best_effort"]

    records, stats = _read(bag, namespace)
    assert not stats.rejected and not stats.warnings
    for name in ("joint_states", "odom", "effort_commands", "policy_info"):
        assert stats.counts[name] == topics[f"{namespace}/{name}"]["message_count"], name
    # Discovery decides which topic the recorder hears first, so either count may lead by a few.
    assert stats.counts["policy_info"] >= 150 and stats.counts["joint_states"] >= 150
    assert stats.skipped["/clock"] == topics["/clock"]["message_count"] > 0
    states, answered = _check_loop(records)
    assert len(answered) >= 150
    starts = [r for r in records if isinstance(r, EpisodeStartRecord)]
    assert [(r.episode, r.num_joints) for r in starts] == [(0, 4), (1, 4), (2, 4)]
    assert all(r.stamp_ns in states for r in starts)
    assert {len(r.names) for r in records if isinstance(r, JointStateRecord)} == {4}

    if f"{namespace}/episode_start" in topics:
        # Latched by the sim: recorded transient-local, so even a recorder started late has episode 0.
        latched = topics[f"{namespace}/episode_start"]["topic_metadata"]["offered_qos_profiles"]
        assert [q["durability"] for q in latched] == ["transient_local"]
        sim_starts = [r for r in BagReader(bag, namespace=namespace).read() if isinstance(r, EpisodeStartRecord)]
        assert sim_starts and sim_starts[0].episode == 0 and sim_starts[0].num_joints == 4

    # The bytes are the publishers' own CDR: rosbags' reader decodes them with the Jazzy types too.
    with Reader(bag) as r:
        assert r.message_count == info["message_count"]
        first = next(m for c, _, m in r.messages() if c.topic.endswith("/policy_info"))
        assert len(JAZZY.deserialize_cdr(first, "trajectory_msgs/msg/JointTrajectory").joint_names) == 4


def _recorded(bag, namespace, topics) -> int:
    """The fewest messages of any of ``topics`` a reader gets from the bag now, while it is being written."""
    try:
        reader = BagReader(bag, namespace=namespace)
        reader.read()
    except BagError:  # no storage file yet, or not its first chunk
        return 0
    return min(reader.stats.counts[t] for t in topics)


@pytest.mark.timeout(180)
@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_sigkilled_recorder_leaves_a_readable_prefix(probe, launch, untrained_checkpoint, tmp_path, namespace, storage):
    bag = tmp_path / "bag"
    recorder = launch("morph-record", output=str(bag), storage=storage, chunk_size=4096, flush_period=0.2)
    _start_loop(launch, untrained_checkpoint)

    # Wait until a reader finds 60 states and 60 policy_info in the bag being written (MCAP: complete
    # chunks; sqlite3: committed), checking twice a second. Both: the recorder matches the two topics one
    # by one, so answers to states it never heard may come first.
    seen_live = [0]
    next_check = [0.0]

    def enough_on_disk() -> bool:
        if time.monotonic() >= next_check[0]:
            next_check[0] = time.monotonic() + 0.5
            seen_live[0] = _recorded(bag, namespace, ("joint_states", "policy_info"))
        return seen_live[0] >= 60

    probe.spin_until(enough_on_disk, 2 * STARTUP, "60 states and 60 policy_info readable from the live bag")
    recorder.proc.kill()
    recorder.proc.wait()
    assert not (bag / "metadata.yaml").exists()

    reader = BagReader(bag, namespace=namespace, required=("joint_states", "policy_info"))
    records = reader.read()
    assert any("no metadata.yaml" in w for w in reader.stats.warnings)
    assert not reader.stats.rejected
    # what was readable before the kill still is
    assert min(reader.stats.counts[t] for t in ("joint_states", "policy_info")) >= seen_live[0]
    # States on the 40 ms grid with none missing. (An answer may be in the bag before its state: the
    # policy's answer can overtake the sim's state on the way to the recorder, so the prefix cut at a
    # chunk or commit may hold efforts for states after its last one.)
    states = sorted({r.stamp_ns for r in records if isinstance(r, JointStateRecord)})
    assert states == list(range(states[0], states[-1] + 1, STEP_NS))
    assert len(states) >= 60


@pytest.mark.timeout(240)
def test_bringup_records_and_exits(untrained_checkpoint, tmp_path, namespace):
    bag = tmp_path / "bag"
    cmd = [sys.executable, "-m", "trainer.bags.record_bringup", "--out", str(bag), "--episodes", "2"]
    # Episodes long enough to outlast DDS matching the policy to the recorder (a lockstep loop can run
    # many steps before it completes: the sim may hear the policy first).
    cmd += ["--steps-per-episode", "100", "--joints", "3", "--namespace", namespace]
    cmd += ["--checkpoint", str(untrained_checkpoint), "--timeout", "150"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=220)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "timed out" not in done.stdout and f"bag {bag}" in done.stdout

    reader = BagReader(bag, namespace=namespace, required=("joint_states", "effort_commands", "policy_info"))
    records = reader.read()
    assert not reader.stats.rejected and not reader.stats.warnings
    if reader.stats.counts["episode_start"]:  # a sim with episodes: two announced, the third not recorded
        assert reader.stats.counts["episode_start"] == 2
    else:  # no episodes: 2 x 100 policy answers
        assert reader.stats.counts["policy_info"] == 200
    # How early policy_info starts is up to DDS: the sim may hear the policy before the recorder does
    # (the bring-up warns then); from there on every state is answered.
    assert reader.stats.counts["policy_info"] > 0
    _check_loop(records)
    assert {len(r.names) for r in records if isinstance(r, JointStateRecord)} == {3}
    info = YAML(typ="safe").load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert jazzy_metadata_problems(info) == []
    assert np.isfinite([r.log_prob for r in records if isinstance(r, PolicyInfoRecord)]).all()


@pytest.mark.timeout(120)
def test_announcements_heard_before_any_sim_starts(probe, launch, tmp_path, namespace):
    # A lockstep sim runs episodes within milliseconds of its start: a recorder that subscribed to the
    # announcements only once it saw the sim recorded data of episodes past max_episodes before hearing them.
    launch("morph-record", output=str(tmp_path / "bag"), max_episodes=1)
    topic = f"{namespace}/episode_start"

    def recorder_latched() -> bool:
        infos = [i for i in probe.node.get_subscriptions_info_by_topic(topic) if i.node_name == "morph_record"]
        return any(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in infos)

    probe.spin_until(recorder_latched, STARTUP, "the recorder reading the announcements, transient local")
    assert not probe.node.get_publishers_info_by_topic(topic)  # with no publisher in sight


@pytest.mark.timeout(240)
@pytest.mark.parametrize("subscribed", ["in_advance", "on_discovery"])
def test_a_late_recorder_records_the_latched_robot_description(
    probe, launch, untrained_checkpoint, tmp_path, namespace, subscribed, capsys
):
    """The sim latches its URDF once, before its first state: a recorder started long after still records it,
    subscribed in advance (a topic of known type) or once it saw the sim's publisher (with the offered QoS)."""
    infos = probe.collect(JointTrajectory, "policy_info", qos_profile_sensor_data)
    _start_loop(launch, untrained_checkpoint, joints=5)
    probe.spin_until(lambda: len(infos) >= 50, STARTUP, "the loop running (50 policy_info)")
    bag = tmp_path / "bag"
    params = {"output": str(bag)}
    if subscribed == "on_discovery":
        params["topic_types"] = [t for t in KNOWN_TYPES if not t.startswith(f"{DESCRIPTION_TOPIC}=")]
    recorder = launch("morph-record", **params)

    def recorder_reads(topic: str) -> bool:
        return any(i.node_name == "morph_record" for i in probe.node.get_subscriptions_info_by_topic(topic))

    loop_topics = [f"{namespace}/{t}" for t in (DESCRIPTION_TOPIC, "joint_states", "policy_info")]
    probe.spin_until(lambda: all(map(recorder_reads, loop_topics)), STARTUP, "the recorder on the loop")
    n = len(infos) + 100
    probe.spin_until(lambda: len(infos) >= n, STARTUP, "100 more policy_info")
    assert recorder.stop() == 0, recorder.log()

    info = YAML(typ="safe").load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert jazzy_metadata_problems(info) == []
    topics = {t["topic_metadata"]["name"]: t for t in info["topics_with_message_count"]}
    described = topics[f"{namespace}/{DESCRIPTION_TOPIC}"]
    assert described["topic_metadata"]["type"] == "std_msgs/msg/String" and described["message_count"] == 1
    offered = described["topic_metadata"]["offered_qos_profiles"]
    assert [(q["reliability"], q["durability"]) for q in offered] == [("reliable", "transient_local")]

    records = BagReader(bag, namespace=namespace).read()
    (description,) = [r for r in records if isinstance(r, DescriptionRecord)]
    assert description.text == swimmer_urdf(5)  # the sim's chain, as it published it at its start
    assert read_urdf(description.text).tree.names == tuple(f"motor{k}_rot" for k in range(1, 6))
    summary = summarize_bag(bag, TransitionConfig(), namespace)
    assert summary.descriptions == 1 and summary.described == ["chain-5"] and summary.stats.descriptions == 1
    assert summary.stats.transitions >= 50 and summary.skips.unknown_joint == summary.skips.missing_joint == 0
    assert summary.stats.boundaries_new_chain == 0  # the chain it describes is the one the states formed
    assert bag_main(["info", str(bag), "--namespace", namespace]) == 0
    assert "robot_description: 1 (chain-5)" in capsys.readouterr().out


@pytest.mark.timeout(120)
def test_morph_record_out_writes_there_and_a_sigterm_stops_it_quietly(tmp_path, namespace):
    """``morph-record --out DIR`` (the parameter output under every tool's name); SIGTERM closes the bag and
    says so, with no "Failed to publish log message to rosout" after the context was shut down."""
    log = tmp_path / "record.log"
    cmd = [str(Path(sys.executable).parent / "morph-record"), "--out", str(tmp_path / "bag"), *ros_arguments(namespace)]
    proc = NodeProcess(cmd, log)
    try:
        deadline = time.monotonic() + STARTUP
        while "recording" not in log.read_text() and time.monotonic() < deadline and proc.alive():
            time.sleep(0.1)
        assert proc.stop(signal.SIGTERM, timeout=30) == 0
    finally:
        proc.stop()
    text = log.read_text()
    assert f"into {tmp_path / 'bag'}" in text and "closed" in text, text
    assert "rosout" not in text and "Traceback" not in text, text
    assert (tmp_path / "bag" / "metadata.yaml").exists()
