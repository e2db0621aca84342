"""What the sim node shows to RViz and Foxglove: ``robot_description`` (URDF) and ``markers``.

- ``robot_description`` (std_msgs/String): the body as URDF
  (``morph_core.env.urdf``: a chain, a tree, or your own robot's model),
  joint names as in ``joint_states``, links named ``<joint_prefix><MJCF
  body>``; reliable, transient local, keep last 1, as robot_state_publisher
  publishes it, so a viewer that starts late gets it. Published at start and
  again whenever the body changes (``num_joints`` set, a new length or tree
  drawn at a reset, ``joint_prefix`` set), before the new body's first
  state; a new episode with the same body leaves it alone.
- ``markers`` (visualization_msgs/MarkerArray), swimmers only (chains and
  trees; a robot model's shapes are its URDF's): one CYLINDER per segment
  (torso first, ids 0..N, namespace ``<joint_prefix>swimmer``) in frame
  ``odom`` with the state's stamp, placed from the published state
  (``morph_core.env.segments``), so the swimmer shows without TF. When the
  body changes the array starts with a DELETEALL, so no segment of an
  earlier body lingers. Built only while someone subscribes: the sim can
  run thousands of steps a second and 65 markers a step would cost more than
  the physics. QoS as ``joint_states`` (reliable, volatile, keep last 10).
"""

from __future__ import annotations

import math

from geometry_msgs.msg import Quaternion
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import ColorRGBA, String
from visualization_msgs.msg import Marker, MarkerArray

from morph_core.env.segments import segment_poses
from morph_core.env.sim import SwimmerSim
from morph_core.policy.tree import KinematicTree

LATCHED_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
"""the latest sample kept for late subscribers (the sim's robot_description and episode_start)"""
DESCRIPTION_QOS = LATCHED_QOS
"""robot_description: latched, as robot_state_publisher's"""
MARKER_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
SEGMENT_COLOR = ColorRGBA(r=0.8, g=0.6, b=0.4, a=1.0)  # the MJCF's segment colour
_HALF_TURN = math.sqrt(0.5)


def _lying(heading: float) -> Quaternion:
    """A marker cylinder (axis z) laid in the plane along ``heading``: yaw about z after 90 deg about y."""
    c, s = math.cos(heading / 2), math.sin(heading / 2)
    # q_z(heading) * q_y(pi/2), expanded
    return Quaternion(w=c * _HALF_TURN, x=-s * _HALF_TURN, y=c * _HALF_TURN, z=s * _HALF_TURN)


class ChainViz:
    """The two publishers: ``describe`` before each published state, ``markers`` after it."""

    def __init__(self, node: Node):
        self._description_pub = node.create_publisher(String, "robot_description", DESCRIPTION_QOS)
        self._marker_pub = node.create_publisher(MarkerArray, "markers", MARKER_QOS)
        self._described: tuple[KinematicTree, str, object] | None = None
        self._marked: KinematicTree | None = None  # the body of the last marker array published

    def describe(self, sim: SwimmerSim, prefix: str) -> None:
        """Publish the URDF of the sim's body unless it is the one already published."""
        tree = sim.tree  # the same object while the body stays the same: the common case costs no comparison
        # A robot's compiled model as well: two generated legged bodies of one tree differ in their sizes, which a
        # policy reading joint descriptions reads off this URDF.
        model = None if sim.robot is None else getattr(sim.robot, "model", None)
        if self._described is None or not (self._described[0] is tree or self._described[0] == tree):
            changed = True
        else:
            changed = self._described[1] != prefix or self._described[2] is not model
        if changed:
            self._description_pub.publish(String(data=sim.urdf(prefix)))
            self._described = (tree, prefix, model)

    def markers(self, sim: SwimmerSim, prefix: str, stamp) -> None:
        """The current state's segments, if anyone listens (a swimmer's: a robot model has none)."""
        if sim.robot is not None:
            return
        if self._marker_pub.get_subscription_count() == 0:
            self._marked = None  # a new listener gets a DELETEALL first
            return
        torso = sim.torso()
        tree = sim.tree
        poses = segment_poses(torso.x, torso.y, torso.yaw, sim.joint_positions, None if tree.is_chain else tree)
        markers = []
        if not (self._marked is tree or self._marked == tree):
            clear = Marker(action=Marker.DELETEALL)
            clear.header.frame_id = "odom"
            clear.header.stamp = stamp
            markers.append(clear)
        for k in range(sim.num_joints + 1):
            m = Marker(ns=f"{prefix}swimmer", id=k, type=Marker.CYLINDER, action=Marker.ADD, color=SEGMENT_COLOR)
            m.header.frame_id = "odom"
            m.header.stamp = stamp
            m.pose.position.x, m.pose.position.y = float(poses.centers[k, 0]), float(poses.centers[k, 1])
            m.pose.orientation = _lying(float(poses.headings[k]))
            m.scale.x = m.scale.y = 2 * float(poses.radii[k])
            m.scale.z = float(poses.lengths[k])
            markers.append(m)
        self._marker_pub.publish(MarkerArray(markers=markers))
        self._marked = tree
