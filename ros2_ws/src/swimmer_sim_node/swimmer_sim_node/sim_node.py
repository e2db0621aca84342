"""MuJoCo swimmer (or your own robot) as a ROS 2 node: JointState, Odometry, /clock, episodes out, efforts in.

All physics and episode logic is ``morph_core.env.sim.SwimmerSim``; this node
only paces it, converts messages and handles parameters.

Bodies (read-only parameters, one of):
- chains (default): ``num_joints``, or ``min_joints``..``max_joints`` (below);
- ``topology``: a body spec of ``morph_core.env.bodies`` (``y:2x2``,
  ``star:3x2``, ``2-10,random:3-10``, ...): swimmers, trees included, one
  drawn at every reset from the sim's seeded generator;
- ``model_file``: your own robot, an MJCF of actuated hinges
  (``morph_core.env.mjcf_robot``; docs/your_robot.md).
With ``topology`` or ``model_file``, ``num_joints`` only reports the body's
joint count: setting it to anything else is refused with the reason (a chain
cannot be rebuilt inside a spec or a model; its value at start-up is
ignored), and ``min_joints``/``max_joints`` must stay 0. Refused at start-up,
one line and exit 1: a bad spec, a model file that cannot be simulated (the
reason: missing, not MJCF, MuJoCo's compile error, an actuator on a
non-hinge, no actuated hinge, more than 64), both set.

Wire conventions
- ``joint_states`` (sensor_msgs/JointState): joints in the body's tree order
  (torso to tail for a chain; depth-first from the root for a tree or a
  robot), under the MJCF's names, or, with ``shuffle_joints``, in an order
  drawn afresh for every state (its own generator, seeded from ``seed``:
  the physics and its draws are unchanged; a state published again keeps its
  order); position [rad], velocity [rad/s], effort = the normalised motor
  command applied over the control period that ended at this state (a
  swimmer's torque = 150 x effort; zeros for an episode's first state);
  stamp = sim time.
- ``odom`` (nav_msgs/Odometry): frame ``odom`` -> ``<joint_prefix><root>``
  (``torso`` for a swimmer, the root body of a robot model); pose in the
  world frame (a swimmer's: x, y and yaw as a quaternion about z; a robot's:
  3-D); twist in the root's (child) frame, as the message defines it.
- ``/clock`` (rosgraph_msgs/Clock): sim time.
- ``episode_start`` (std_msgs/Int64MultiArray): one message per episode,
  published just before the episode's first state; ``layout.dim[0]`` =
  (label ``"episode,stamp_ns,num_joints,cause"``, size 4, stride 4) and
  ``data = [episode, stamp_ns, num_joints, cause]``: the episode's index (0
  first), the stamp of its first ``joint_states`` in ns (sec * 10**9 +
  nanosec), its body's joint count, and why it began (0 node start, 1 the previous
  one ran ``episode_steps``, 2 reset service, 3 ``num_joints`` set, 4 the
  physics diverged, 5 a legged body fell: its last step terminated). Layout
  and decoding: ``morph_core.msgs.episode_start``.
- ``effort_commands`` (std_msgs/Float64MultiArray): one value per joint,
  clipped to [-1, 1]. A command whose layout names its joints (a
  ``names=<JSON list>`` dimension, ``morph_core.msgs.effort_names``) is
  applied by name (a name the body does not have, or a joint left out, is
  rejected: ``unknown_joint``, ``missing_joint``); one without is in the
  order of the state it answers (the tagged one; untagged, the latest
  published; the order of the last 64 states is kept, an
  answer to an older one is rejected: ``order``). Without shuffling that is
  the tree order: without names, exactly as before names existed. A command
  whose ``tree=`` dimension gives another joint layout than the body's
  (``KinematicTree.layout_hash``: the controller computed it on another
  tree, e.g. a new body's first state answered before its description
  reached the controller) is rejected: ``wrong_tree``; in lockstep the state
  is published again after ``effort_timeout`` and answered on the right tree.
- ``~/reset`` (std_srvs/Trigger): end the episode now; the next one's first
  state is published (and announced) at once; the response names it.
- ``robot_description`` (std_msgs/String, latched URDF) and ``markers``
  (visualization_msgs/MarkerArray, frame ``odom``): see ``chain_viz``.
Odometry is published before the joint state of the same stamp, so a
controller that acts on joint states finds the matching odometry first.

QoS: ``joint_states``, ``odom``, ``/clock``: reliable, volatile, keep last 10
(any subscriber matches). ``episode_start``: reliable, transient local, keep
last 1: a recorder or trainer that starts late still gets the current
episode's announcement (``ros2 bag record`` adopts the publisher's
durability). ``effort_commands`` is read best effort, keep last 10: it
matches reliable and best-effort publishers, and no publisher can make this
reader wait on repairs (a reliable reader can be made to spin on a malformed
sample). No publisher here blocks: all keep last.

Episodes: each lasts ``episode_steps`` control steps (0 = until a reset is
asked for). A chain's length is ``num_joints``, or drawn at every reset
from ``min_joints``..``max_joints`` when those are set (then ``num_joints``
follows the drawn length; setting it rebuilds the chain at that length for
one episode). Reset noise and draws come from the sim's generator seeded
once with ``seed``, so a lockstep recording replays exactly in
``MorphSwimmerEnv(num_joints=(min_joints, max_joints))`` (or
``num_joints``, or ``MorphSwimmerEnv(bodies=topology)``): ``reset(seed=seed)``,
then ``reset()`` at each announced episode, the recorded efforts (in tree
order) stepped in between. Sim time counts on across
resets: an episode's first state is one control period after the previous
episode's last, so /clock never goes back and episodes are split by the
announcements (and by the joint names when the length changes). Efforts
tagged as answering a state of an earlier episode are dropped in every mode
(counted in ``old_episode_answers``). In lockstep the answer to an episode's
last state is what lets the sim reset (those efforts are never applied), so
even an untagged controller stays in step across ``episode_steps`` resets;
a ``~/reset`` or ``num_joints`` change cuts in at any moment, and an untagged
answer to the old state still in flight is then taken for the new one.

Pacing (``morph_core.protocol.pacing``): free-running steps track
``real_time_factor`` x wall time (0: as fast as possible). With ``lockstep``
(``morph_core.protocol.lockstep``) the sim steps only once efforts have
arrived for the latest published state (a deterministic closed loop with a
deterministic controller); if none arrive within ``effort_timeout`` the state
is published again, so a lost message or a late-starting controller cannot
stall the loop for good. A controller may tag its efforts with the state they
answer (``layout.dim[0].label = "joints@<sec>.<nanosec>"``, see
``morph_core.msgs.stamps``; morph_policy_node does); in lockstep, tagged
efforts for any other state are dropped, so a re-sent state answered twice
cannot shift the loop by a step. Untagged efforts (any other controller) are
taken as the answer. Efforts labelled ``silence`` (a controller's fail-safe
zeros after its input went quiet, ``SILENCE_TAG``) answer no state: free
running they are applied, in lockstep ignored (counted in
``silence_ignored``): stepping on them would put zeros into a loop that was
only slow, which made lockstep runs differ from the in-process rollout under load.

Bad input (the rules: ``morph_core.protocol.effort_intake``, and
``SwimmerSim.command`` for the values): an effort command of the wrong length, with NaN/inf, with a tag
that starts ``joints@`` but does not parse, tagged with a state not yet
published, with a names dimension that does not parse (``names``) or does not
name the body's joints (``unknown_joint``, ``missing_joint``), or, shuffled
and unnamed, answering a state whose order is forgotten (``order``) is
rejected (the previous command stays in force, the loop does not step);
counts of what each input received, rejected and ignored, by reason, go out
on ``/diagnostics`` every second (``morph_ros_util.diagnostics``); warnings
are throttled. See ``docs/robustness.md``.
"""

from __future__ import annotations

import array
import math
import time
from typing import NoReturn

from builtin_interfaces.msg import Time
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, Int64MultiArray, MultiArrayDimension
from std_srvs.srv import Trigger

from morph_core.constants import MAX_JOINTS, MAX_NAME_CHARS, MIN_JOINTS
from morph_core.env.bodies import parse_bodies
from morph_core.env.mjcf_robot import load_robot
from morph_core.env.sim import EffortError, SwimmerSim
from morph_core.msgs.episode_start import EpisodeCause, pack_episode_start
from morph_core.msgs.stamps import from_ns
from morph_core.policy.tree import KinematicTree, UrdfRobot
from morph_core.protocol.effort_intake import ShuffledOrders, read_effort_command
from morph_core.protocol.input_counts import InputCounts
from morph_core.protocol.joint_map import JointMap
from morph_core.protocol.lockstep import Action, LockstepGate
from morph_core.protocol.pacing import RealTimePacer, tick_period
from morph_ros_util import node_runner
from morph_ros_util.diagnostics import InputDiagnostics
from morph_ros_util.parameters import NodeParameter, declare_parameters
from swimmer_sim_node.chain_viz import LATCHED_QOS, ChainViz

# A free-running tick steps for at most this long before letting the executor
# serve commands and parameter requests.
_TICK_BUDGET = 0.02
_LOG_THROTTLE = 5.0
_MAX_EPISODE_STEPS = 2**31 - 1
EFFORTS = "effort_commands"
MAX_PREFIX_CHARS = MAX_NAME_CHARS - len("motor64_rot")  # the longest name a swimmer has: <prefix>motor<k>_rot

STATE_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
"""joint_states, odom, /clock"""
EPISODE_QOS = LATCHED_QOS
"""episode_start: latched, so a late subscriber still learns where the current episode began"""
COMMAND_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)
"""effort_commands (read): depth 10 so a stale answer queued behind the awaited one cannot push it out"""


PARAMETERS = (
    NodeParameter(
        "num_joints",
        6,
        "actuated joints in the chain (with a range set: the current episode's, drawn); setting it starts a new "
        "episode with that chain; with topology or model_file it reports the body's count and cannot be set",
        (MIN_JOINTS, MAX_JOINTS),
    ),
    *(
        NodeParameter(
            bound,
            0,
            "chain lengths drawn at each reset, min_joints..max_joints inclusive; both 0 = a fixed chain of num_joints",
            (0, MAX_JOINTS),
            read_only=True,
        )
        for bound in ("min_joints", "max_joints")
    ),
    NodeParameter(
        "episode_steps",
        0,
        "control steps per episode before the sim resets; 0 = only on request",
        (0, _MAX_EPISODE_STEPS),
    ),  # fmt: skip
    NodeParameter("joint_prefix", "", "prefix of joint, link and root frame names"),
    NodeParameter("real_time_factor", 1.0, "sim seconds per wall second; 0 = as fast as possible", (0.0, 10000.0)),
    NodeParameter("lockstep", False, "step only when efforts for the latest published state have arrived"),
    NodeParameter(
        "effort_timeout",
        0.25,
        "wall seconds without efforts before they drop to zero (lockstep: before re-publishing)",
        (0.001, 3600.0),
    ),
    NodeParameter("seed", 0, "seed of the reset noise, body draws and joint shuffling", read_only=True),
    NodeParameter(
        "topology",
        "",
        "body spec of the swimmers drawn at each reset (e.g. y:2x2, star:3x2, 2-10,random:3-10); "
        "'' = chains of num_joints / min_joints..max_joints",
        read_only=True,
    ),
    NodeParameter(
        "model_file", "", "MJCF of your own robot (actuated hinges) to simulate instead of a swimmer", read_only=True
    ),
    NodeParameter(
        "shuffle_joints",
        False,
        "list the joints of every joint state in a random order (efforts map by name or by the order of the state "
        "they answer)",
        read_only=True,
    ),
)
"""the node's parameters, declared from here (``morph_ros_util.parameters``) and listed by ``--help``"""


def _time(ns: int) -> Time:
    sec, nanosec = from_ns(ns)
    return Time(sec=sec, nanosec=nanosec)


def _doubles(values) -> array.array:
    # Assigning a typed array skips the per-element checks of a Python list.
    return array.array("d", values.tobytes())


def chain_lengths(num_joints: int, min_joints: int, max_joints: int) -> int | tuple[int, int]:
    """The sim's ``num_joints`` argument from the three parameters: a fixed chain when no range is set
    (both 0), else the range. Raises ValueError naming the parameters for anything else."""
    if min_joints == 0 and max_joints == 0:
        return num_joints
    if not MIN_JOINTS <= min_joints <= max_joints <= MAX_JOINTS:
        raise ValueError(
            f"min_joints and max_joints must both be 0 (a fixed chain of num_joints) or satisfy "
            f"{MIN_JOINTS} <= min_joints <= max_joints <= {MAX_JOINTS}; got {min_joints} and {max_joints}"
        )
    return min_joints, max_joints


def prefix_error(prefix: str, longest_name: int = MAX_NAME_CHARS - MAX_PREFIX_CHARS) -> str | None:
    """Why ``prefix`` cannot start joint names of up to ``longest_name`` characters (a controller refuses
    names that are not short printable ASCII, ``msgs.joint_state``), or None."""
    most = MAX_NAME_CHARS - longest_name
    if len(prefix) > most or not (prefix.isascii() and prefix.isprintable()):
        return f"must be at most {most} printable ASCII characters"
    return None


def make_sim(
    num_joints: int, min_joints: int, max_joints: int, topology: str, model_file: str, **kwargs
) -> tuple[SwimmerSim, str]:
    """The sim the body parameters ask for, and a phrase naming its bodies for the log. ValueError (one line,
    naming the parameters) for a combination that is refused, a bad spec or a model file that cannot run."""
    if topology and model_file:
        raise ValueError("topology and model_file are both set: the sim runs swimmers of a spec or one robot model")
    given = "topology" if topology else "model_file" if model_file else None
    if given and (min_joints or max_joints):
        raise ValueError(f"{given} is set: min_joints and max_joints must stay 0 (its bodies are the {given}'s)")
    if topology:
        try:
            bodies = parse_bodies(topology)
        except ValueError as err:
            raise ValueError(f"topology {topology[:60]!r}: {err}") from None
        lo, hi = bodies.joint_range
        kind = "centipedes" if bodies.has_centipedes else "swimmers"  # a spec mixes no families (the sim refuses)
        return SwimmerSim(bodies=bodies, **kwargs), f"{kind} of {str(bodies)!r} ({lo}..{hi} joints)"
    if model_file:
        robot = load_robot(model_file)  # RobotModelError, a ValueError, says why not
        described = f"robot {robot.name!r} from {model_file} ({robot.num_joints} joints, root {robot.tree.root_link!r})"
        return SwimmerSim(robot=robot, **kwargs), described
    lengths = chain_lengths(num_joints, min_joints, max_joints)
    described = f"{lengths[0]}..{lengths[1]} joints" if isinstance(lengths, tuple) else f"{lengths} joints"
    return SwimmerSim(num_joints=lengths, **kwargs), f"swimmer with {described}"


class SwimmerSimNode(Node):
    def __init__(self):
        super().__init__("swimmer_sim")
        declare_parameters(self, PARAMETERS)
        p = self.get_parameter
        self._prefix = p("joint_prefix").value
        self._rtf = p("real_time_factor").value
        self._lockstep = p("lockstep").value
        self.sim, described = make_sim(
            p("num_joints").value,
            p("min_joints").value,
            p("max_joints").value,
            p("topology").value,
            p("model_file").value,
            seed=p("seed").value,
            effort_timeout=p("effort_timeout").value,
            episode_steps=p("episode_steps").value,
        )
        self._fixed_body = "topology" if p("topology").value else "model_file" if p("model_file").value else None
        # The longest joint name a body can have: a swimmer's motor64_rot, or the robot's own.
        self._longest_name = max(map(len, self.sim.tree.names)) if self.sim.robot else len("motor64_rot")
        if prefix_error(self._prefix, self._longest_name) is not None:
            raise ValueError(f"joint_prefix {prefix_error(self._prefix, self._longest_name)}")
        self._follow_body()
        self._shuffle = p("shuffle_joints").value
        self._orders = ShuffledOrders(p("seed").value) if self._shuffle else None
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        self._state_pub = self.create_publisher(JointState, "joint_states", STATE_QOS)
        self._odom_pub = self.create_publisher(Odometry, "odom", STATE_QOS)
        self._clock_pub = self.create_publisher(Clock, "/clock", STATE_QOS)
        self._episode_pub = self.create_publisher(Int64MultiArray, "episode_start", EPISODE_QOS)
        self.create_subscription(Float64MultiArray, "effort_commands", self._on_efforts, COMMAND_QOS)
        self.create_service(Trigger, "~/reset", self._on_reset)
        self._viz = ChainViz(self)  # robot_description and markers (see chain_viz)
        self._viz.describe(self.sim, self._prefix)

        self._pacer = RealTimePacer(self._rtf)
        self._gate = LockstepGate(resend_after=p("effort_timeout").value)
        self._announced = -1  # the last episode announced
        self._started = False  # the first state has been published
        self.old_episode_answers = 0
        self.counts = InputCounts([EFFORTS])  # on /diagnostics every second
        self._diagnostics = InputDiagnostics(self, self.counts)
        self.silence_ignored = 0  # fail-safe efforts a lockstep loop does not step on
        self._timer = None
        self._restart_pacing()
        self._follow_chain()
        self.get_logger().info(
            f"{described}, episode_steps {self.sim.episode_steps or 'unlimited'}, "
            f"real_time_factor {self._rtf}, lockstep {self._lockstep}"
            + (", joints shuffled in every state" if self._shuffle else "")
        )

    # -- parameters -------------------------------------------------------------
    def _validate_parameters(self, params: list[Parameter]) -> SetParametersResult:
        for param in params:
            if param.name == "num_joints":
                if param.type_ != Parameter.Type.INTEGER or not MIN_JOINTS <= param.value <= MAX_JOINTS:
                    return SetParametersResult(
                        successful=False, reason=f"num_joints must be an integer in {MIN_JOINTS}..{MAX_JOINTS}"
                    )
                if self._fixed_body is not None and param.value != self.sim.num_joints:
                    # The node's own report of a new body passes (equal); a chain cannot be built in a spec or model.
                    return SetParametersResult(
                        successful=False,
                        reason=f"num_joints follows the body of {self._fixed_body} ({self.sim.num_joints} joints now) "
                        f"and cannot be set while {self._fixed_body} is",
                    )
            elif param.name == "episode_steps":
                if param.type_ != Parameter.Type.INTEGER or not 0 <= param.value <= _MAX_EPISODE_STEPS:
                    return SetParametersResult(successful=False, reason="episode_steps must be an integer >= 0")
            elif param.name == "real_time_factor":
                if param.type_ != Parameter.Type.DOUBLE or not (math.isfinite(param.value) and param.value >= 0):
                    return SetParametersResult(successful=False, reason="real_time_factor must be a finite double >= 0")
            elif param.name == "effort_timeout":
                if param.type_ != Parameter.Type.DOUBLE or not (math.isfinite(param.value) and param.value > 0):
                    return SetParametersResult(successful=False, reason="effort_timeout must be a finite double > 0")
            elif param.name == "joint_prefix":
                is_text = param.type_ == Parameter.Type.STRING
                reason = prefix_error(param.value, self._longest_name) if is_text else "must be a string"
                if reason is not None:
                    return SetParametersResult(successful=False, reason=f"joint_prefix {reason}")
        return SetParametersResult(successful=True)

    def _apply_parameters(self, params: list[Parameter]) -> None:
        for param in params:
            if param.name == "num_joints" and param.value != self.sim.num_joints:
                self.sim.rebuild(param.value)
                self.get_logger().info(f"rebuilt the swimmer with {param.value} joints")
                self._episode_began()
            elif param.name == "episode_steps":
                self.sim.episode_steps = param.value
            elif param.name == "joint_prefix":
                self._prefix = param.value
                self._follow_body()
                if self._orders is not None:
                    self._orders.forget()  # orders under the old names: a state published again gets one of the new
            elif param.name == "real_time_factor":
                self._rtf = self._pacer.real_time_factor = param.value
                self._restart_pacing()
            elif param.name == "lockstep":
                self._lockstep = param.value
                self._gate.restart()
                self._restart_pacing()
            elif param.name == "effort_timeout":
                self.sim.effort_timeout = self._gate.resend_after = param.value

    def _follow_chain(self) -> None:
        """Keep ``num_joints`` telling the chain's length when it was drawn (no rebuild: it is equal)."""
        if self.get_parameter("num_joints").value != self.sim.num_joints:
            self.set_parameters([Parameter("num_joints", value=self.sim.num_joints)])

    # -- episodes ---------------------------------------------------------------
    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self.sim.reset(EpisodeCause.RESET)
        self._episode_began()
        response.success = True
        response.message = (
            f"episode {self.sim.episode}: {self.sim.num_joints} joints, first state at t={self.sim.time:.2f} s"
        )
        return response

    def _episode_began(self) -> None:
        """A reset outside the loop's own stepping: publish the new episode's first state now (in
        lockstep it asks for its own efforts; an answer pending for the old state goes stale)."""
        self._gate.restart()
        self._publish(time.monotonic())

    def _announce(self, stamp_ns: int) -> None:
        self._announced = self.sim.episode
        self._follow_body()
        label, data = pack_episode_start(self.sim.episode, stamp_ns, self.sim.num_joints, self.sim.episode_cause)
        msg = Int64MultiArray(data=data)
        msg.layout.dim = [MultiArrayDimension(label=label, size=len(data), stride=len(data))]
        self._episode_pub.publish(msg)
        self._follow_chain()
        self.get_logger().debug(f"episode {self.sim.episode}: {self.sim.num_joints} joints from t={self.sim.time} s")

    # -- pacing -----------------------------------------------------------------
    def _restart_pacing(self) -> None:
        self._pacer.restart(time.monotonic(), self.sim.time)
        if self._timer is not None:
            self.destroy_timer(self._timer)
        self._timer = self.create_timer(tick_period(self.sim.dt, self._rtf, self._lockstep), self._on_timer)

    def _due(self, now: float) -> bool:
        return self._pacer.due(now, self.sim.time, self.sim.time + self.sim.dt)

    def _on_timer(self) -> None:
        now = time.monotonic()
        if self._lockstep:
            action = self._gate.poll(now, lambda: self._state_pub.get_subscription_count() > 0)
            if action is Action.STEP:
                self._lockstep_step(now)
            elif action is Action.PUBLISH:
                self._publish(now)  # the first state waited for a listener, so it is not lost unheard
            elif action is Action.RESEND:
                self.get_logger().warn(
                    f"no efforts for the state at t={self.sim.time:.2f} s within the effort timeout: "
                    f"publishing it again ({self._gate.resends} so far)",
                    throttle_duration_sec=_LOG_THROTTLE,
                )
                self._publish(now)
            return
        if not self._started:
            self._publish(now)  # the first episode's first state
        end = now + _TICK_BUDGET
        while self._due(now):
            self._advance(now)
            self._publish(now)
            now = time.monotonic()
            if now > end:
                break

    def _lockstep_step(self, now: float) -> None:
        if self._due(now):
            self._advance(now)
            self._gate.stepped()
            self._publish(now)

    def _advance(self, now: float) -> None:
        if self.sim.advance(now) and self.sim.episode_cause is EpisodeCause.DIVERGED:
            self.get_logger().error(
                f"physics diverged; swimmer reset ({self.sim.unstable_resets} so far)",
                throttle_duration_sec=_LOG_THROTTLE,
            )

    # -- messages ---------------------------------------------------------------
    def _on_efforts(self, msg: Float64MultiArray) -> None:
        now = time.monotonic()
        self.counts.received(EFFORTS)
        verdict = read_effort_command(
            [d.label for d in msg.layout.dim],
            msg.data,
            latest_ns=self.sim.stamp_ns,
            episode_start_ns=self.sim.episode_start_ns,
            lockstep=self._lockstep,
            is_stale=self._gate.is_stale,
            body=self._body,
            orders=self._orders,
        )
        if verdict.ignored is not None:
            if verdict.ignored == "silence":
                self.silence_ignored += 1  # a controller's fail-safe zeros answer no state: the loop holds still
            elif verdict.ignored == "old_episode":
                self.old_episode_answers += 1
            self.counts.ignored(EFFORTS, verdict.ignored)
            return
        if verdict.rejected is not None:
            self._reject(verdict.rejected, verdict.error)
            return
        try:
            self.sim.command(verdict.efforts, now)
        except EffortError as err:
            self._reject("efforts", err)
            return
        if self._lockstep and self._gate.answer():
            self._lockstep_step(now)

    def _follow_body(self) -> None:
        """The published joint names and the body's joints by those names (``protocol.joint_map``), set when
        either can change: a new episode (two bodies may share names: the map's tree is the layout answers are
        checked on) and a new prefix."""
        self._names = self.sim.joint_names(self._prefix)
        tree = KinematicTree(self._names, self.sim.tree.parents, self._prefix + (self.sim.tree.root_link or ""))
        self._body = JointMap(UrdfRobot(tree, frozenset()))

    def _reject(self, reason: str, err: Exception) -> None:
        self.counts.rejected(EFFORTS, reason, str(err))
        self.get_logger().warn(
            f"rejected effort command ({self.counts.rejected_total} so far): {err}",
            throttle_duration_sec=_LOG_THROTTLE,
        )

    def _publish(self, now: float) -> None:
        stamp_ns = self.sim.stamp_ns
        if self.sim.episode != self._announced:
            self._announce(stamp_ns)
        stamp = _time(stamp_ns)
        root = self.sim.odometry()
        self._viz.describe(self.sim, self._prefix)  # a changed body's URDF before its first state

        self._clock_pub.publish(Clock(clock=stamp))

        odom = Odometry()
        odom.header.stamp = stamp
        odom.header.frame_id = "odom"
        odom.child_frame_id = self._prefix + root.frame
        pose, twist = odom.pose.pose, odom.twist.twist
        pose.position.x, pose.position.y, pose.position.z = root.position
        pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = root.orientation
        twist.linear.x, twist.linear.y, twist.linear.z = root.linear
        twist.angular.x, twist.angular.y, twist.angular.z = root.angular
        self._odom_pub.publish(odom)

        state = JointState()
        state.header.stamp = stamp
        positions, velocities, efforts = self.sim.joint_positions, self.sim.joint_velocities, self.sim.applied
        if self._orders is not None:
            names = self._orders.order_for(stamp_ns, self._names)
            order = self._body.order(names)
            positions, velocities, efforts = (order.to_message(v) for v in (positions, velocities, efforts))
            state.name = list(names)
        else:
            state.name = self._names
        state.position = _doubles(positions)
        state.velocity = _doubles(velocities)
        state.effort = _doubles(efforts)
        self._state_pub.publish(state)
        self._viz.markers(self.sim, self._prefix, stamp)

        self._started = True
        self._gate.published(stamp_ns, now)


def main(args=None) -> NoReturn:
    # A bad parameter combination (e.g. the joint range) is one line and exit 1.
    node_runner.run(SwimmerSimNode, "swimmer_sim", args, startup_errors=(ValueError,), parameters=PARAMETERS,
                    summary=__doc__.splitlines()[0])  # fmt: skip


if __name__ == "__main__":
    main()
