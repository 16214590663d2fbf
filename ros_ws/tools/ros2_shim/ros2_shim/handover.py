"""When ``ros2`` hands over to a real ros2cli, and when it stays.

The real ros2cli takes over only when it runs on this very Python (it is importable
here and loads) and sees this environment's packages: the venv's prefix is put on
``AMENT_PREFIX_PATH`` for it. A ROS 2 install built for another Python (a sourced
/opt/ros whose ros2cli lives under lib/python3.12) cannot load this venv's rclpy or
nodes, so the shim stays and says why, once per install seen (a marker in the venv).
``ROS2_SHIM_NO_HANDOVER=1`` keeps the shim in any case.
"""

from __future__ import annotations

import glob
import importlib.util
import os
import re
import sys
from pathlib import Path

HERE = f"python{sys.version_info.major}.{sys.version_info.minor}"
NOTICE = Path(sys.prefix) / "share" / "ros2_shim" / "handover-notice"


def usable_ros2cli() -> tuple[bool, str | None]:
    """(hand over?, why not, for a ros2cli that exists but cannot serve this venv)."""
    if os.environ.get("ROS2_SHIM_NO_HANDOVER"):
        return False, None
    try:
        spec = importlib.util.find_spec("ros2cli")
    except (ImportError, ValueError):
        spec = None
    if spec is not None and spec.origin:
        location = str(Path(spec.origin).parent)
        other = re.search(r"/(python3\.\d+)/", location)
        if other and other.group(1) != HERE:
            return False, f"the ros2cli at {location} is for {other.group(1)}, this environment is {HERE}"
        try:
            import ros2cli.cli  # noqa: F401 - it must load here, with its dependencies
        except Exception as exc:  # noqa: BLE001 - whatever stops it, the shim serves
            return False, f"the ros2cli at {location} does not load on this Python ({type(exc).__name__}: {exc})"
        return True, None
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        for found in glob.glob(os.path.join(prefix, "lib", "python3*", "site-packages", "ros2cli")) if prefix else []:
            version = re.search(r"python3\.\d+", found).group(0)
            if version != HERE:
                return False, f"the ros2cli at {found} is for {version}, this environment is {HERE}"
            return False, f"the ros2cli at {found} is not on this Python's path (source its setup script)"
    return False, None


def hand_over(argv: list[str]) -> int:
    """Run the real ros2cli with this venv's prefix on AMENT_PREFIX_PATH."""
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    if sys.prefix not in prefixes:
        os.environ["AMENT_PREFIX_PATH"] = os.pathsep.join([sys.prefix, *prefixes])
    from ros2cli.cli import main as ros2cli_main

    return ros2cli_main(argv=argv)


def say_once(reason: str) -> None:
    """Tell why the shim serves, once for each ros2cli install it has seen."""
    try:
        if NOTICE.is_file() and NOTICE.read_text() == reason:
            return
        NOTICE.parent.mkdir(parents=True, exist_ok=True)
        NOTICE.write_text(reason)
    except OSError:
        pass  # a read-only environment: say it every time rather than never
    print(f"ros2: using this project's ros2 command: {reason}", file=sys.stderr)
