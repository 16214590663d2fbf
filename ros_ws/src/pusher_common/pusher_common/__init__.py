"""Plumbing shared by the pusher-rl nodes; no node logic lives here.

- :mod:`pusher_common.node_main`: ``run_node``, every node's ``main()``: rclpy set-up,
  one-line errors (``UserError`` -> exit 2), clean Ctrl-C / SIGTERM shutdown.
- :mod:`pusher_common.params`: settings declared as ROS parameters with descriptors,
  with the old command-line flags as aliases.
- :mod:`pusher_common.stamps`: ``stamp_key`` (a stamp as integer nanoseconds).
- :mod:`pusher_common.spin`: a message-fast ``spin_until_future_complete``.
- :mod:`pusher_common.estop`: ``EStopInput``, a node's ``estop`` topic and ``estop/reset`` service.
- :mod:`pusher_common.status`: ``NodeStatus``, a node's ``~/status`` (messages taken,
  rejections by reason) and its throttled warnings about refused messages.
- :mod:`pusher_common.diagnostics`: ``NodeDiagnostics``, the node's entry on ``/diagnostics``.
- :mod:`pusher_common.markers`: ``marker_array``, the arm's markers as a MarkerArray.
"""

from .stamps import stamp_from_ns, stamp_key

__all__ = ["stamp_from_ns", "stamp_key"]
