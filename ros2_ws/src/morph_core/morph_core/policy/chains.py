"""The joint graph of a robot, batched over chains (swimmers) and kinematic trees of different sizes.

Links are nodes (link 0 is the torso), joints are edges: joint j connects
link parents[j] + 1 (parent) and link j+1 (child) and carries the joint state
(angle, angular velocity) as its edge attribute; a chain's parents are
[-1, 0, ..., N-2], so its joint j connects links j and j+1 (``index_plan``
has the model of a tree). A batch is held padded to its largest sample,
``J`` joints, with a validity mask and, for trees, the parents; nothing
per-graph is built in Python.

The network itself runs on ``ChainBatch.packed``: the chains laid end to end
as one long chain, cut between consecutive chains (PyG's disjoint union of
graphs, in chain order). Padding costs nothing there, which on the 2..10-joint
training mix is about 40% of the padded work. Trees are laid out the same way;
only the link sending across each joint differs (``index_plan.IndexPlan``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from morph_core.constants import NUM_EDGE_FEATURES, NUM_GLOBAL_FEATURES
from morph_core.policy.index_plan import IndexPlan, chain_parents, check_parents, is_chain


@dataclass(frozen=True)
class ChainBatch:
    """B chains or trees padded to J joints.

    joint_pos, joint_vel: [B, J] float32, zero beyond each sample's last joint.
    global_feats: [B, G] float32 (G = 4 for swimmers; the policy checks it is its config's width).
    num_joints: [B] int64.
    mask: [B, J] bool, True where the joint exists.
    parents: [B, J] int64 parent joint of each joint (-1: the torso; -1 at padding), checked
        (``index_plan.check_parents``); None when every sample is a chain, however it was given, so that
        a batch of chains is one thing (and the network takes its chain path).
    joint_desc: [B, J, D] float32 each joint's description (``policy.joint_description``; zero at padding), for
        a policy that reads them (``PolicyConfig.joint_features`` = D); None: no descriptions (the edges carry
        the joint states alone, as before descriptions existed).
    """

    joint_pos: torch.Tensor
    joint_vel: torch.Tensor
    global_feats: torch.Tensor
    num_joints: torch.Tensor
    mask: torch.Tensor
    parents: torch.Tensor | None = None
    joint_desc: torch.Tensor | None = None
    packed: PackedChains = field(init=False, repr=False, compare=False)
    """the batch as one cut chain, which the network runs on (no gradients flow through it)"""

    def __post_init__(self):
        # Built here, outside any compiled region: its sizes depend on the data.
        packed = PackedChains.from_mask(self.joint_pos, self.joint_vel, self.mask, self.parents, self.joint_desc)
        object.__setattr__(self, "packed", packed)

    @property
    def batch_size(self) -> int:
        return self.joint_pos.shape[0]

    @property
    def max_joints(self) -> int:
        return self.joint_pos.shape[1]

    @classmethod
    def from_padded(
        cls, joint_pos, joint_vel, global_feats, num_joints, trim: bool = True, parents=None, joint_desc=None
    ) -> ChainBatch:
        """Build from padded arrays or tensors; ``trim`` drops padding beyond the longest chain. ``parents``
        [B, J] integers (padding ignored) makes the samples trees; None: chains. ``joint_desc`` [B, J, D] the
        joints' descriptions (padding ignored; finite), or None. ValueError if invalid."""
        pos = torch.as_tensor(joint_pos, dtype=torch.float32)
        vel = torch.as_tensor(joint_vel, dtype=torch.float32)
        glob = torch.as_tensor(global_feats, dtype=torch.float32)
        n = torch.as_tensor(num_joints, dtype=torch.int64)
        if pos.ndim != 2 or vel.shape != pos.shape:
            raise ValueError(f"joint_pos/joint_vel must both be [B, J], got {tuple(pos.shape)}, {tuple(vel.shape)}")
        if glob.ndim != 2 or glob.shape[0] != pos.shape[0] or glob.shape[1] < 1 or n.shape != (pos.shape[0],):
            raise ValueError(
                f"global_feats must be [B, G] (G >= 1, {NUM_GLOBAL_FEATURES} for swimmers) and num_joints [B] for "
                f"B={pos.shape[0]}, got {tuple(glob.shape)}, {tuple(n.shape)}"
            )
        counts = n.numpy()  # checks and mask in NumPy: a fraction of torch's per-operation cost
        if counts.size and (counts.min() < 1 or counts.max() > pos.shape[1]):
            raise ValueError(f"num_joints must be in 1..{pos.shape[1]}, got {counts.tolist()}")
        if trim and counts.size:
            j = int(counts.max())
            pos, vel = pos[:, :j], vel[:, :j]
        mask = _joint_mask(counts, pos.shape[1])
        tree = _tree_parents(parents, mask, width=joint_pos.shape[1])
        # Zero the padding so nothing beyond a chain's end can leak into sums.
        pos, vel = (torch.from_numpy(x.detach().numpy() * mask) for x in (pos, vel))
        desc = _descriptions(joint_desc, mask, width=joint_pos.shape[1])
        return cls(pos, vel, glob, n, torch.from_numpy(mask), tree, desc)

    @classmethod
    def from_zero_padded(
        cls, joint_pos, joint_vel, global_feats, num_joints, parents=None, joint_desc=None
    ) -> ChainBatch:
        """Build from NumPy arrays as ``from_padded`` leaves them (float32 and int64, trimmed to the longest
        chain, zero beyond each chain's end), without its checks and copies: for batches whose padding this
        code wrote itself (a rollout's minibatches, gathered before every update step). ``parents`` [B, J]
        (trees) is still checked: its cost is the trees' alone."""
        mask = _joint_mask(num_joints, joint_pos.shape[1])
        tree = _tree_parents(parents, mask, width=joint_pos.shape[1])
        desc = None if joint_desc is None else torch.from_numpy(joint_desc)  # [B, J, D], zero padded by its writer
        return cls(*(torch.from_numpy(x) for x in (joint_pos, joint_vel, global_feats, num_joints, mask)), tree, desc)

    @classmethod
    def from_observations(cls, observations: Sequence[dict]) -> ChainBatch:
        """Batch graph-mode observations of ``MorphSwimmer-v0`` (dicts with joint_pos, joint_vel, global, and
        for a tree "parents"; without it a chain; "joint_desc" [N, D] when every observation has one)."""
        *arrays, parents = pad_observations(observations, with_parents=True)
        return cls.from_padded(*arrays, parents=parents, joint_desc=pad_descriptions(observations, arrays[0].shape[1]))

    def select(self, index: torch.Tensor) -> ChainBatch:
        """The sub-batch at ``index`` (e.g. a minibatch), trimmed to its own longest chain."""
        parents = None if self.parents is None else self.parents[index]
        desc = None if self.joint_desc is None else self.joint_desc[index]
        return ChainBatch.from_padded(
            self.joint_pos[index], self.joint_vel[index], self.global_feats[index], self.num_joints[index],
            parents=parents, joint_desc=desc,
        )  # fmt: skip


def _joint_mask(num_joints: np.ndarray, width: int) -> np.ndarray:
    """[B, width] True where chain b has a joint j (j < num_joints[b])."""
    return np.arange(width) < num_joints[:, None]


def _tree_parents(parents, mask: np.ndarray, width: int) -> torch.Tensor | None:
    """``parents`` [B, width] checked and cut to ``mask``'s width, or None for chains (given or not)."""
    if parents is None:
        return None
    p = parents.detach().numpy() if isinstance(parents, torch.Tensor) else np.asarray(parents)
    if p.shape != (mask.shape[0], width):
        raise ValueError(f"parents must be [B, J] like joint_pos, {[mask.shape[0], width]}, got {list(p.shape)}")
    p = check_parents(p[:, : mask.shape[1]], mask)
    return None if is_chain(p, mask) else torch.from_numpy(p)


def _descriptions(joint_desc, mask: np.ndarray, width: int) -> torch.Tensor | None:
    """``joint_desc`` [B, width, D] as float32 cut to ``mask``'s width, zero at padding; None stays None."""
    if joint_desc is None:
        return None
    d = joint_desc.detach().numpy() if isinstance(joint_desc, torch.Tensor) else np.asarray(joint_desc)
    if d.ndim != 3 or d.shape[:2] != (mask.shape[0], width):
        raise ValueError(f"joint_desc must be [B, J, D] like joint_pos, {[mask.shape[0], width]}, got {list(d.shape)}")
    d = d[:, : mask.shape[1]].astype(np.float32) * mask[:, :, None]
    if not np.isfinite(d).all():
        raise ValueError("joint_desc holds NaN or inf")
    return torch.from_numpy(np.ascontiguousarray(d))


def pad_descriptions(observations: Sequence[dict], width: int) -> np.ndarray | None:
    """The observations' "joint_desc" ([N, D] each) as [B, width, D] float32, zero padded; None when none has one
    (ValueError when some have and some have not, or their widths differ)."""
    have = ["joint_desc" in o for o in observations]
    if not any(have):
        return None
    if not all(have):
        raise ValueError("some observations carry joint descriptions and some do not")
    widths = {np.shape(o["joint_desc"])[1] for o in observations}
    if len(widths) != 1:
        raise ValueError(f"observations' joint descriptions differ in width: {sorted(widths)}")
    out = np.zeros((len(observations), width, widths.pop()), np.float32)
    for i, o in enumerate(observations):
        out[i, : len(o["joint_desc"])] = o["joint_desc"]
    return out


def pad_observations(observations: Sequence[dict], width: int | None = None, with_parents: bool = False):
    """Graph-mode observations as float32 arrays zero-padded to ``width`` joints (default: the largest).

    Returns joint_pos [B, width], joint_vel [B, width], global_feats [B, G] (G the observations' one global
    width: 4 for swimmers; ValueError when they differ), num_joints [B], and with
    ``with_parents`` parents [B, width] int64 (an observation's "parents", a chain's without; -1 at
    padding) or None when no observation carries "parents".
    """
    n = np.array([len(o["joint_pos"]) for o in observations], dtype=np.int64)
    width = width if width is not None else int(n.max()) if len(n) else 0
    pos, vel = np.zeros((len(n), width), np.float32), np.zeros((len(n), width), np.float32)
    for i, o in enumerate(observations):
        pos[i, : n[i]], vel[i, : n[i]] = o["joint_pos"], o["joint_vel"]
    widths = {np.shape(o["global"]) for o in observations}
    if len(widths) > 1:
        raise ValueError(f"observations' global features differ in shape: {sorted(widths)}")
    g = widths.pop()[0] if widths else NUM_GLOBAL_FEATURES
    glob = np.array([o["global"] for o in observations], dtype=np.float32).reshape(len(n), g)
    if not with_parents:
        return pos, vel, glob, n
    if not any("parents" in o for o in observations):
        return pos, vel, glob, n, None
    parents = np.full((len(n), width), -1, np.int64)
    for i, o in enumerate(observations):
        p = np.asarray(o.get("parents", chain_parents(n[i])))
        if p.shape != (n[i],):
            raise ValueError(f"observation {i}: parents must be [{n[i]}] like its joint_pos, got {list(p.shape)}")
        parents[i, : n[i]] = p
    return pos, vel, glob, n, parents


def chain_batch(positions: np.ndarray, velocities: np.ndarray, global_feats: np.ndarray) -> ChainBatch:
    """A ``ChainBatch`` of one chain, joints in the given order (joint 0 next to the torso): a controller's one
    state (``msgs.joint_state``'s arrays) for the torch policy."""
    n = len(positions)
    glob = np.asarray(global_feats, dtype=np.float32).reshape(1, -1)  # the policy's width: 4, or 12 (legged)
    return ChainBatch.from_padded(
        np.asarray(positions, dtype=np.float32).reshape(1, n),
        np.asarray(velocities, dtype=np.float32).reshape(1, n),
        glob,
        np.array([n], dtype=np.int64),
    )


@dataclass(frozen=True)
class PackedChains:
    """B chains or trees back to back: L = V + B links in one sequence, V = total joint count.

    Slot k sits between links k and k+1. It holds a joint when both links belong
    to one sample, and a cut (no joint: zero state, no message) where one sample
    ends and the next begins. Joint j of sample b is slot j + b + (joints of the
    samples before b), its child link the next link; its parent link is that
    slot's index in a chain, ``sender[slot]`` in a tree (``index_plan``).

    edge_attr: [L-1, 2 + D] joint states per slot, then (with descriptions) the joint's description, zero at cuts.
    slot_mask: [L-1] bool, True where the slot holds a joint.
    joint_link: [V] the link behind each joint (its child), in the padded batch's row-major order.
    joint_chain: [V] sample (batch row) of each joint.
    joint_padded: [V] each joint's flat index in the padded [B * J] layout.
    sender: [L-1] int64 the parent link of each slot's joint (a cut's own index), or None when every
        sample is a chain (then the sender of slot k is link k, and the network takes shifted adds).
    """

    edge_attr: torch.Tensor
    slot_mask: torch.Tensor
    joint_link: torch.Tensor
    joint_chain: torch.Tensor
    joint_padded: torch.Tensor
    sender: torch.Tensor | None = None

    @classmethod
    def from_mask(
        cls,
        joint_pos: torch.Tensor,
        joint_vel: torch.Tensor,
        mask: torch.Tensor,
        parents: torch.Tensor | None = None,
        joint_desc: torch.Tensor | None = None,
    ) -> PackedChains:
        """The packed batch of samples ``mask`` [B, J] with ``parents`` [B, J] (checked; None: chains) and the
        joints' descriptions ``joint_desc`` [B, J, D] (None: none)."""
        # In NumPy: a dozen index operations on a few thousand numbers, each ~10x cheaper than torch's
        # (built once per minibatch step, outside the compiled region); the same values.
        b, _ = mask.shape
        plan = IndexPlan.of(mask.numpy(), None if parents is None else parents.numpy())
        joint_padded, joint_slot = plan.joint_padded, plan.joint_slot
        num_slots = max(joint_padded.size + b - 1, 0)
        pos, vel = joint_pos.detach().numpy(), joint_vel.detach().numpy()
        width = NUM_EDGE_FEATURES if joint_desc is None else NUM_EDGE_FEATURES + joint_desc.shape[2]
        edge_attr = np.zeros((num_slots, width), pos.dtype)
        edge_attr[joint_slot, 0] = pos.reshape(-1)[joint_padded]
        edge_attr[joint_slot, 1] = vel.reshape(-1)[joint_padded]
        if joint_desc is not None:
            desc = joint_desc.detach().numpy()
            edge_attr[joint_slot, NUM_EDGE_FEATURES:] = desc.reshape(-1, desc.shape[2])[joint_padded]
        slot_mask = np.zeros(num_slots, dtype=bool)
        slot_mask[joint_slot] = True
        t = torch.from_numpy
        sender = None if plan.slot_sender is None else t(plan.slot_sender)
        return cls(t(edge_attr), t(slot_mask), t(joint_slot + 1), t(plan.joint_sample), t(joint_padded), sender)

    @property
    def num_links(self) -> int:
        """L: one more than the slots between them (none in an empty batch). Read off a tensor's size, so
        that a compiled graph takes it as a size, not as a constant (``algo.compiled``)."""
        slots = self.edge_attr.shape[0]
        return slots + 1 if slots else 0
