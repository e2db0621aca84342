"""Which joints an effort command covers: a ``layout.dim`` of the ``Float64MultiArray`` naming them.

``effort_commands`` carries one effort per joint. Its ``layout.dim[0]`` says
which state it answers (``msgs.stamps``); a further dimension labelled
``names=<JSON list>`` (size 1, stride 1: the efforts as an N x 1 array) says
which joints the N efforts are for, in the data's order. A reader maps
efforts to its joints by those names; a command without one is in the order
of the state it answers (the convention before names were sent, and that of
any controller that does not name them). JSON, so that any joint name
(printable ASCII, commas and quotes included) goes through unchanged.

A dimension labelled ``tree=<16 hex digits>`` (size 1, stride 1) says on
which joint layout the efforts were computed: ``KinematicTree.layout_hash``
of the tree the policy read the state onto (its joint names in order and
their parents). A simulator whose body has another layout refuses the
command: names alone cannot tell two trees of equal joint names apart (a
swimmer's star and Y of six joints are both ``motor1_rot..motor6_rot``), and
a policy may answer a new body's first state before that body's description
has reached it (DDS orders no messages across topics).
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from functools import lru_cache

NAMES_PREFIX = "names="
TREE_PREFIX = "tree="
_TREE = re.compile(r"tree=[0-9a-f]{16}")


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


def tree_label(layout_hash: str) -> str:
    """The label of the dimension giving the joint layout the efforts were computed on."""
    return TREE_PREFIX + layout_hash


def effort_tree(labels: Sequence[str]) -> str | None:
    """The ``layout_hash`` a command's layout gives, or None when it gives none; ``EffortNamesError`` for a
    tree dimension that does not parse, or for two of them."""
    found = [label for label in labels[1:] if label.startswith(TREE_PREFIX)]
    if not found:
        return None
    if len(found) > 1 or _TREE.fullmatch(found[0]) is None:
        raise EffortNamesError(f"tree dimension {found[-1][:40]!r} is not one tree=<16 hex digits>")
    return found[0][len(TREE_PREFIX) :]
