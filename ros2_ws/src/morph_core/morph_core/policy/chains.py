"""The joint graph of a swimmer chain, batched over chains of different lengths.

Links are nodes (link 0 is the torso), joints are edges: joint j connects
link j (parent) and link j+1 (child) and carries the joint state
(angle, angular velocity) as its edge attribute. A batch of chains is held
padded to its longest chain, ``J`` joints, with a validity mask; nothing
per-graph is built in Python.

The network itself runs on ``ChainBatch.packed``: the chains laid end to end
as one long chain, cut between consecutive chains (PyG's disjoint union of
graphs, in chain order). Padding costs nothing there, which on the 2..10-joint
training mix is about 40% of the padded work.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

NUM_GLOBAL_FEATURES = 4  # yaw, yaw rate, vx, vy of the torso frame
NUM_EDGE_FEATURES = 2  # joint angle, joint angular velocity


@dataclass(frozen=True)
class ChainBatch:
    """B chains padded to J joints.

    joint_pos, joint_vel: [B, J] float32, zero beyond each chain's end.
    global_feats: [B, 4] float32.
    num_joints: [B] int64.
    mask: [B, J] bool, True where the joint exists.
    """

    joint_pos: torch.Tensor
    joint_vel: torch.Tensor
    global_feats: torch.Tensor
    num_joints: torch.Tensor
    mask: torch.Tensor
    packed: PackedChains = field(init=False, repr=False, compare=False)
    """the batch as one cut chain, which the network runs on (no gradients flow through it)"""

    def __post_init__(self):
        # Built here, outside any compiled region: its sizes depend on the data.
        object.__setattr__(self, "packed", PackedChains.from_mask(self.joint_pos, self.joint_vel, self.mask))

    @property
    def batch_size(self) -> int:
        return self.joint_pos.shape[0]

    @property
    def max_joints(self) -> int:
        return self.joint_pos.shape[1]

    @classmethod
    def from_padded(cls, joint_pos, joint_vel, global_feats, num_joints, trim: bool = True) -> ChainBatch:
        """Build from padded arrays or tensors; ``trim`` drops padding beyond the longest chain."""
        pos = torch.as_tensor(joint_pos, dtype=torch.float32)
        vel = torch.as_tensor(joint_vel, dtype=torch.float32)
        glob = torch.as_tensor(global_feats, dtype=torch.float32)
        n = torch.as_tensor(num_joints, dtype=torch.int64)
        if pos.ndim != 2 or vel.shape != pos.shape:
            raise ValueError(f"joint_pos/joint_vel must both be [B, J], got {tuple(pos.shape)}, {tuple(vel.shape)}")
        if glob.shape != (pos.shape[0], NUM_GLOBAL_FEATURES) or n.shape != (pos.shape[0],):
            raise ValueError(
                f"global_feats must be [B, {NUM_GLOBAL_FEATURES}] and num_joints [B] for B={pos.shape[0]}, "
                f"got {tuple(glob.shape)}, {tuple(n.shape)}"
            )
        counts = n.numpy()  # checks and mask in NumPy: a fraction of torch's per-operation cost
        if counts.size and (counts.min() < 1 or counts.max() > pos.shape[1]):
            raise ValueError(f"num_joints must be in 1..{pos.shape[1]}, got {counts.tolist()}")
        if trim and counts.size:
            j = int(counts.max())
            pos, vel = pos[:, :j], vel[:, :j]
        mask = _joint_mask(counts, pos.shape[1])
        # Zero the padding so nothing beyond a chain's end can leak into sums.
        pos, vel = (torch.from_numpy(x.detach().numpy() * mask) for x in (pos, vel))
        return cls(pos, vel, glob, n, torch.from_numpy(mask))

    @classmethod
    def from_zero_padded(cls, joint_pos, joint_vel, global_feats, num_joints) -> ChainBatch:
        """Build from NumPy arrays as ``from_padded`` leaves them (float32 and int64, trimmed to the longest
        chain, zero beyond each chain's end), without its checks and copies: for batches whose padding this
        code wrote itself (a rollout's minibatches, gathered before every update step)."""
        mask = _joint_mask(num_joints, joint_pos.shape[1])
        return cls(*(torch.from_numpy(x) for x in (joint_pos, joint_vel, global_feats, num_joints, mask)))

    @classmethod
    def from_observations(cls, observations: Sequence[dict]) -> ChainBatch:
        """Batch graph-mode observations of ``MorphSwimmer-v0`` (dicts with joint_pos, joint_vel, global)."""
        return cls.from_padded(*pad_observations(observations))

    def select(self, index: torch.Tensor) -> ChainBatch:
        """The sub-batch at ``index`` (e.g. a minibatch), trimmed to its own longest chain."""
        return ChainBatch.from_padded(
            self.joint_pos[index], self.joint_vel[index], self.global_feats[index], self.num_joints[index]
        )


def _joint_mask(num_joints: np.ndarray, width: int) -> np.ndarray:
    """[B, width] True where chain b has a joint j (j < num_joints[b])."""
    return np.arange(width) < num_joints[:, None]


def pad_observations(
    observations: Sequence[dict], width: int | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Graph-mode observations as float32 arrays zero-padded to ``width`` joints (default: the longest).

    Returns joint_pos [B, width], joint_vel [B, width], global_feats [B, 4], num_joints [B].
    """
    n = np.array([len(o["joint_pos"]) for o in observations], dtype=np.int64)
    width = width if width is not None else int(n.max()) if len(n) else 0
    pos, vel = np.zeros((len(n), width), np.float32), np.zeros((len(n), width), np.float32)
    for i, o in enumerate(observations):
        pos[i, : n[i]], vel[i, : n[i]] = o["joint_pos"], o["joint_vel"]
    glob = np.array([o["global"] for o in observations], dtype=np.float32).reshape(len(n), NUM_GLOBAL_FEATURES)
    return pos, vel, glob, n


@dataclass(frozen=True)
class PackedChains:
    """B chains back to back: L = V + B links in one sequence, V = total joint count.

    Slot k sits between links k and k+1. It holds a joint when both links belong
    to one chain, and a cut (no joint: zero state, no message) where one chain
    ends and the next begins. Joint j of chain b is slot j + b + (joints of the
    chains before b), its parent link that slot's index, its child link the next.

    edge_attr: [L-1, 2] joint states per slot, zero at cuts.
    slot_mask: [L-1] bool, True where the slot holds a joint.
    joint_link: [V] the link behind each joint (its child), in the padded batch's row-major order.
    joint_chain: [V] chain (batch row) of each joint.
    joint_padded: [V] each joint's flat index in the padded [B * J] layout.
    """

    edge_attr: torch.Tensor
    slot_mask: torch.Tensor
    joint_link: torch.Tensor
    joint_chain: torch.Tensor
    joint_padded: torch.Tensor

    @classmethod
    def from_mask(cls, joint_pos: torch.Tensor, joint_vel: torch.Tensor, mask: torch.Tensor) -> PackedChains:
        # In NumPy: a dozen index operations on a few thousand numbers, each ~10x cheaper than torch's
        # (built once per minibatch step, outside the compiled region); the same values.
        b, j = mask.shape
        joint_padded = np.flatnonzero(mask.numpy())
        joint_chain = joint_padded // j if j else joint_padded
        joint_slot = np.arange(joint_padded.size) + joint_chain  # each earlier chain adds one cut
        num_links = joint_padded.size + b
        num_slots = max(num_links - 1, 0)
        pos, vel = joint_pos.detach().numpy(), joint_vel.detach().numpy()
        edge_attr = np.zeros((num_slots, NUM_EDGE_FEATURES), pos.dtype)
        edge_attr[joint_slot, 0] = pos.reshape(-1)[joint_padded]
        edge_attr[joint_slot, 1] = vel.reshape(-1)[joint_padded]
        slot_mask = np.zeros(num_slots, dtype=bool)
        slot_mask[joint_slot] = True
        t = torch.from_numpy
        return cls(t(edge_attr), t(slot_mask), t(joint_slot + 1), t(joint_chain), t(joint_padded))

    @property
    def num_links(self) -> int:
        """L: one more than the slots between them (none in an empty batch). Read off a tensor's size, so
        that a compiled graph takes it as a size, not as a constant (``algo.compiled``)."""
        slots = self.edge_attr.shape[0]
        return slots + 1 if slots else 0
