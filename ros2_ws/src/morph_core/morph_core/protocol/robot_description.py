"""A policy node's robot description: the kinematic tree each joint state is read on, by joint name (no ROS).

``robot_description`` (std_msgs/String, a URDF, latched as
``robot_state_publisher`` publishes it) says which joints the robot has and
how they hang together. ``RobotDescriptions`` holds the one a node acts on:

- ``offer(text)`` reads a description (``JointMap.from_urdf``). One that is
  no robot (malformed XML, too large, a cycle, two roots, duplicate names,
  more than 64 actuated joints, ...: ``policy.tree.TreeError``) is rejected
  with its one-line reason and the current graph is kept. The same text as
  the current one changes nothing (a latched publisher sends it again to a
  reader that re-matches). Any other valid text replaces the graph at once:
  the node acts on it from the next state on.
- ``order(names)`` lays one state's joint names onto the current tree
  (``JointMap.order``: any order, extra unactuated joints left alone).
  A state that does not fit raises ``JointMapError`` with its code:
  ``unknown_joint`` or ``missing_joint`` (rejected), or
  ``PREVIOUS_DESCRIPTION`` when it fits the description before the current
  one: a state of the robot before a swap, still in flight, which the node
  ignores and counts apart from malformed states.
- Until a description arrives every state's joints form a chain in the
  message's order (``JointMap()``, the fallback: today's chains need no
  description). The fallback is never a "previous description": it fits
  every state, so nothing could be told apart by it.

The two latest descriptions are kept, text and map, so a description
alternating between two robots costs a comparison, not a parse.

Joint descriptions (``policy.joint_description``): with ``describe`` (a
controller whose policy reads them) each new description's per-joint vectors
are built when it is offered, in its tree's order; one whose vectors cannot be
built (``TreeError``: NaN origins, a zero axis, an absurd size, ...) is
rejected like a malformed one, with ``describe_code``, and the current graph
is kept. ``joint_descriptions()`` gives the current one's (built then, if the
policy began to read them after it was adopted).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from morph_core.policy.tree import TreeError, UrdfRobot
from morph_core.protocol.joint_map import JointMap, JointMapError, JointOrder

DESCRIPTION = "description"
"""reason code of a rejected description (``TreeError``)"""
UNCHANGED = "unchanged"
"""reason code of an ignored description: the same text as the current one"""
PREVIOUS_DESCRIPTION = "previous_description"
"""``JointMapError.code`` of a state that fits the description before the current one (ignored, not rejected)"""


@dataclass(frozen=True)
class DescriptionOffer:
    """What ``offer`` did with one description."""

    outcome: str
    """"adopted" (the graph from now on), "unchanged" (the current text again) or "rejected\""""
    reason: str = ""
    """why it was rejected, in one line (``TreeError``'s text)"""
    code: str = ""
    """``DESCRIPTION`` or the check's code (rejected), ``UNCHANGED`` (unchanged), '' (adopted)"""


@dataclass(eq=False)
class _Described:
    text: str
    map: JointMap
    joint_desc: np.ndarray | None = None
    """its joint descriptions, once built (``describe``)"""


class RobotDescriptions:
    """The description a node acts on, the one before it, and what became of each offered."""

    def __init__(
        self,
        check: Callable[[UrdfRobot], str | None] | None = None,
        refusal_code: str = "",
        describe: Callable[[object], np.ndarray | None] | None = None,
        describe_code: str = "",
    ) -> None:
        """``check``: a further condition on a robot (its reason, or None), whose refusal counts as
        ``refusal_code`` (a controller's effort units: ``protocol.controller``). ``describe``: a description's
        text -> its joint descriptions (None: not wanted now; ``TreeError``: rejected as ``describe_code``)."""
        self._check, self._refusal_code = check, refusal_code
        self._describe, self._describe_code = describe, describe_code
        self._fallback = JointMap()
        self._current: _Described | None = None
        self._previous: _Described | None = None
        self.generation = 0
        """0 while on the fallback; counts the descriptions adopted (a swap back to an earlier text counts too)"""
        self.adopted = self.unchanged = self.rejected = 0
        self.last_error = ""

    @property
    def map(self) -> JointMap:
        """The current joint map (the fallback's while no description has been adopted)."""
        return self._fallback if self._current is None else self._current.map

    @property
    def previous(self) -> JointMap | None:
        """The map of the description before the current one (None: there was none)."""
        return None if self._previous is None else self._previous.map

    @property
    def is_fallback(self) -> bool:
        return self._current is None

    def offer(self, text: object) -> DescriptionOffer:
        """Read one description; a valid new one becomes the current graph, anything else leaves it be."""
        if self._current is not None and text == self._current.text:
            self.unchanged += 1
            return DescriptionOffer("unchanged", code=UNCHANGED)
        if self._previous is not None and text == self._previous.text:
            described = self._previous  # a swap back: the map is the one read before
        else:
            try:
                described = _Described(text, JointMap.from_urdf(text))  # TreeError for anything but a str/bytes too
            except TreeError as err:
                self.rejected += 1
                self.last_error = str(err)
                return DescriptionOffer("rejected", reason=str(err), code=DESCRIPTION)
            reason = None if self._check is None else self._check(described.map.robot)
            if reason is not None:
                self.rejected += 1
                self.last_error = reason
                return DescriptionOffer("rejected", reason=reason, code=self._refusal_code)
            if self._describe is not None:
                try:
                    described.joint_desc = self._describe(text)
                except TreeError as err:
                    self.rejected += 1
                    self.last_error = reason = f"its joint descriptions cannot be built: {err}"
                    return DescriptionOffer("rejected", reason=reason, code=self._describe_code)
        self._previous, self._current = self._current, described
        self.generation += 1
        self.adopted += 1
        return DescriptionOffer("adopted")

    def joint_descriptions(self) -> np.ndarray | None:
        """The current description's joint descriptions, in its tree's order (None on the fallback, or when
        ``describe`` wants none); built now if they were not when it was adopted (``TreeError`` if they cannot)."""
        if self._current is None or self._describe is None:
            return None
        if self._current.joint_desc is None:
            self._current.joint_desc = self._describe(self._current.text)
        return self._current.joint_desc

    def order(self, names: tuple[str, ...]) -> JointOrder:
        """Where each of the current tree's joints is among a state's ``names`` (distinct, valid joint names).

        Raises ``JointMapError``: ``PREVIOUS_DESCRIPTION`` if the state does not fit the current description but
        fits the one before it, else the current map's ``unknown_joint`` / ``missing_joint``."""
        try:
            return self.map.order(names)
        except JointMapError as err:
            if self._previous is None:
                raise
            try:
                self._previous.map.order(names)
            except JointMapError:
                raise err from None
            raise JointMapError(
                PREVIOUS_DESCRIPTION,
                f"the state fits the previous robot_description, not the current one ({err}): a state of the "
                "robot before the swap, still in flight",
            ) from None
