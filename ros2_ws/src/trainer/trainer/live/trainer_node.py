"""Live training over DDS: K sim+policy pairs in namespaces, one trainer, new weights pushed back.

    morph-train --live --namespaces /swimmer0 /swimmer1 --out runs/live [--resume] [TrainConfig options]

Per namespace the node subscribes to ``episode_start``,
``robot_description``, ``joint_states``, ``odom``, ``effort_commands`` and
``policy_info`` (decoded into records by ``trainer.codec``'s decoders, as
from a bag) and feeds one ``protocol.transitions.TransitionAssembler``: the
same transitions as training from recorded topics, lost or reordered
messages counted as skips, each state read on the tree of the pair's latest
robot description by joint name (a chain in the message's order while the
pair has none).
Each finished episode goes to ``trainer.live.learner.LiveLearner`` with the
weights version of each step (``policy_info``'s ``header.frame_id``); once it
holds a batch it updates (in a worker thread, so the subscriptions keep
draining; the same thread compiles the update as the node starts, while the
first batch comes in) and the new policy is published on every namespace's
``policy_weights`` (``msgs.policy_weights``; reliable, transient local, keep
last 1, for tools that record it), and re-published every ``weights_period``
seconds: policy nodes read it best effort, so a node that starts or restarts
late gets the latest within a period.

With a signing key (``--signing-key``, ``protocol.trust``) every weights
message and checkpoint is signed; policy nodes take only weights a key they
trust signed (``morph_policy_node``'s ``trusted_keys``).

With ``stream_chunks`` (``--stream-chunks``) the node instead reads each
pair's ``stream_chunks`` (``msgs.stream_chunk``): the same messages as its
policy node received and sent them, a few dozen steps per chunk, decoded
with the same decoders into the same assembler. The trainer then wakes once
per chunk instead of four times per step and is no extra reader of the
loop's own topics. It hears what the policy node heard: effort commands of
other controllers on the namespace are not in the chunks; the robot
descriptions it received are (``msgs.stream_chunk.TOPICS``). A chunk lost
or malformed is counted; the assembler sees a stamp gap there.

Episodes: when a pair appears (at start, or back after a fault) the trainer
sets its sim's ``episode_steps`` and calls its ``~/reset`` service, so the
sim starts a fresh episode with a chain length redrawn from the
``min_joints``..``max_joints`` it was started with (2..10 in the bring-up).

Faults. A pair joins when its loop runs (a ``policy_info`` arrives). A
pair whose sim publishes no new state for ``silence_timeout`` seconds (sim
killed; or policy killed: a lockstep sim then only re-sends its state) is
dropped: the episode it was in is thrown away (logged, counted), the others go
on (the complete episodes its assembler still held unjudged go to the learner:
``learner.EpisodeCutter``); when its policy answers again it is taken back (episode steps set,
reset). The trainer killed: ``--resume`` continues from the state saved at
its last update and re-publishes that version; policy nodes run the
last weights they got meanwhile.

Subscription QoS: reliable keep-last 10,000 for the data topics (a deep queue:
the worker thread's update must not cost samples; reliable readers match the
nodes' reliable writers and a best-effort writer is still heard by nobody:
the project's publishers of these topics are reliable), reliable transient
local for ``episode_start`` (the sim latches the current announcement), reliable
transient local keep last 1 for ``robot_description`` (as the sim latches it:
a trainer that starts late, or a sim that restarts, still gives the robot).
The description is subscribed before the data topics, so when it and the
body's first state wait together it is taken first, as the sim sent it.
"""

from __future__ import annotations

import os
import threading
import time
from collections import Counter, OrderedDict
from dataclasses import InitVar, dataclass, field

import rclpy
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import MultiArrayDimension, UInt8MultiArray
from std_srvs.srv import Trigger

from morph_core.algo.config import TrainerConfig
from morph_core.msgs.policy_weights import TOPIC as WEIGHTS_TOPIC
from morph_core.msgs.policy_weights import parse_policy_version
from morph_core.msgs.records import PolicyInfoRecord
from morph_core.msgs.stream_chunk import TOPIC as CHUNK_TOPIC
from morph_core.msgs.stream_chunk import StreamChunkError, StreamEntry, unpack_stream_chunk
from morph_core.protocol.input_counts import InputCounts
from morph_core.protocol.transitions import (
    SkipCounts,
    StreamStats,
    TransitionAssembler,
    TransitionConfig,
    task_of,
)
from morph_core.protocol.trust import Signer
from morph_ros_util.diagnostics import InputDiagnostics
from morph_ros_util.stop_signals import init_stopping_on_signals
from trainer.codec import (
    DATA_TOPIC_TYPES,
    DECODERS,
    DESCRIPTION_TOPIC,
    EPISODE_TOPIC,
    TOPIC_TYPES,
    TYPESTORE,
    DecodeError,
    episode_start_record,
    message_class,
    policy_info_record,
)
from trainer.live.learner import EpisodeCutter, LiveLearner, LiveOptions

DATA_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10_000, reliability=ReliabilityPolicy.RELIABLE)
"""deep: an update starves the executor for tens of seconds on a loaded machine, and a full queue drops the
oldest messages (stamp gaps that cut episodes into fragments)"""
SETTLE_STATES = 500
"""states a step waits for its other messages: a reliable reader repairs a lost sample only after the
writer's next heartbeat, seconds later on a loaded machine (a bag has no such delay: 10 suffice there)"""
EPISODE_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=10,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
DESCRIPTION_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
"""robot_description, as the sim latches it (robot_state_publisher's profile): the latest URDF, even late"""
WEIGHTS_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
"""the weights topic: the latest policy kept for late joiners"""
CHUNK_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1_000, reliability=ReliabilityPolicy.RELIABLE)
"""deep for the same reason as DATA_QOS (a chunk holds dozens of steps)"""
DATA_TOPICS = {topic: (message_class(msgtype), DECODERS[topic]) for topic, msgtype in DATA_TOPIC_TYPES.items()}
"""a pair's data topics: message type and decoder into a record (the codec's)"""
ANNOUNCEMENTS = (message_class(TOPIC_TYPES[EPISODE_TOPIC]), episode_start_record)
DESCRIPTION = (message_class(TOPIC_TYPES[DESCRIPTION_TOPIC]), DECODERS[DESCRIPTION_TOPIC])
STREAM_TOPICS = {EPISODE_TOPIC: ANNOUNCEMENTS, DESCRIPTION_TOPIC: DESCRIPTION, **DATA_TOPICS}
"""every topic of a pair's stream the trainer reads (its topics, or its policy node's chunks): type and decoder"""
REPORT_PERIOD = 10.0
"""seconds between the trainer's report lines"""
SIM_NODE = "swimmer_sim"
_VERSIONS_KEPT = 4096  # stamps whose policy_info version is remembered, per pair


def chunk_message(entry: StreamEntry):
    """A stream chunk's entry as a message, by rosbags' CDR reader as a bag's (in half the time of rclpy's, whose
    messages check every field as they are built); raises on bytes that are not the entry type's CDR."""
    return TYPESTORE.deserialize_cdr(entry.data, TOPIC_TYPES[entry.topic])


def lost_messages_warning(gaps: int, transitions: int) -> str | None:
    """What the trainer says when lost messages made ``gaps`` stamp gaps over ``transitions`` since its last
    report (None when there were none). Runs cut short bootstrap at every cut, and learning from them was slow
    in-process; lost messages also mean the trainer is falling behind, and stale samples made the update
    diverge (docs/results.md, "Why the earlier live attempts diverged")."""
    if gaps <= 0:
        return None
    return (
        f"{gaps} stamp gaps in the last {REPORT_PERIOD:.0f} s (one per {max(transitions, 1) / gaps:.0f} "
        "transitions): lost messages cut episodes into short runs and the trainer is likely falling behind (stale "
        "samples make updates diverge); pace the pairs (real_time_factor 1) or run fewer pairs per trainer"
    )


@dataclass
class _Pair:
    """One namespace's stream."""

    ns: str
    task: str = "swimmer"
    """the run's task (``protocol.transitions.task_of``: a swimmer's, or a legged body's)"""
    assembler: TransitionAssembler = field(init=False)
    episodes: EpisodeCutter = field(init=False)
    """the assembler's transitions cut into episodes for the learner"""
    versions: OrderedDict = field(default_factory=OrderedDict)
    """policy_info stamp -> weights version (None: not said)"""
    states: int = 0
    last_new_state: float = 0.0
    active: bool = False
    configure: bool = False
    """episode_steps and a reset still to send (the sim's services may not be discovered yet)"""
    messages: int = 0
    """messages taken off the pair's topics or chunks, decodable or not"""
    decode_errors: Counter = field(default_factory=Counter)
    """messages refused before the assembler, by reason"""
    dropped_partial: int = 0
    drops: int = 0
    chunk_sequence: int | None = None
    """the last stream chunk's sequence number"""
    chunks_lost: int = 0

    learner: InitVar[LiveLearner | None] = None

    def __post_init__(self, learner: LiveLearner | None):
        self.assembler = TransitionAssembler(TransitionConfig(task=self.task, settle_states=SETTLE_STATES))
        self.episodes = EpisodeCutter(learner, self.versions.get)

    def refuse(self, reason: str) -> None:
        """A message taken that could not be read (counted, never passed on)."""
        self.messages += 1
        self.decode_errors[reason] += 1


def _nonzero(skips: SkipCounts) -> str:
    """The reasons that counted, e.g. 'not_applied 12, late_message 3'."""
    return ", ".join(f"{k} {v}" for k, v in skips.as_dict().items() if v) or "none"


def input_counts(pairs) -> InputCounts:
    """The trainer's inputs on ``/diagnostics``, summed over its pairs (the report line gives them per pair):
    ``messages`` received, rejected by the decoder's reason (a stream chunk or a message that is not its type),
    ignored by the assembler's message reasons (orphans, late, a description that is no robot); ``steps``
    received (transitions made and steps skipped), rejected by skip reason (``protocol.transitions.SkipCounts``:
    e.g. ``malformed`` for an odometry whose quaternion is no rotation, ``non_finite`` for NaN in it)."""
    counts = InputCounts(["messages", "steps"])
    messages, steps = counts.inputs["messages"], counts.inputs["steps"]
    for p in pairs:
        messages.received += p.messages
        messages.rejected.update(p.decode_errors)
        skips = p.assembler.skips
        messages.ignored.update({r: n for r, n in skips.messages().items() if n})
        steps.received += p.assembler.stats.transitions + skips.steps_skipped
        steps.rejected.update({r: n for r, n in skips.steps().items() if n})
    return counts


def _losses(pair: _Pair) -> str:
    """What a pair's stream lost before the assembler, if anything: chunks, undecodable messages by reason."""
    lost = [f"{pair.chunks_lost} chunks lost"] if pair.chunks_lost else []
    lost += [f"{n} {reason}" for reason, n in sorted(pair.decode_errors.items())]
    return f" ({', '.join(lost)})" if lost else ""


class LiveTrainer(Node):
    def __init__(self, cfg: TrainerConfig, options: LiveOptions, signer: Signer | None = None, on_row=None):
        super().__init__("morph_live_trainer")
        self.options = options
        self.learner = LiveLearner(cfg, options.out, resume=options.resume, max_staleness=options.max_staleness,
                                   signer=signer, on_row=on_row, init=options.init)  # fmt: skip
        if signer is None:
            self.get_logger().warn(
                "no --signing-key: the weights go out UNSIGNED, and policy nodes take them only with "
                "accept_unsigned_weights:=true (tests). Make a key pair with morph-keys new KEY, pass --signing-key "
                "KEY here and trusted_keys:=[KEY.pub] to the policy nodes"
            )
        else:
            self.get_logger().info(f"signing the weights with {signer.fingerprint} ({signer.source})")
        self.pairs: dict[str, _Pair] = {}
        self._weights_pubs = []
        self._sim_params: dict[str, object] = {}
        self._sim_reset: dict[str, object] = {}
        self._updating: threading.Thread | None = None
        self._published = -1  # the version last published
        self._updates_here = 0
        self._done = False
        self._lock = threading.Lock()
        services = MutuallyExclusiveCallbackGroup()
        for ns in options.namespaces:
            ns = "/" + ns.strip("/")
            pair = self.pairs[ns] = _Pair(ns, task_of(cfg.policy.global_features), learner=self.learner)
            if options.stream_chunks:
                self.create_subscription(UInt8MultiArray, f"{ns}/{CHUNK_TOPIC}", self._chunk_handler(pair), CHUNK_QOS)
            else:
                msg_type, decode = ANNOUNCEMENTS
                self.create_subscription(msg_type, f"{ns}/episode_start", self._handler(pair, decode), EPISODE_QOS)
                msg_type, decode = DESCRIPTION
                self.create_subscription(msg_type, f"{ns}/{DESCRIPTION_TOPIC}", self._handler(pair, decode),
                                         DESCRIPTION_QOS)  # fmt: skip
                for topic, (msg_type, decode) in DATA_TOPICS.items():
                    self.create_subscription(msg_type, f"{ns}/{topic}", self._handler(pair, decode), DATA_QOS)
            self._weights_pubs.append(self.create_publisher(UInt8MultiArray, f"{ns}/{WEIGHTS_TOPIC}", WEIGHTS_QOS))
            self._sim_params[ns] = self.create_client(SetParameters, f"{ns}/{SIM_NODE}/set_parameters",
                                                      callback_group=services)  # fmt: skip
            self._sim_reset[ns] = self.create_client(Trigger, f"{ns}/{SIM_NODE}/reset", callback_group=services)
        self.publish_weights()
        # The update compiled while the first batch comes in, not when it is full (~25 s in which samples
        # would pile up and age): the first update waits for it.
        self._compiling = threading.Thread(target=self._compile_update, daemon=True)
        self._compiling.start()
        self.create_timer(0.05, self._on_timer)
        self._reported = (0, 0)  # (stamp gaps from lost messages, transitions) at the last report
        self.create_timer(REPORT_PERIOD, self._report)
        self._diagnostics = InputDiagnostics(self, self.input_counts)
        # Policy nodes read the weights best effort (immune to the Fast DDS wedge, docs/design.md), so they get
        # no history: the latest weights go out again periodically for nodes that start late or lost a sample.
        self.create_timer(options.weights_period, self._republish_weights)
        what = "resumed at" if self.learner.resumed else "started with"
        self.get_logger().info(
            f"live training {what} version {self.learner.version} on {len(self.pairs)} pairs "
            f"({', '.join(self.pairs)}), batch {cfg.batch_size} samples, run {options.out}"
        )

    # -- input ---------------------------------------------------------------------------
    def _handler(self, pair: _Pair, decode):
        return lambda msg: self._take(pair, decode, msg, time.time_ns())

    def _chunk_handler(self, pair: _Pair):
        decoders = {topic: decode for topic, (_, decode) in STREAM_TOPICS.items()}

        def on_chunk(chunk: UInt8MultiArray) -> None:
            try:
                sequence, entries = unpack_stream_chunk(chunk.data)
            except StreamChunkError:
                pair.refuse("stream_chunk")
                return
            if pair.chunk_sequence is not None and sequence > pair.chunk_sequence + 1:
                pair.chunks_lost += sequence - pair.chunk_sequence - 1
            pair.chunk_sequence = sequence  # lower: a restarted policy node counts from 0 again
            for entry in entries:
                if entry.topic not in decoders:  # a topic of a newer chunk layout, which this trainer does not read
                    pair.refuse(f"unread_{entry.topic}")
                    continue
                try:
                    msg = chunk_message(entry)
                except Exception:  # noqa: BLE001 - rosbags raises several types for bytes that are not the type's CDR
                    pair.refuse(f"cdr_{entry.topic}")
                    continue
                self._take(pair, decoders[entry.topic], msg, entry.log_ns)

        return on_chunk

    def _take(self, pair: _Pair, decode, msg, log_ns: int) -> None:
        """One message of a pair's stream: decoded into a record (or counted) and pushed to its assembler."""
        try:
            record = decode(msg, log_ns)
        except DecodeError as err:
            pair.refuse(err.reason)
            return
        pair.messages += 1
        if decode is policy_info_record:
            pair.versions[record.stamp_ns] = parse_policy_version(msg.header.frame_id)
            while len(pair.versions) > _VERSIONS_KEPT:
                pair.versions.popitem(last=False)
        self._push(pair, record)

    def _push(self, pair: _Pair, record) -> None:
        with self._lock:
            out = pair.assembler.push(record)
            if pair.assembler.stats.states != pair.states:
                pair.states = pair.assembler.stats.states
                pair.last_new_state = time.monotonic()
            # A pair joins when its loop runs: a new state and an answer from its sampling policy (a lockstep
            # sim alone only re-sends its state; resetting it then would just repeat).
            if not pair.active and isinstance(record, PolicyInfoRecord):
                pair.last_new_state = time.monotonic()
                self._join(pair)
            pair.episodes.take(out)

    # -- pairs joining and leaving ---------------------------------------------------------
    def _join(self, pair: _Pair) -> None:
        pair.active = True
        pair.configure = True
        self.get_logger().info(f"pair {pair.ns} is running: setting episode_steps and resetting its sim")

    def _configure(self, pair: _Pair) -> None:
        """episode_steps, then a reset (a fresh episode, chain length redrawn), once the services answer."""
        steps = self.options.episode_steps
        params, reset = self._sim_params[pair.ns], self._sim_reset[pair.ns]
        if not (reset.service_is_ready() and (steps <= 0 or params.service_is_ready())):
            return
        pair.configure = False
        if steps > 0:
            value = ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=steps)
            params.call_async(SetParameters.Request(parameters=[ParameterMsg(name="episode_steps", value=value)]))
        reset.call_async(Trigger.Request())

    def _drop(self, pair: _Pair, why: str) -> None:
        lost = pair.episodes.drop(pair.assembler)
        pair.active = False
        pair.dropped_partial += lost
        pair.drops += 1
        self.get_logger().warn(f"pair {pair.ns} {why}: dropped its partial episode ({lost} steps); training on")

    # -- learning ------------------------------------------------------------------------
    def _on_timer(self) -> None:
        now = time.monotonic()
        with self._lock:
            for pair in self.pairs.values():
                if pair.active and now - pair.last_new_state > self.options.silence_timeout:
                    self._drop(pair, f"silent for {self.options.silence_timeout} s")
                elif pair.active and pair.configure:
                    self._configure(pair)
        if self._updating is not None and not self._updating.is_alive():
            self._updating = None
            if self.learner.version != self._published:
                self.publish_weights()
            if self._finished():
                self._done = True
        if self._updating is None and not self._done and self.learner.ready() and not self._compiling.is_alive():
            with self._lock:
                pool = self.learner.take_pool()
            active = sum(p.active for p in self.pairs.values())
            self._updating = threading.Thread(target=self._update, args=(pool, active), daemon=True)
            self._updating.start()

    def _compile_update(self) -> None:
        try:
            seconds = self.learner.compile_update()
        except Exception as err:  # noqa: BLE001 - the first update compiles (or falls back) instead
            self.get_logger().warn(f"compiling the update ahead failed: {type(err).__name__}: {err}")
            return
        if self.learner.cfg.compile:
            self.get_logger().info(f"update compiled in {seconds:.1f} s")

    def _update(self, pool, active: int) -> None:
        try:
            row = self.learner.update(pool, pairs=active)
        except Exception as err:  # noqa: BLE001 - a bad pool costs that pool, not the run
            self.get_logger().error(f"update failed, its {len(pool[0])} episodes dropped: {type(err).__name__}: {err}")
            return
        self._updates_here += 1
        self.get_logger().info(
            f"update {row['iteration']}: version {row['version']}, {row['batch_size']} samples "
            f"({row['pool_episodes']} episodes, mean return {row['return_mean']:.2f}), "
            f"update {row['update_s']:.2f} s, weight {row['is_weight_mean']:.3f}, lag {row['version_lag_mean']:.2f}"
        )

    def _finished(self) -> bool:
        if self.options.max_updates and self._updates_here >= self.options.max_updates:
            return True
        return self.learner.counters["global_step"] >= self.learner.cfg.total_timesteps

    @property
    def done(self) -> bool:
        return self._done

    def publish_weights(self) -> None:
        """Publish the current weights (after an update; at start, the initial or resumed version)."""
        dims, data = self.learner.weights_message()
        msg = UInt8MultiArray()
        msg.layout.dim = [MultiArrayDimension(label=label, size=size, stride=stride) for label, size, stride in dims]
        msg.data = data
        self._weights_msg = msg
        self._published = self.learner.version
        for pub in self._weights_pubs:
            pub.publish(msg)

    def _republish_weights(self) -> None:
        if self._updating is None:  # between an update and its publication the old version is not re-sent
            for pub in self._weights_pubs:
                pub.publish(self._weights_msg)

    def skips(self) -> tuple[SkipCounts, StreamStats]:
        skips, stats = SkipCounts(), StreamStats()
        for p in self.pairs.values():
            skips.merge(p.assembler.skips)
            stats.merge(p.assembler.stats)
        return skips, stats

    def input_counts(self) -> InputCounts:
        with self._lock:
            return input_counts(self.pairs.values())

    def _report(self) -> None:
        skips, stats = self.skips()
        parts = [f"{p.ns}: {'up' if p.active else 'down'}, {p.states} states, {p.drops} drops{_losses(p)}"
                 for p in self.pairs.values()]  # fmt: skip
        self.get_logger().info(
            f"version {self.learner.version}, pool {self.learner.pool_size}/{self.learner.cfg.batch_size}, "
            f"{stats.transitions} transitions in {stats.episodes} runs, {stats.boundaries_stamp_gap} stamp gaps, "
            f"{skips.steps_skipped} steps skipped ({_nonzero(skips)}), dropped stale "
            f"{self.learner.dropped_stale}; " + "; ".join(parts)
        )
        lost = stats.lost_state_gaps
        warning = lost_messages_warning(lost - self._reported[0], stats.transitions - self._reported[1])
        self._reported = (lost, stats.transitions)
        if warning:
            self.get_logger().warn(warning)

    def close(self) -> None:
        if self._updating is not None:
            self._updating.join()
        self.learner.close()


def run_live(cfg: TrainerConfig, options: LiveOptions, args=None, signer: Signer | None = None, on_row=None) -> int:
    """Run the live trainer until done (``max_updates`` / ``total_timesteps``) or SIGINT/SIGTERM; ``signer``
    signs the weights (``options.signing_key`` loaded); ``on_row(row, saved)`` hears each update's row
    (``algo.run.Run``)."""
    # Before any thread starts (DDS, torch): they inherit it.
    os.setpriority(os.PRIO_PROCESS, 0, max(os.getpriority(os.PRIO_PROCESS, 0), options.nice))
    stop = init_stopping_on_signals(args)
    node = None
    # One executor for the whole run: rclpy.spin_once(node) adds and removes the node on every call, which
    # rebuilds the wait set for every message (4 per step per pair). (rclpy's experimental EventsExecutor
    # used less CPU still in a one-off trial, but stopped dispatching in 2 of 2 runs of tests/test_live.py.)
    executor = SingleThreadedExecutor()
    try:
        node = LiveTrainer(cfg, options, signer, on_row)
        executor.add_node(node)
        while not stop.is_set() and not node.done:
            executor.spin_once(timeout_sec=0.1)
        if node.done:
            node.get_logger().info(
                f"done: version {node.learner.version}, {node.learner.counters['global_step']} steps"
            )
            end = time.monotonic() + 1.0  # let reliable readers fetch the last weights
            while not stop.is_set() and time.monotonic() < end:
                executor.spin_once(timeout_sec=0.05)
    except ExternalShutdownException:  # the context shut down by another hand (a test's)
        pass
    finally:
        executor.shutdown()
        if node is not None:
            node.close()
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
