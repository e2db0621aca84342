"""The morphology-agnostic GNN policy as a ROS 2 node: JointState (+ Odometry) in, efforts out.

This module holds the node's topics, parameters and timers. Everything between a message and the efforts is
``morph_core.protocol.controller.Controller``'s (the one the loopback and the trainer's transition rebuild use
too); the counts, silence and log lines ``protocol.answer_watch``'s, live weights ``protocol.policy_updates``',
the stream for a live trainer ``protocol.stream_notes``'. Topics, QoS, outputs, live training and bad input,
for users: docs/guides/nodes.md ("The policy node in detail").
"""

from __future__ import annotations

import array
import time
from pathlib import Path
from typing import NoReturn

import numpy as np
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy.exceptions import ParameterUninitializedException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.serialization import serialize_message
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, Int64MultiArray, MultiArrayDimension, String, UInt8MultiArray
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from morph_core.msgs.effort_names import names_label, tree_label
from morph_core.msgs.episode_start import EpisodeStartError, unpack_episode_start
from morph_core.msgs.joint_state import JointStateError
from morph_core.msgs.policy_weights import TOPIC as WEIGHTS
from morph_core.msgs.policy_weights import policy_version_frame_id
from morph_core.msgs.records import JointStateRecord, OdometryRecord
from morph_core.msgs.stamps import SILENCE_TAG, StampError, answer_tag, check_stamp, from_ns
from morph_core.msgs.stream_chunk import TOPIC as CHUNK_TOPIC
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.weights import CheckpointError, PolicyWeights
from morph_core.protocol.answer_watch import (
    DESCRIPTION,
    EPISODES,
    HANDOVER_CODES,
    KEYS,
    ODOM,
    STATES,
    AnswerWatch,
    Notice,
    updates_notices,
)
from morph_core.protocol.controller import (
    Controller,
    EffortOrderError,
    PolicyOutputError,
    Ready,
    effort_order,
    effort_units,
)
from morph_core.protocol.joint_map import JointMapError
from morph_core.protocol.policy_updates import CheckpointTrust, PolicyUpdates, checkpoint_trust, drivable, numpy_policy
from morph_core.protocol.stream_notes import StreamNotes
from morph_policy_node.policy_choice import UNTRAINED_LABEL, choose_policy
from morph_ros_util import node_runner
from morph_ros_util.diagnostics import InputDiagnostics
from morph_ros_util.parameters import NodeParameter, declare_parameters

SHIPPED_MODEL = Path(__file__).resolve().parent / "models" / "swimmer_gnn.safetensors"
_WATCHDOG_PERIOD = 0.04  # also the rate of zero efforts while the input is silent
_LOG_THROTTLE = 5.0
_WEIGHTS_LOG_THROTTLE = 1.0  # weights come about once a second: each bad one shows, a flood cannot fill the log
_DESCRIPTION_LOG_THROTTLE = 1.0  # a bad description is rare and says why the robot is not driven: show each
# Live announcements only (volatile), best effort: matches the sim's latched reliable publisher and
# no publisher can make this reader wait on repairs.
EPISODE_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)
# The newest weights only; best effort for the same reason as every input (the trainer re-publishes).
WEIGHTS_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)
# The latched URDF: reliable + transient local, so a description published before this node started still
# arrives (a best-effort reader is sent no history). Exposed to the Fast DDS wedge (docs/design.md) like the
# services, bounded by node_runner's exit; a description is normally one datagram.
DESCRIPTION_QOS = QoSProfile(
    depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
)
# Chunks are never fragmented (msgs.stream_chunk), so a reliable reader of them is safe from the wedge.
CHUNK_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)


def default_checkpoint() -> str:
    """The shipped model if it is installed beside this module, else '' (which needs allow_untrained)."""
    return str(SHIPPED_MODEL) if SHIPPED_MODEL.is_file() else ""


def parameters() -> tuple[NodeParameter, ...]:
    """The node's parameters, declared from here (``morph_ros_util.parameters``) and listed by ``--help``."""
    return (
        NodeParameter(
            "checkpoint",
            default_checkpoint(),
            "policy .safetensors (config .json beside it); '' = untrained (needs allow_untrained)",
        ),
        NodeParameter("deterministic", True, "act with the Gaussian mean; false samples and publishes policy_info"),
        NodeParameter(
            "input_timeout",
            0.5,
            "wall seconds without a state answered before publishing zero efforts",
            (0.001, 3600.0),
        ),
        NodeParameter(
            "allow_untrained",
            False,
            "with checkpoint '': run a freshly initialised policy (efforts marked untrained_policy)",
            read_only=True,
        ),
        NodeParameter("seed", 0, "seed of the action sampling and of an untrained policy", read_only=True),
        NodeParameter(
            "accept_weights",
            True,
            f"adopt policies a trusted live trainer publishes on {WEIGHTS} (false: never)",
            read_only=True,
        ),
        NodeParameter(
            KEYS,
            Parameter.Type.STRING_ARRAY,
            f"public key files (OpenSSH ssh-ed25519 or PEM) whose signed {WEIGHTS} are adopted; none: live updates off",
            read_only=True,
        ),
        NodeParameter(
            "accept_unsigned_weights",
            False,
            f"FOR TESTS: adopt unsigned {WEIGHTS} from any peer on the domain",
            read_only=True,
        ),
        NodeParameter(
            "stream_chunk_period",
            0.1,
            f"seconds between {CHUNK_TOPIC} (this node's messages, for a live trainer); 0 = none",
            (0.0, 60.0),
            read_only=True,
        ),
        NodeParameter(
            "effort_order",
            "state",
            "efforts in the order of the state's joint names ('state') or in robot_description's depth-first order "
            "of its actuated joints ('description', for a JointGroupEffortController)",
            read_only=True,
        ),
        NodeParameter(
            "effort_units",
            "normalized",
            "efforts in the policy's [-1, 1] ('normalized') or each times its joint's URDF <limit effort> ('urdf', "
            "for a JointGroupEffortController; needs robot_description)",
            read_only=True,
        ),
    )


class MorphPolicyNode(Node):
    def __init__(self):
        super().__init__("morph_policy")
        declare_parameters(self, parameters())
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        p = self.get_parameter
        self._allow_untrained, self._seed = p("allow_untrained").value, p("seed").value
        order, units = effort_order(p("effort_order").value), effort_units(p("effort_units").value)  # main()
        self.watch = AnswerWatch(p("input_timeout").value, time.monotonic())  # counts on /diagnostics each second
        self._candidate: tuple[PolicyWeights, CheckpointTrust] | None = None  # checked, set after validation
        self._updates = PolicyUpdates(numpy_policy, None, self._trusted_keys(), p("accept_unsigned_weights").value)
        # Everything between a message and the efforts: this node only moves messages in and out of it.
        self.controller = Controller(
            deterministic=p("deterministic").value, seed=self._seed, effort_order=order, effort_units=units
        )
        self._use(*self._checked(p("checkpoint").value))  # CheckpointError: main()
        self._stream = StreamNotes(serialize_message)
        self._unfit: JointStateRecord | None = None
        """the latest state that fit no description (a new body's, come before its robot_description: the topics
        race at a swap): answered once a description is adopted, as a lockstep sim waits for it"""

        self._effort_pub = self.create_publisher(Float64MultiArray, "effort_commands", 10)
        self._info_pub = self.create_publisher(JointTrajectory, "policy_info", 10)
        # Sensor-data QoS (best effort, keep last): matches any publisher and never queues stale states.
        # Announcements first: one ready together with its first state is handled before it.
        self.create_subscription(Int64MultiArray, EPISODES, self._on_episode_start, EPISODE_QOS)
        self.create_subscription(Odometry, ODOM, self._on_odom, qos_profile_sensor_data)
        self.create_subscription(JointState, STATES, self._on_joint_states, qos_profile_sensor_data)
        self.create_subscription(String, DESCRIPTION, self._on_description, DESCRIPTION_QOS)
        if p("accept_weights").value and self._updates.enabled:
            self.create_subscription(UInt8MultiArray, WEIGHTS, self._on_weights, WEIGHTS_QOS)
        for notice in updates_notices(p("accept_weights").value, self._updates.enabled, self._updates.accept_unsigned):
            self._say(notice.text, notice.warn)
        self.create_timer(_WATCHDOG_PERIOD, self._on_watchdog)
        if p("stream_chunk_period").value > 0:
            self._chunk_pub = self.create_publisher(UInt8MultiArray, CHUNK_TOPIC, CHUNK_QOS)
            self.create_timer(p("stream_chunk_period").value, self._on_chunk_timer)
        self._diagnostics = InputDiagnostics(self, self.watch.counts)

    def _say(self, text: str, warn: bool, /) -> None:
        """Log one line said once or seldom, unthrottled. Two call sites, not one with a chosen severity: rclpy
        refuses a call site whose severity changes ("Logger severity cannot be changed between calls")."""
        if warn:
            self.get_logger().warn(text)
        else:
            self.get_logger().info(text)

    # -- policy and parameters ---------------------------------------------------
    def _trusted_keys(self):
        """The keys of ``trusted_keys``; a file that holds no usable public key is logged, counted and skipped."""
        try:
            paths = self.get_parameter(KEYS).value or []
        except ParameterUninitializedException:  # declared by type with no default: none given
            paths = []
        keys, taken, refused = self.watch.trusted_keys(list(paths))
        for line in taken:
            self.get_logger().info(line)
        for line in refused:
            self.get_logger().error(line)
        return keys

    def _checked(self, checkpoint: str) -> tuple[PolicyWeights, CheckpointTrust]:
        """The policy ``checkpoint`` names and what its signature says; ``CheckpointError`` for a file that cannot
        be used, or whose trusted signature does not match it."""
        weights = drivable(choose_policy(checkpoint, self._allow_untrained, self._seed))
        return weights, checkpoint_trust(weights, self._updates.keys)

    def _use(self, weights: PolicyWeights, trust: CheckpointTrust) -> None:
        """Run a checkpoint (or an untrained policy) from now on; pushed weights follow when newer than any taken
        before (and than the file's version, if a trusted key signed it)."""
        running = (weights, NumpyPolicy(weights))
        self._updates.replace(running, trust.order)
        self._weights, self.controller.policy = running
        if weights.trained:
            self.get_logger().info(f"policy loaded from {weights.source} ({trust.description})")
        else:
            self.get_logger().warn(
                f"running an UNTRAINED policy ({weights.source}); every effort is marked {UNTRAINED_LABEL!r}"
            )

    def _validate_parameters(self, params: list[Parameter]) -> SetParametersResult:
        # Types and ranges: the table's descriptors, which rclpy enforces before this is called.
        for param in params:
            if param.name == "checkpoint":
                try:
                    self._candidate = self._checked(param.value)
                except CheckpointError as err:
                    return SetParametersResult(successful=False, reason=f"refused checkpoint {err}")
        return SetParametersResult(successful=True)

    def _apply_parameters(self, params: list[Parameter]) -> None:
        for param in params:
            if param.name == "checkpoint" and self._candidate is not None:
                self._use(*self._candidate)
                self._candidate = None
            elif param.name == "deterministic":
                self.controller.deterministic = param.value
            elif param.name == "input_timeout":
                self.watch.input_timeout = param.value

    # -- inputs -----------------------------------------------------------------
    def _reject(self, what: str, err: Exception, reason: str) -> None:
        self._rejected(self.watch.reject(what, reason, err))

    def _rejected(self, notice: Notice) -> None:
        if notice.warn:  # two call sites: rclpy refuses one whose severity changes, which ended the node once
            self.get_logger().warn(notice.text, throttle_duration_sec=_LOG_THROTTLE)
        else:  # counted, not a fault (a hand-over between bodies)
            self.get_logger().info(notice.text, throttle_duration_sec=_LOG_THROTTLE)

    def _on_weights(self, msg: UInt8MultiArray) -> None:
        self.watch.counts.received(WEIGHTS)
        offer = self._updates.offer([d.label for d in msg.layout.dim], [d.size for d in msg.layout.dim], msg.data)
        notice = self.watch.weights(offer, self._updates.rejected_total)
        if offer.outcome == "rejected":
            self.get_logger().warn(notice.text, throttle_duration_sec=_WEIGHTS_LOG_THROTTLE)
        elif notice is not None:
            self._say(notice.text, notice.warn)

    def _on_episode_start(self, msg: Int64MultiArray) -> None:
        self.watch.counts.received(EPISODES)
        self._note(EPISODES, msg)
        try:
            start = unpack_episode_start(0, msg.layout.dim[0].label if msg.layout.dim else "", msg.data)
        except EpisodeStartError as err:
            self._reject(EPISODES, err, "layout")
            return
        self.controller.episode_start(start.stamp_ns)

    def _on_odom(self, msg: Odometry) -> None:
        self.watch.counts.received(ODOM)
        self._note(ODOM, msg)
        q, p = msg.pose.pose.orientation, msg.pose.pose.position
        lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
        try:
            stamp_ns = check_stamp(msg.header.stamp.sec, msg.header.stamp.nanosec)
            odom = OdometryRecord.of(
                0, stamp_ns, (p.x, p.y, p.z), (q.x, q.y, q.z, q.w), (lin.x, lin.y, lin.z), (ang.x, ang.y, ang.z)
            )
            ready = self.controller.odometry(odom)  # checked in every width: unwrapped when a state uses it
        except (JointStateError, StampError) as err:
            self._reject(ODOM, err, "stamp" if isinstance(err, StampError) else "odometry")
            return
        for state in ready:
            self._act(state)

    def _on_description(self, msg: String) -> None:
        self.watch.counts.received(DESCRIPTION)
        self._stream.note_description(msg, time.time_ns())
        offer = self.controller.description(msg.data)
        if offer.outcome == "adopted":
            self._stream.adopted_description(msg)  # the current one, for a stream reader that matches later
        notice = self.watch.description(offer, self.controller.descriptions, self.controller.joint_features)
        if notice is not None and notice.warn:  # a robot swapped 100 times a second: throttled
            self.get_logger().warn(notice.text, throttle_duration_sec=_DESCRIPTION_LOG_THROTTLE)
        elif notice is not None:
            self.get_logger().info(notice.text, throttle_duration_sec=_DESCRIPTION_LOG_THROTTLE)
        if offer.outcome == "adopted":
            self._answer_unfit()

    def _on_joint_states(self, msg: JointState) -> None:
        self.watch.counts.received(STATES)
        self._note(STATES, msg)
        try:
            stamp_ns = check_stamp(msg.header.stamp.sec, msg.header.stamp.nanosec)
            state = JointStateRecord(0, stamp_ns, tuple(msg.name), msg.position, msg.velocity, msg.effort)
            ready = self.controller.state(state, time.monotonic())  # laid onto the tree, or waits for its odometry
        except (JointStateError, StampError) as err:
            self._reject(STATES, err, "stamp" if isinstance(err, StampError) else "joint_state")
            return
        except JointMapError as err:
            self._unfit = state if err.code in HANDOVER_CODES else None
            unmapped = self.watch.unmapped(err.code, err, driving=bool(self.controller.names))
            if unmapped.rejection is not None:
                self._rejected(unmapped.rejection)
            elif unmapped.notice is not None and unmapped.throttled:  # the robot before a swap
                self.get_logger().info(unmapped.notice.text, throttle_duration_sec=_LOG_THROTTLE)
            elif unmapped.notice is not None:  # waiting for a description, said once
                self._say(unmapped.notice.text, unmapped.notice.warn)
            return
        self._unfit = None
        for state in ready:
            self._act(state)

    def _answer_unfit(self) -> None:
        """A description was adopted: the state that fit none before it, if it fits now, is answered (else the
        lockstep sim waits its effort timeout and re-sends it, a stall at every body swap that lost the race)."""
        state, self._unfit = self._unfit, None
        if state is None:
            return
        try:
            ready = self.controller.state(state, time.monotonic())
        except JointMapError:  # not this robot's either: already counted when it came
            return
        for ready_state in ready:
            self._act(ready_state)

    def _on_watchdog(self) -> None:
        now = time.monotonic()
        late = self.controller.expired(now)
        if late is not None:
            self.get_logger().warn(
                "no odometry with the joint state's stamp: using the latest one", throttle_duration_sec=_LOG_THROTTLE
            )
            self._act(late)
        names = self.controller.names  # the robot answered last, in the efforts' order
        due, notice = self.watch.silence(now, answering=bool(names))
        if notice is not None:
            self._say(notice.text, notice.warn)  # info after a hand-over, else a warning
        if due:
            self._publish_efforts(np.zeros(len(names)), SILENCE_TAG, names, self.controller.layout)  # answers none

    # -- acting -----------------------------------------------------------------
    def _act(self, ready: Ready) -> None:
        """Answer one state (``Controller.answer``) and publish the answer."""
        adopted = self._updates.adopted
        self._weights, self.controller.policy = self._updates.current()  # new weights between two answers only
        if self._updates.adopted != adopted:
            self.get_logger().info(f"running weights version {self._updates.version} ({self._weights.source})")
        notice = self.watch.fallback(ready.generation)
        if notice is not None:
            self._say(notice.text, notice.warn)
        try:
            out = self.controller.answer(ready)
        except PolicyOutputError as err:
            self._reject(STATES, err, "policy_output")  # nothing goes out: the watchdog's zero efforts follow
            return
        self.watch.answered(time.monotonic())
        # Say which state this answers (a lockstep sim drops answers to states it re-sent).
        sec, nanosec = from_ns(out.stamp_ns)
        self._publish_efforts(out.efforts, answer_tag(sec, nanosec), out.names, out.layout)
        if out.info is not None:
            self._publish_info(sec, nanosec, out.names, out.info)
        self._publish_chunks(*self._stream.serialize())  # after the answer: the loop waits on it, not on this

    def _publish_efforts(self, efforts: np.ndarray, tag: str, names: tuple[str, ...], layout: str) -> None:
        n = len(efforts)
        msg = Float64MultiArray(data=array.array("d", np.asarray(efforts, dtype=np.float64).tobytes()))
        # The answer's tag, the joints the efforts are for in the data's order, and the joint layout they were
        # computed on (msgs.effort_names: a sim refuses efforts computed on another tree).
        msg.layout.dim = [
            MultiArrayDimension(label=tag, size=n, stride=n),
            MultiArrayDimension(label=names_label(names), size=1, stride=1),
            MultiArrayDimension(label=tree_label(layout), size=1, stride=1),
        ]
        if not self._weights.trained:
            msg.layout.dim.append(MultiArrayDimension(label=UNTRAINED_LABEL, size=1, stride=1))
        self._effort_pub.publish(msg)
        self._note("effort_commands", msg)

    def _publish_info(self, sec: int, nanosec: int, names: tuple[str, ...], fields: dict[str, np.ndarray]) -> None:
        point = JointTrajectoryPoint()
        for field, values in fields.items():
            setattr(point, field, array.array("d", values.tobytes()))
        info = JointTrajectory()
        info.header.stamp.sec, info.header.stamp.nanosec = sec, nanosec
        info.header.frame_id = policy_version_frame_id(self._updates.version)
        info.joint_names = list(names)
        info.points = [point]
        self._info_pub.publish(info)
        self._note("policy_info", info)

    # -- the stream for a live trainer (protocol.stream_notes) ---------------------
    def _note(self, topic: str, msg) -> None:
        self._stream.note(topic, msg, time.time_ns())

    def _publish_chunks(self, chunks: list[bytes], errors: list[str]) -> None:
        for err in errors:  # larger than a chunk: the trainer sees a gap in the stream there
            self.get_logger().warn(err, throttle_duration_sec=_LOG_THROTTLE)
        for chunk in chunks:
            self._chunk_pub.publish(UInt8MultiArray(data=chunk))

    def _on_chunk_timer(self) -> None:
        self._publish_chunks(*self._stream.tick(self._chunk_pub.get_subscription_count() > 0, time.time_ns()))


def main(args=None) -> NoReturn:
    # A checkpoint that cannot be loaded (or none without allow_untrained), or an unknown effort_order, is one
    # line and exit 1.
    node_runner.run(MorphPolicyNode, "morph_policy", args, startup_errors=(CheckpointError, EffortOrderError),
                    parameters=parameters(), summary=__doc__.splitlines()[0])  # fmt: skip


if __name__ == "__main__":
    main()
