"""Where the swimmer's segments are, from the torso's planar pose and the joint angles.

The swimmer is planar (every hinge turns about z), so each segment's pose is a
running sum down its branch: heading_k = heading_parent + rest_k + q_k (rest_k,
the rest angle of a tree's side branch, 0 along a chain), and each body's
origin is its parent's plus the parent-frame offset turned by the parent's
heading. The offsets and rest angles are read off the compiled model, so this
is MuJoCo's own forward kinematics for this body (tested equal to
``mj_kinematics`` for chains and trees), without touching the simulation's
``MjData``: a publisher can place the segments of a state it has already
reported.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import mujoco
import numpy as np

from morph_core.env.model import body_parents, swimmer_model


@dataclass(frozen=True)
class SegmentPoses:
    """Capsule centres [N+1, 2] (world x, y), headings [N+1] (rad; the capsule's axis is the heading's
    direction), straight lengths [N+1] and radii [N+1]; index 0 is the torso, index j + 1 joint j's segment."""

    centers: np.ndarray
    headings: np.ndarray
    lengths: np.ndarray
    radii: np.ndarray


@dataclass(frozen=True)
class _Layout:
    ancestors: np.ndarray  # [N+1, N+1] 1 where column i is row k's body or one of its ancestors (torso: 0)
    parent_of: np.ndarray  # [N+1] each body's parent body (the torso: itself; its offset is 0)
    rest: np.ndarray  # [N+1] each body's rest angle about z in its parent's frame (rad)
    body_offsets: np.ndarray  # [N+1] complex: each body's origin in its parent's frame (torso: 0)
    geom_offsets: np.ndarray  # [N+1] complex: each capsule's centre in its body's frame
    lengths: np.ndarray
    radii: np.ndarray


@lru_cache(maxsize=256)
def _layout(parents: tuple[int, ...]) -> _Layout:
    m = swimmer_model(parents)
    n = len(parents)
    bodies = np.arange(1, m.nbody)  # the torso, then joint j's segment at j + 2 (pre-order)
    parent_of = np.array([0] + [p + 1 for p in parents])
    if not np.array_equal(m.body_parentid[bodies[1:]] - 1, parent_of[1:]):
        raise ValueError("the swimmer model's bodies do not follow its parent array")
    geoms = np.array([np.flatnonzero(m.geom_bodyid == b)[0] for b in bodies])
    # A capsule's axis is its local z; here it must lie along its body's x (the segment's direction).
    axes = np.array([_z_axis(m.geom_quat[g]) for g in geoms])
    if not np.allclose(np.abs(axes[:, 0]), 1.0):
        raise ValueError("a segment capsule does not lie along its body's x axis")
    quats = m.body_quat[bodies]
    if not np.allclose(quats[:, 1:3], 0.0):
        raise ValueError("a segment is turned about an axis other than z")
    rest = 2 * np.arctan2(quats[:, 3], quats[:, 0])
    rest[0] = 0.0  # the torso's own heading is the pose given
    offsets = m.body_pos[bodies, 0] + 1j * m.body_pos[bodies, 1]
    offsets[0] = 0  # the torso's own place is the pose given
    ancestors = np.zeros((n + 1, n + 1))
    for k in range(n + 1):
        ancestors[k, k] = 1.0
        if k:
            ancestors[k] += ancestors[parent_of[k]]
    ancestors[:, 0] = 1.0
    return _Layout(
        ancestors=ancestors,
        parent_of=parent_of,
        rest=rest,
        body_offsets=offsets,
        geom_offsets=m.geom_pos[geoms, 0] + 1j * m.geom_pos[geoms, 1],
        lengths=2 * m.geom_size[geoms, 1],
        radii=m.geom_size[geoms, 0].copy(),
    )


def _z_axis(quat: np.ndarray) -> np.ndarray:
    mat = np.empty(9)
    mujoco.mju_quat2Mat(mat, quat)
    return mat.reshape(3, 3)[:, 2]


def segment_poses(x: float, y: float, yaw: float, joint_positions: np.ndarray, parents=None) -> SegmentPoses:
    """Poses of the torso and every segment of a swimmer whose torso frame is at (x, y, yaw) and whose
    hinges stand at ``joint_positions`` (in the body's joint order). ``parents``: the body's parent array
    or ``KinematicTree`` (None: a chain as long as ``joint_positions``)."""
    q = np.asarray(joint_positions, dtype=np.float64)
    shape = body_parents(q.shape[0] if parents is None else parents)
    if len(shape) != q.shape[0]:
        raise ValueError(f"{q.shape[0]} joint positions for a body of {len(shape)} joints")
    layout = _layout(shape)
    headings = yaw + layout.ancestors @ (layout.rest + np.concatenate([[0.0], q]))
    turn = np.exp(1j * headings)
    # body k's origin = its parent's origin + R(heading of its parent) offset_k, summed down the branch
    origins = (x + 1j * y) + layout.ancestors @ (turn[layout.parent_of] * layout.body_offsets)
    centers = origins + turn * layout.geom_offsets
    return SegmentPoses(np.stack([centers.real, centers.imag], axis=1), headings, layout.lengths, layout.radii)
