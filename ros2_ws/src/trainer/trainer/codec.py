"""The ROS codec: the nodes' messages and the core's records (``morph_core.msgs.records``), both ways, in one place.

    topic            message type                          record
    joint_states     sensor_msgs/msg/JointState            JointStateRecord
    odom             nav_msgs/msg/Odometry                 OdometryRecord
    effort_commands  std_msgs/msg/Float64MultiArray        EffortRecord (answers_ns from the answer tag, the
                                                           names dimension: ``msgs.effort_names``)
    policy_info      trajectory_msgs/msg/JointTrajectory   PolicyInfoRecord (``msgs.policy_info``'s layout)
    episode_start    std_msgs/msg/Int64MultiArray          EpisodeStartRecord (``msgs.episode_start``; decoded
                     (or any stamped type)                 from any stamped message too: ``episode_start_record``)
    robot_description std_msgs/msg/String                  DescriptionRecord (the URDF)

Decoding (``*_record``, ``DECODERS``) reads a message by its fields, so it takes rosbags' types (a bag's CDR,
a stream chunk's) and rclpy's (a live subscription) alike; a message that does not fit raises ``DecodeError``
with a short reason it is counted under. Encoding (``record_message``) writes rosbags' Jazzy types
(``TYPESTORE``): recordings made without DDS (``morph_core.protocol.loopback``) go into real bags exactly as
the sim and the policy node would have published them. ``message_class`` gives rclpy's class of a type.
"""

from __future__ import annotations

import importlib
import re
from collections.abc import Sequence

import numpy as np
from rosbags.typesys import Stores, get_typestore

from morph_core.msgs.effort_names import EffortNamesError, effort_names, effort_tree, names_label, tree_label
from morph_core.msgs.episode_start import EpisodeCause, EpisodeStartError, pack_episode_start, unpack_episode_start
from morph_core.msgs.policy_info import PolicyInfoError, unpack_policy_info
from morph_core.msgs.records import (
    DescriptionRecord,
    EffortRecord,
    EpisodeStartRecord,
    JointStateRecord,
    OdometryRecord,
    PolicyInfoRecord,
    Record,
)
from morph_core.msgs.stamps import StampError, answer_tag, check_stamp, from_ns, parse_answer_tag

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


# -- decoding: messages into records -----------------------------------------------------------
class DecodeError(ValueError):
    """One message that does not fit its record; ``reason`` is the short key it is counted under."""

    def __init__(self, reason: str, detail: str = ""):
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


# -- the episode announcement: one small function, adapt it to the sim's message -------------
_EPISODE_FIELDS = ("episode", "episode_index", "index")
_JOINTS_FIELDS = ("num_joints", "joints", "joint_count")
_NAME_LISTS = ("name", "joint_names", "names")


def episode_start_record(msg, log_ns: int) -> EpisodeStartRecord:
    """An episode announcement as a record: the sim's layout, or any stamped message.

    The sim's announcement (``std_msgs/Int64MultiArray``, fields named by
    ``layout.dim[0].label``, e.g. "episode,stamp_ns,num_joints,cause") is
    decoded by ``morph_core.msgs.episode_start.unpack_episode_start``.

    Any other type needs a stamp (the first state of the episode):
    ``header.stamp`` or a ``stamp`` field (builtin_interfaces/Time). The
    episode index comes from an integer field ``episode`` /
    ``episode_index`` / ``index``, the joint count from ``num_joints`` /
    ``joints`` / ``joint_count`` or the length of a name list (``name``,
    ``joint_names``); else from ``key=value`` pairs in a string field
    (``frame_id``, ``header.frame_id`` or ``data``, e.g. a std_msgs/Header
    with frame_id "episode=3 num_joints=6"). Missing values are None.
    Raises ``DecodeError`` when the message does not fit.
    """
    layout = getattr(msg, "layout", None)
    if layout is not None and hasattr(msg, "data"):
        if not len(layout.dim):
            raise DecodeError("bad layout", "a multi-array announcement without layout.dim[0] naming its fields")
        try:
            return unpack_episode_start(log_ns, layout.dim[0].label, [int(v) for v in msg.data])
        except EpisodeStartError as err:
            raise DecodeError("bad layout", str(err)) from None
    stamp = getattr(getattr(msg, "header", None), "stamp", None) or getattr(msg, "stamp", None)
    if stamp is None or not hasattr(stamp, "nanosec"):
        raise DecodeError("no stamp", f"{type(msg).__name__} has neither header.stamp nor stamp")
    episode = _int_field(msg, _EPISODE_FIELDS)
    joints = _int_field(msg, _JOINTS_FIELDS)
    if joints is None:
        names = next((getattr(msg, f) for f in _NAME_LISTS if isinstance(getattr(msg, f, None), list)), None)
        joints = len(names) if names else None
    header = getattr(msg, "header", None)
    strings = (getattr(header, "frame_id", None), getattr(msg, "frame_id", None), getattr(msg, "data", None))
    text = " ".join(s for s in strings if isinstance(s, str))
    if episode is None:
        episode = _int_in_text(text, _EPISODE_FIELDS)
    if joints is None:
        joints = _int_in_text(text, _JOINTS_FIELDS)
    return EpisodeStartRecord(log_ns, _checked_ns(stamp), episode, joints)


def _int_field(msg, names: Sequence[str]) -> int | None:
    for name in names:
        value = getattr(msg, name, None)
        if isinstance(value, int | np.integer) and not isinstance(value, bool):
            return int(value)
    return None


def _int_in_text(text: str, names: Sequence[str]) -> int | None:
    for name in names:
        m = re.search(rf"\b{name}\s*[=:]\s*(\d+)", text)
        if m:
            return int(m.group(1))
    return None


# -- decoding the other topics ---------------------------------------------------------------
def _checked_ns(stamp) -> int:
    """A stamp as ns; one that is no time (nanosec of 10**9 or more, a negative sec) is refused, as the nodes
    refuse it: read as ns it would land on another message's stamp."""
    try:
        return check_stamp(stamp.sec, stamp.nanosec)
    except StampError as err:
        raise DecodeError("bad stamp", str(err)) from None


def _stamp_ns(msg) -> int:
    return _checked_ns(msg.header.stamp)


def _f64(values) -> np.ndarray:
    return np.array(values, dtype=np.float64)


def joint_state_record(msg, log_ns: int) -> JointStateRecord:
    names = tuple(msg.name)
    pos, vel, eff = _f64(msg.position), _f64(msg.velocity), _f64(msg.effort)
    n = len(names)
    if len(pos) != n or len(vel) != n or len(eff) not in (0, n):
        raise DecodeError(
            "length mismatch", f"{n} names, {len(pos)} positions, {len(vel)} velocities, {len(eff)} efforts"
        )
    return JointStateRecord(log_ns, _stamp_ns(msg), names, pos, vel, eff)


def odometry_record(msg, log_ns: int) -> OdometryRecord:
    """The pose and the body-frame twist in 3-D (a swimmer's sim publishes zeros out of its plane: a bag recorded
    before the record held them reads as it did)."""
    p, q, lin, ang = msg.pose.pose.position, msg.pose.pose.orientation, msg.twist.twist.linear, msg.twist.twist.angular
    return OdometryRecord(
        log_ns, _stamp_ns(msg), float(p.x), float(p.y), (q.x, q.y, q.z, q.w), (lin.x, lin.y), float(ang.z),
        float(p.z), float(lin.z), (float(ang.x), float(ang.y)),
    )  # fmt: skip


def effort_record(msg, log_ns: int) -> EffortRecord:
    labels = [d.label for d in msg.layout.dim]
    answers = parse_answer_tag(labels[0]) if labels else None
    data = _f64(msg.data)
    try:
        names, layout = effort_names(labels, len(data)), effort_tree(labels)
    except EffortNamesError as err:
        raise DecodeError("bad names dimension", str(err)) from None
    return EffortRecord(log_ns, answers, data, names, layout)


def description_record(msg, log_ns: int) -> DescriptionRecord:
    return DescriptionRecord(log_ns, msg.data)


def policy_info_record(msg, log_ns: int):
    if not msg.points:
        raise DecodeError("no trajectory point")
    p = msg.points[0]
    try:
        return unpack_policy_info(
            log_ns, _stamp_ns(msg), msg.joint_names, p.positions, p.velocities, p.accelerations, p.effort
        )
    except PolicyInfoError as err:
        raise DecodeError("bad layout", str(err)) from None


DECODERS = {
    DESCRIPTION_TOPIC: description_record,
    "joint_states": joint_state_record,
    "odom": odometry_record,
    "effort_commands": effort_record,
    "policy_info": policy_info_record,
}
"""topic -> the decoder of its messages (the episode announcement's is ``episode_start_record``: a bag may
announce on another topic)"""


def message_class(msgtype: str):
    """The rclpy class of ``pkg/msg/Type``, imported when asked: the codec itself reads and writes bags without
    ROS (subscriptions need the class for type support)."""
    pkg, kind, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.{kind}"), name)
