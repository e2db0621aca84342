"""MuJoCo swimmer (or your own robot) as a ROS 2 node: JointState, Odometry, /clock, episodes out, efforts in.

The physics and episodes are ``morph_core.env.sim.SwimmerSim``'s, the messages' contents and the reading of
efforts ``morph_core.protocol.sim_wire``'s; this node paces the sim, converts messages and handles parameters.
Topics, QoS, bodies, episodes, pacing and bad input, for users: docs/guides/nodes.md ("The sim node in detail").
"""

from __future__ import annotations

import array
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

from morph_core.constants import MAX_JOINTS, MIN_JOINTS
from morph_core.msgs.episode_start import EpisodeCause
from morph_core.msgs.stamps import from_ns
from morph_core.protocol.lockstep import Action, LockstepGate
from morph_core.protocol.pacing import RealTimePacer, tick_period
from morph_core.protocol.sim_wire import SimWire, make_sim
from morph_ros_util import node_runner
from morph_ros_util.diagnostics import InputDiagnostics
from morph_ros_util.parameters import NodeParameter, declare_parameters
from swimmer_sim_node.chain_viz import LATCHED_QOS, ChainViz

# A free-running tick steps for at most this long before letting the executor
# serve commands and parameter requests.
_TICK_BUDGET = 0.02
_LOG_THROTTLE = 5.0
_MAX_EPISODE_STEPS = 2**31 - 1

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


class SwimmerSimNode(Node):
    def __init__(self):
        super().__init__("swimmer_sim")
        declare_parameters(self, PARAMETERS)
        p = self.get_parameter
        self._rtf, self._lockstep = p("real_time_factor").value, p("lockstep").value
        body = {name: p(name).value for name in ("num_joints", "min_joints", "max_joints", "topology", "model_file")}
        self.sim, described = make_sim(**body, seed=p("seed").value, effort_timeout=p("effort_timeout").value,
                                       episode_steps=p("episode_steps").value)  # fmt: skip
        fixed_body = "topology" if body["topology"] else "model_file" if body["model_file"] else None
        shuffle_seed = p("seed").value if p("shuffle_joints").value else None
        self.wire = SimWire(self.sim, p("joint_prefix").value, fixed_body, shuffle_seed)  # ValueError: main()
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        self._state_pub = self.create_publisher(JointState, "joint_states", STATE_QOS)
        self._odom_pub = self.create_publisher(Odometry, "odom", STATE_QOS)
        self._clock_pub = self.create_publisher(Clock, "/clock", STATE_QOS)
        self._episode_pub = self.create_publisher(Int64MultiArray, "episode_start", EPISODE_QOS)
        self.create_subscription(Float64MultiArray, "effort_commands", self._on_efforts, COMMAND_QOS)
        self.create_service(Trigger, "~/reset", self._on_reset)
        self._viz = ChainViz(self)  # robot_description and markers (see chain_viz)
        self._viz.describe(self.sim, self.wire.prefix)
        self._diagnostics = InputDiagnostics(self, self.wire.counts)  # on /diagnostics every second

        self._pacer = RealTimePacer(self._rtf)
        self._gate = LockstepGate(resend_after=p("effort_timeout").value)
        self._started = False  # the first state has been published
        self._timer = None
        self._restart_pacing()
        self._follow_chain()
        self.get_logger().info(
            f"{described}, episode_steps {self.sim.episode_steps or 'unlimited'}, "
            f"real_time_factor {self._rtf}, lockstep {self._lockstep}"
            + (", joints shuffled in every state" if shuffle_seed is not None else "")
        )

    # -- parameters (types and ranges: the table's descriptors, which rclpy enforces) --
    def _validate_parameters(self, params: list[Parameter]) -> SetParametersResult:
        for param in params:
            reason = self.wire.refusal(param.name, param.value)
            if reason is not None:
                return SetParametersResult(successful=False, reason=reason)
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
                self.wire.set_prefix(param.value)
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
        labels = [d.label for d in msg.layout.dim]
        taken = self.wire.take_efforts(labels, msg.data, now, self._lockstep, self._gate.is_stale)
        if taken.rejection is not None:
            self.get_logger().warn(taken.rejection, throttle_duration_sec=_LOG_THROTTLE)
        elif taken.applied and self._lockstep and self._gate.answer():
            self._lockstep_step(now)

    def _publish(self, now: float) -> None:
        stamp_ns = self.sim.stamp_ns
        announcement = self.wire.announcement()  # a new episode: announced before its first state
        if announcement is not None:
            label, data = announcement
            msg = Int64MultiArray(data=data)
            msg.layout.dim = [MultiArrayDimension(label=label, size=len(data), stride=len(data))]
            self._episode_pub.publish(msg)
            self._follow_chain()
            self.get_logger().debug(
                f"episode {self.sim.episode}: {self.sim.num_joints} joints from t={self.sim.time} s"
            )
        stamp = _time(stamp_ns)
        root = self.sim.odometry()
        self._viz.describe(self.sim, self.wire.prefix)  # a changed body's URDF before its first state

        self._clock_pub.publish(Clock(clock=stamp))

        odom = Odometry()
        odom.header.stamp = stamp
        odom.header.frame_id = "odom"
        odom.child_frame_id = self.wire.prefix + root.frame
        pose, twist = odom.pose.pose, odom.twist.twist
        pose.position.x, pose.position.y, pose.position.z = root.position
        pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = root.orientation
        twist.linear.x, twist.linear.y, twist.linear.z = root.linear
        twist.angular.x, twist.angular.y, twist.angular.z = root.angular
        self._odom_pub.publish(odom)

        out = self.wire.joint_state()
        state = JointState()
        state.header.stamp = stamp
        state.name = out.names
        state.position = _doubles(out.position)
        state.velocity = _doubles(out.velocity)
        state.effort = _doubles(out.effort)
        self._state_pub.publish(state)
        self._viz.markers(self.sim, self.wire.prefix, stamp)

        self._started = True
        self._gate.published(stamp_ns, now)


def main(args=None) -> NoReturn:
    # A bad parameter combination (e.g. the joint range) is one line and exit 1.
    node_runner.run(SwimmerSimNode, "swimmer_sim", args, startup_errors=(ValueError,), parameters=PARAMETERS,
                    summary=__doc__.splitlines()[0])  # fmt: skip


if __name__ == "__main__":
    main()
