"""The morphology-agnostic GNN policy as a ROS 2 node: JointState (+ Odometry) in, efforts out.

Each ``joint_states`` message is its own robot description: the joint graph
is built from it (joint order = message order, joint 0 next to the torso),
so any chain length works with no restart and no parameter change. The
latest ``odom`` gives the global features; see ``morph_core.msgs.joint_state``
for how they are turned back into the training features (yaw unwrapped,
body-frame twist rotated to the world frame; the unwrapping restarts with
each new chain and with each episode announced on ``episode_start``, see
``morph_core.protocol.episode_tracker``). If the odometry for a state's
stamp has not arrived yet the state waits for it briefly (a simulator
publishes both at once; a state must not be paired with the previous
odometry, or a lockstep loop would not be deterministic; the rule is
``morph_core.protocol.pairing``).

Outputs
- ``effort_commands`` (std_msgs/Float64MultiArray): one effort per joint, in
  the message's joint order, clipped to [-1, 1]; ``layout.dim[0]`` is
  labelled ``joints@<sec>.<nanosec>`` with the stamp of the state answered.
- ``policy_info`` (trajectory_msgs/JointTrajectory, only when sampling): what
  a trainer needs, stamped with the state's stamp; layout in ``morph_core.msgs.policy_info``.

No state answered for ``input_timeout`` -> zero efforts at 25 Hz for the last
chain seen, labelled ``silence`` (``msgs.stamps.SILENCE_TAG``: they answer no
state, so a lockstep sim never steps on them). Malformed messages are
rejected, counted and logged (throttled);
so is a state for which the policy's output is not finite (nothing is
published for it, so the zero efforts follow); the node keeps answering good
ones. What each input received, rejected and ignored, by reason, goes out on
``/diagnostics`` every second (``morph_ros_util.diagnostics``); each case and
what the node does with it: ``docs/robustness.md``.

Policy (``policy_choice``): ``checkpoint`` (default: the shipped model) is
loaded with NumPy alone, without torch; a file that cannot be loaded stops
the node at start-up with one line naming it and the reason (exit code 1),
and is refused at runtime with the reason in the ``SetParametersResult``
while the current policy keeps running. An untrained policy runs only with
``checkpoint:=''`` and ``allow_untrained:=true``; its efforts then carry a
second ``layout.dim`` labelled ``untrained_policy``.

Live training: a trainer publishes each new policy on ``policy_weights``
(``morph_core.msgs.policy_weights``: the safetensors bytes, the config, a
version and the trainer's Ed25519 signature). Weights are code for the
robot, so the node takes them only from a trainer it trusts: ``trusted_keys``
lists public key files (``morph-keys new``; OpenSSH format), and only
weights one of them signed, newer than any taken before, are adopted
(``protocol.trust``, ``protocol.policy_updates``). With no trusted key the
node does not even subscribe, and says so once at start-up; unsigned
weights are taken only with ``accept_unsigned_weights:=true``, an opt-in for
tests that the node logs loudly. Adopted weights are checked as a checkpoint
is and taken between two answers, never within one; anything refused is
counted by reason on ``/diagnostics`` and logged (throttled), and the
current policy keeps running. Every ``policy_info`` says which weights
produced it: ``header.frame_id`` is ``weights@<version>`` ('' for a checkpoint
file). Setting ``checkpoint`` replaces pushed weights until the trainer's next
version. A checkpoint file runs whether signed or not (it is on the robot's
own disk); the node says whether it is signed and by which key, and refuses
one whose trusted signature does not match its bytes.

For a live trainer the node also hands over its whole message stream on
``stream_chunks`` (``morph_core.msgs.stream_chunk``), every
``stream_chunk_period`` seconds or 60 KB: each ``episode_start``,
``joint_states`` and ``odom`` it received and each ``effort_commands`` and
``policy_info`` it sent, serialized as on the wire, in its order. A trainer
reading them wakes once per chunk instead of four times per step. Messages
are serialized after the answer to their state has gone out, and only
while a reader is matched.

QoS: every input is read best effort, keep last (``joint_states`` and
``odom`` depth 5 as sensor data, ``episode_start`` depth 10, volatile): it
matches reliable and best-effort publishers, never queues stale states, and
a reliable reader in Fast DDS 2.14 can be driven into a take that never
returns by a peer's fragmented sample and a GAP (see docs). That holds for
``policy_weights`` too (best effort, keep last 1): the trainer's writer is
reliable and transient local for tools that record it, and it re-publishes
the latest weights every second, which is how a node that starts late gets
them (a best-effort reader is sent no history). Outputs are reliable,
volatile, keep last 10.
"""

from __future__ import annotations

import array
import math
import time
from pathlib import Path
from typing import NoReturn

import numpy as np
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor, SetParametersResult
from rclpy.exceptions import ParameterUninitializedException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.serialization import serialize_message
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, Int64MultiArray, MultiArrayDimension, UInt8MultiArray
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from morph_core.msgs.joint_state import (
    JointStateError,
    YawUnwrapper,
    global_features,
    validate_joint_state,
)
from morph_core.msgs.policy_info import pack_policy_info
from morph_core.msgs.policy_weights import TOPIC as WEIGHTS_TOPIC
from morph_core.msgs.policy_weights import PolicyWeights as WeightsMessage
from morph_core.msgs.policy_weights import policy_version_frame_id
from morph_core.msgs.stamps import SILENCE_TAG, StampError, answer_tag, check_stamp, to_ns
from morph_core.msgs.stream_chunk import TOPIC as CHUNK_TOPIC
from morph_core.msgs.stream_chunk import ChunkWriter
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.weights import CheckpointError, PolicyWeights, weights_from_arrays
from morph_core.protocol.episode_start import EpisodeStartError, unpack_episode_start
from morph_core.protocol.episode_tracker import EpisodeTracker
from morph_core.protocol.input_counts import InputCounts
from morph_core.protocol.pairing import StatePairing
from morph_core.protocol.policy_updates import CheckpointTrust, PolicyUpdates, checkpoint_trust
from morph_core.protocol.trust import load_trusted_keys
from morph_policy_node.policy_choice import UNTRAINED_LABEL, PolicyOutputError, answer, choose_policy
from morph_ros_util import node_runner
from morph_ros_util.diagnostics import InputDiagnostics

SHIPPED_MODEL = Path(__file__).resolve().parent / "models" / "swimmer_gnn.safetensors"
_WATCHDOG_PERIOD = 0.04  # also the rate of zero efforts while the input is silent
_LOG_THROTTLE = 5.0
_WEIGHTS_LOG_THROTTLE = 1.0
STATES, ODOM, EPISODES, WEIGHTS = "joint_states", "odom", "episode_start", WEIGHTS_TOPIC  # inputs, as counted
KEYS = "trusted_keys"  # the key files, counted as an input: each loaded or rejected with its reason
# Live announcements only (volatile), best effort: matches the sim's latched reliable publisher and
# no publisher can make this reader wait on repairs.
EPISODE_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)
# The newest weights only; best effort for the same reason as every input (the trainer re-publishes).
WEIGHTS_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)
# Chunks are never fragmented (msgs.stream_chunk), so a reliable reader of them is safe from the wedge.
CHUNK_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)


def pushed_policy(weights: WeightsMessage) -> tuple[PolicyWeights, NumpyPolicy]:
    """A trainer's weights, checked like a checkpoint (``CheckpointError``, a ``ValueError``, if they do not fit
    their config), and the NumPy policy that runs them."""
    checked = weights_from_arrays(
        weights.config, weights.tensors, f"policy_weights version {weights.version}", trained=weights.version > 0,
        metadata=weights.metadata,
    )  # fmt: skip
    return checked, NumpyPolicy(checked)


def default_checkpoint() -> str:
    """The shipped model if it is installed beside this module, else '' (which needs allow_untrained)."""
    return str(SHIPPED_MODEL) if SHIPPED_MODEL.is_file() else ""


class MorphPolicyNode(Node):
    def __init__(self):
        super().__init__("morph_policy")
        self.declare_parameter(
            "checkpoint",
            default_checkpoint(),
            ParameterDescriptor(
                description="policy .safetensors (config .json beside it); '' = untrained (needs allow_untrained)"
            ),
        )
        self.declare_parameter(
            "deterministic",
            True,
            ParameterDescriptor(description="act with the Gaussian mean; false samples and publishes policy_info"),
        )
        self.declare_parameter(
            "input_timeout",
            0.5,
            ParameterDescriptor(
                description="wall seconds without a state answered before publishing zero efforts",
                floating_point_range=[FloatingPointRange(from_value=0.001, to_value=3600.0, step=0.0)],
            ),
        )
        self.declare_parameter(
            "allow_untrained",
            False,
            ParameterDescriptor(
                description="with checkpoint '': run a freshly initialised policy (efforts marked untrained_policy)",
                read_only=True,
            ),
        )
        self.declare_parameter(
            "seed",
            0,
            ParameterDescriptor(description="seed of the action sampling and of an untrained policy", read_only=True),
        )
        self.declare_parameter(
            "accept_weights",
            True,
            ParameterDescriptor(
                description=f"adopt policies a trusted live trainer publishes on {WEIGHTS_TOPIC} (false: never)",
                read_only=True,
            ),
        )
        self.declare_parameter(
            KEYS,
            Parameter.Type.STRING_ARRAY,
            ParameterDescriptor(
                description=f"public key files (OpenSSH ssh-ed25519 or PEM) whose signed {WEIGHTS_TOPIC} are adopted;"
                " none: live updates off",
                read_only=True,
            ),
        )
        self.declare_parameter(
            "accept_unsigned_weights",
            False,
            ParameterDescriptor(
                description=f"FOR TESTS: adopt unsigned {WEIGHTS_TOPIC} from any peer on the domain", read_only=True
            ),
        )
        self.declare_parameter(
            "stream_chunk_period",
            0.1,
            ParameterDescriptor(
                description=f"seconds between {CHUNK_TOPIC} (this node's messages, for a live trainer); 0 = none",
                floating_point_range=[FloatingPointRange(from_value=0.0, to_value=60.0, step=0.0)],
                read_only=True,
            ),
        )
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        p = self.get_parameter
        self._allow_untrained = p("allow_untrained").value
        self._seed = p("seed").value
        self.counts = InputCounts([STATES, ODOM, EPISODES, WEIGHTS, KEYS])  # on /diagnostics every second
        self._candidate: tuple[PolicyWeights, CheckpointTrust] | None = None  # checked, set after validation
        self._updates = PolicyUpdates(pushed_policy, None, self._trusted_keys(), p("accept_unsigned_weights").value)
        self._use(*self._checked(p("checkpoint").value))  # CheckpointError: main()
        self._deterministic = p("deterministic").value
        self._input_timeout = p("input_timeout").value
        self._rng = np.random.default_rng(self._seed)

        self._effort_pub = self.create_publisher(Float64MultiArray, "effort_commands", 10)
        self._info_pub = self.create_publisher(JointTrajectory, "policy_info", 10)
        # Sensor-data QoS (best effort, keep last): matches any publisher and never queues stale states.
        # Announcements first: one ready together with its first state is handled before it.
        self.create_subscription(Int64MultiArray, "episode_start", self._on_episode_start, EPISODE_QOS)
        self.create_subscription(Odometry, "odom", self._on_odom, qos_profile_sensor_data)
        self.create_subscription(JointState, "joint_states", self._on_joint_states, qos_profile_sensor_data)
        if p("accept_weights").value and self._updates.enabled:
            self.create_subscription(UInt8MultiArray, WEIGHTS_TOPIC, self._on_weights, WEIGHTS_QOS)
        self._say_how_updates_are_taken(p("accept_weights").value)
        self.create_timer(_WATCHDOG_PERIOD, self._on_watchdog)
        self._chunks = ChunkWriter()
        self._unserialized: list[tuple[str, int, object]] = []  # (topic, log ns, message) for the next chunk
        self._streaming = False  # a reader of stream_chunks is matched
        self.unstreamed = 0
        if p("stream_chunk_period").value > 0:
            self._chunk_pub = self.create_publisher(UInt8MultiArray, CHUNK_TOPIC, CHUNK_QOS)
            self.create_timer(p("stream_chunk_period").value, self._on_chunk_timer)

        self.rejected = 0
        self._diagnostics = InputDiagnostics(self, self.counts)
        self._odom = None  # (quaternion, body linear xy, angular z) of the latest valid odometry
        self._unwrap = YawUnwrapper()
        self._episodes = EpisodeTracker()  # when the unwrapping restarts
        self._pairing: StatePairing[tuple] = StatePairing()  # states wait here for their odometry
        self._names: list[str] = []  # joints of the last chain answered
        self._last_answer = time.monotonic()  # the watchdog's zero efforts follow silence from here
        self._silent = False

    # -- policy and parameters ---------------------------------------------------
    def _trusted_keys(self):
        """The keys of ``trusted_keys``; a file that holds no usable public key is logged, counted and skipped."""
        try:
            paths = self.get_parameter(KEYS).value or []
        except ParameterUninitializedException:  # declared by type with no default: none given
            paths = []
        keys, errors = load_trusted_keys(list(paths))
        for key in keys.keys.values():
            self.counts.received(KEYS)
            self.get_logger().info(f"trusting weights signed by {key.fingerprint} ({key.source})")
        for err in errors:
            self.counts.received(KEYS)
            self.counts.rejected(KEYS, "key_file", str(err))
            self.get_logger().error(f"trusted key file refused, its signatures will not be taken: {err}")
        return keys

    def _say_how_updates_are_taken(self, accept_weights: bool) -> None:
        log = self.get_logger()
        if not accept_weights:
            log.info(f"live policy updates are off (accept_weights:=false): {WEIGHTS_TOPIC} is not read")
        elif not self._updates.enabled:
            log.info(
                f"live policy updates are OFF: no trusted key, so {WEIGHTS_TOPIC} is not read. To take a trainer's "
                "weights, make a key pair (morph-keys new KEY), start the trainer with --signing-key KEY and this "
                f"node with -p {KEYS}:=[KEY.pub]"
            )
        if accept_weights and self._updates.accept_unsigned:
            log.warn(
                f"accept_unsigned_weights:=true: ANY peer on this DDS domain can replace this robot's policy through "
                f"{WEIGHTS_TOPIC}. For tests only; use {KEYS} on a robot"
            )

    def _checked(self, checkpoint: str) -> tuple[PolicyWeights, CheckpointTrust]:
        """The policy ``checkpoint`` names and what its signature says; ``CheckpointError`` for a file that cannot
        be used, or whose trusted signature does not match it."""
        weights = choose_policy(checkpoint, self._allow_untrained, self._seed)
        return weights, checkpoint_trust(weights, self._updates.keys)

    def _use(self, weights: PolicyWeights, trust: CheckpointTrust) -> None:
        """Run a checkpoint (or an untrained policy) from now on; pushed weights follow when newer than any taken
        before (and than the file's version, if a trusted key signed it)."""
        running = (weights, NumpyPolicy(weights))
        self._updates.replace(running, trust.order)
        self._weights, self._policy = running
        if weights.trained:
            self.get_logger().info(f"policy loaded from {weights.source} ({trust.description})")
        else:
            self.get_logger().warn(
                f"running an UNTRAINED policy ({weights.source}); every effort is marked {UNTRAINED_LABEL!r}"
            )

    def _validate_parameters(self, params: list[Parameter]) -> SetParametersResult:
        for param in params:
            if param.name == "checkpoint":
                if param.type_ != Parameter.Type.STRING:
                    return SetParametersResult(successful=False, reason="checkpoint must be a string path")
                try:
                    self._candidate = self._checked(param.value)
                except CheckpointError as err:
                    return SetParametersResult(successful=False, reason=f"refused checkpoint {err}")
            elif param.name == "input_timeout":
                if param.type_ != Parameter.Type.DOUBLE or not (math.isfinite(param.value) and param.value > 0):
                    return SetParametersResult(successful=False, reason="input_timeout must be a finite double > 0")
            elif param.name == "deterministic" and param.type_ != Parameter.Type.BOOL:
                return SetParametersResult(successful=False, reason="deterministic must be a bool")
        return SetParametersResult(successful=True)

    def _apply_parameters(self, params: list[Parameter]) -> None:
        for param in params:
            if param.name == "checkpoint" and self._candidate is not None:
                self._use(*self._candidate)
                self._candidate = None
            elif param.name == "deterministic":
                self._deterministic = param.value
            elif param.name == "input_timeout":
                self._input_timeout = param.value

    # -- inputs -----------------------------------------------------------------
    def _reject(self, what: str, err: Exception, reason: str = "invalid") -> None:
        self.rejected += 1
        self.counts.rejected(what, reason, str(err))
        self.get_logger().warn(f"rejected {what} ({self.rejected} so far): {err}", throttle_duration_sec=_LOG_THROTTLE)

    def _on_weights(self, msg: UInt8MultiArray) -> None:
        self.counts.received(WEIGHTS)
        labels, sizes = [d.label for d in msg.layout.dim], [d.size for d in msg.layout.dim]
        offer = self._updates.offer(labels, sizes, msg.data)
        if offer.outcome == "ignored":
            self.counts.ignored(WEIGHTS, offer.code)
        if offer.outcome == "rejected":
            self.counts.rejected(WEIGHTS, offer.code, offer.reason)
            # Counted with the other rejections; logged on its own (weights come about once a second, so a
            # second's throttle shows each bad one a trainer sends, yet a flood cannot fill the log).
            self.rejected += 1
            self.get_logger().warn(
                f"rejected policy_weights ({self._updates.rejected_total} so far), current policy kept: {offer.reason}",
                throttle_duration_sec=_WEIGHTS_LOG_THROTTLE,
            )
        elif offer.outcome == "pending" and not offer.signer:
            self.get_logger().warn(f"UNSIGNED weights version {offer.version} received (accept_unsigned_weights): "
                                   "adopted at the next state")  # fmt: skip
        elif offer.outcome == "pending":
            self.get_logger().info(
                f"weights version {offer.version} signed by {offer.signer} received: adopted at the next state"
            )

    def _on_episode_start(self, msg: Int64MultiArray) -> None:
        self.counts.received(EPISODES)
        self._note(EPISODES, msg)
        label = msg.layout.dim[0].label if msg.layout.dim else ""
        try:
            start = unpack_episode_start(0, label, msg.data)
        except EpisodeStartError as err:
            self._reject(EPISODES, err, "layout")
            return
        if self._episodes.announced(start.stamp_ns):
            self._unwrap.reset()  # its first state was answered already: restart from the next one

    def _on_odom(self, msg: Odometry) -> None:
        self.counts.received(ODOM)
        self._note(ODOM, msg)
        q = msg.pose.pose.orientation
        lin, ang = msg.twist.twist.linear, msg.twist.twist.angular
        quat, body = (q.x, q.y, q.z, q.w), (lin.x, lin.y)
        try:
            global_features(quat, body, ang.z)  # validation only; unwrapping happens when a state uses it
            stamp_ns = check_stamp(msg.header.stamp.sec, msg.header.stamp.nanosec)
        except (JointStateError, StampError) as err:
            self._reject(ODOM, err, "stamp" if isinstance(err, StampError) else "odometry")
            return
        self._odom = (quat, body, ang.z)
        ready = self._pairing.odometry(stamp_ns)
        if ready is not None:
            self._act(*ready)

    def _on_joint_states(self, msg: JointState) -> None:
        self.counts.received(STATES)
        self._note(STATES, msg)
        try:
            pos, vel = validate_joint_state(msg.name, msg.position, msg.velocity)
            stamp_ns = check_stamp(msg.header.stamp.sec, msg.header.stamp.nanosec)
        except (JointStateError, StampError) as err:
            self._reject(STATES, err, "stamp" if isinstance(err, StampError) else "joint_state")
            return
        for ready in self._pairing.state(stamp_ns, (msg, list(msg.name), pos, vel), time.monotonic()):
            self._act(*ready)

    def _on_watchdog(self) -> None:
        now = time.monotonic()
        late = self._pairing.expired(now)
        if late is not None:
            self.get_logger().warn(
                "no odometry with the joint state's stamp: using the latest one", throttle_duration_sec=_LOG_THROTTLE
            )
            self._act(*late)
        if now - self._last_answer > self._input_timeout and self._names:
            if not self._silent:
                self.get_logger().warn(f"no state answered for {self._input_timeout} s: publishing zero efforts")
                self._silent = True
            self._publish_efforts(np.zeros(len(self._names)), SILENCE_TAG)  # answers no state

    # -- acting -----------------------------------------------------------------
    def _act(self, msg: JointState, names: list[str], pos: np.ndarray, vel: np.ndarray) -> None:
        stamp = msg.header.stamp
        adopted = self._updates.adopted
        self._weights, self._policy = self._updates.current()  # new weights between two answers only
        if self._updates.adopted != adopted:
            self.get_logger().info(f"running weights version {self._updates.version} ({self._weights.source})")
        new_episode = self._episodes.state(to_ns(stamp.sec, stamp.nanosec))
        if names != self._names or new_episode:
            self._names = names
            self._unwrap.reset()  # a new robot, or a new episode: its yaw starts afresh
        if self._odom is None:
            glob = np.zeros(4)  # no odometry yet: the torso at rest at the origin
        else:
            quat, body, wz = self._odom
            glob = global_features(quat, body, wz, self._unwrap)
        try:
            out = answer(self._policy, pos, vel, glob, None if self._deterministic else self._rng)
        except PolicyOutputError as err:
            self._reject(STATES, err, "policy_output")  # nothing goes out: the watchdog's zero efforts follow
            return
        self._silent = False
        self._last_answer = time.monotonic()
        # Say which state this answers (a lockstep sim drops answers to states it re-sent).
        self._publish_efforts(out.efforts, answer_tag(stamp.sec, stamp.nanosec))
        if out.mean is not None:
            self._publish_info(msg, names, out.action, out.mean)
        self._serialize_noted()  # after the answer: the loop waits on it, not on this

    def _publish_efforts(self, efforts: np.ndarray, tag: str) -> None:
        n = len(efforts)
        msg = Float64MultiArray(data=array.array("d", np.asarray(efforts, dtype=np.float64).tobytes()))
        msg.layout.dim = [MultiArrayDimension(label=tag, size=n, stride=n)]
        if not self._weights.trained:
            msg.layout.dim.append(MultiArrayDimension(label=UNTRAINED_LABEL, size=1, stride=1))
        self._effort_pub.publish(msg)
        self._note("effort_commands", msg)

    def _publish_info(self, msg: JointState, names: list[str], action: np.ndarray, mean: np.ndarray) -> None:
        fields = pack_policy_info(action, mean, self._policy.log_std)
        point = JointTrajectoryPoint()
        for field, values in fields.items():
            setattr(point, field, array.array("d", values.tobytes()))
        info = JointTrajectory()
        info.header.stamp = msg.header.stamp
        info.header.frame_id = policy_version_frame_id(self._updates.version)
        info.joint_names = names
        info.points = [point]
        self._info_pub.publish(info)
        self._note("policy_info", info)

    # -- the stream for a live trainer -------------------------------------------
    def _note(self, topic: str, msg) -> None:
        if self._streaming:
            self._unserialized.append((topic, time.time_ns(), msg))

    def _serialize_noted(self) -> None:
        for topic, log_ns, msg in self._unserialized:
            try:
                full = self._chunks.add(topic, log_ns, serialize_message(msg))
            except ValueError as err:  # larger than a chunk: the trainer sees a gap in the stream there
                self.unstreamed += 1
                self.get_logger().warn(f"not streamed ({self.unstreamed} so far): {err}",
                                       throttle_duration_sec=_LOG_THROTTLE)  # fmt: skip
                continue
            if full is not None:
                self._chunk_pub.publish(UInt8MultiArray(data=full))
        self._unserialized.clear()

    def _on_chunk_timer(self) -> None:
        self._serialize_noted()
        chunk = self._chunks.take()
        if chunk is not None:
            self._chunk_pub.publish(UInt8MultiArray(data=chunk))
        self._streaming = self._chunk_pub.get_subscription_count() > 0


def main(args=None) -> NoReturn:
    # A checkpoint that cannot be loaded (or none without allow_untrained) is one line and exit 1.
    node_runner.run(MorphPolicyNode, "morph_policy", args, startup_errors=(CheckpointError,))


if __name__ == "__main__":
    main()
