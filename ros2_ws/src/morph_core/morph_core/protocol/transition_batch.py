"""Transitions as flat per-step arrays: the layout ``morph-bag export`` writes and a trainer reads.

One row per transition, in stream order; chains of different lengths are
zero-padded to the longest one (``num_joints`` says how many entries of a row
are real). Rows of one ``episode`` are consecutive control periods of one
swimmer; the last row of every episode is ``terminated`` or ``truncated``,
and ``next_*`` always hold the observation after the step (what a truncated
step is bootstrapped on: ``reward + gamma * V(next)``, as the simulator
trainer does).

Keys of the ``.npz`` (T rows, J = longest chain, 0 if T = 0):

    episode          int64   [T]     run of consecutive transitions (0, 1, ... in stream order)
    stamp_ns         int64   [T]     the state's stamp
    num_joints       int64   [T]
    joint_pos        float64 [T, J]  joint angles, torso to tail
    joint_vel        float64 [T, J]
    global           float64 [T, 4]  yaw (unwrapped), yaw rate, vx, vy (world frame), as the policy sees them
    action           float64 [T, J]  the sampled action (policy_info), else the effort command
    log_prob         float64 [T]     behaviour log-prob of the action; NaN without policy_info
    reward           float64 [T]     Swimmer-v5's reward over the control period
    terminated       bool    [T]
    truncated        bool    [T]
    has_policy_info  bool    [T]     False: no behaviour log-prob, the step cannot enter a PPO ratio
    next_joint_pos   float64 [T, J]  observation at the next state
    next_joint_vel   float64 [T, J]
    next_global      float64 [T, 4]
"""

from __future__ import annotations

import io
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from morph_core.policy.chains import NUM_GLOBAL_FEATURES
from morph_core.util.atomic import atomic_write_bytes

# npz key -> (dataclass field, dtype, per-row shape: "J" = padded joints)
_LAYOUT: dict[str, tuple[str, type, tuple]] = {
    "episode": ("episode", np.int64, ()),
    "stamp_ns": ("stamp_ns", np.int64, ()),
    "num_joints": ("num_joints", np.int64, ()),
    "joint_pos": ("joint_pos", np.float64, ("J",)),
    "joint_vel": ("joint_vel", np.float64, ("J",)),
    "global": ("global_feats", np.float64, (NUM_GLOBAL_FEATURES,)),
    "action": ("action", np.float64, ("J",)),
    "log_prob": ("log_prob", np.float64, ()),
    "reward": ("reward", np.float64, ()),
    "terminated": ("terminated", np.bool_, ()),
    "truncated": ("truncated", np.bool_, ()),
    "has_policy_info": ("has_policy_info", np.bool_, ()),
    "next_joint_pos": ("next_joint_pos", np.float64, ("J",)),
    "next_joint_vel": ("next_joint_vel", np.float64, ("J",)),
    "next_global": ("next_global", np.float64, (NUM_GLOBAL_FEATURES,)),
}
EXPORT_KEYS = tuple(_LAYOUT)
"""every key of an exported ``.npz``, in the order written"""


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

    def __post_init__(self):
        _check(self.arrays())

    # -- building ---------------------------------------------------------------
    @classmethod
    def empty(cls) -> TransitionBatch:
        return cls.from_arrays({k: np.zeros((0, *_row_shape(s, 0)), dtype=d) for k, (_, d, s) in _LAYOUT.items()})

    @classmethod
    def from_transitions(cls, transitions: Sequence) -> TransitionBatch:
        """Pad a sequence of ``protocol.transitions.Transition`` into one batch (episode ids kept)."""
        if not transitions:
            return cls.empty()
        t_count = len(transitions)
        width = max(len(t.joint_pos) for t in transitions)
        out = {k: np.zeros((t_count, *_row_shape(s, width)), dtype=d) for k, (_, d, s) in _LAYOUT.items()}
        for i, t in enumerate(transitions):
            n = len(t.joint_pos)
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
        """From a dict with exactly the layout's keys (raises ``TransitionBatchError`` otherwise)."""
        missing = [k for k in EXPORT_KEYS if k not in arrays]
        extra = sorted(set(arrays) - set(EXPORT_KEYS))
        if missing or extra:
            raise TransitionBatchError(f"not a transition batch: missing keys {missing}, unknown keys {extra}")
        return cls(**{field: np.asarray(arrays[k]) for k, (field, _, _) in _LAYOUT.items()})

    @classmethod
    def concatenate(cls, batches: Sequence[TransitionBatch]) -> TransitionBatch:
        """One batch from several (e.g. one per bag): episode ids renumbered so none are shared."""
        batches = [b for b in batches if len(b)]
        if not batches:
            return cls.empty()
        width = max(b.max_joints for b in batches)
        out: dict[str, list[np.ndarray]] = {k: [] for k in EXPORT_KEYS}
        offset = 0
        for b in batches:
            arrays = b.arrays()
            for k, (_, _, shape) in _LAYOUT.items():
                a = arrays[k]
                if "J" in shape:
                    a = np.pad(a, ((0, 0), (0, width - a.shape[1])))
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
    def num_episodes(self) -> int:
        return len(np.unique(self.episode))

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
        """Read a file written by ``to_npz``; raises ``TransitionBatchError`` if it is not one."""
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {k: data[k] for k in data.files}
        except (zipfile.BadZipFile, ValueError, EOFError) as err:
            raise TransitionBatchError(f"{path}: not an .npz of arrays ({err})") from err
        return cls.from_arrays(arrays)


def _row_shape(shape: tuple, width: int) -> tuple[int, ...]:
    return tuple(width if s == "J" else s for s in shape)


def _check(arrays: dict[str, np.ndarray]) -> None:
    t_count = len(arrays["episode"]) if arrays["episode"].ndim == 1 else -1
    width = arrays["joint_pos"].shape[1] if arrays["joint_pos"].ndim == 2 else -1
    for k, (_, dtype, shape) in _LAYOUT.items():
        a = arrays[k]
        want = (t_count, *_row_shape(shape, width))
        if a.dtype != dtype or a.shape != want:
            raise TransitionBatchError(f"{k}: expected {np.dtype(dtype)} {want}, got {a.dtype} {a.shape}")
    n = arrays["num_joints"]
    if t_count and (n.min() < 1 or n.max() > width):
        raise TransitionBatchError(f"num_joints must be in 1..{width} (the padded width), got {n.min()}..{n.max()}")
