"""Where the swimmer's segments are, from the torso's planar pose and the joint angles.

The chain is planar (every hinge turns about z), so each segment's pose is a
running sum: heading_k = yaw + q_1 + ... + q_k, and each body's origin is its
parent's plus the parent-frame offset turned by the parent's heading. The
offsets are read off the compiled model, so this is MuJoCo's own forward
kinematics for this chain (tested equal to ``mj_kinematics``), without
touching the simulation's ``MjData``: a publisher can place the segments of a
state it has already reported.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import mujoco
import numpy as np

from morph_core.env.model import check_num_joints, swimmer_model


@dataclass(frozen=True)
class SegmentPoses:
    """Capsule centres [N+1, 2] (world x, y), headings [N+1] (rad; the capsule's axis is the heading's
    direction), straight lengths [N+1] and radii [N+1]; index 0 is the torso."""

    centers: np.ndarray
    headings: np.ndarray
    lengths: np.ndarray
    radii: np.ndarray


@dataclass(frozen=True)
class _Chain:
    body_offsets: np.ndarray  # [N+1] complex: each body's origin in its parent's frame (torso: 0)
    geom_offsets: np.ndarray  # [N+1] complex: each capsule's centre in its body's frame
    lengths: np.ndarray
    radii: np.ndarray


@lru_cache(maxsize=64)
def _chain(num_joints: int) -> _Chain:
    m = swimmer_model(num_joints)
    bodies = np.arange(1, m.nbody)
    if not np.array_equal(m.body_parentid[bodies], np.arange(m.nbody - 1)):
        raise ValueError("the swimmer model is not a single chain")
    geoms = np.array([np.flatnonzero(m.geom_bodyid == b)[0] for b in bodies])
    # A capsule's axis is its local z; here it must lie along its body's x (the chain's direction).
    axes = np.array([_z_axis(m.geom_quat[g]) for g in geoms])
    if not np.allclose(np.abs(axes[:, 0]), 1.0):
        raise ValueError("a segment capsule does not lie along its body's x axis")
    offsets = m.body_pos[bodies, 0] + 1j * m.body_pos[bodies, 1]
    offsets[0] = 0  # the torso's own place is the pose given
    return _Chain(
        body_offsets=offsets,
        geom_offsets=m.geom_pos[geoms, 0] + 1j * m.geom_pos[geoms, 1],
        lengths=2 * m.geom_size[geoms, 1],
        radii=m.geom_size[geoms, 0].copy(),
    )


def _z_axis(quat: np.ndarray) -> np.ndarray:
    mat = np.empty(9)
    mujoco.mju_quat2Mat(mat, quat)
    return mat.reshape(3, 3)[:, 2]


def segment_poses(x: float, y: float, yaw: float, joint_positions: np.ndarray) -> SegmentPoses:
    """Poses of the torso and every segment of a swimmer whose torso frame is at (x, y, yaw) and whose
    hinges stand at ``joint_positions`` (torso to tail; its length is the chain's)."""
    q = np.asarray(joint_positions, dtype=np.float64)
    chain = _chain(check_num_joints(q.shape[0]))
    headings = yaw + np.concatenate([[0.0], np.cumsum(q)])
    turn = np.exp(1j * headings)
    # body k's origin = body k-1's origin + R(heading_{k-1}) offset_k
    origins = (x + 1j * y) + np.cumsum(np.concatenate([[0.0], turn[:-1]]) * chain.body_offsets)
    centers = origins + turn * chain.geom_offsets
    return SegmentPoses(np.stack([centers.real, centers.imag], axis=1), headings, chain.lengths, chain.radii)
