"""The topics a trainer reads, as plain records: what a bag or a live subscription decodes into.

Nothing here imports ROS. ``log_ns`` is when the message was received (a
bag's log time), ``stamp_ns`` the stamp it carries. Arrays are float64 in
the message's joint order (which joint is which: the names they come
with, laid onto the robot's tree by ``protocol.joint_map``). These are the
inputs of episode assembly (``protocol``); recorders and live trainers only
fill them in.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class JointStateRecord:
    """``joint_states`` (sensor_msgs/JointState): ``effort`` is what was applied over the period
    that ended at this state (empty if the publisher does not say)."""

    log_ns: int
    stamp_ns: int
    names: tuple[str, ...]
    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray


@dataclass(frozen=True)
class OdometryRecord:
    """``odom`` (nav_msgs/Odometry): pose in the world frame, twist in the body frame. The planar fields come
    first (a swimmer's: all a 4-feature policy reads); the rest complete the 3-D pose and twist a legged
    policy reads (``msgs.joint_state.legged_global_features``), zero where a source does not give them."""

    log_ns: int
    stamp_ns: int
    x: float
    y: float
    orientation_xyzw: tuple[float, float, float, float]
    body_linear_xy: tuple[float, float]
    angular_z: float
    z: float = 0.0
    body_linear_z: float = 0.0
    angular_xy: tuple[float, float] = (0.0, 0.0)

    @classmethod
    def of(cls, log_ns: int, stamp_ns: int, position, orientation_xyzw, body_linear, body_angular) -> OdometryRecord:
        """The record of an odometry message's 3-D pose (world frame) and twist (body frame), each as the message
        lists it (x, y, z; x, y, z, w): the one place its fields are laid out."""
        (x, y, z), (vx, vy, vz), (wx, wy, wz) = position, body_linear, body_angular
        return cls(log_ns, stamp_ns, x, y, tuple(orientation_xyzw), (vx, vy), wz, z, vz, (wx, wy))

    @property
    def position(self) -> tuple[float, float, float]:
        return self.x, self.y, self.z

    @property
    def body_linear(self) -> tuple[float, float, float]:
        return self.body_linear_xy[0], self.body_linear_xy[1], self.body_linear_z

    @property
    def body_angular(self) -> tuple[float, float, float]:
        return self.angular_xy[0], self.angular_xy[1], self.angular_z

    @property
    def planar(self) -> bool:
        """A body in the plane (a swimmer's: the orientation a turn about z alone, as its sim writes it); False
        for one in 3-D (a legged body: a centipede, a legged robot)."""
        qx, qy, _, _ = self.orientation_xyzw
        return qx == 0.0 and qy == 0.0


@dataclass(frozen=True)
class EffortRecord:
    """``effort_commands`` (std_msgs/Float64MultiArray): ``answers_ns`` is the stamp of the state it
    answers, from its answer tag (``msgs.stamps``), or None for an untagged command."""

    log_ns: int
    answers_ns: int | None
    effort: np.ndarray
    names: tuple[str, ...] | None = None
    """the joints the efforts are for, in their order (the command's names dimension, ``msgs.effort_names``);
    None: the command names none, and its efforts are in the order of the state it answers"""
    layout: str | None = None
    """the joint layout the efforts were computed on (the command's tree dimension: ``KinematicTree.layout_hash``),
    None when it gives none"""


@dataclass(frozen=True)
class PolicyInfoRecord:
    """``policy_info``: a sampling policy's action for the state stamped ``stamp_ns``
    (layout: ``msgs.policy_info``)."""

    log_ns: int
    stamp_ns: int
    names: tuple[str, ...]
    action: np.ndarray
    """sampled action, before any clip to the motors' range"""
    mean: np.ndarray
    log_std: np.ndarray
    log_prob_per_joint: np.ndarray

    @property
    def log_prob(self) -> float:
        """Log-probability of the whole action under the policy that sampled it."""
        return float(self.log_prob_per_joint.sum())


@dataclass(frozen=True)
class EpisodeStartRecord:
    """An episode announcement: the episode begins with the state stamped ``stamp_ns``."""

    log_ns: int
    stamp_ns: int
    episode: int | None = None
    num_joints: int | None = None
    cause: str | None = None
    """why it began, hence how the previous episode ended: "start", "steps" (time limit), "reset",
    "rebuild", "diverged" or "fell" (a legged body fell: its last step terminated;
    ``msgs.episode_start.EpisodeCause``)"""


@dataclass(frozen=True)
class DescriptionRecord:
    """``robot_description`` (std_msgs/String): the robot's URDF, published (latched) whenever the robot
    changes, before its first state. Read by ``protocol.joint_map.JointMap.from_urdf``; not checked here."""

    log_ns: int
    text: str


Record = JointStateRecord | OdometryRecord | EffortRecord | PolicyInfoRecord | EpisodeStartRecord | DescriptionRecord
