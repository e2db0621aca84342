"""MuJoCo swimmer as a ROS 2 node: JointState, Odometry and /clock out, efforts in.

All physics is ``morph_core.env.sim.SwimmerSim``; this node only paces it, converts
messages and handles parameters.

Wire conventions
- ``joint_states`` (sensor_msgs/JointState): joints torso to tail; position
  [rad], velocity [rad/s], effort = the normalised motor command applied over
  the control period that ended at this state (torque = 150 x effort);
  stamp = sim time.
- ``odom`` (nav_msgs/Odometry): frame ``odom`` -> ``<joint_prefix>torso``;
  pose in the world frame (yaw as a quaternion about z); twist in the torso
  (child) frame, as the message defines it.
- ``/clock`` (rosgraph_msgs/Clock): sim time.
- ``effort_commands`` (std_msgs/Float64MultiArray): one value per joint in
  ``joint_states`` order, clipped to [-1, 1].
Odometry is published before the joint state of the same stamp, so a
controller that acts on joint states finds the matching odometry first.

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
taken as the answer.
"""

from __future__ import annotations

import array
import math
import time

import rclpy
from builtin_interfaces.msg import Time
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from morph_core.env.model import MAX_JOINTS, MIN_JOINTS
from morph_core.env.sim import EffortError, SwimmerSim
from morph_core.msgs.joint_state import quaternion_from_yaw, world_to_body
from morph_core.msgs.stamps import from_ns, parse_answer_tag, seconds_to_ns
from morph_core.protocol.lockstep import Action, LockstepGate
from morph_core.protocol.pacing import RealTimePacer, tick_period

# A free-running tick steps for at most this long before letting the executor
# serve commands and parameter requests.
_TICK_BUDGET = 0.02
_LOG_THROTTLE = 5.0


def _time(ns: int) -> Time:
    sec, nanosec = from_ns(ns)
    return Time(sec=sec, nanosec=nanosec)


def _doubles(values) -> array.array:
    # Assigning a typed array skips the per-element checks of a Python list.
    return array.array("d", values.tobytes())


class SwimmerSimNode(Node):
    def __init__(self):
        super().__init__("swimmer_sim")
        self.declare_parameter(
            "num_joints",
            6,
            ParameterDescriptor(
                description="actuated joints in the chain; setting it rebuilds the swimmer in place",
                integer_range=[IntegerRange(from_value=MIN_JOINTS, to_value=MAX_JOINTS, step=1)],
            ),
        )
        self.declare_parameter(
            "joint_prefix", "", ParameterDescriptor(description="prefix of joint and torso frame names")
        )
        self.declare_parameter(
            "real_time_factor",
            1.0,
            ParameterDescriptor(
                description="sim seconds per wall second; 0 = as fast as possible",
                floating_point_range=[FloatingPointRange(from_value=0.0, to_value=10000.0, step=0.0)],
            ),
        )
        self.declare_parameter(
            "lockstep",
            False,
            ParameterDescriptor(description="step only when efforts for the latest published state have arrived"),
        )
        self.declare_parameter(
            "effort_timeout",
            0.25,
            ParameterDescriptor(
                description="wall seconds without efforts before they drop to zero (lockstep: before re-publishing)",
                floating_point_range=[FloatingPointRange(from_value=0.001, to_value=3600.0, step=0.0)],
            ),
        )
        self.declare_parameter("seed", 0, ParameterDescriptor(description="seed of the reset noise", read_only=True))
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)

        p = self.get_parameter
        self._prefix = p("joint_prefix").value
        self._rtf = p("real_time_factor").value
        self._lockstep = p("lockstep").value
        self.sim = SwimmerSim(
            num_joints=p("num_joints").value, seed=p("seed").value, effort_timeout=p("effort_timeout").value
        )
        self._names = self.sim.joint_names(self._prefix)

        self._state_pub = self.create_publisher(JointState, "joint_states", 10)
        self._odom_pub = self.create_publisher(Odometry, "odom", 10)
        self._clock_pub = self.create_publisher(Clock, "/clock", 10)
        self.create_subscription(Float64MultiArray, "effort_commands", self._on_efforts, 10)

        self._pacer = RealTimePacer(self._rtf)
        self._gate = LockstepGate(resend_after=p("effort_timeout").value)
        self._timer = None
        self._restart_pacing()
        self.get_logger().info(
            f"swimmer with {self.sim.num_joints} joints, real_time_factor {self._rtf}, lockstep {self._lockstep}"
        )

    # -- parameters -------------------------------------------------------------
    def _validate_parameters(self, params: list[Parameter]) -> SetParametersResult:
        for param in params:
            if param.name == "num_joints":
                if param.type_ != Parameter.Type.INTEGER or not MIN_JOINTS <= param.value <= MAX_JOINTS:
                    return SetParametersResult(
                        successful=False, reason=f"num_joints must be an integer in {MIN_JOINTS}..{MAX_JOINTS}"
                    )
            elif param.name == "real_time_factor":
                if param.type_ != Parameter.Type.DOUBLE or not (math.isfinite(param.value) and param.value >= 0):
                    return SetParametersResult(successful=False, reason="real_time_factor must be a finite double >= 0")
            elif param.name == "effort_timeout":
                if param.type_ != Parameter.Type.DOUBLE or not (math.isfinite(param.value) and param.value > 0):
                    return SetParametersResult(successful=False, reason="effort_timeout must be a finite double > 0")
        return SetParametersResult(successful=True)

    def _apply_parameters(self, params: list[Parameter]) -> None:
        for param in params:
            if param.name == "num_joints" and param.value != self.sim.num_joints:
                self.sim.rebuild(param.value)
                self._names = self.sim.joint_names(self._prefix)
                self.get_logger().info(f"rebuilt the swimmer with {param.value} joints")
                if self._lockstep:
                    self._gate.restart()
                    self._publish(time.monotonic())  # the new chain asks for its own efforts
            elif param.name == "joint_prefix":
                self._prefix = param.value
                self._names = self.sim.joint_names(self._prefix)
            elif param.name == "real_time_factor":
                self._rtf = self._pacer.real_time_factor = param.value
                self._restart_pacing()
            elif param.name == "lockstep":
                self._lockstep = param.value
                self._gate.restart()
                self._restart_pacing()
            elif param.name == "effort_timeout":
                self.sim.effort_timeout = self._gate.resend_after = param.value

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
        end = now + _TICK_BUDGET
        while self._due(now):
            self._step(now)
            self._publish(now)
            now = time.monotonic()
            if now > end:
                break

    def _lockstep_step(self, now: float) -> None:
        if self._due(now):
            self._step(now)
            self._gate.stepped()
            self._publish(now)

    def _step(self, now: float) -> None:
        if not self.sim.step(now):
            self.get_logger().error(
                f"physics diverged; swimmer reset ({self.sim.unstable_resets} so far)",
                throttle_duration_sec=_LOG_THROTTLE,
            )

    # -- messages ---------------------------------------------------------------
    def _on_efforts(self, msg: Float64MultiArray) -> None:
        now = time.monotonic()
        if self._lockstep and msg.layout.dim:
            # An answer to an earlier (re-sent) state: taking it for the current one would
            # shift the whole loop by a step.
            if self._gate.is_stale(parse_answer_tag(msg.layout.dim[0].label)):
                return
        try:
            self.sim.command(msg.data, now)
        except EffortError as err:
            self.get_logger().warn(
                f"rejected effort command ({self.sim.rejected} so far): {err}", throttle_duration_sec=_LOG_THROTTLE
            )
            return
        if self._lockstep and self._gate.answer():
            self._lockstep_step(now)

    def _publish(self, now: float) -> None:
        stamp_ns = seconds_to_ns(self.sim.time)
        stamp = _time(stamp_ns)
        torso = self.sim.torso()

        self._clock_pub.publish(Clock(clock=stamp))

        odom = Odometry()
        odom.header.stamp = stamp
        odom.header.frame_id = "odom"
        odom.child_frame_id = f"{self._prefix}torso"
        odom.pose.pose.position.x = torso.x
        odom.pose.pose.position.y = torso.y
        q = odom.pose.pose.orientation
        q.x, q.y, q.z, q.w = quaternion_from_yaw(torso.yaw)
        odom.twist.twist.linear.x, odom.twist.twist.linear.y = world_to_body(torso.yaw, torso.vx, torso.vy)
        odom.twist.twist.angular.z = torso.yaw_rate
        self._odom_pub.publish(odom)

        state = JointState()
        state.header.stamp = stamp
        state.name = self._names
        state.position = _doubles(self.sim.joint_positions)
        state.velocity = _doubles(self.sim.joint_velocities)
        state.effort = _doubles(self.sim.applied)
        self._state_pub.publish(state)

        self._gate.published(stamp_ns, now)


def main(args=None):
    rclpy.init(args=args)
    node = None
    try:
        node = SwimmerSimNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        # A callback that was publishing when SIGINT/SIGTERM shut the context down
        # fails on the dead context: that is still a normal end.
        if rclpy.ok():
            raise
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
