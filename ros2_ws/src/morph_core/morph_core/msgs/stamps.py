"""Stamps on the wire: nanoseconds <-> (sec, nanosec), and the answer tag an effort message carries.

A controller says which state its efforts answer by labelling
``layout.dim[0]`` of the ``Float64MultiArray`` ``joints@<sec>.<nanosec>``
with that state's stamp (nanoseconds as 9 digits). A lockstep sim drops
answers to states it re-sent; a trainer pairs each effort with its state.
A controller's fail-safe efforts, sent because no state came in time, are
labelled ``SILENCE_TAG`` instead: they answer no state, so a lockstep sim
must not step on them (an untagged message it would take as the answer).
"""

from __future__ import annotations

import re

NS_PER_S = 1_000_000_000
_TAG_PREFIX = "joints@"
_TAG = re.compile(r"joints@(\d+)\.(\d{9})")


def to_ns(sec: int, nanosec: int) -> int:
    return sec * NS_PER_S + nanosec


def from_ns(ns: int) -> tuple[int, int]:
    """(sec, nanosec) of a non-negative stamp in nanoseconds."""
    return ns // NS_PER_S, ns % NS_PER_S


def seconds_to_ns(seconds: float) -> int:
    """A sim time in seconds as integer nanoseconds (rounded, so 0.04 * k lands on whole ns)."""
    return int(round(seconds * 1e9))


SILENCE_TAG = "silence"
"""label of ``layout.dim[0]`` on efforts sent because no state arrived in time (they answer none)"""


def answer_tag(sec: int, nanosec: int) -> str:
    """Label of ``layout.dim[0]`` naming the state (by its stamp) that efforts answer."""
    return f"joints@{sec}.{nanosec:09d}"


class StampError(ValueError):
    """A stamp or an answer tag that cannot be a state's; ``str(err)`` is the reason."""


def parse_answer_tag(label: str, strict: bool = False) -> int | None:
    """The answered state's stamp in ns, or None when ``label`` is not an answer tag.

    ``strict``: a label that starts like one (``joints@``) but does not parse raises ``StampError``: it
    was meant to name a state and names none, so it must not be taken for an untagged answer."""
    m = _TAG.fullmatch(label)
    if m is None:
        if strict and label.startswith(_TAG_PREFIX):
            raise StampError(f"answer tag {label[:60]!r} does not parse (expected joints@<sec>.<9-digit nanosec>)")
        return None
    return to_ns(int(m.group(1)), int(m.group(2)))


def check_stamp(sec: int, nanosec: int) -> int:
    """A message stamp as ns; raises ``StampError`` for a negative time or nanosec >= 10**9 (not a time)."""
    if sec < 0 or not 0 <= nanosec < NS_PER_S:
        raise StampError(f"stamp {sec}.{nanosec} is not a time (sec >= 0, 0 <= nanosec < 10**9)")
    return to_ns(sec, nanosec)
