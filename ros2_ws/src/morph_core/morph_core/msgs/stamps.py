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


def parse_answer_tag(label: str) -> int | None:
    """The answered state's stamp in ns, or None when ``label`` is not an answer tag."""
    m = _TAG.fullmatch(label)
    return None if m is None else to_ns(int(m.group(1)), int(m.group(2)))
