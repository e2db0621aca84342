"""What a node received on each input, and what it rejected or ignored and why: counts a test or an operator reads.

A node counts every message it takes off an input (``received``), every one
it refused as malformed (``rejected``, by reason) and every well-formed one it
did not act on (``ignored``: an answer to a state it re-sent, weights not newer
than those running). The nodes publish these counts on ``/diagnostics``
(``morph_ros_util.diagnostics``) as ``diagnostic_msgs/KeyValue`` pairs; the
keys are ``to_key_values``'s and ``from_key_values`` reads them back, so a
test or a monitoring tool needs no knowledge of the node's internals.

Reasons are short fixed words chosen by the node (``"joint_state"``,
``"stamp"``, ``"layout"``...), never the error text, so the number of keys
stays bounded however varied the malformed traffic; the latest error text of
each input is kept (cut to ``MAX_REASON_CHARS``) for a human.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

MAX_REASON_CHARS = 200
"""the latest rejection's text is cut to this (a 1 MB joint name must not travel on in every report)"""


@dataclass
class InputCount:
    """One input's counts."""

    received: int = 0
    rejected: Counter[str] = field(default_factory=Counter)
    """rejections by reason"""
    ignored: Counter[str] = field(default_factory=Counter)
    """well-formed messages not acted on, by reason"""
    last_rejection: str = ""

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())

    @property
    def ignored_total(self) -> int:
        return sum(self.ignored.values())


class InputCounts:
    """Counts per input of one node; the inputs are named up front so a report lists each, even at zero."""

    def __init__(self, inputs: list[str]):
        self.inputs: dict[str, InputCount] = {name: InputCount() for name in inputs}

    def received(self, name: str) -> None:
        self.inputs[name].received += 1

    def rejected(self, name: str, reason: str, detail: str = "") -> None:
        count = self.inputs[name]
        count.rejected[reason] += 1
        count.last_rejection = f"{reason}: {detail}"[:MAX_REASON_CHARS] if detail else reason

    def ignored(self, name: str, reason: str) -> None:
        self.inputs[name].ignored[reason] += 1

    @property
    def rejected_total(self) -> int:
        return sum(c.rejected_total for c in self.inputs.values())

    @property
    def received_total(self) -> int:
        return sum(c.received for c in self.inputs.values())

    def summary(self) -> str:
        return f"{self.received_total} received, {self.rejected_total} rejected"

    def to_key_values(self) -> list[tuple[str, str]]:
        """(key, value) pairs: ``<input>/received``, ``<input>/rejected``, ``<input>/ignored``,
        ``<input>/rejected/<reason>``, ``<input>/ignored/<reason>``, ``<input>/last_rejection``."""
        pairs: list[tuple[str, str]] = []
        for name, c in self.inputs.items():
            pairs += [(f"{name}/received", str(c.received)), (f"{name}/rejected", str(c.rejected_total)),
                      (f"{name}/ignored", str(c.ignored_total))]  # fmt: skip
            pairs += [(f"{name}/rejected/{r}", str(n)) for r, n in sorted(c.rejected.items())]
            pairs += [(f"{name}/ignored/{r}", str(n)) for r, n in sorted(c.ignored.items())]
            pairs.append((f"{name}/last_rejection", c.last_rejection))
        return pairs


def from_key_values(pairs) -> dict[str, InputCount]:
    """The counts in a report's (key, value) pairs (``to_key_values``; other keys are skipped)."""
    out: dict[str, InputCount] = {}
    for key, value in pairs:
        name, _, rest = key.partition("/")
        if not rest:
            continue
        count = out.setdefault(name, InputCount())
        kind, _, reason = rest.partition("/")
        if kind == "received" and not reason:
            count.received = int(value)
        elif kind in ("rejected", "ignored") and reason:
            getattr(count, kind)[reason] = int(value)
        elif kind == "last_rejection":
            count.last_rejection = value
    return out
