"""From a joint-state message and the torso's odometry to the policy's input, without ROS.

The policy was trained on ``MorphSwimmerEnv``'s graph observation: per joint
(angle, angular velocity), globally (yaw, yaw rate, vx, vy) where yaw is the
torso hinge angle ``qpos[2]`` (never wrapped), yaw rate is ``qvel[2]`` and
vx, vy are the torso frame's velocity in the WORLD frame (``qvel[0:2]``).

On the wire the torso arrives as an odometry message whose pose is in the
world ("odom") frame and whose twist is, by the ROS convention, in the body
(child) frame. This module turns both back into exactly the training
features: yaw from the orientation quaternion, unwrapped across messages;
linear velocity rotated from body to world by that yaw.

Nothing here imports ROS: callers pass plain sequences and numbers. Nor torch:
the nodes run without it (the torch policy's one-chain batch is ``policy.chains.chain_batch``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from morph_core.constants import LEGGED_GLOBAL_FEATURES, MAX_JOINTS
from morph_core.policy.tree import joint_name_error


class JointStateError(ValueError):
    """A joint state that cannot be turned into a chain; ``str(err)`` is the reason."""


QUATERNION_NORM_TOLERANCE = 1e-3
"""|norm - 1| allowed in an odometry's orientation: any estimator's unit quaternion is far closer; a
non-unit one gives a wrong yaw (``yaw_from_quaternion`` assumes a unit quaternion), so it is refused"""


def validate_joint_state(
    names: Sequence[str], positions: Sequence[float], velocities: Sequence[float], max_joints: int = MAX_JOINTS
) -> tuple[np.ndarray, np.ndarray]:
    """Check one joint state and return (positions, velocities) as float64 arrays, message order.

    Raises ``JointStateError`` for: no joints, more than ``max_joints``, names /
    positions / velocities of different lengths, a name that is empty, longer than
    ``MAX_NAME_CHARS`` or not printable ASCII (ROS and URDF names are), duplicate names, NaN or inf.
    """
    n = len(names)
    if n == 0:
        raise JointStateError("empty joint state (no joint names)")
    if n > max_joints:
        raise JointStateError(f"{n} joints, more than the maximum of {max_joints}")
    if len(positions) != n or len(velocities) != n:
        raise JointStateError(f"length mismatch: {n} names, {len(positions)} positions, {len(velocities)} velocities")
    bad_name = joint_name_error(names)
    if bad_name is not None:
        raise JointStateError(bad_name)
    if len(set(names)) != n:
        seen: set[str] = set()
        dups = sorted({x for x in names if x in seen or seen.add(x)})
        raise JointStateError(f"duplicate joint names: {dups}")
    pos = np.asarray(positions, dtype=np.float64)
    vel = np.asarray(velocities, dtype=np.float64)
    if not (np.isfinite(pos).all() and np.isfinite(vel).all()):
        raise JointStateError("NaN or inf in positions or velocities")
    return pos, vel


# -- torso frame conversions -----------------------------------------------------------
def quaternion_from_yaw(yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation by ``yaw`` about z."""
    return 0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw)


def yaw_from_quaternion(x: float, y: float, z: float, w: float) -> float:
    """Rotation about z of a quaternion, in (-pi, pi]; exact inverse of ``quaternion_from_yaw`` there."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def world_to_body(yaw: float, vx: float, vy: float) -> tuple[float, float]:
    """Planar velocity from the world frame into a frame rotated by ``yaw``."""
    c, s = math.cos(yaw), math.sin(yaw)
    return c * vx + s * vy, -s * vx + c * vy


def body_to_world(yaw: float, vx: float, vy: float) -> tuple[float, float]:
    """Inverse of ``world_to_body``."""
    c, s = math.cos(yaw), math.sin(yaw)
    return c * vx - s * vy, s * vx + c * vy


class YawUnwrapper:
    """Turns a stream of wrapped yaws into the continuous hinge angle the policy was trained on.

    A swimmer that turns around accumulates yaw beyond +-pi (the torso hinge is
    unlimited); a quaternion forgets that. Consecutive messages 40 ms apart
    cannot turn by pi, so the nearest branch is the right one. The first yaw
    is taken as it is (a fresh swimmer starts near 0); ``reset`` when the
    robot is rebuilt.
    """

    def __init__(self):
        self._last: float | None = None

    def reset(self) -> None:
        self._last = None

    def __call__(self, wrapped: float) -> float:
        if self._last is None:
            self._last = wrapped
        else:
            step = math.remainder(wrapped - self._last, math.tau)  # in [-pi, pi]
            self._last += step
        return self._last


def global_features(
    orientation_xyzw: Sequence[float],
    body_linear_xy: Sequence[float],
    angular_z: float,
    unwrap: YawUnwrapper | None = None,
) -> np.ndarray:
    """[4] float64 (yaw, yaw rate, vx, vy) as in ``MorphSwimmerEnv``, from an odometry's pose and body twist.

    Raises ``JointStateError`` on NaN/inf or a quaternion that is not of unit length
    (within ``QUATERNION_NORM_TOLERANCE``; a zero one included).
    """
    q = [float(v) for v in orientation_xyzw]
    lin = [float(v) for v in body_linear_xy]
    wz = float(angular_z)
    if not all(math.isfinite(v) for v in (*q, *lin, wz)):
        raise JointStateError("NaN or inf in odometry")
    norm = math.sqrt(sum(v * v for v in q))
    if norm < 1e-6:
        raise JointStateError("odometry orientation is a zero quaternion")
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise JointStateError(f"odometry orientation is not a unit quaternion (norm {norm:.6g})")
    yaw = yaw_from_quaternion(*q)
    if unwrap is not None:
        yaw = unwrap(yaw)
    vx, vy = body_to_world(yaw, lin[0], lin[1])
    return np.array([yaw, wz, vx, vy], dtype=np.float64)


def write_global_features(qpos, qvel, out) -> None:
    """``GLOBAL_FEATURES`` of a free-floating root (qpos[0:7], qvel[0:6]: MuJoCo's free joint, quaternion w x y z,
    angular velocity in the body frame) into ``out`` [12]. The quaternion is normalised first: reset noise
    leaves it off unit length, and MuJoCo uses it normalised."""
    w, x, y, z = qpos[3], qpos[4], qpos[5], qpos[6]
    s = 1.0 / math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w * s, x * s, y * s, z * s
    # the rotation matrix's first column (x axis) and third row (world z in body coordinates)
    r00, r10 = 1 - 2 * (y * y + z * z), 2 * (x * y + z * w)
    r20, r21, r22 = 2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)
    wx, wy, wz = qvel[3], qvel[4], qvel[5]
    out[0] = math.atan2(r10, r00)  # heading of the body's x axis
    out[1] = r20 * wx + r21 * wy + r22 * wz  # world z component of the angular velocity
    out[2], out[3], out[4], out[5] = qvel[0], qvel[1], qvel[2], qpos[2]
    out[6], out[7], out[8] = -r20, -r21, -r22  # R^T (0, 0, -1)
    out[9], out[10], out[11] = wx, wy, wz


def legged_global_features(
    orientation_xyzw: Sequence[float],
    position: Sequence[float],
    body_linear: Sequence[float],
    body_angular: Sequence[float],
) -> np.ndarray:
    """[12] float64 ``env.centipede.GLOBAL_FEATURES`` from an odometry of a root in 3-D (pose in the world
    frame, twist in the root's frame, as ``odom`` carries it): the free joint's state rebuilt (the linear
    velocity turned into the world frame, as MuJoCo's free joint holds it) and passed through the env's own
    ``write_global_features``. The yaw is not unwrapped: the env's is atan2's, in [-pi, pi].

    Raises ``JointStateError`` on NaN/inf or a quaternion that is not of unit length."""
    x, y, z, w = (float(v) for v in orientation_xyzw)
    pos, lin, ang = ([float(v) for v in a] for a in (position, body_linear, body_angular))
    if not all(math.isfinite(v) for v in (x, y, z, w, *pos, *lin, *ang)):
        raise JointStateError("NaN or inf in odometry")
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise JointStateError(f"odometry orientation is not a unit quaternion (norm {norm:.6g})")
    w, x, y, z = w / norm, x / norm, y / norm, z / norm
    rot = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])  # fmt: skip
    qpos = np.array([*pos, w, x, y, z])
    qvel = np.array([*(rot @ np.array(lin)), *ang])
    out = np.empty(LEGGED_GLOBAL_FEATURES)
    write_global_features(qpos, qvel, out)
    return out
