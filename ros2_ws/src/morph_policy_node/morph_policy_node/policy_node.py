"""The morphology-agnostic GNN policy as a ROS 2 node: JointState (+ Odometry) in, efforts out.

This module holds the node's topics, parameters and timers; everything
between a message and the efforts (pairing, episodes and the yaw
unwrapping, the joint map, the global features, the answer) is
``morph_core.protocol.controller.Controller``'s, the one the loopback and the
trainer's transition rebuild use too.

The joint graph comes from ``robot_description`` (std_msgs/String, a URDF,
as ``robot_state_publisher`` or the sim publishes it): its actuated hinges
(revolute and continuous joints; with ``<ros2_control>`` blocks, those with a
command interface) form the kinematic tree, joints in depth-first order
(``morph_core.policy.tree.read_urdf``). Every ``joint_states`` message is laid
onto that tree by joint name (``morph_core.protocol.joint_map``), so a driver
may list its joints in any order and add joints the policy does not drive
(fixed joints, hinges without a command interface), which it leaves alone.
A state that names a joint the description does not have (``unknown_joint``)
or lacks one of its actuated joints (``missing_joint``) is rejected with the
reason, nothing published for it. A new description at runtime (a robot
swapped, a chain grown) replaces the graph between two messages; a state of
the robot before it, still in flight (it fits the previous description and
not the new one), is ignored and counted as ``previous_description``, apart
from malformed input; the yaw unwrapping restarts with the new robot. A
description that is no robot (not XML, over 10 MB, a cycle, two roots,
duplicate names, more than 64 actuated joints...) is rejected with its
reason and the current graph is kept; the same text again changes nothing
(``morph_core.protocol.robot_description``).

Without any description the node keeps the fallback of a chain robot: each
state's joints form a chain in message order, joint 0 next to the torso, so
any chain length works with no description, no restart and no parameter
change (it says so once, at the first state it answers).

The latest ``odom`` gives the global features, as many as the policy reads
(4, a swimmer's: yaw unwrapped, yaw rate, the body-frame twist rotated to
the world frame; 12, a legged body's in 3-D; ``morph_core.msgs.joint_state``).
The unwrapping restarts with each new robot and with each episode announced
on ``episode_start`` (the rule: ``morph_core.protocol.controller``). If the odometry for a state's
stamp has not arrived yet the state waits for it briefly (a simulator
publishes both at once; a state must not be paired with the previous
odometry, or a lockstep loop would not be deterministic; the rule is
``morph_core.protocol.pairing``).

Outputs
- ``effort_commands`` (std_msgs/Float64MultiArray): one effort per actuated
  joint, clipped to [-1, 1] (``effort_units:=normalized``, the default), or
  that times the joint's URDF ``<limit effort>`` (``effort_units:=urdf``: a
  description whose actuated joints lack a usable limit is refused as
  ``effort_limit``, and no state is answered before one with limits has been
  adopted, ``no_effort_limits``); ``layout.dim[0]`` is labelled
  ``joints@<sec>.<nanosec>`` with the stamp of the state answered, and
  ``layout.dim[1]`` (size 1, stride 1) ``names=<JSON list>`` names the joints
  in the data's order (``morph_core.msgs.effort_names``). The order is
  ``effort_order``'s: ``state`` (default) that of the names in the state
  answered, its unactuated joints left out (with no description: the
  message's order, as before); ``description`` the description's actuated
  joints in its depth-first order, whatever the state's order.
  ``layout.dim[2]`` (size 1, stride 1) ``tree=<16 hex digits>`` is the joint
  layout the efforts were computed on (``KinematicTree.layout_hash``): a sim
  refuses efforts computed on another tree, as happens when a new body's
  first state arrives before its description.
- ``policy_info`` (trajectory_msgs/JointTrajectory, only when sampling): what
  a trainer needs, stamped with the state's stamp; ``joint_names`` lists the
  joints in the order of its arrays, the efforts' order; layout in
  ``morph_core.msgs.policy_info``.

Wiring to ros2_control. With the default order, a controller or bridge that
reads the names dimension maps each effort to its joint by name (a command
without it is in the order of the state it answers). With
``effort_order:=description`` the efforts always come in the same order, the
one a ``JointGroupEffortController`` (``effort_controllers``) expects when its
``joints:`` list is the URDF's actuated joints in the description's
depth-first order (parent before child, a link's child joints in document
order; the node logs the count when it reads the description, and the names
dimension lists them); remap ``effort_commands`` to the controller's
``~/commands``, and with ``effort_units:=urdf`` it takes them in its joints'
units (``docs/robustness.md``).

No state answered for ``input_timeout`` -> zero efforts at 25 Hz for the last
robot seen (named as its efforts are), labelled ``silence``
(``msgs.stamps.SILENCE_TAG``: they answer no state, so a lockstep sim never
steps on them). Malformed messages are rejected, counted and logged
(throttled); so is a state for which the policy's output is not finite (nothing is
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
``policy_info`` it sent, serialized as on the wire, in its order, and each
``robot_description`` it received (the current one first when a reader
matches later) once the chunk layout lists that topic
(``msgs.stream_chunk.TOPICS``). A trainer reading them wakes once per chunk
instead of four times per step. Messages
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
them (a best-effort reader is sent no history). ``robot_description`` is
the exception: reliable, transient local, keep last 1, so a description
published before the node started still arrives (nobody re-publishes a
latched URDF). That reader is exposed to the wedge like the parameter
services are, and bounded the same way (``morph_ros_util.node_runner``
ends a node stuck for 2 s; its supervisor restarts it); a description is
normally one datagram. Outputs are reliable, volatile, keep last 10.
"""

from __future__ import annotations

import array
import math
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
from morph_core.msgs.policy_weights import TOPIC as WEIGHTS_TOPIC
from morph_core.msgs.policy_weights import PolicyWeights as WeightsMessage
from morph_core.msgs.policy_weights import policy_version_frame_id
from morph_core.msgs.records import JointStateRecord, OdometryRecord
from morph_core.msgs.stamps import SILENCE_TAG, StampError, answer_tag, check_stamp, from_ns
from morph_core.msgs.stream_chunk import TOPIC as CHUNK_TOPIC
from morph_core.msgs.stream_chunk import TOPICS as CHUNK_TOPICS
from morph_core.msgs.stream_chunk import ChunkWriter
from morph_core.policy.numpy_actor import NumpyPolicy
from morph_core.policy.weights import CheckpointError, PolicyWeights, weights_from_arrays
from morph_core.protocol.controller import (
    NO_DESCRIPTION,
    Controller,
    EffortOrderError,
    PolicyOutputError,
    Ready,
    effort_order,
    effort_units,
    policy_error,
)
from morph_core.protocol.input_counts import InputCounts
from morph_core.protocol.joint_map import JointMapError
from morph_core.protocol.policy_updates import CheckpointTrust, PolicyUpdates, checkpoint_trust
from morph_core.protocol.robot_description import PREVIOUS_DESCRIPTION
from morph_core.protocol.trust import load_trusted_keys
from morph_policy_node.policy_choice import UNTRAINED_LABEL, choose_policy
from morph_ros_util import node_runner
from morph_ros_util.diagnostics import InputDiagnostics
from morph_ros_util.parameters import NodeParameter, declare_parameters

SHIPPED_MODEL = Path(__file__).resolve().parent / "models" / "swimmer_gnn.safetensors"
_WATCHDOG_PERIOD = 0.04  # also the rate of zero efforts while the input is silent
_LOG_THROTTLE = 5.0
_WEIGHTS_LOG_THROTTLE = 1.0
STATES, ODOM, EPISODES, WEIGHTS = "joint_states", "odom", "episode_start", WEIGHTS_TOPIC  # inputs, as counted
DESCRIPTION = "robot_description"  # an input too
_DESCRIPTION_LOG_THROTTLE = 1.0  # a bad description is rare and says why the robot is not driven: show each
_WAITING = (
    f"the policy reads joint descriptions: waiting for {DESCRIPTION} (no chain fallback); states are not answered "
    "until one is adopted"
)  # said once
KEYS = "trusted_keys"  # the key files, counted as an input: each loaded or rejected with its reason
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


def pushed_policy(weights: WeightsMessage) -> tuple[PolicyWeights, NumpyPolicy]:
    """A trainer's weights, checked like a checkpoint (``CheckpointError``, a ``ValueError``, if they do not fit
    their config or read global features no controller builds), and the NumPy policy that runs them."""
    source = f"policy_weights version {weights.version}"
    checked = weights_from_arrays(
        weights.config, weights.tensors, source, trained=weights.version > 0, metadata=weights.metadata
    )
    return _drivable(checked), NumpyPolicy(checked)


def _drivable(weights: PolicyWeights) -> PolicyWeights:
    """``weights`` if the controller can build their inputs from the topics, else ``CheckpointError``."""
    error = policy_error(weights.config)
    if error is not None:
        raise CheckpointError(weights.source, f"the policy {error}")
    return weights


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
            f"adopt policies a trusted live trainer publishes on {WEIGHTS_TOPIC} (false: never)",
            read_only=True,
        ),
        NodeParameter(
            KEYS,
            Parameter.Type.STRING_ARRAY,
            f"public key files (OpenSSH ssh-ed25519 or PEM) whose signed {WEIGHTS_TOPIC} are adopted; none: live "
            "updates off",
            read_only=True,
        ),
        NodeParameter(
            "accept_unsigned_weights",
            False,
            f"FOR TESTS: adopt unsigned {WEIGHTS_TOPIC} from any peer on the domain",
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
        self._allow_untrained = p("allow_untrained").value
        self._seed = p("seed").value
        order, units = effort_order(p("effort_order").value), effort_units(p("effort_units").value)  # main()
        self.counts = InputCounts([STATES, ODOM, EPISODES, WEIGHTS, KEYS, DESCRIPTION])  # on /diagnostics each second
        self._candidate: tuple[PolicyWeights, CheckpointTrust] | None = None  # checked, set after validation
        self._updates = PolicyUpdates(pushed_policy, None, self._trusted_keys(), p("accept_unsigned_weights").value)
        # Everything between a message and the efforts (pairing, episodes, the joint map, the features, the
        # answer): this node only moves messages in and out of it.
        self.controller = Controller(
            deterministic=p("deterministic").value, seed=self._seed, effort_order=order, effort_units=units
        )
        self._use(*self._checked(p("checkpoint").value))  # CheckpointError: main()
        self._input_timeout = p("input_timeout").value

        self._effort_pub = self.create_publisher(Float64MultiArray, "effort_commands", 10)
        self._info_pub = self.create_publisher(JointTrajectory, "policy_info", 10)
        # Sensor-data QoS (best effort, keep last): matches any publisher and never queues stale states.
        # Announcements first: one ready together with its first state is handled before it.
        self.create_subscription(Int64MultiArray, "episode_start", self._on_episode_start, EPISODE_QOS)
        self.create_subscription(Odometry, "odom", self._on_odom, qos_profile_sensor_data)
        self.create_subscription(JointState, "joint_states", self._on_joint_states, qos_profile_sensor_data)
        self._description_msg: String | None = None  # the current one, for a stream reader that matches later
        self.create_subscription(String, DESCRIPTION, self._on_description, DESCRIPTION_QOS)
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
        self._said_fallback = False
        self._said_waiting = False
        self._last_answer = time.monotonic()  # the watchdog's zero efforts follow silence from here
        self._silent = False
        self._handover = False  # the last rejected state was of a body whose description had not arrived

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
        weights = _drivable(choose_policy(checkpoint, self._allow_untrained, self._seed))
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
                self.controller.deterministic = param.value
            elif param.name == "input_timeout":
                self._input_timeout = param.value

    # -- inputs -----------------------------------------------------------------
    def _reject(self, what: str, err: Exception, reason: str = "invalid", expected: bool = False) -> None:
        self.rejected += 1
        self.counts.rejected(what, reason, str(err))
        message = f"rejected {what} ({self.rejected} so far): {err}"
        # Two call sites, not one with a chosen severity: rclpy refuses a call site whose severity changes
        # ("Logger severity cannot be changed between calls"), which ended the node at a hand-over.
        if expected:  # counted, not a fault
            self.get_logger().info(message, throttle_duration_sec=_LOG_THROTTLE)
        else:
            self.get_logger().warn(message, throttle_duration_sec=_LOG_THROTTLE)

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
        self.controller.episode_start(start.stamp_ns)

    def _on_odom(self, msg: Odometry) -> None:
        self.counts.received(ODOM)
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
        self.counts.received(DESCRIPTION)
        if DESCRIPTION in CHUNK_TOPICS:  # streamed once the chunk layout carries it (msgs.stream_chunk)
            self._note(DESCRIPTION, msg)
        descriptions = self.controller.descriptions
        offer = self.controller.description(msg.data)
        if offer.outcome == "unchanged":
            self.counts.ignored(DESCRIPTION, offer.code)
        elif offer.outcome == "rejected":
            self.rejected += 1
            self.counts.rejected(DESCRIPTION, offer.code, offer.reason)
            kept = "the current graph kept"
            if descriptions.is_fallback:
                kept = "still waiting for one" if self.controller.joint_features else "the chain fallback kept"
            self.get_logger().warn(
                f"rejected robot_description ({descriptions.rejected} so far), {kept}: {offer.reason}",
                throttle_duration_sec=_DESCRIPTION_LOG_THROTTLE,
            )
        else:
            self._description_msg = msg
            robot = descriptions.map.robot
            tree = robot.tree
            shape = "a chain" if tree.is_chain else f"a tree (topology {tree.topology_hash})"
            self.get_logger().info(
                f"robot_description: {tree.num_joints} actuated joints, {shape}, below link {tree.root_link!r}; "
                f"{len(robot.unactuated)} other joints left alone; states are read on it by joint name from now on",
                throttle_duration_sec=_DESCRIPTION_LOG_THROTTLE,  # a robot swapped 100 times a second
            )

    def _on_joint_states(self, msg: JointState) -> None:
        self.counts.received(STATES)
        self._note(STATES, msg)
        try:
            stamp_ns = check_stamp(msg.header.stamp.sec, msg.header.stamp.nanosec)
            state = JointStateRecord(0, stamp_ns, tuple(msg.name), msg.position, msg.velocity, msg.effort)
            ready = self.controller.state(state, time.monotonic())  # laid onto the tree, or waits for its odometry
        except (JointStateError, StampError) as err:
            self._reject(STATES, err, "stamp" if isinstance(err, StampError) else "joint_state")
            return
        except JointMapError as err:
            if err.code == NO_DESCRIPTION:  # a policy that reads joint descriptions waits for one: not a fault
                self.counts.ignored(STATES, err.code)
                if not self._said_waiting:
                    self._said_waiting = True
                    self.get_logger().info(_WAITING)
                return
            if err.code != PREVIOUS_DESCRIPTION:
                # The next body's states before its description (a sim's hand-over between bodies): info, and so
                # is the silence it causes; states that never fit (nothing answered, or silent since) warn.
                driving = bool(self.controller.names) and not self._silent  # a body answered until now: a hand-over
                self._handover = err.code in ("missing_joint", "unknown_joint") and driving
                self._reject(STATES, err, err.code, expected=self._handover)
                return
            self.counts.ignored(STATES, err.code)  # the robot before a swap: not malformed, not answered
            self.get_logger().info(f"ignored joint_states: {err}", throttle_duration_sec=_LOG_THROTTLE)
            return
        for state in ready:
            self._act(state)

    def _on_watchdog(self) -> None:
        now = time.monotonic()
        late = self.controller.expired(now)
        if late is not None:
            self.get_logger().warn(
                "no odometry with the joint state's stamp: using the latest one", throttle_duration_sec=_LOG_THROTTLE
            )
            self._act(late)
        names = self.controller.names  # the robot answered last, in the efforts' order
        if now - self._last_answer > self._input_timeout and names:
            if not self._silent:
                silence = f"no state answered for {self._input_timeout} s: publishing zero efforts"
                if self._handover:  # two call sites: rclpy refuses one whose severity changes (see _reject)
                    self.get_logger().info(silence)
                else:
                    self.get_logger().warn(silence)
                self._silent = True
            self._publish_efforts(np.zeros(len(names)), SILENCE_TAG, names, self.controller.layout)  # answers none

    # -- acting -----------------------------------------------------------------
    def _act(self, ready: Ready) -> None:
        """Answer one state (``Controller.answer``) and publish the answer."""
        adopted = self._updates.adopted
        self._weights, self.controller.policy = self._updates.current()  # new weights between two answers only
        if self._updates.adopted != adopted:
            self.get_logger().info(f"running weights version {self._updates.version} ({self._weights.source})")
        if ready.generation == 0 and not self._said_fallback:
            self._said_fallback = True
            self.get_logger().info(
                f"no {DESCRIPTION} yet: joints taken as a chain in message order (joint 0 next to the torso)"
            )
        try:
            out = self.controller.answer(ready)
        except PolicyOutputError as err:
            self._reject(STATES, err, "policy_output")  # nothing goes out: the watchdog's zero efforts follow
            return
        self._silent = False
        self._handover = False
        self._last_answer = time.monotonic()
        # Say which state this answers (a lockstep sim drops answers to states it re-sent).
        sec, nanosec = from_ns(out.stamp_ns)
        self._publish_efforts(out.efforts, answer_tag(sec, nanosec), out.names, out.layout)
        if out.info is not None:
            self._publish_info(sec, nanosec, out.names, out.info)
        self._serialize_noted()  # after the answer: the loop waits on it, not on this

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
        streaming = self._chunk_pub.get_subscription_count() > 0
        if streaming and not self._streaming and self._description_msg is not None and DESCRIPTION in CHUNK_TOPICS:
            # A reader that matches after the description arrived gets it first all the same (it is latched).
            self._unserialized.append((DESCRIPTION, time.time_ns(), self._description_msg))
        self._streaming = streaming


def main(args=None) -> NoReturn:
    # A checkpoint that cannot be loaded (or none without allow_untrained), or an unknown effort_order, is one
    # line and exit 1.
    node_runner.run(MorphPolicyNode, "morph_policy", args, startup_errors=(CheckpointError, EffortOrderError),
                    parameters=parameters(), summary=__doc__.splitlines()[0])  # fmt: skip


if __name__ == "__main__":
    main()
