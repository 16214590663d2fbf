"""pusher-rl's ``ros2`` command for machines with rclpy from PyPI but no ros2cli.

Where a real ros2cli runs on this Python and sees this environment, ``ros2`` hands over
to it (see handover.py).
"""

__version__ = "0.1.0"
