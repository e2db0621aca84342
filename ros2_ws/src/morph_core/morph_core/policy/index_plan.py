"""The index plan of a batch of kinematic trees: which link sends and which receives across each joint.

A robot is a tree: links are graph nodes (link 0 is the torso, the root body), actuated joints are
edges. Per sample the joints are in topological order and ``parents[j]`` is joint j's parent joint
(< j), or -1 when joint j hangs off the torso; joint j joins link ``parents[j] + 1`` (its parent link)
to link ``j + 1`` (its child link) and carries (angle, angular velocity). A chain of N joints is
parents = [-1, 0, 1, ..., N-2].

The samples of a batch are laid back to back (``chains.PackedChains``): sample b's links follow those
of the samples before it, and slot k of the sequence lies between links k and k + 1. Joint j of sample b
sits in the slot before its child link, so a slot either holds a joint, whose receiver (child link) is
the next link, or is a cut between two samples (no joint: zero state, no message). What a tree adds to
a chain is only the sender: a chain's joint in slot k is sent across from link k, a tree's from its
parent link, anywhere before it in the sample. Messages to a child are therefore one shifted add in
every executor, messages to a parent a scatter-add over ``sender`` (several children share a parent);
a batch of chains (``sender`` None) keeps the two shifted adds.

NumPy only, no torch: read by the torch policy (``chains``), the NumPy actor (``numpy_actor``) and,
for one tree, the ONNX graph (``onnx_export``, which computes the same ``parents + 1`` in the graph).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


def chain_parents(num_joints: int) -> np.ndarray:
    """[N] int64 parents of a chain of N joints: [-1, 0, 1, ..., N-2]."""
    return np.arange(num_joints, dtype=np.int64) - 1


def joint_depths(parents) -> np.ndarray:
    """[N] int64 each joint's number of joint ancestors (0: hangs off the torso; a chain's joint j: j)."""
    depth = np.zeros(len(parents), dtype=np.int64)
    for j, p in enumerate(parents):
        depth[j] = 0 if p < 0 else depth[p] + 1
    return depth


def check_parents(parents, mask: np.ndarray) -> np.ndarray:
    """``parents`` as int64 [B, J] (or [N] for one tree, ``mask`` [N]), checked: every joint's parent must
    be in -1..j-1 (joints in topological order); entries where ``mask`` is False (padding) are ignored and
    set to -1. Raises ValueError naming the first bad sample and joint."""
    p = np.asarray(parents)
    if p.shape != mask.shape:
        raise ValueError(f"parents must have the joints' shape {list(mask.shape)}, got {list(p.shape)}")
    if p.size and not np.issubdtype(p.dtype, np.integer):
        raise ValueError(f"parents must be integers (joint indices, -1 for the torso), got dtype {p.dtype}")
    p = np.where(mask, p, -1).astype(np.int64)
    j = np.arange(p.shape[-1])
    bad = (p < -1) | (p >= j)
    if bad.any():
        at = np.argwhere(bad)[0]
        where = f"joint {at[-1]}" + (f" of sample {at[0]}" if p.ndim == 2 else "")
        raise ValueError(
            f"parents[{', '.join(map(str, at))}] = {int(p[tuple(at)])}: the parent of {where} must be -1 "
            f"(the torso) or an earlier joint (0..{at[-1] - 1}); joints go in topological order"
        )
    return p


def is_chain(parents: np.ndarray, mask: np.ndarray) -> bool:
    """True when every sample's joints (``mask``) form a chain: parents[j] = j - 1."""
    return bool(np.all((parents == np.arange(parents.shape[-1]) - 1) | ~mask))


class IndexPlan(NamedTuple):
    """B samples laid back to back: L = V + B links, L - 1 slots, V joints (in the padded batch's row-major
    order, the packed order of every executor)."""

    joint_padded: np.ndarray
    """[V] each joint's flat index in the padded [B * J] layout"""
    joint_sample: np.ndarray
    """[V] the sample (batch row) of each joint"""
    joint_slot: np.ndarray
    """[V] the slot holding each joint; its receiver, the child link, is ``joint_slot + 1``"""
    slot_sender: np.ndarray | None
    """[L - 1] the link sending across each slot torso-to-tail (the parent link of its joint; a cut's own
    index, its message being zero); None when every sample is a chain (slot k's sender is link k)"""

    @classmethod
    def of(cls, mask: np.ndarray, parents: np.ndarray | None = None) -> IndexPlan:
        """The plan of samples whose joints are ``mask`` [B, J] (a prefix of each row) with ``parents``
        [B, J] (checked by ``check_parents``; None: chains)."""
        b, j = mask.shape
        joint_padded = np.flatnonzero(mask)
        joint_sample = joint_padded // j if j else joint_padded
        joint_slot = np.arange(joint_padded.size) + joint_sample  # each earlier sample adds one cut
        sender = None
        if parents is not None:
            num_slots = max(joint_padded.size + b - 1, 0)
            sender = np.arange(num_slots, dtype=np.int64)
            # Parent link = the sample's torso link (joint_slot - j) + parents + 1.
            column = joint_padded - joint_sample * j
            sender[joint_slot] = joint_slot - column + parents.reshape(-1)[joint_padded] + 1
        return cls(joint_padded, joint_sample, joint_slot, sender)
