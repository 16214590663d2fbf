"""pusher-rl's ``ros2`` command for machines with rclpy from PyPI but no ros2cli.

Where the real ros2cli is importable, ``ros2`` hands over to it unchanged.
"""

__version__ = "0.1.0"
