"""The learning core stands alone: no ROS import anywhere in offline_rl_core."""

import re
from pathlib import Path

CORE = Path(__file__).resolve().parents[1] / "offline_rl_core"
ROS_IMPORT = re.compile(r"^\s*(import|from)\s+(rclpy|std_msgs|sensor_msgs|geometry_msgs|std_srvs|builtin_interfaces)\b")


def test_offline_rl_core_imports_no_ros():
    offenders = [
        f"{path.relative_to(CORE.parent)}:{n}"
        for path in CORE.rglob("*.py")
        for n, line in enumerate(path.read_text().splitlines(), 1)
        if ROS_IMPORT.match(line)
    ]
    assert offenders == []
