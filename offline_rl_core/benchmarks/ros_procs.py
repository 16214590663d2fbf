"""ROS 2 processes for the serve and record figures, isolated on a random DDS domain.

The bench process joins the same domain (``isolate()`` sets ``ROS_DOMAIN_ID`` and
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` before rclpy starts); every node it spawns
runs in its own process group and is stopped by that group's id, never by name.
"""

from __future__ import annotations

import os
import random
import shutil
import subprocess
import sys
import time
from pathlib import Path

from ..rosproc import RosProcess, isolated_ros_env


def ros_missing() -> str | None:
    """Why the ROS figures cannot run here, or None when they can."""
    try:
        import rclpy  # noqa: F401
        from sensor_msgs.msg import JointState  # noqa: F401
    except Exception as exc:
        return f"rclpy not importable ({type(exc).__name__}: {exc}); install the 'ros' extra"
    if ros2_command() is None:
        return "no `ros2` command beside the interpreter (make setup installs it)"
    return None


def ros2_command() -> str | None:
    local = Path(sys.executable).parent / "ros2"
    if local.exists():
        return str(local)
    return shutil.which("ros2")


_DOMAIN: list[int] = []


def isolate() -> int:
    """Pick one random domain for this process (once) and its children."""
    if not _DOMAIN:
        _DOMAIN.append(random.SystemRandom().randint(30, 200))
    os.environ["ROS_DOMAIN_ID"] = str(_DOMAIN[0])
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    return _DOMAIN[0]


class NodeProcess(RosProcess):
    """A node process on the bench's domain, started at once and stopped by its pid on exit."""

    def __init__(self, argv: list[str], log_path: Path):
        super().__init__(argv, isolated_ros_env(isolate()), log_path)
        self.start()

    def wait(self, timeout: float) -> int | None:
        """Exit status, or None while it still runs after ``timeout`` s."""
        try:
            return super().wait(timeout)
        except subprocess.TimeoutExpired:
            return None

    def log_tail(self, chars: int = 600) -> str:
        return self.output()[-chars:]


ECHO_NODE = r'''
"""A bare echo node: answers each /pusher/state with a /policy/action of the same stamp."""
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from sensor_msgs.msg import JointState


class Echo(Node):
    def __init__(self):
        super().__init__("bench_echo")
        self.pub = self.create_publisher(JointState, "/policy/action", 10)
        self.create_subscription(JointState, "/pusher/state", self.on_state, 10)
        self.out = JointState(name=["shoulder", "elbow"])

    def on_state(self, msg):
        self.out.header.stamp = msg.header.stamp
        self.out.effort = [0.0, 0.0]
        self.pub.publish(self.out)


rclpy.init()
node = Echo()
try:
    rclpy.spin(node)
except (KeyboardInterrupt, ExternalShutdownException):
    pass
finally:
    node.destroy_node()
    rclpy.try_shutdown()
'''


def wait_until(predicate, timeout_s: float, spin=None, step_s: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        if spin is not None:
            spin(step_s)
        else:
            time.sleep(step_s)
    return predicate()
