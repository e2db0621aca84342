"""A node's input counts on ``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``), the standard ROS channel.

Once per ``PERIOD`` a node publishes one ``DiagnosticStatus`` named
``<fully qualified node name>: inputs`` whose ``values`` are the
``morph_core.protocol.input_counts`` key/value pairs (received, rejected and
ignored per input, by reason, and the latest rejection's text). Level OK,
WARN while rejections keep coming (more since the last report). ``rqt_robot_monitor``
and ``diagnostic_aggregator`` show it as it is; a test reads it back with
``input_counts.from_key_values``.
"""

from __future__ import annotations

from collections.abc import Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node

from morph_core.protocol.input_counts import InputCounts

TOPIC = "/diagnostics"
PERIOD = 1.0
"""seconds between reports"""


def status_name(node: Node) -> str:
    return f"{node.get_fully_qualified_name()}: inputs"


class InputDiagnostics:
    """Publishes ``counts`` of ``node`` on ``/diagnostics`` every ``period`` seconds: the node's ``InputCounts``,
    or a function that makes them anew for each report (a node whose counts live in several objects, as the
    live trainer's in its pairs' assemblers)."""

    def __init__(self, node: Node, counts: InputCounts | Callable[[], InputCounts], period: float = PERIOD):
        self._node = node
        self._counts = counts
        self._pub = node.create_publisher(DiagnosticArray, TOPIC, 10)
        self._name = status_name(node)
        self._last_rejected = 0
        node.create_timer(period, self.publish)

    @property
    def counts(self) -> InputCounts:
        return self._counts() if callable(self._counts) else self._counts

    def publish(self) -> None:
        counts = self.counts
        rejected = counts.rejected_total
        level = DiagnosticStatus.WARN if rejected > self._last_rejected else DiagnosticStatus.OK
        self._last_rejected = rejected
        status = DiagnosticStatus(level=level, name=self._name, message=counts.summary(), hardware_id="")
        status.values = [KeyValue(key=k, value=v) for k, v in counts.to_key_values()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self._node.get_clock().now().to_msg()
        self._pub.publish(msg)
