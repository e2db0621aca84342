"""Legged bodies are not learned from over ROS yet: the one refusal of live training and of bags.

The transitions that bags and live training assemble (``morph_core.protocol.transitions``) carry a swimmer's
4 global features, read from planar odometry (yaw, yaw rate, vx, vy); a legged body's policy reads 12
(``env.centipede.GLOBAL_FEATURES``). Until a controller makes legged bodies work there, every such case is
refused in one line before anything runs, here alone: ``refuse_legged_bodies`` (a body spec given to
``morph-train --live``, which ``scripts/live.sh`` checks first) and ``refuse_legged_odometry`` (a bag's
odometry records, read by ``morph-bag`` and ``morph-train --from-bags``). Making them work removes this module
and its calls.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator

from morph_core.env.bodies import parse_bodies
from morph_core.msgs.records import OdometryRecord
from trainer.bags.io import BagError

WHY = (
    "learning from bags and live runs swimmers only for now (their transitions carry a swimmer's 4 planar "
    "global features, a legged body's policy reads 12); train legged bodies in the simulator: "
    "morph-train --bodies centipede:2-4 (docs/centipedes.md)"
)


def refuse_legged_bodies(spec: str, what: str) -> None:
    """ValueError naming ``what`` (the option) when the body spec ``spec`` holds bodies with legs."""
    if spec and parse_bodies(spec).has_centipedes:
        raise ValueError(f"{what} {spec!r} holds centipedes: {WHY}")


def is_planar(record: OdometryRecord) -> bool:
    """A swimmer's odometry: its orientation a yaw alone (quaternion x = y = 0, as the swimmer sim writes it)."""
    qx, qy, _, _ = record.orientation_xyzw
    return qx == 0.0 and qy == 0.0


def refuse_legged_odometry(records: Iterable, bag) -> Iterator:
    """``records`` as they are, until an odometry leaves the plane (a body tilted in 3-D: a legged robot, a
    centipede): then ``BagError`` naming ``bag``, before any of its steps is used."""
    for record in records:
        if isinstance(record, OdometryRecord) and not is_planar(record):
            raise BagError(f"{bag}: its odometry is of a body in 3-D (legs: a centipede, a legged robot): {WHY}")
        yield record
