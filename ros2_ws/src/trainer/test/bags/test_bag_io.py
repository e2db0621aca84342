"""Bags written for real (rosbags' own writer and trainer.bags.writer, MCAP and sqlite3, messages
serialized with the Jazzy type store) read back into records; every bad input gets a clear error."""

from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from ruamel.yaml import YAML

from morph_core.env.bodies import swimmer_tree
from morph_core.msgs.policy_info import pack_policy_info
from morph_core.msgs.records import (
    DescriptionRecord,
    EffortRecord,
    EpisodeStartRecord,
    JointStateRecord,
    OdometryRecord,
    PolicyInfoRecord,
)
from morph_core.msgs.stamps import answer_tag, from_ns
from morph_core.protocol.loopback import GaussianController, record_episodes
from trainer.bags.io import BagError, BagReader, read_bag
from trainer.bags.writer import BagTopic, BagWriter, BagWriterError, WriterOptions, jazzy_metadata_problems
from trainer.codec import TOPIC_TYPES, record_message

TS = get_typestore(Stores.ROS2_JAZZY)
T = TS.types
NS = "/robot"
STEP_NS = 40_000_000
NAMES = ["j0", "j1", "j2"]
INF = QosTime(9223372036, 854775807)
RELIABLE = Qos(
    QosHistory.UNKNOWN,
    0,
    QosReliability.RELIABLE,
    QosDurability.VOLATILE,
    INF,
    INF,
    QosLiveliness.AUTOMATIC,
    INF,
    False,
)
TYPES = {
    f"{NS}/episode_start": "std_msgs/msg/Header",
    f"{NS}/joint_states": "sensor_msgs/msg/JointState",
    f"{NS}/odom": "nav_msgs/msg/Odometry",
    f"{NS}/effort_commands": "std_msgs/msg/Float64MultiArray",
    f"{NS}/policy_info": "trajectory_msgs/msg/JointTrajectory",
    "/clock": "rosgraph_msgs/msg/Clock",
}


# -- messages as a lockstep sim + sampling policy would publish them ---------------------------
def _time(ns):
    sec, nanosec = from_ns(ns)
    return T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)


def _header(ns, frame_id=""):
    return T["std_msgs/msg/Header"](stamp=_time(ns), frame_id=frame_id)


def joint_state(k):
    pos = np.array([0.1 * k, -0.2, 0.3 + k]) / 10
    return T["sensor_msgs/msg/JointState"](
        header=_header(k * STEP_NS), name=NAMES, position=pos, velocity=pos * 2, effort=np.full(3, 0.5)
    )


def odometry(k):
    m = T["nav_msgs/msg/Odometry"]
    g = T
    pose = g["geometry_msgs/msg/PoseWithCovariance"](
        pose=g["geometry_msgs/msg/Pose"](
            position=g["geometry_msgs/msg/Point"](x=0.01 * k, y=-0.02 * k, z=0.0),
            orientation=g["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=np.sin(0.05 * k), w=np.cos(0.05 * k)),
        ),
        covariance=np.zeros(36),
    )
    twist = g["geometry_msgs/msg/TwistWithCovariance"](
        twist=g["geometry_msgs/msg/Twist"](
            linear=g["geometry_msgs/msg/Vector3"](x=0.3, y=-0.1, z=0.0),
            angular=g["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.7 * k),
        ),
        covariance=np.zeros(36),
    )
    return m(header=_header(k * STEP_NS, "odom"), child_frame_id="torso", pose=pose, twist=twist)


def efforts(k, tagged=True):
    sec, nanosec = from_ns(k * STEP_NS)
    dims = [T["std_msgs/msg/MultiArrayDimension"](label=answer_tag(sec, nanosec), size=3, stride=3)] if tagged else []
    layout = T["std_msgs/msg/MultiArrayLayout"](dim=dims, data_offset=0)
    return T["std_msgs/msg/Float64MultiArray"](layout=layout, data=np.array([0.1, -0.2, 0.3]) * (k % 5))


def policy_info(k, rng=None, points=True):
    action = np.array([0.2, -0.1, 0.4]) + 0.01 * k
    f = pack_policy_info(action, action * 0.5, -0.7)
    point = T["trajectory_msgs/msg/JointTrajectoryPoint"](
        positions=f["positions"],
        velocities=f["velocities"],
        accelerations=f["accelerations"],
        effort=f["effort"],
        time_from_start=T["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
    )
    return T["trajectory_msgs/msg/JointTrajectory"](
        header=_header(k * STEP_NS), joint_names=NAMES, points=[point] if points else []
    )


def episode_start(k, episode):
    return _header(k * STEP_NS, f"episode={episode} num_joints=3")


def clock(k):
    return T["rosgraph_msgs/msg/Clock"](clock=_time(k * STEP_NS))


def loop_messages(steps, episode_every=10, t0=1_000_000_000):
    """(topic, log_ns, msg) of a closed loop: per step the announcement (every ``episode_every``),
    clock, odom, joint state, then the policy's answer."""
    out, log = [], t0
    for k in range(steps):
        batch = []
        if k % episode_every == 0:
            batch.append((f"{NS}/episode_start", episode_start(k, k // episode_every)))
        batch += [
            ("/clock", clock(k)),
            (f"{NS}/odom", odometry(k)),
            (f"{NS}/joint_states", joint_state(k)),
            (f"{NS}/effort_commands", efforts(k)),
            (f"{NS}/policy_info", policy_info(k)),
        ]
        for topic, msg in batch:
            out.append((topic, log, msg))
            log += 1000
    return out


def ser(msg):
    return TS.serialize_cdr(msg, msg.__msgtype__)


def write_with_rosbags(path, messages, storage="mcap", types=TYPES):
    """A bag from another writer (rosbags' own Writer), as any rosbag2 tool would leave it."""
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        conns = {t: w.add_connection(t, ty, typestore=TS, offered_qos_profiles=[RELIABLE]) for t, ty in types.items()}
        for topic, log_ns, msg in messages:
            w.write(conns[topic], log_ns, msg if isinstance(msg, bytes) else ser(msg))
    return path


def write_with_bag_writer(path, messages, **options):
    w = BagWriter(path, WriterOptions(**options))
    ids = {t: w.add_topic(BagTopic(t, ty, (RELIABLE,))) for t, ty in TYPES.items()}
    for topic, log_ns, msg in messages:
        w.write(ids[topic], log_ns, ser(msg))
    return w.close()


def by_type(records, kind):
    return [r for r in records if isinstance(r, kind)]


# -- reading back -------------------------------------------------------------------------
@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_bag_from_another_writer_reads_into_records(tmp_path, storage):
    msgs = loop_messages(30)
    records, stats = read_bag(write_with_rosbags(tmp_path / "bag", msgs, storage), required=("joint_states",))

    assert stats.counts == {
        "episode_start": 3,
        "joint_states": 30,
        "odom": 30,
        "effort_commands": 30,
        "policy_info": 30,
    }
    assert stats.skipped == {"/clock": 30} and not stats.rejected and not stats.warnings
    logs = [r.log_ns for r in records]
    assert logs == sorted(logs) and logs == [m[1] for m in msgs if m[0] != "/clock"]

    states = by_type(records, JointStateRecord)
    assert [s.stamp_ns for s in states] == [k * STEP_NS for k in range(30)]
    np.testing.assert_array_equal(states[7].position, joint_state(7).position)
    np.testing.assert_array_equal(states[7].velocity, joint_state(7).velocity)
    assert states[7].names == tuple(NAMES) and states[7].effort.tolist() == [0.5] * 3

    odom = by_type(records, OdometryRecord)[4]
    assert odom.stamp_ns == 4 * STEP_NS and odom.x == pytest.approx(0.04) and odom.y == pytest.approx(-0.08)
    assert odom.orientation_xyzw == pytest.approx((0, 0, np.sin(0.2), np.cos(0.2)))
    assert odom.body_linear_xy == pytest.approx((0.3, -0.1)) and odom.angular_z == pytest.approx(2.8)

    eff = by_type(records, EffortRecord)
    assert [e.answers_ns for e in eff] == [s.stamp_ns for s in states]
    np.testing.assert_allclose(eff[3].effort, [0.3, -0.6, 0.9])

    info = by_type(records, PolicyInfoRecord)
    assert [i.stamp_ns for i in info] == [s.stamp_ns for s in states]
    expected = pack_policy_info(np.array([0.2, -0.1, 0.4]) + 0.05, (np.array([0.2, -0.1, 0.4]) + 0.05) * 0.5, -0.7)
    np.testing.assert_allclose(info[5].action, expected["positions"])
    np.testing.assert_allclose(info[5].log_std, [-0.7] * 3)
    assert info[5].log_prob == pytest.approx(expected["effort"].sum())

    starts = by_type(records, EpisodeStartRecord)
    assert [(s.stamp_ns, s.episode, s.num_joints) for s in starts] == [(k * STEP_NS, k // 10, 3) for k in (0, 10, 20)]


def test_untagged_efforts_answer_nothing(tmp_path):
    msgs = [(f"{NS}/joint_states", 10, joint_state(0)), (f"{NS}/effort_commands", 20, efforts(0, tagged=False))]
    records, _ = read_bag(write_with_rosbags(tmp_path / "bag", msgs))
    assert by_type(records, EffortRecord)[0].answers_ns is None


@pytest.mark.slow
@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_split_bag_is_read_whole_and_in_order(tmp_path, storage):
    msgs = loop_messages(120)
    # sqlite3 files start at ~25 kB of schema; MCAP files at a few hundred bytes.
    bag = write_with_bag_writer(tmp_path / "bag", msgs, storage=storage, max_bag_size=60_000, chunk_size=8192)
    ext = ".mcap" if storage == "mcap" else ".db3"
    files = sorted(p.name for p in bag.iterdir() if p.suffix == ext)
    assert len(files) >= 3, files

    info = YAML(typ="safe").load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert jazzy_metadata_problems(info) == []
    assert info["version"] == 9 and info["storage_identifier"] == storage
    assert sorted(info["relative_file_paths"]) == files
    assert sum(f["message_count"] for f in info["files"]) == info["message_count"] == len(msgs)
    per_topic = {t["topic_metadata"]["name"]: t for t in info["topics_with_message_count"]}
    assert per_topic[f"{NS}/joint_states"]["message_count"] == 120
    meta = per_topic[f"{NS}/joint_states"]["topic_metadata"]
    assert meta["type_description_hash"] == TS.hash_rihs01("sensor_msgs/msg/JointState")
    assert meta["offered_qos_profiles"][0]["reliability"] == "reliable"

    records, stats = read_bag(bag)
    assert stats.counts["joint_states"] == 120 and not stats.warnings
    assert [r.log_ns for r in records] == [m[1] for m in msgs if m[0] != "/clock"]

    # rosbags' own reader agrees on every message (an independent check of the files).
    with Reader(bag) as r:
        assert [(c.topic, t) for c, t, _ in r.messages()] == [(m[0], m[1]) for m in msgs]

    # One storage file on its own is a bag too.
    first, _ = read_bag(bag / files[0])
    assert 0 < len(first) < len(records) and [r.log_ns for r in first] == [r.log_ns for r in records[: len(first)]]


def test_split_by_duration(tmp_path):
    msgs = loop_messages(50)  # log times 1000 ns apart
    bag = write_with_bag_writer(tmp_path / "bag", msgs, max_bag_duration_ns=100_000)
    info = YAML(typ="safe").load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert len(info["files"]) == -(-len(msgs) // 100)  # 100 messages per 100 us file
    assert all(f["duration"]["nanoseconds"] < 100_000 for f in info["files"])
    assert len(read_bag(bag)[0]) == len(msgs) - 50


def test_several_bags_merge_by_log_time(tmp_path):
    a = loop_messages(10, t0=1_000)
    b = [(t, log + 500, m) for t, log, m in loop_messages(10, t0=1_000)]
    records, stats = read_bag([write_with_rosbags(tmp_path / "a", a), write_with_rosbags(tmp_path / "b", b, "sqlite3")])
    logs = [r.log_ns for r in records]
    assert logs == sorted(logs) and stats.counts["joint_states"] == 20


def test_namespace_is_found_or_given(tmp_path):
    bag = write_with_rosbags(tmp_path / "bag", loop_messages(3))
    reader = BagReader(bag)
    assert reader.namespaces == [NS]
    assert not BagReader(bag, namespace="/elsewhere").read()  # nothing under another namespace
    two = {**TYPES, "/other/joint_states": "sensor_msgs/msg/JointState"}
    with pytest.raises(BagError, match="several joint_states topics"):
        BagReader(write_with_rosbags(tmp_path / "two", [], types=two))


# -- messages that do not decode are counted, not raised ----------------------------------------
def test_bad_messages_are_counted_by_reason(tmp_path):
    short = T["sensor_msgs/msg/JointState"](
        header=_header(0), name=NAMES, position=np.zeros(2), velocity=np.zeros(3), effort=np.zeros(0)
    )
    nan_info = policy_info(1)
    nan_info.points[0].positions[0] = np.nan
    msgs = [
        (f"{NS}/joint_states", 1, joint_state(0)),
        (f"{NS}/joint_states", 2, b"\x00\x01\x00\x00\x05"),  # cut-off CDR
        (f"{NS}/joint_states", 3, short),
        (f"{NS}/policy_info", 4, policy_info(0, points=False)),
        (f"{NS}/policy_info", 5, nan_info),
        (f"{NS}/policy_info", 6, policy_info(2)),
    ]
    records, stats = read_bag(write_with_rosbags(tmp_path / "bag", msgs))
    assert len(records) == 2
    assert stats.rejected == {
        ("joint_states", "undecodable CDR"): 1,
        ("joint_states", "length mismatch"): 1,
        ("policy_info", "no trajectory point"): 1,
        ("policy_info", "bad layout"): 1,
    }
    assert "2 positions" in stats.examples[("joint_states", "length mismatch")]


def test_episode_announcement_of_a_custom_type(tmp_path):
    """A type the Jazzy store lacks is decoded from the definition the bag carries."""
    text = "std_msgs/Header header\nuint32 episode\nuint16 num_joints\n"
    custom = get_typestore(Stores.ROS2_JAZZY)
    custom.register(get_types_from_msg(text, "morph_msgs/msg/EpisodeStart"))
    Ep = custom.types["morph_msgs/msg/EpisodeStart"]
    path = tmp_path / "bag"
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection(f"{NS}/episode_start", "morph_msgs/msg/EpisodeStart", typestore=custom)
        s = w.add_connection("/std/episode_start", "std_msgs/msg/String", typestore=custom)
        for k in range(3):
            msg = Ep(header=_header(k * 7 * STEP_NS), episode=k + 4, num_joints=5)
            w.write(c, k, custom.serialize_cdr(msg, "morph_msgs/msg/EpisodeStart"))
        w.write(s, 9, custom.serialize_cdr(T["std_msgs/msg/String"](data="episode=1"), "std_msgs/msg/String"))
    records, _ = read_bag(path, namespace=NS)
    assert [(r.stamp_ns, r.episode, r.num_joints) for r in records] == [(k * 7 * STEP_NS, k + 4, 5) for k in range(3)]
    # A message with no stamp is no announcement: counted, not raised.
    records, stats = read_bag(path, namespace="/std")
    assert not records and stats.rejected == {("episode_start", "no stamp"): 1}


def test_the_sims_episode_announcement(tmp_path):
    """std_msgs/Int64MultiArray with the fields named in layout.dim[0].label (msgs.episode_start)."""

    def announcement(label, data):
        dim = T["std_msgs/msg/MultiArrayDimension"](label=label, size=len(data), stride=len(data))
        layout = T["std_msgs/msg/MultiArrayLayout"](dim=[dim], data_offset=0)
        return T["std_msgs/msg/Int64MultiArray"](layout=layout, data=np.array(data, dtype=np.int64))

    msgs = [
        (f"{NS}/episode_start", 1, announcement("episode,stamp_ns,num_joints,cause", [0, 0, 4, 0])),
        (f"{NS}/episode_start", 2, announcement("episode,stamp_ns,num_joints,cause", [1, 10 * STEP_NS, 6, 1])),
        (f"{NS}/episode_start", 3, announcement("episode,stamp_ns", [2, 20 * STEP_NS, 7])),  # 2 names, 3 values
        (f"{NS}/joint_states", 4, joint_state(0)),
    ]
    types = {**TYPES, f"{NS}/episode_start": "std_msgs/msg/Int64MultiArray"}
    records, stats = read_bag(write_with_rosbags(tmp_path / "bag", msgs, types=types))
    starts = by_type(records, EpisodeStartRecord)
    assert [(r.stamp_ns, r.episode, r.num_joints, r.cause) for r in starts] == [
        (0, 0, 4, "start"),
        (10 * STEP_NS, 1, 6, "steps"),
    ]
    assert stats.rejected == {("episode_start", "bad layout"): 1}


# -- bad input: clear errors naming the file and the problem ------------------------------------
def test_bad_paths(tmp_path):
    with pytest.raises(BagError, match="no such file or directory") as e:
        read_bag(tmp_path / "nope")
    assert str(tmp_path / "nope") in str(e.value)
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "readme.txt").write_text("hello")
    with pytest.raises(BagError, match="not a rosbag2 bag"):
        read_bag(tmp_path / "notes")
    with pytest.raises(BagError, match="not a rosbag2 storage file"):
        read_bag(tmp_path / "notes" / "readme.txt")
    (tmp_path / "fake.mcap").write_bytes(b"this is no mcap file at all")
    with pytest.raises(BagError, match="fake.mcap: not an MCAP file"):
        read_bag(tmp_path / "fake.mcap")
    (tmp_path / "fake.db3").write_bytes(b"neither a database" * 100)
    with pytest.raises(BagError, match="fake.db3: cannot read the sqlite3 storage file"):
        read_bag(tmp_path / "fake.db3")
    (tmp_path / "badmeta").mkdir()
    (tmp_path / "badmeta" / "metadata.yaml").write_text("just: [unclosed")
    with pytest.raises(BagError, match="metadata.yaml: not a rosbag2 metadata file"):
        read_bag(tmp_path / "badmeta")


def test_missing_required_topic_and_wrong_type(tmp_path):
    bag = write_with_rosbags(tmp_path / "bag", loop_messages(2), types={**TYPES})
    with pytest.raises(BagError, match=f"required topic {NS}/action_log is not in the bag"):
        read_bag(bag, required=("joint_states", "action_log"))
    wrong = {**TYPES, f"{NS}/odom": "geometry_msgs/msg/PoseStamped"}
    msgs = [(f"{NS}/joint_states", 1, joint_state(0))]
    bag = write_with_rosbags(tmp_path / "wrong", msgs, "sqlite3", types=wrong)
    with pytest.raises(BagError, match=r"wrong(_0)?\.db3: topic /robot/odom has type geometry_msgs/msg/PoseStamped"):
        read_bag(bag)


def test_writer_refuses_an_existing_bag_and_bad_options(tmp_path):
    (tmp_path / "taken").mkdir()
    with pytest.raises(BagWriterError, match="exists already"):
        BagWriter(tmp_path / "taken")
    with pytest.raises(BagWriterError, match="storage"):
        WriterOptions(storage="rosbag1")
    with pytest.raises(BagWriterError, match="no definition of my_pkg/msg/Thing"):
        BagWriter(tmp_path / "new").add_topic(BagTopic("/x", "my_pkg/msg/Thing"))


def test_truncated_mcap_gives_the_complete_chunks_and_a_warning(tmp_path):
    """A file cut inside a chunk: exactly the messages of the chunks before the cut."""
    w = BagWriter(tmp_path / "bag", WriterOptions(chunk_size=1))  # one message per chunk
    tid = w.add_topic(BagTopic(f"{NS}/joint_states", "sensor_msgs/msg/JointState"))
    file = tmp_path / "bag" / "bag_0.mcap"
    ends = []
    for k in range(40):
        w.write(tid, 1000 + k, ser(joint_state(k)))
        ends.append(file.stat().st_size)  # each chunk is flushed as it closes
    w.close()
    cut = ends[24] + 20  # inside the chunk of message 25
    cut_dir = tmp_path / "cut"
    cut_dir.mkdir()
    (cut_dir / "cut_0.mcap").write_bytes(file.read_bytes()[:cut])

    records, stats = read_bag(cut_dir)
    assert [r.stamp_ns for r in records] == [k * STEP_NS for k in range(25)]
    assert any("no metadata.yaml" in x for x in stats.warnings)
    assert any("cut_0.mcap: incomplete MCAP file" in x and "cut off mid-record" in x for x in stats.warnings)


_KILLED_WRITER = textwrap.dedent(
    """
    import os, signal, sys
    sys.path[:0] = {paths!r}
    from test_bag_io import joint_state, ser, NS
    from trainer.bags.writer import BagTopic, BagWriter, WriterOptions
    w = BagWriter({bag!r}, WriterOptions(storage={storage!r}))
    tid = w.add_topic(BagTopic(NS + "/joint_states", "sensor_msgs/msg/JointState"))
    for k in range(60):
        w.write(tid, 1000 + k, ser(joint_state(k)))
        if k == 49:
            w.flush()
    os.kill(os.getpid(), signal.SIGKILL)
    """
)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_killed_writer_keeps_what_was_flushed(tmp_path, storage):
    """A writer process SIGKILLed mid-recording: no metadata.yaml; every flushed message reads back."""
    bag = tmp_path / "bag"
    script = _KILLED_WRITER.format(paths=[str(Path(__file__).parent), *sys.path], bag=str(bag), storage=storage)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()
    assert not (bag / "metadata.yaml").exists()

    records, stats = read_bag(bag, required=("joint_states",))
    # MCAP keeps the flushed chunk; sqlite3 the committed transaction: messages 0..49 either way.
    assert [r.stamp_ns for r in records] == [k * STEP_NS for k in range(50)]
    assert any("no metadata.yaml" in w for w in stats.warnings)
    if storage == "sqlite3":
        assert os.path.exists(str(bag / "bag_0.db3") + "-wal")  # the committed data lives in the WAL


# -- the robot's description, and efforts that name their joints ------------------------------------
def _same_record(a, b) -> bool:
    """Equal fields, arrays bit for bit (an announcement's cause aside: the loopback does not say it)."""
    if type(a) is not type(b):
        return False
    pairs = [(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a) if f.name != "cause"]
    return all(np.array_equal(x, y) if isinstance(x, np.ndarray) else x == y for x, y in pairs)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_descriptions_and_named_efforts_read_back_as_recorded(tmp_path, storage):
    """A tree swimmer's loop with its robot_description, joints shuffled per state and efforts naming theirs:
    written as the nodes publish it (bag_messages), every record comes back the same."""
    records = record_episodes(
        GaussianController(seed=2),
        ((swimmer_tree([-1, 0, 0, 2]), 8), (swimmer_tree([-1, -1, 1]), 6)),
        describe=True,
        shuffle_seed=1,
        name_efforts=True,
    )
    untagged = EffortRecord(records[-1].log_ns + 1, None, np.zeros(3), ("motor3_rot", "motor1_rot", "motor2_rot"))
    records.append(untagged)
    assert sum(isinstance(r, DescriptionRecord) for r in records) == 2
    assert {len(r.layout) for r in records[:-1] if isinstance(r, EffortRecord)} == {16}  # the tree they were on
    path = tmp_path / "bag"
    with BagWriter(path, WriterOptions(storage=storage)) as w:
        ids = {name: w.add_topic(BagTopic(f"{NS}/{name}", ty)) for name, ty in TOPIC_TYPES.items()}
        for r in records:
            name, msg = record_message(r)
            w.write(ids[name], r.log_ns, ser(msg))
    back, stats = read_bag(path)
    assert not stats.rejected and stats.counts["robot_description"] == 2
    assert len(back) == len(records) and all(_same_record(a, b) for a, b in zip(back, records, strict=True))
    assert back[-1].names == untagged.names and back[-1].answers_ns is None


def test_a_bad_names_dimension_rejects_the_effort_and_a_description_of_another_type_the_bag(tmp_path):
    def named(label, data=(0.1, 0.2, 0.3)):
        dims = [T["std_msgs/msg/MultiArrayDimension"](label=x, size=s, stride=s) for x, s in ((answer_tag(0, 0), 3),
                                                                                            (label, 1))]  # fmt: skip
        layout = T["std_msgs/msg/MultiArrayLayout"](dim=dims, data_offset=0)
        return T["std_msgs/msg/Float64MultiArray"](layout=layout, data=np.array(data))

    msgs = [
        (f"{NS}/joint_states", 1, joint_state(0)),
        (f"{NS}/effort_commands", 2, named('names=["j0","j1","j2"]')),
        (f"{NS}/effort_commands", 3, named("names=[j0,j1,j2]")),  # not JSON
        (f"{NS}/effort_commands", 4, named('names=["j0","j1"]')),  # two names for three efforts
        (f"{NS}/effort_commands", 5, named('names=["j0","j0","j1"]')),
    ]
    records, stats = read_bag(write_with_rosbags(tmp_path / "bag", msgs))
    assert [r.names for r in by_type(records, EffortRecord)] == [("j0", "j1", "j2")]
    assert stats.rejected == {("effort_commands", "bad names dimension"): 3}
    assert "is not JSON" in stats.examples[("effort_commands", "bad names dimension")]
    wrong = {**TYPES, f"{NS}/robot_description": "std_msgs/msg/Header"}
    bag = write_with_rosbags(tmp_path / "wrong", msgs[:1], types=wrong)
    with pytest.raises(BagError, match="topic /robot/robot_description has type std_msgs/msg/Header"):
        read_bag(bag)


@pytest.mark.parametrize("sec, nanosec", [(3, 1_500_000_000), (3, 10**9), (-1, 0)])
def test_a_stamp_that_is_no_time_is_refused_not_read_as_another(tmp_path, sec, nanosec):
    # (3, 1.5e9) read as ns would be the stamp 4.5 s: another state's. The nodes refuse it; so does the reader.
    records = record_episodes(GaussianController(seed=2), [(2, 5)])
    bag = tmp_path / "bag"
    ts = get_typestore(Stores.ROS2_JAZZY)
    with BagWriter(bag, WriterOptions()) as w:
        ids = {name: w.add_topic(BagTopic(f"/{name}", ty)) for name, ty in TOPIC_TYPES.items()}
        for r in records:
            name, msg = record_message(r)
            w.write(ids[name], r.log_ns, ts.serialize_cdr(msg, msg.__msgtype__))
        name, msg = record_message(next(r for r in records if isinstance(r, OdometryRecord)))
        msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
        w.write(ids[name], records[-1].log_ns + 1, ts.serialize_cdr(msg, msg.__msgtype__))
    back, stats = read_bag(bag)
    assert len(back) == len(records)
    assert dict(stats.rejected) == {("odom", "bad stamp"): 1}, stats.rejected
