"""Record the swimmer's topics into a rosbag2 bag (MCAP or sqlite3), as ``ros2 bag record`` would.

    morph-record --out bags/run1 --ros-args -r __ns:=/robot1 -p max_episodes:=10
    (``-p output:=bags/run1``, the parameter ``--out`` sets, works as well)

Topics (relative names resolve under the node's namespace): ``episode_start``,
``robot_description``, ``joint_states``, ``odom``, ``effort_commands``,
``policy_info`` and ``/clock`` by default (parameter ``topics``). Topics of a known type
(``topic_types``: the project's conventions) are subscribed at once,
reliable, so a node started after the recorder is recorded from its first
message (a lockstep loop runs hundreds of steps in the time graph discovery
takes); any other topic (the episode announcement) is subscribed once a
publisher appears, with whatever type the graph says it has. Messages are
written as the serialized CDR bytes received (raw subscriptions, never
re-serialized), with the reception time (the node's clock) as log time; a
topic enters the bag at its first message, with the QoS profiles its
publishers offer then.

Subscription QoS follows the publishers' offers, as rosbag2 does: reliable
only if every publisher is reliable (a reliable reader gets nothing from a
best-effort writer: a subscription made in advance is replaced when a
best-effort publisher appears), transient-local only if every publisher is
(then the recorder still gets what a latched publisher kept, e.g. the
current episode's announcement and the robot's description, however late it
starts), keep-last with a deep queue
(``queue_depth``) so a burst is not dropped while a chunk is written.

The bag (``trainer.bags.writer``): metadata.yaml version 9 with each topic's
offered QoS profiles and type hash, MCAP (default) or sqlite3, split by size
or duration, flushed every ``flush_period`` so a kill loses at most that
much. SIGINT/SIGTERM close the bag; so does a stop condition
(``max_messages``, ``max_duration``, ``max_episodes``), after which the
process exits: a bring-up can record N episodes and wait for it.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from datetime import datetime
from pathlib import Path

import rclpy
import rclpy.utilities
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

from morph_core.util.config_cli import CommandLineParser
from morph_ros_util.parameters import NodeParameter, declare_parameters, parameters_help
from morph_ros_util.stop_signals import init_stopping_on_signals
from trainer.bags.writer import BagTopic, BagWriter, BagWriterError, WriterOptions
from trainer.codec import DATA_TOPIC_TYPES, DESCRIPTION_TOPIC, EPISODE_TOPIC, TOPIC_TYPES, message_class

# The announcement and the description first: subscribed to before joint_states in the same discovery pass, so a
# lockstep sim (which starts once joint_states has a listener) cannot announce its first episode unheard, and the
# description, published before the body's first state, is not taken after it when both are waiting.
CLOCK = ("/clock", "rosgraph_msgs/msg/Clock")
DEFAULT_TOPICS = [EPISODE_TOPIC, DESCRIPTION_TOPIC, *DATA_TOPIC_TYPES, CLOCK[0]]
# The project's own conventions, subscribed to before any publisher appears; the announcement and the description
# as transient local (the sim latches them). Subscribed only once discovery saw the sim, the announcement came
# after a lockstep loop had run more than max_episodes. A publisher that offers otherwise gets the subscription
# replaced by discovery.
LATCHED_TOPICS = (EPISODE_TOPIC, DESCRIPTION_TOPIC)
KNOWN_TYPES = [f"{topic}={msgtype}" for topic, msgtype in (*TOPIC_TYPES.items(), CLOCK)]
_LOG_THROTTLE = 5.0

PARAMETERS = (
    NodeParameter(
        "output", "", "bag folder to create (must not exist); '' = rosbag2_<date>-<time> here", read_only=True
    ),
    NodeParameter("topics", DEFAULT_TOPICS, "topics to record (relative: in the node's namespace)", read_only=True),
    NodeParameter(
        "episode_topic", EPISODE_TOPIC, "the topic announcing episodes (counted by max_episodes)", read_only=True
    ),
    NodeParameter(
        "topic_types",
        KNOWN_TYPES,
        "topic=pkg/msg/Type pairs subscribed at once (reliable), before any publisher exists, so a node that "
        "starts later is recorded from its first message; other topics are subscribed once discovered, with the "
        "type and QoS the graph shows",
        read_only=True,
    ),
    NodeParameter("storage", "mcap", "mcap or sqlite3", read_only=True),
    NodeParameter(
        "max_bag_size", 0, "bytes per storage file before splitting; 0 = no split", (0, 2**62), read_only=True
    ),
    NodeParameter(
        "max_bag_duration",
        0.0,
        "seconds of log time per storage file before splitting; 0 = no split",
        (0.0, 1e9),
        read_only=True,
    ),
    NodeParameter(
        "chunk_size",
        WriterOptions.chunk_size,
        "MCAP chunk size in bytes: a kill loses at most the chunk being filled",
        (1, 2**20),
        read_only=True,
    ),
    NodeParameter(
        "flush_period",
        1.0,
        "wall seconds between flushes (MCAP: close the chunk; sqlite3: commit)",
        (0.01, 3600.0),
        read_only=True,
    ),
    NodeParameter("queue_depth", 1000, "keep-last depth of each subscription", (1, 100000), read_only=True),
    NodeParameter(
        "max_messages",
        0,
        "stop after writing this many messages (of count_topic, or of all); 0 = no limit",
        (0, 2**62),
        read_only=True,
    ),
    NodeParameter("count_topic", "", "topic counted by max_messages; '' = every topic", read_only=True),
    NodeParameter(
        "max_duration",
        0.0,
        "stop this many wall seconds after the first message; 0 = no limit",
        (0.0, 1e9),
        read_only=True,
    ),
    NodeParameter(
        "max_episodes",
        0,
        "stop when episode max_episodes+1 is announced (not recorded); 0 = no limit",
        (0, 2**62),
        read_only=True,
    ),
)
"""the node's parameters, all read-only (``morph_ros_util.parameters``; ``--help`` lists them)"""


def subscription_qos(offers: list[QoSProfile], depth: int) -> QoSProfile:
    """A profile that matches every offer: reliable / transient-local only when all offers are."""
    reliable = bool(offers) and all(o.reliability == ReliabilityPolicy.RELIABLE for o in offers)
    latched = bool(offers) and all(o.durability == DurabilityPolicy.TRANSIENT_LOCAL for o in offers)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


def _qos_time(duration) -> QosTime:
    sec, nsec = divmod(duration.nanoseconds, 1_000_000_000)
    return QosTime(sec, nsec)


def bag_qos(profile: QoSProfile) -> Qos:
    """An offered rclpy profile as rosbags stores it (enums by name: rclpy and rmw number them differently)."""
    return Qos(
        QosHistory[profile.history.name],
        profile.depth,
        QosReliability[profile.reliability.name],
        QosDurability[profile.durability.name],
        _qos_time(profile.deadline),
        _qos_time(profile.lifespan),
        QosLiveliness[profile.liveliness.name],
        _qos_time(profile.liveliness_lease_duration),
        profile.avoid_ros_namespace_conventions,
    )


def _msg_file(msgtype: str) -> Path:
    """Where ``pkg/msg/Type`` is defined: the ament index of a sourced ROS install, else this
    environment's share/ (the PyPI ROS wheels install there and set no AMENT_PREFIX_PATH)."""
    pkg, kind, name = msgtype.split("/")
    candidates = [Path(sys.prefix) / "share" / pkg]
    if os.environ.get("AMENT_PREFIX_PATH"):
        # a sourced ROS install's index, only when there is one (the PyPI wheels have none)
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

        try:
            candidates.insert(0, Path(get_package_share_directory(pkg)))
        except PackageNotFoundError:
            pass
    for share in candidates:
        if (share / kind / f"{name}.msg").is_file():
            return share / kind / f"{name}.msg"
    raise FileNotFoundError(f"no definition of {msgtype} in {[str(c) for c in candidates]}")


def ensure_type(typestore, msgtype: str) -> None:
    """Make ``typestore`` know ``msgtype``: types the Jazzy store lacks are read from their installed
    ``.msg`` files (share/<pkg>/msg/<Type>.msg), with the types they use."""
    if msgtype in typestore.fielddefs:
        return
    # the .msg parser only for a type the Jazzy store lacks
    from rosbags.typesys import get_types_from_msg
    from rosbags.typesys.base import Nodetype

    types = get_types_from_msg(_msg_file(msgtype).read_text(), msgtype)
    for _, (node, detail) in types[msgtype][1]:
        if node in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            node, detail = detail[0]
        if node == Nodetype.NAME:
            ensure_type(typestore, detail)
    typestore.register(types)


class RecorderNode(Node):
    def __init__(self):
        super().__init__("morph_record")
        declare_parameters(self, PARAMETERS)
        p = lambda name: self.get_parameter(name).value  # noqa: E731
        output = p("output") or datetime.now().strftime("rosbag2_%Y_%m_%d-%H_%M_%S")
        options = WriterOptions(
            storage=p("storage"),
            max_bag_size=p("max_bag_size"),
            max_bag_duration_ns=int(round(p("max_bag_duration") * 1e9)),
            chunk_size=p("chunk_size"),
        )
        self.writer = BagWriter(Path(output), options)  # refuses an existing path
        self._wanted = {self.resolve_topic_name(t): t for t in p("topics")}
        self._episode_topic = self.resolve_topic_name(p("episode_topic"))
        self._count_topic = self.resolve_topic_name(p("count_topic")) if p("count_topic") else ""
        self._depth = p("queue_depth")
        self._max_messages = p("max_messages")
        self._max_duration = p("max_duration")
        self._max_episodes = p("max_episodes")
        self._counted = 0
        self._episodes = 0
        self._first_at: float | None = None
        self._subs: dict[str, tuple] = {}  # topic -> (type, reliable, latched, subscription)
        self._ids: dict[str, int] = {}  # topic -> writer id, from its first message on
        self._failed: set[str] = set()
        self.finished = False
        self.stop_reason = ""
        declared = {}
        for pair in p("topic_types"):
            name, _, msgtype = pair.partition("=")
            if msgtype.count("/") != 2:
                raise BagWriterError(f"topic_types entry {pair!r} is not topic=pkg/msg/Type")
            declared[self.resolve_topic_name(name)] = msgtype
        latched = {self._episode_topic, *(self.resolve_topic_name(t) for t in LATCHED_TOPICS)}
        for topic in self._wanted:
            if topic in declared:  # our nodes publish reliably, and latch the announcement and the description
                self._subscribe(topic, declared[topic], reliable=True, latched=topic in latched)
        self._discover()
        self.create_timer(0.1, self._discover)
        self.create_timer(p("flush_period"), self._flush)
        self.get_logger().info(f"recording {sorted(self._wanted)} into {self.writer.path} ({options.storage})")

    # -- discovery ----------------------------------------------------------------------------
    def _discover(self) -> None:
        """Subscribe to topics that gained a publisher; follow the type or QoS the graph shows when a
        subscription made in advance does not fit it (until the topic's first message)."""
        for topic in self._wanted:
            if topic in self._failed or topic in self._ids:
                continue
            infos = self.get_publishers_info_by_topic(topic)
            if not infos:
                continue
            types = sorted({i.topic_type for i in infos})
            msgtype = types[0]
            if len(types) > 1:
                self.get_logger().warn(
                    f"{topic} is published with several types {types}: recording {msgtype}",
                    throttle_duration_sec=_LOG_THROTTLE,
                )
            wanted = subscription_qos([i.qos_profile for i in infos if i.topic_type == msgtype], 1)
            reliable = wanted.reliability == ReliabilityPolicy.RELIABLE
            latched = wanted.durability == DurabilityPolicy.TRANSIENT_LOCAL
            current = self._subs.get(topic)
            if current is not None:
                # Keep one that matches every publisher (a reliable reader gets nothing from a
                # best-effort writer) and asks for what latched publishers keep.
                if current[0] == msgtype and (reliable or not current[1]) and current[2] == latched:
                    continue
                self.destroy_subscription(current[3])
            self._subscribe(topic, msgtype, reliable, latched)

    def _subscribe(self, topic: str, msgtype: str, reliable: bool, latched: bool = False) -> None:
        try:
            cls = message_class(msgtype)
        except (ImportError, AttributeError, ValueError) as err:
            self.get_logger().error(f"cannot record {topic}: no message type {msgtype} here ({err})")
            self._failed.add(topic)
            return
        qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=self._depth,
            reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
        )
        sub = self.create_subscription(
            cls, topic, lambda data, t=topic, ty=msgtype: self._on_message(t, ty, data), qos, raw=True
        )
        self._subs[topic] = (msgtype, reliable, latched, sub)
        self.get_logger().info(
            f"subscribed to {topic} ({msgtype}, {qos.reliability.name.lower()}, {qos.durability.name.lower()})"
        )

    def _add_to_bag(self, topic: str, msgtype: str) -> int | None:
        """The topic's writer id; registered at its first message, with what its publishers offer now."""
        infos = [i for i in self.get_publishers_info_by_topic(topic) if i.topic_type == msgtype]
        type_hash = str(infos[0].topic_type_hash) if infos else ""
        try:
            ensure_type(self.writer.typestore, msgtype)
            topic_id = self.writer.add_topic(
                BagTopic(
                    name=topic,
                    msgtype=msgtype,
                    offered_qos=tuple(bag_qos(i.qos_profile) for i in infos),
                    type_hash=type_hash if type_hash.startswith("RIHS01_") and set(type_hash[7:]) != {"0"} else "",
                )
            )
        except (OSError, ValueError, KeyError, BagWriterError) as err:
            self.get_logger().error(f"cannot record {topic} ({msgtype}): {err}")
            self._failed.add(topic)
            self.destroy_subscription(self._subs.pop(topic)[3])
            return None
        self._ids[topic] = topic_id
        return topic_id

    # -- writing ------------------------------------------------------------------------------
    def _on_message(self, topic: str, msgtype: str, data: bytes) -> None:
        if self.finished or topic in self._failed:
            return
        topic_id = self._ids.get(topic)
        if topic_id is None:
            topic_id = self._add_to_bag(topic, msgtype)
            if topic_id is None:
                return
        if topic == self._episode_topic and self._max_episodes:
            self._episodes += 1
            if self._episodes > self._max_episodes:
                self._finish(f"episode {self._episodes} announced after {self._max_episodes} episodes")
                return
        self.writer.write(topic_id, self.get_clock().now().nanoseconds, data)
        now = time.monotonic()
        if self._first_at is None:
            self._first_at = now
        if not self._count_topic or topic == self._count_topic:
            self._counted += 1
        if self._max_messages and self._counted >= self._max_messages:
            self._finish(f"{self._counted} messages written")
        elif self._max_duration and now - self._first_at >= self._max_duration:
            self._finish(f"{self._max_duration} s recorded")

    def _flush(self) -> None:
        if not self.finished:
            self.writer.flush()

    def _finish(self, reason: str) -> None:
        self.finished = True
        self.stop_reason = reason

    def close(self) -> None:
        """Close the bag (metadata.yaml written) and say what is in it."""
        path = self.writer.close()
        counts = ", ".join(f"{t}: {n}" for t, n in self.writer.counts().items()) or "no topics"
        missing = sorted(t for t in self._wanted if t not in self._ids)
        self.get_logger().info(
            f"bag {path} closed{' (' + self.stop_reason + ')' if self.stop_reason else ''}: "
            f"{self.writer.message_count} messages ({counts})"
            f"{'; nothing recorded on: ' + ', '.join(missing) if missing else ''}"
        )


def build_parser() -> CommandLineParser:
    """The recorder's own command line: ``--help`` (its options are ROS parameters, after ``--ros-args``)."""
    parser = CommandLineParser(
        prog="morph-record",
        usage="morph-record [-h] [--out DIR] [--ros-args -r __ns:=NS -p NAME:=VALUE ...]",
        description=__doc__,
        epilog=parameters_help(PARAMETERS),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--out", default=None, metavar="DIR",
                        help="bag folder to create (must not exist): the parameter output")  # fmt: skip
    return parser


def with_out(argv: list[str], out: str | None) -> list[str]:
    """``argv`` with ``--out DIR`` as the ROS parameter ``output`` (a ValueError when ``-p output:=`` is given too)."""
    if out is None:
        return argv
    if any(arg.startswith("output:=") for arg in argv):
        raise ValueError("--out and -p output:= name the bag twice: give --out alone")
    return [*argv, "--ros-args", "-p", f"output:={json.dumps(out)}"]  # a quoted YAML string: a path stays one


def main(args=None) -> int:
    argv = list(sys.argv if args is None else args)
    # Arguments outside --ros-args are the recorder's own: --help prints it and exits before anything is
    # created; anything else is refused (it used to be ignored, and the recorder started in this folder).
    parser = build_parser()
    own = parser.parse_args(rclpy.utilities.remove_ros_args(argv)[1:])
    try:
        argv = with_out(argv, own.out)  # rclpy reads the arguments after --ros-args alone
    except ValueError as err:
        parser.error(str(err))
    # SIGINT/SIGTERM end the loop here, not rclpy's handler: that one shut the context down first, and the
    # bag's closing line then failed to reach rosout ("publisher's context is invalid") on every stop.
    stop = init_stopping_on_signals(argv)
    node = None
    executor = SingleThreadedExecutor()  # one for the run: rclpy.spin_once(node) rebuilds the wait set per call
    try:
        node = RecorderNode()
        executor.add_node(node)
        while rclpy.ok() and not node.finished and not stop.is_set():
            executor.spin_once(timeout_sec=0.1)
    except ExternalShutdownException:
        pass
    except BagWriterError as err:
        print(f"morph-record: error: {err}", file=sys.stderr)
        return 1
    finally:
        executor.shutdown()
        if node is not None:
            node.close()
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
