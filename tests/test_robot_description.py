"""The sim node's robot_description (latched URDF) and segment markers (chains and trees), over real DDS.

Runs inside a private network namespace (``scripts/test.sh``). The URDF is
parsed with a real URDF parser; the markers are checked against MuJoCo's own
kinematics run here on the state the sim published with the same stamp.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest
from nav_msgs.msg import Odometry
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, String
from urdf_parser_py.urdf import URDF
from visualization_msgs.msg import Marker, MarkerArray

from morph_core.env.bodies import parse_bodies
from morph_core.env.model import swimmer_model

pytestmark = pytest.mark.slow  # every test here starts processes (nodes, bring-ups, installs)

STARTUP = 60.0
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _stamp_ns(header) -> int:
    return header.stamp.sec * 10**9 + header.stamp.nanosec


def _revolute_names(urdf_text: str) -> list[str]:
    robot = URDF.from_xml_string(urdf_text)
    return [j.name for j in robot.joints if j.type == "revolute"]


@pytest.mark.timeout(180)
def test_late_subscriber_gets_the_urdf_and_it_follows_num_joints(probe, launch, namespace):
    states = probe.collect(JointState, "joint_states")
    odoms = probe.collect(Odometry, "odom")
    launch("swimmer_sim_node", num_joints=6, joint_prefix="s1/")
    probe.spin_until(lambda: states and odoms, STARTUP, "the sim's first states")

    # Subscribed only now, after the sim published it: the latched sample arrives all the same.
    descriptions = probe.collect(String, "robot_description", LATCHED)
    probe.spin_until(lambda: descriptions, 20.0, "the latched robot_description")
    robot = URDF.from_xml_string(descriptions[-1].data)
    assert _revolute_names(descriptions[-1].data) == list(states[-1].name)
    assert robot.get_root() == odoms[-1].child_frame_id == "s1/torso"
    assert len(robot.links) == 7

    result = probe.set_parameter(f"{namespace}/swimmer_sim", "num_joints", 11)
    assert result.successful, result.reason
    n = len(states)
    probe.spin_until(
        lambda: len(descriptions) >= 2 and any(len(s.name) == 11 for s in states[n:]),
        20.0,
        "a new robot_description and 11-joint states",
    )
    assert len(_revolute_names(descriptions[-1].data)) == 11
    assert _revolute_names(descriptions[-1].data) == list(states[-1].name)
    # A second late subscriber now gets only the current chain.
    late = []
    probe.node.create_subscription(String, "robot_description", late.append, LATCHED)
    probe.spin_until(lambda: late, 20.0, "the latched 11-joint robot_description")
    assert [len(_revolute_names(m.data)) for m in late] == [11]


def _mujoco_geoms(odom: Odometry, state: JointState, body) -> tuple[np.ndarray, np.ndarray, mujoco.MjModel]:
    """World capsule centres and axes of the published state, by MuJoCo's own kinematics."""
    m = swimmer_model(body)
    d = mujoco.MjData(m)
    q = odom.pose.pose.orientation
    yaw = 2 * math.atan2(q.z, q.w)  # a rotation about z only
    d.qpos[:3] = odom.pose.pose.position.x, odom.pose.pose.position.y, yaw
    d.qpos[3:] = state.position
    mujoco.mj_kinematics(m, d)
    return d.geom_xpos[1:], d.geom_xmat[1:].reshape(-1, 3, 3)[:, :, 2], m


def _marker_axis(marker: Marker) -> np.ndarray:
    """The marker cylinder's axis (its local z) in the world frame."""
    o = marker.pose.orientation
    mat = np.empty(9)
    mujoco.mju_quat2Mat(mat, np.array([o.w, o.x, o.y, o.z]))
    return mat.reshape(3, 3)[:, 2]


@pytest.mark.timeout(180)
@pytest.mark.parametrize("spec", ["1", "6", "y:1x2"])
def test_markers_are_the_sims_segments(probe, launch, namespace, spec):
    body = parse_bodies(spec).first()  # one member: the sim's body throughout
    joints = body.num_joints
    states = probe.collect(JointState, "joint_states")
    odoms = probe.collect(Odometry, "odom")
    arrays = probe.collect(MarkerArray, "markers")
    efforts = probe.node.create_publisher(Float64MultiArray, "effort_commands", 10)
    t0 = probe.node.get_clock().now().nanoseconds
    # A travelling wave bends the chain well away from straight, so the check sees real angles.
    probe.node.create_timer(
        0.04,
        lambda: efforts.publish(
            Float64MultiArray(
                data=[math.sin(3.0 * (probe.node.get_clock().now().nanoseconds - t0) * 1e-9 - k) for k in range(joints)]
            )
        ),
    )
    body_param = {"num_joints": joints} if body.is_chain else {"topology": spec}  # chains as they always were
    launch("swimmer_sim_node", real_time_factor=2.0, **body_param)
    probe.spin_until(lambda: len(arrays) >= 40, STARTUP, "40 marker arrays")

    odom_at = {_stamp_ns(o.header): o for o in odoms}
    state_at = {_stamp_ns(s.header): s for s in states}
    checked, bent = 0, 0.0
    for array in arrays:
        segments = [mk for mk in array.markers if mk.action == Marker.ADD]
        assert [mk.id for mk in segments] == list(range(joints + 1))
        stamp = _stamp_ns(segments[0].header)
        if stamp not in odom_at or stamp not in state_at:
            continue  # published before this probe matched both state topics
        centres, axes, m = _mujoco_geoms(odom_at[stamp], state_at[stamp], body)
        for k, mk in enumerate(segments):
            assert mk.header.frame_id == "odom" and mk.type == Marker.CYLINDER
            assert _stamp_ns(mk.header) == stamp
            np.testing.assert_allclose(
                [mk.pose.position.x, mk.pose.position.y, mk.pose.position.z], centres[k], atol=1e-9
            )
            assert abs(abs(_marker_axis(mk) @ axes[k]) - 1.0) < 1e-9
            assert mk.scale.x == mk.scale.y == pytest.approx(2 * m.geom_size[k + 1][0])
            assert mk.scale.z == pytest.approx(2 * m.geom_size[k + 1][1])
        bent = max(bent, float(np.abs(state_at[stamp].position).max()))
        checked += 1
    assert checked >= 20
    assert bent > 0.3  # the wave bent the joints: the comparison was not of a straight chain only
    # The first array a subscriber gets clears whatever an earlier chain left.
    assert arrays[0].markers[0].action == Marker.DELETEALL
    assert all(mk.action == Marker.ADD for a in arrays[1:] for mk in a.markers)
