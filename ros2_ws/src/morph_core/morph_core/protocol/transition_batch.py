"""Transitions as flat per-step arrays: the layout ``morph-bag export`` writes and a trainer reads.

One row per transition, in stream order; robots with different numbers of
joints are zero-padded to the largest one (``num_joints`` says how many entries
of a row are real). Rows of one ``episode`` are consecutive control periods of
one robot, so they share ``num_joints`` and ``parents`` (checked); the last
row of every episode is ``terminated`` or ``truncated``, and ``next_*`` always
hold the observation after the step, of the same robot (what a truncated step
is bootstrapped on: ``reward + gamma * V(next)``, as the simulator trainer
does).

The robot's graph is ``parents`` (``policy.index_plan``): joints in
topological order, each row's parent joint of each joint, -1 when the joint
hangs off the torso and at padding; a chain of N joints is [-1, 0, ..., N-2].
From recorded topics it is the tree of the robot's ``robot_description``
(``protocol.transitions``), or without one a chain in the ``joint_states``
message's order. A file written before the key existed holds chains, and
reads as such. Parents that are
not int64 [T, J], not -1 at padding, a parent not earlier than its joint, or
two trees in one episode are refused (``TransitionBatchError``, naming the row
and, from ``from_npz``, the file).

Keys of the ``.npz`` (T rows, J = longest chain, 0 if T = 0):

    episode          int64   [T]     run of consecutive transitions (0, 1, ... in stream order)
    stamp_ns         int64   [T]     the state's stamp
    num_joints       int64   [T]
    joint_pos        float64 [T, J]  joint angles, in the robot's tree order (a chain's: torso to tail)
    joint_vel        float64 [T, J]
    global           float64 [T, G]  the global features as the policy sees them: G = 4, a swimmer's yaw
                                     (unwrapped), yaw rate, vx, vy (world frame); G = 12, a legged body's
                                     (``env.centipede.GLOBAL_FEATURES``); any G >= 1 is read, one per file
    action           float64 [T, J]  the sampled action (policy_info), else the effort command
    log_prob         float64 [T]     behaviour log-prob of the action; NaN without policy_info
    reward           float64 [T]     the task's reward over the control period (Swimmer-v5's, Ant-v5's)
    terminated       bool    [T]
    truncated        bool    [T]
    has_policy_info  bool    [T]     False: no behaviour log-prob, the step cannot enter a PPO ratio
    next_joint_pos   float64 [T, J]  observation at the next state
    next_joint_vel   float64 [T, J]
    next_global      float64 [T, G]
    parents          int64   [T, J]  parent joint of each joint (-1: the torso, and at padding); optional when
                                     read: without it every row is a chain
"""

from __future__ import annotations

import io
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from morph_core.constants import NUM_GLOBAL_FEATURES
from morph_core.env.bodies import body_label, swimmer_tree
from morph_core.policy.index_plan import chain_parents
from morph_core.util.atomic import atomic_write_bytes

# npz key -> (dataclass field, dtype, per-row shape: "J" = padded joints, "G" = the global features' width)
_LAYOUT: dict[str, tuple[str, type, tuple]] = {
    "episode": ("episode", np.int64, ()),
    "stamp_ns": ("stamp_ns", np.int64, ()),
    "num_joints": ("num_joints", np.int64, ()),
    "joint_pos": ("joint_pos", np.float64, ("J",)),
    "joint_vel": ("joint_vel", np.float64, ("J",)),
    "global": ("global_feats", np.float64, ("G",)),
    "action": ("action", np.float64, ("J",)),
    "log_prob": ("log_prob", np.float64, ()),
    "reward": ("reward", np.float64, ()),
    "terminated": ("terminated", np.bool_, ()),
    "truncated": ("truncated", np.bool_, ()),
    "has_policy_info": ("has_policy_info", np.bool_, ()),
    "next_joint_pos": ("next_joint_pos", np.float64, ("J",)),
    "next_joint_vel": ("next_joint_vel", np.float64, ("J",)),
    "next_global": ("next_global", np.float64, ("G",)),
    "parents": ("parents", np.int64, ("J",)),
}
EXPORT_KEYS = tuple(_LAYOUT)
"""every key of an exported ``.npz``, in the order written"""
OPTIONAL_KEYS = ("parents",)
"""keys a reader may find missing (files written before them): without ``parents`` every row is a chain"""
_PAD = {"parents": -1}
"""padding value of a [T, J] key other than 0"""


class TransitionBatchError(ValueError):
    """An array set that does not fit the layout; ``str(err)`` says what is wrong."""


class MissingPolicyInfoError(TransitionBatchError):
    """Steps without a behaviour log-prob where one is required (PPO)."""


@dataclass(frozen=True)
class TransitionBatch:
    """T transitions as padded arrays (see the module docstring for each field)."""

    episode: np.ndarray
    stamp_ns: np.ndarray
    num_joints: np.ndarray
    joint_pos: np.ndarray
    joint_vel: np.ndarray
    global_feats: np.ndarray
    """npz key ``global`` (a Python keyword, so not a field name)"""
    action: np.ndarray
    log_prob: np.ndarray
    reward: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    has_policy_info: np.ndarray
    next_joint_pos: np.ndarray
    next_joint_vel: np.ndarray
    next_global: np.ndarray
    parents: np.ndarray | None = None
    """[T, J] int64; None (as given) means every row is a chain, and becomes chain parents"""

    def __post_init__(self):
        if self.parents is None:
            object.__setattr__(self, "parents", _chain_rows(np.asarray(self.num_joints), _width(self.joint_pos)))
        _check(self.arrays())

    # -- building ---------------------------------------------------------------
    @classmethod
    def empty(cls, global_width: int = NUM_GLOBAL_FEATURES) -> TransitionBatch:
        return cls.from_arrays(cls._blank(0, 0, global_width))

    @classmethod
    def _blank(cls, t_count: int, width: int, global_width: int) -> dict[str, np.ndarray]:
        layout = _LAYOUT.items()
        return {
            k: np.full((t_count, *_row_shape(s, width, global_width)), _PAD.get(k, 0), dtype=d)
            for k, (_, d, s) in layout
        }

    @classmethod
    def from_transitions(cls, transitions: Sequence) -> TransitionBatch:
        """Pad a sequence of ``protocol.transitions.Transition`` into one batch (episode ids kept; a
        transition's ``parents`` None is a chain)."""
        if not transitions:
            return cls.empty()
        t_count = len(transitions)
        width = max(len(t.joint_pos) for t in transitions)
        out = cls._blank(t_count, width, len(transitions[0].global_feats))  # one width: checked by the assignment
        for i, t in enumerate(transitions):
            n = len(t.joint_pos)
            out["parents"][i, :n] = chain_parents(n) if t.parents is None else t.parents
            out["episode"][i] = t.episode
            out["stamp_ns"][i] = t.stamp_ns
            out["num_joints"][i] = n
            out["joint_pos"][i, :n] = t.joint_pos
            out["joint_vel"][i, :n] = t.joint_vel
            out["global"][i] = t.global_feats
            out["action"][i, :n] = t.action
            out["log_prob"][i] = t.log_prob
            out["reward"][i] = t.reward
            out["terminated"][i] = t.terminated
            out["truncated"][i] = t.truncated
            out["has_policy_info"][i] = t.has_policy_info
            out["next_joint_pos"][i, :n] = t.next_joint_pos
            out["next_joint_vel"][i, :n] = t.next_joint_vel
            out["next_global"][i] = t.next_global
        return cls.from_arrays(out)

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> TransitionBatch:
        """From a dict with exactly the layout's keys, those of ``OPTIONAL_KEYS`` optional (raises
        ``TransitionBatchError`` otherwise). Without ``parents`` every row is a chain."""
        missing = [k for k in EXPORT_KEYS if k not in arrays and k not in OPTIONAL_KEYS]
        extra = sorted(set(arrays) - set(EXPORT_KEYS))
        if missing or extra:
            raise TransitionBatchError(f"not a transition batch: missing keys {missing}, unknown keys {extra}")
        return cls(**{field: np.asarray(arrays[k]) for k, (field, _, _) in _LAYOUT.items() if k in arrays})

    @classmethod
    def concatenate(cls, batches: Sequence[TransitionBatch]) -> TransitionBatch:
        """One batch from several (e.g. one per bag): episode ids renumbered so none are shared."""
        batches = [b for b in batches if len(b)]
        if not batches:
            return cls.empty()
        widths = {b.global_width for b in batches}
        if len(widths) > 1:
            raise TransitionBatchError(f"batches of {' and '.join(map(str, sorted(widths)))} global features: one "
                                       "policy reads one width")  # fmt: skip
        width = max(b.max_joints for b in batches)
        out: dict[str, list[np.ndarray]] = {k: [] for k in EXPORT_KEYS}
        offset = 0
        for b in batches:
            arrays = b.arrays()
            for k, (_, _, shape) in _LAYOUT.items():
                a = arrays[k]
                if "J" in shape:
                    a = np.pad(a, ((0, 0), (0, width - a.shape[1])), constant_values=_PAD.get(k, 0))
                out[k].append(a)
            # Episode ids restart at 0 per batch in stream order: shift past the previous batch's.
            out["episode"][-1] = np.unique(arrays["episode"], return_inverse=True)[1].astype(np.int64) + offset
            offset = int(out["episode"][-1].max()) + 1
        return cls.from_arrays({k: np.concatenate(v) for k, v in out.items()})

    # -- reading ----------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.episode)

    @property
    def max_joints(self) -> int:
        return self.joint_pos.shape[1]

    @property
    def global_width(self) -> int:
        """The global features per row (4 a swimmer's, 12 a legged body's)."""
        return self.global_feats.shape[1]

    @property
    def is_chains(self) -> bool:
        """Whether every row is a chain (as every file written before ``parents`` existed)."""
        return bool(np.array_equal(self.parents, _chain_rows(self.num_joints, self.max_joints)))

    @property
    def num_episodes(self) -> int:
        return len(np.unique(self.episode))

    def body_labels(self) -> list[str]:
        """Each row's body as logs name it (``env.bodies.body_label`` of its tree: ``chain-N``, a named
        shape such as ``star-2x2``, else ``tree-`` and its topology hash)."""
        if not len(self):
            return []
        shapes, inverse = np.unique(np.c_[self.num_joints, self.parents], axis=0, return_inverse=True)
        labels = [body_label(swimmer_tree(row[1 : 1 + row[0]])) for row in shapes]
        return [labels[i] for i in inverse.reshape(-1)]

    def steps_per_body(self) -> dict[str, int]:
        """Rows per body label, in the order the bodies first appear."""
        out: dict[str, int] = {}
        for label in self.body_labels():
            out[label] = out.get(label, 0) + 1
        return out

    @property
    def ppo_ready(self) -> bool:
        """Whether every step carries its behaviour log-prob."""
        return bool(self.has_policy_info.all())

    def require_policy_info(self) -> None:
        """Raise ``MissingPolicyInfoError`` unless every step has its behaviour log-prob (PPO's old log-prob)."""
        missing = int((~self.has_policy_info).sum())
        if missing:
            raise MissingPolicyInfoError(
                f"{missing} of {len(self)} steps have no policy_info (no behaviour log-prob): PPO needs the "
                "policy to sample and publish policy_info (morph_policy deterministic:=false) while recording"
            )

    def arrays(self) -> dict[str, np.ndarray]:
        """The layout's key -> array."""
        return {k: getattr(self, field) for k, (field, _, _) in _LAYOUT.items()}

    # -- files ------------------------------------------------------------------
    def to_npz(self, path: str | Path) -> None:
        """Write an uncompressed ``.npz`` atomically (a reader sees the old file or the new one)."""
        buf = io.BytesIO()
        np.savez(buf, **self.arrays())
        atomic_write_bytes(path, buf.getvalue())

    @classmethod
    def from_npz(cls, path: str | Path) -> TransitionBatch:
        """Read a file written by ``to_npz`` (or before ``parents`` existed: chains); raises
        ``TransitionBatchError``, naming the file, if it is not one."""
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {k: data[k] for k in data.files}
        except (zipfile.BadZipFile, ValueError, EOFError, OSError) as err:
            raise TransitionBatchError(f"{path}: not an .npz of arrays ({err})") from err
        try:
            return cls.from_arrays(arrays)
        except TransitionBatchError as err:
            raise TransitionBatchError(f"{path}: {err}") from None


def _row_shape(shape: tuple, width: int, global_width: int) -> tuple[int, ...]:
    return tuple(width if s == "J" else global_width if s == "G" else s for s in shape)


def _width(joint_pos: np.ndarray) -> int:
    return joint_pos.shape[1] if joint_pos.ndim == 2 else 0


def _chain_rows(num_joints: np.ndarray, width: int) -> np.ndarray:
    """[T, width] int64 chain parents of rows of ``num_joints`` joints (-1 at padding)."""
    j = np.arange(width, dtype=np.int64)
    # num_joints not [T] integers: no rows here, and _check refuses num_joints itself (before parents)
    n = num_joints.reshape(-1, 1) if num_joints.ndim == 1 and num_joints.dtype.kind in "iu" else np.zeros((0, 1))
    return np.where(j < n, j - 1, -1).astype(np.int64)


def _check(arrays: dict[str, np.ndarray]) -> None:
    t_count = len(arrays["episode"]) if arrays["episode"].ndim == 1 else -1
    width = arrays["joint_pos"].shape[1] if arrays["joint_pos"].ndim == 2 else -1
    glob = arrays["global"]
    global_width = glob.shape[1] if glob.ndim == 2 and glob.shape[1] >= 1 else -1
    for k, (_, dtype, shape) in _LAYOUT.items():
        a = arrays[k]
        want = (t_count, *_row_shape(shape, width, global_width))
        if a.dtype != dtype or a.shape != want:
            raise TransitionBatchError(f"{k}: expected {np.dtype(dtype)} {want}, got {a.dtype} {a.shape}")
    n = arrays["num_joints"]
    if t_count and (n.min() < 1 or n.max() > width):
        raise TransitionBatchError(f"num_joints must be in 1..{width} (the padded width), got {n.min()}..{n.max()}")
    _check_parents(arrays["parents"], n, arrays["episode"])


def _check_parents(parents: np.ndarray, num_joints: np.ndarray, episode: np.ndarray) -> None:
    """Each row's parents a tree in topological order, -1 at padding, one tree per episode (shape and dtype
    are checked with the other keys)."""
    j = np.arange(parents.shape[1])
    real = j < num_joints[:, None]
    bad = real & ((parents < -1) | (parents >= j))
    if bad.any():
        row, joint = (int(x) for x in np.argwhere(bad)[0])
        raise TransitionBatchError(
            f"parents: row {row}, joint {joint} has parent {int(parents[row, joint])}: it must be -1 (the torso) "
            f"or an earlier joint (0..{joint - 1}); joints go in topological order"
        )
    bad = ~real & (parents != -1)
    if bad.any():
        row, joint = (int(x) for x in np.argwhere(bad)[0])
        raise TransitionBatchError(
            f"parents: row {row}, joint {joint} is padding (the row has {int(num_joints[row])} joints) but has "
            f"parent {int(parents[row, joint])}, not -1"
        )
    same = episode[1:] == episode[:-1]
    changed = same & ((num_joints[1:] != num_joints[:-1]) | (parents[1:] != parents[:-1]).any(axis=1))
    if changed.any():
        row = int(np.flatnonzero(changed)[0]) + 1
        raise TransitionBatchError(
            f"parents: row {row} continues episode {int(episode[row])} with another robot than row {row - 1} "
            f"({int(num_joints[row])} joints, parents {parents[row, : num_joints[row]].tolist()} after "
            f"{int(num_joints[row - 1])}, {parents[row - 1, : num_joints[row - 1]].tolist()}): an episode has one tree"
        )
