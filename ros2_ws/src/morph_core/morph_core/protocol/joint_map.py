"""Joint states onto a robot's kinematic tree, by joint name.

A driver publishes its joints in its own order, and may add joints the
policy does not drive (``joint_state_broadcaster`` publishes every joint it
has). ``JointMap`` binds a state's names to the tree of the robot's
description (``policy.tree.read_urdf``): ``order(names)`` says where in the
message each of the tree's joints is. The policy then sees the joints in
the tree's order, whatever the message's, and its answer goes back under
the same names.

Refused, with the reason (``JointMapError.code``): a state naming a joint
the description does not have at all (``unknown_joint``), and a state
lacking one of the description's actuated joints (``missing_joint``). Joints
the description has but does not actuate (fixed joints, hinges no
``<ros2_control>`` command interface drives) are left alone.

Without a description (``JointMap()``) the joints form a chain in the
message's order: the convention of a chain robot, and the fallback.
"""

from __future__ import annotations

import functools
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from morph_core.policy.tree import KinematicTree, UrdfRobot, read_urdf

_CACHED_ORDERS = 16  # a robot publishes one name list (a shuffling test a few): a handful covers it


class JointMapError(ValueError):
    """A state that does not fit the robot's description; ``code`` names the reason for counting."""

    def __init__(self, code: str, reason: str):
        super().__init__(reason)
        self.code = code


@dataclass(frozen=True, eq=False)
class JointOrder:
    """How one list of joint names lays onto the tree.

    tree: the robot's tree (joints in its depth-first order).
    index: [J] int64, read-only: the tree's joint j is the message's joint ``index[j]``.
    in_message_order: the message lists exactly the tree's joints, in the tree's order (``index`` = 0..J-1).
    """

    tree: KinematicTree
    index: np.ndarray
    in_message_order: bool

    # Cached: an order is made once per list of names (``JointMap`` keeps it) and used on every state.
    @functools.cached_property
    def _message_index(self) -> np.ndarray:
        return np.argsort(self.index, kind="stable")

    @functools.cached_property
    def message_names(self) -> tuple[str, ...]:
        """The tree's joints in the order the message lists them (its unactuated joints left out)."""
        return tuple(self.tree.names[j] for j in self._message_index)

    def to_tree(self, values: np.ndarray) -> np.ndarray:
        """Per-joint values of the message (one per name it carries) in the tree's order."""
        return values if self.in_message_order else values[self.index]

    def to_message(self, values: np.ndarray) -> np.ndarray:
        """Per-joint values in the tree's order, in ``message_names``' order."""
        return values if self.in_message_order else values[self._message_index]


class JointMap:
    """The joint order of every state from one robot description (None: a chain in message order)."""

    def __init__(self, robot: UrdfRobot | None = None):
        self.robot = robot
        self._orders: OrderedDict[tuple[str, ...], JointOrder] = OrderedDict()
        if robot is not None:
            self._position = {name: j for j, name in enumerate(robot.tree.names)}

    @classmethod
    def from_urdf(cls, text: str | bytes) -> JointMap:
        """A map from a URDF (``policy.tree.TreeError``, a ``ValueError``, for one that is no robot)."""
        return cls(read_urdf(text))

    @property
    def is_fallback(self) -> bool:
        """No description: each state's joints form a chain in the message's order."""
        return self.robot is None

    def order(self, names: tuple[str, ...]) -> JointOrder:
        """Where each of the tree's joints is among ``names`` (a state's distinct, valid joint names).

        Raises ``JointMapError`` for a name the description does not have, or an actuated joint missing."""
        order = self._orders.get(names)
        if order is None:
            order = self._bind(names)
            self._orders[names] = order
            if len(self._orders) > _CACHED_ORDERS:
                self._orders.popitem(last=False)
        else:
            self._orders.move_to_end(names)
        return order

    def _bind(self, names: tuple[str, ...]) -> JointOrder:
        if self.robot is None:
            index = np.arange(len(names), dtype=np.int64)
            index.setflags(write=False)
            return JointOrder(KinematicTree.chain(len(names), names, root_link=None), index, True)
        tree, position = self.robot.tree, self._position
        index = np.full(tree.num_joints, -1, dtype=np.int64)
        for i, name in enumerate(names):
            j = position.get(name)
            if j is not None:
                index[j] = i
            elif name not in self.robot.unactuated:
                raise JointMapError(
                    "unknown_joint",
                    f"the state names joint {name[:60]!r}, which robot_description does not have "
                    f"(its {tree.num_joints} actuated joints: {_listed(tree.names)})",
                )
        if (index < 0).any():
            missing = [tree.names[j] for j in np.flatnonzero(index < 0)]
            raise JointMapError(
                "missing_joint",
                f"the state lacks {len(missing)} of robot_description's {tree.num_joints} actuated joints: "
                f"{_listed(missing)}",
            )
        index.setflags(write=False)
        in_order = len(names) == tree.num_joints and bool((index == np.arange(tree.num_joints)).all())
        return JointOrder(tree, index, in_order)


def _listed(names, shown: int = 4) -> str:
    text = ", ".join(repr(n[:40]) for n in names[:shown])
    return text + (f" and {len(names) - shown} more" if len(names) > shown else "")
