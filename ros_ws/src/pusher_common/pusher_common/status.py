"""A node's ``~/status``: what it took and what it refused (std_msgs/String, JSON, once a second).

    self.status = NodeStatus(self, fields=lambda: {"answered": self.answered})
    self.status.took("pusher/state")                  # every message a callback takes
    self.status.reject("pusher/state", rejection)     # counted; a throttled warning
    self.status.warn(topic, rejection)   # only the warning, where the logic's own counter counted it

The JSON is ``{"messages": {topic: n}, "rejected": {reason: n}, ...fields}``, the same
keys on every node (reasons: ``offline_rl_core.common.rejections.REASONS``), so a test or an
operator reads any node's refusals the same way. The timer runs on the steady clock: a
node under ``use_sim_time`` reports while the sim is stopped too.
"""

from __future__ import annotations

import json
from typing import Callable

from rclpy.clock import Clock, ClockType
from std_msgs.msg import String

from offline_rl_core.common.rejections import Rejection, RejectionCounter
from offline_rl_core.nodes.diagnostics import StatusDiagnosis

from .diagnostics import NodeDiagnostics

STATUS_PERIOD_S = 1.0


class NodeStatus:
    def __init__(self, node, fields: Callable[[], dict] = dict, counter: RejectionCounter | None = None,
                 period_s: float = STATUS_PERIOD_S, diagnosis: StatusDiagnosis | None = None,
                 hardware_id: str = ""):
        self.node = node
        self.fields = fields
        self.rejections = counter if counter is not None else RejectionCounter()
        self.messages: dict[str, int] = {}
        self.publisher = node.create_publisher(String, "~/status", 10)
        # published by this timer, not its own: one dict per tick for both topics
        self.diagnostics = NodeDiagnostics(node, self.as_dict, diagnosis, hardware_id, period_s=None)
        node.create_timer(period_s, self.publish, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def took(self, topic: str) -> None:
        self.messages[topic] = self.messages.get(topic, 0) + 1

    def reject(self, topic: str, rejection: Rejection) -> None:
        """Count a refused message; warn about it unless its reason was warned about lately."""
        self.rejections.add(rejection)
        self.warn(topic, rejection)

    def warn(self, topic: str, rejection: Rejection) -> None:
        """Warn (throttled) about a rejection already counted by the node's logic."""
        line = self.rejections.warning(topic, rejection)
        if line is not None:
            self.node.get_logger().warning(line)

    def as_dict(self) -> dict:
        return {**self.fields(), "messages": dict(self.messages), "rejected": dict(self.rejections.counts)}

    def publish(self) -> None:
        status = self.as_dict()
        self.publisher.publish(String(data=json.dumps(status)))
        self.diagnostics.publish(status)
