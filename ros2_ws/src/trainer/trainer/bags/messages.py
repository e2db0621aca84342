"""Records back into the nodes' messages (Jazzy types from ``rosbags``): the inverse of ``bag_io``'s decoders.

For writing recordings made without DDS (``morph_core.protocol.loopback``) into real bags, exactly as
the sim and the policy node would have published them.
"""

from __future__ import annotations

import numpy as np
from rosbags.typesys import Stores, get_typestore

from morph_core.msgs.effort_names import names_label, tree_label
from morph_core.msgs.episode_start import EpisodeCause, pack_episode_start
from morph_core.msgs.records import (
    DescriptionRecord,
    EffortRecord,
    EpisodeStartRecord,
    JointStateRecord,
    OdometryRecord,
    PolicyInfoRecord,
    Record,
)
from morph_core.msgs.stamps import answer_tag, from_ns

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
_T = TYPESTORE.types

TOPIC_TYPES = {
    "episode_start": "std_msgs/msg/Int64MultiArray",
    "robot_description": "std_msgs/msg/String",
    "joint_states": "sensor_msgs/msg/JointState",
    "odom": "nav_msgs/msg/Odometry",
    "effort_commands": "std_msgs/msg/Float64MultiArray",
    "policy_info": "trajectory_msgs/msg/JointTrajectory",
}
"""relative topic name -> message type, as the two nodes publish them"""
EPISODE_TOPIC = "episode_start"
"""the topic announcing episodes (its messages are not data: they say where episodes start)"""
DESCRIPTION_TOPIC = "robot_description"
"""the robot's URDF (latched; not data either: it says which robot the states that follow are of)"""
DATA_TOPIC_TYPES = {
    name: msgtype for name, msgtype in TOPIC_TYPES.items() if name not in (EPISODE_TOPIC, DESCRIPTION_TOPIC)
}
"""the data topics' types (all but the announcement and the description)"""


def stamp(ns: int):
    sec, nanosec = from_ns(ns)
    return _T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)


def header(ns: int, frame_id: str = ""):
    return _T["std_msgs/msg/Header"](stamp=stamp(ns), frame_id=frame_id)


def _dim(label: str, size: int):
    return _T["std_msgs/msg/MultiArrayDimension"](label=label, size=size, stride=size)


def _vector(x=0.0, y=0.0, z=0.0):
    return _T["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)


def record_message(r: Record):
    """(relative topic, message) that the sim or the policy node publishes for record ``r``."""
    if isinstance(r, JointStateRecord):
        msg = _T["sensor_msgs/msg/JointState"](
            header=header(r.stamp_ns), name=list(r.names), position=r.position, velocity=r.velocity, effort=r.effort
        )
        return "joint_states", msg
    if isinstance(r, OdometryRecord):
        pose = _T["geometry_msgs/msg/Pose"](
            position=_T["geometry_msgs/msg/Point"](x=r.x, y=r.y, z=r.z),
            orientation=_T["geometry_msgs/msg/Quaternion"](*r.orientation_xyzw),
        )
        twist = _T["geometry_msgs/msg/Twist"](linear=_vector(*r.body_linear), angular=_vector(*r.body_angular))
        msg = _T["nav_msgs/msg/Odometry"](
            header=header(r.stamp_ns, "odom"),
            child_frame_id="torso",
            pose=_T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=_T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
        )
        return "odom", msg
    if isinstance(r, EffortRecord):
        dims = [] if r.answers_ns is None else [_dim(answer_tag(*from_ns(r.answers_ns)), r.effort.size)]
        if r.names is not None:  # after dim[0] (an empty label: untagged), the names dimension
            dims = (dims or [_dim("", r.effort.size)]) + [_dim(names_label(r.names), 1)]
        if r.layout is not None:  # and the joint layout the efforts were computed on
            dims = (dims or [_dim("", r.effort.size)]) + [_dim(tree_label(r.layout), 1)]
        layout = _T["std_msgs/msg/MultiArrayLayout"](dim=dims, data_offset=0)
        return "effort_commands", _T["std_msgs/msg/Float64MultiArray"](layout=layout, data=r.effort)
    if isinstance(r, PolicyInfoRecord):
        point = _T["trajectory_msgs/msg/JointTrajectoryPoint"](
            positions=r.action, velocities=r.mean, accelerations=r.log_std, effort=r.log_prob_per_joint,
            time_from_start=_T["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
        )  # fmt: skip
        msg = _T["trajectory_msgs/msg/JointTrajectory"](
            header=header(r.stamp_ns), joint_names=list(r.names), points=[point]
        )
        return "policy_info", msg
    if isinstance(r, EpisodeStartRecord):
        if r.cause is not None:  # the record's own (a fall's included); else what a plain recording holds
            cause = EpisodeCause[r.cause.upper()]
        else:
            cause = EpisodeCause.START if r.episode == 0 else EpisodeCause.STEPS
        label, data = pack_episode_start(r.episode, r.stamp_ns, r.num_joints, cause)
        layout = _T["std_msgs/msg/MultiArrayLayout"](dim=[_dim(label, len(data))], data_offset=0)
        return "episode_start", _T["std_msgs/msg/Int64MultiArray"](layout=layout, data=np.array(data, np.int64))
    if isinstance(r, DescriptionRecord):
        text = r.text.decode(errors="replace") if isinstance(r.text, bytes) else r.text
        return DESCRIPTION_TOPIC, _T["std_msgs/msg/String"](data=text)
    raise TypeError(f"not a record: {r!r}")
