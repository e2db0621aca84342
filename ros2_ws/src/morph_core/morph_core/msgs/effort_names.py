"""Which joints an effort command covers: a ``layout.dim`` of the ``Float64MultiArray`` naming them.

``effort_commands`` carries one effort per joint. Its ``layout.dim[0]`` says
which state it answers (``msgs.stamps``); a further dimension labelled
``names=<JSON list>`` (size 1, stride 1: the efforts as an N x 1 array) says
which joints the N efforts are for, in the data's order. A reader maps
efforts to its joints by those names; a command without one is in the order
of the state it answers (the convention before names were sent, and that of
any controller that does not name them). JSON, so that any joint name
(printable ASCII, commas and quotes included) goes through unchanged.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from functools import lru_cache

NAMES_PREFIX = "names="


class EffortNamesError(ValueError):
    """A names dimension that does not parse, or does not fit the efforts; ``str(err)`` is the reason."""


@lru_cache(maxsize=64)
def names_label(names: tuple[str, ...]) -> str:
    """The label of the dimension naming ``names`` (cached: a node sends the same names every step)."""
    return NAMES_PREFIX + json.dumps(list(names), separators=(",", ":"))


def effort_names(labels: Sequence[str], count: int) -> tuple[str, ...] | None:
    """The joint names a command's layout gives for its ``count`` efforts, or None when it names none.

    Raises ``EffortNamesError`` for a names dimension that is not a JSON list of distinct strings, or that
    names another number of joints than there are efforts."""
    found = [label for label in labels[1:] if label.startswith(NAMES_PREFIX)]
    if not found:
        return None
    if len(found) > 1:
        raise EffortNamesError(f"{len(found)} names dimensions, expected at most one")
    try:
        names = json.loads(found[0][len(NAMES_PREFIX) :])
    except (ValueError, RecursionError):
        raise EffortNamesError(f"names dimension {found[0][:60]!r} is not JSON") from None
    if not isinstance(names, list) or not all(isinstance(name, str) for name in names):
        raise EffortNamesError("names dimension is not a JSON list of strings")
    if len(set(names)) != len(names):
        raise EffortNamesError("names dimension names a joint twice")
    if len(names) != count:
        raise EffortNamesError(f"names dimension names {len(names)} joints for {count} efforts")
    return tuple(names)
