"""A node's entry on ``/diagnostics`` (diagnostic_msgs/DiagnosticArray), once a second.

    NodeDiagnostics(node, status=lambda: {...}, diagnosis=StatusDiagnosis(checks=(...)))

What the entry says (level, message, key-values) is ``offline_rl_core.nodes.diagnostics``
applied to the same dict the node reports on ``~/status``; this only makes the message.
The topic is absolute, as diagnostic_updater publishes it: every node of every namespace
on one topic, told apart by the entry's name (the node's fully qualified name). The timer
runs on the steady clock, so a node under ``use_sim_time`` reports while the sim is stopped.
"""

from __future__ import annotations

from typing import Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType

from offline_rl_core.nodes.diagnostics import Diagnosis, StatusDiagnosis

DIAGNOSTICS_TOPIC = "/diagnostics"
DIAGNOSTICS_PERIOD_S = 1.0


def diagnostic_status(diagnosis: Diagnosis, name: str, hardware_id: str = "") -> DiagnosticStatus:
    return DiagnosticStatus(level=bytes([diagnosis.level]), name=name, message=diagnosis.message,
                            hardware_id=hardware_id,
                            values=[KeyValue(key=k, value=v) for k, v in diagnosis.values])


class NodeDiagnostics:
    def __init__(self, node, status: Callable[[], dict], diagnosis: StatusDiagnosis | None = None,
                 hardware_id: str = "", period_s: float | None = DIAGNOSTICS_PERIOD_S, qos=10):
        """Publish the node's entry every ``period_s`` (None: ``pusher_common.status`` does, on its tick).

        ``qos``: the publisher's, a depth or a profile (a short-lived node latches its last entry).
        """
        self.node = node
        self.status = status
        self.diagnosis = diagnosis if diagnosis is not None else StatusDiagnosis()
        self.hardware_id = hardware_id
        self.publisher = node.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, qos)
        if period_s is not None:
            node.create_timer(period_s, self.publish, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def publish(self, status: dict | None = None) -> None:
        report = self.diagnosis.report(self.status() if status is None else status)
        msg = DiagnosticArray(status=[diagnostic_status(report, self.node.get_fully_qualified_name(),
                                                        self.hardware_id)])
        msg.header.stamp = self.node.get_clock().now().to_msg()
        self.publisher.publish(msg)
