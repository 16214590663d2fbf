"""A node's e-stop: the ``estop`` topic and the ``estop/reset`` service around an EStopLatch.

    self.estop = EStopInput(self, on_engage=self.stop_now, on_reset=self.clear_faults)

``estop`` is std_msgs/Bool, reliable and transient local: a node started after the button
was pressed is engaged at once. ``estop/reset`` (std_srvs/Trigger) releases it, and clears
the node's latched faults; every node that listens serves it, so one call releases them all.
The logic (engage, release, refused while held) is ``offline_rl_core.nodes.estop``.
"""

from __future__ import annotations

from typing import Callable

from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Bool
from std_srvs.srv import Trigger

from offline_rl_core.nodes.estop import EStopLatch

ESTOP_TOPIC = "estop"
ESTOP_RESET = "estop/reset"
ESTOP_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


class EStopInput:
    def __init__(self, node, on_engage: Callable[[], None] = lambda: None,
                 on_reset: Callable[[], None] = lambda: None, latch: EStopLatch | None = None,
                 namespace: str = ""):
        """``namespace`` (e.g. ``/arm1``): that namespace's e-stop instead of the node's own."""
        self.node = node
        self.latch = latch if latch is not None else EStopLatch()
        self.on_engage, self.on_reset = on_engage, on_reset
        prefix = f"{namespace}/" if namespace else ""
        node.create_subscription(Bool, prefix + ESTOP_TOPIC, self.on_estop, ESTOP_QOS)
        node.create_service(Trigger, prefix + ESTOP_RESET, self.on_reset_request)

    @property
    def engaged(self) -> bool:
        return self.latch.engaged

    def on_estop(self, msg: Bool) -> None:
        if self.latch.on_estop(msg.data):
            self.node.get_logger().error("e-stop engaged: the safe command applies until estop/reset")
            self.on_engage()

    def on_reset_request(self, request, response):
        was_engaged = self.latch.engaged
        response.success, response.message = self.latch.reset()
        if response.success:
            self.on_reset()
            if was_engaged:
                self.node.get_logger().warning("e-stop released by estop/reset")
        return response
