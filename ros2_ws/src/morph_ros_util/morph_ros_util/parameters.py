"""A node's parameters as one table: declared from it, and listed by the node's ``--help`` from it.

Each node writes its parameters once, as ``NodeParameter`` rows (name, default, description, range,
read-only); ``declare_parameters`` turns them into rclpy's declarations with their descriptors (the range
as rclpy enforces it: integers in steps of 1, doubles without a step), and ``parameters_help`` into the
text ``node_runner`` prints for ``--help``, so what a user reads is what the node declares.
"""

from __future__ import annotations

import textwrap
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node
from rclpy.parameter import Parameter


@dataclass(frozen=True)
class NodeParameter:
    """One parameter of a node."""

    name: str
    default: Any
    """its value when not given; a ``Parameter.Type`` for one that has none (e.g. ``STRING_ARRAY``: unset)"""
    description: str
    bounds: tuple[float, float] | None = None
    """(lowest, highest) allowed, inclusive; an integer range when the default is an int"""
    read_only: bool = False
    """set at start-up only (``-p NAME:=VALUE``); changing it at runtime is refused"""

    def descriptor(self) -> ParameterDescriptor:
        ranges = {}
        if self.bounds is not None:
            lo, hi = self.bounds
            if isinstance(self.default, bool) or not isinstance(self.default, (int, float)):
                raise TypeError(f"parameter {self.name}: a range needs a numeric default, got {self.default!r}")
            if isinstance(self.default, int):
                ranges["integer_range"] = [IntegerRange(from_value=int(lo), to_value=int(hi), step=1)]
            else:
                ranges["floating_point_range"] = [FloatingPointRange(from_value=lo, to_value=hi, step=0.0)]
        return ParameterDescriptor(description=self.description, read_only=self.read_only, **ranges)

    def shown_default(self) -> str:
        if isinstance(self.default, Parameter.Type):
            return "unset"
        if isinstance(self.default, bool):
            return "true" if self.default else "false"
        if isinstance(self.default, list):
            return "[" + ", ".join(map(str, self.default)) + "]"
        return repr(self.default)


def declare_parameters(node: Node, table: Sequence[NodeParameter]) -> None:
    """Declare every row of ``table`` on ``node``."""
    for row in table:
        node.declare_parameter(row.name, row.default, row.descriptor())


def parameters_help(table: Sequence[NodeParameter], width: int = 110) -> str:
    """The table as ``--help`` lists it: one entry per parameter, its description, default, range, read-only."""
    name_width = max((len(row.name) for row in table), default=0)
    lines = ["parameters (-p NAME:=VALUE after --ros-args):"]
    for row in table:
        extra = [f"default: {row.shown_default()}"]
        if row.bounds is not None:
            extra.append(f"{row.bounds[0]}..{row.bounds[1]}")
        if row.read_only:
            extra.append("read-only")
        text = f"{row.name:<{name_width}}  {row.description} ({'; '.join(extra)})"
        indent = " " * (name_width + 4)
        lines.append(textwrap.fill(text, width, initial_indent="  ", subsequent_indent=indent, break_long_words=False))
    return "\n".join(lines)
