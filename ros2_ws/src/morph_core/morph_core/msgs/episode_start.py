"""The episode announcement on the wire: which state begins an episode, as plain integers.

A simulator that resets announces each new episode on ``episode_start``, a
``std_msgs/Int64MultiArray`` (a standard type every recorder and tool knows):

    layout.dim[0]   label "episode,stamp_ns,num_joints,cause", size 4, stride 4
    data            [episode, stamp_ns, num_joints, cause]

- ``episode``: 0 for the simulator's first episode, +1 at every reset;
- ``stamp_ns``: the stamp of the episode's first ``joint_states``
  (``sec * 10**9 + nanosec``), so a recording is split at that state;
- ``num_joints``: the episode's chain length;
- ``cause``: why it began (``EpisodeCause``), which says how the previous
  episode ended.

The label names the fields, so a reader finds them by name and later fields
can be appended. Nodes only copy these integers into and out of the message.
"""

from __future__ import annotations

import enum
from collections.abc import Sequence

from morph_core.constants import MAX_JOINTS, MIN_JOINTS
from morph_core.msgs.records import EpisodeStartRecord

FIELDS = ("episode", "stamp_ns", "num_joints", "cause")
LABEL = ",".join(FIELDS)


class EpisodeCause(enum.IntEnum):
    """Why an episode began; its name (lower case) is ``EpisodeStartRecord.cause``."""

    START = 0
    """the simulator started"""
    STEPS = 1
    """the previous episode ran its ``episode_steps`` (a time limit: truncated)"""
    RESET = 2
    """someone asked for a reset (the reset service)"""
    REBUILD = 3
    """the chain was rebuilt (``num_joints`` set)"""
    DIVERGED = 4
    """the previous episode's physics diverged; its last step's state was never published"""
    FELL = 5
    """the previous episode's body fell (a legged body's health rule, Ant-v5's: the env's ``terminated``); its
    last state, the fallen one, was published: the step into it is the episode's last, terminated"""


class EpisodeStartError(ValueError):
    """An announcement whose fields do not fit the layout; ``str(err)`` is the reason."""


def pack_episode_start(episode: int, stamp_ns: int, num_joints: int, cause: EpisodeCause) -> tuple[str, list[int]]:
    """(label of ``layout.dim[0]``, ``data``) of one announcement."""
    return LABEL, [int(episode), int(stamp_ns), int(num_joints), int(cause)]


def unpack_episode_start(log_ns: int, label: str, data: Sequence[int]) -> EpisodeStartRecord:
    """A record from the message's label and data; raises ``EpisodeStartError`` when they do not fit.

    ``episode`` and ``stamp_ns`` are required; ``num_joints`` and ``cause`` are taken when present.
    """
    names = label.split(",")
    if len(names) != len(data) or len(set(names)) != len(names):
        raise EpisodeStartError(f"label {label!r} names {len(names)} fields but data has {len(data)}")
    values = {name: int(v) for name, v in zip(names, data, strict=True)}
    if "episode" not in values or "stamp_ns" not in values:
        raise EpisodeStartError(f"label {label!r} lacks episode or stamp_ns")
    if values["episode"] < 0 or values["stamp_ns"] < 0:
        raise EpisodeStartError(f"negative episode or stamp: {values}")
    num_joints = values.get("num_joints")
    if num_joints is not None and not MIN_JOINTS <= num_joints <= MAX_JOINTS:
        raise EpisodeStartError(f"num_joints {num_joints} outside {MIN_JOINTS}..{MAX_JOINTS}")
    cause = values.get("cause")
    if cause is not None:
        try:
            cause = EpisodeCause(cause).name.lower()
        except ValueError:
            raise EpisodeStartError(f"unknown cause {cause}") from None
    return EpisodeStartRecord(log_ns, values["stamp_ns"], values["episode"], num_joints, cause)
