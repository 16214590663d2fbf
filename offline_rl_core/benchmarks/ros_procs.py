"""ROS 2 processes for the serve and record figures, isolated on a random DDS domain.

The bench process joins the same domain (``isolate()`` sets ``ROS_DOMAIN_ID`` and
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` before rclpy starts); every node it spawns
runs in its own process group and is stopped by that group's id, never by name.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from ..pipelines.processes import RosProcess, claim_free_domain, isolated_ros_env

# The rclpy side of the DDS figures runs in its own process from the source tree:
# offline_rl_core itself never imports ROS.
PROBES = Path(__file__).resolve().parents[2] / "ros_ws" / "tools" / "bench_probes" / "dds_probes.py"


def run_probe(args: list, timeout: float):
    """Run a DDS probe on this process's (isolated) domain; its last stdout line is JSON."""
    proc = subprocess.run([sys.executable, str(PROBES), *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, env=dict(os.environ))
    if proc.returncode != 0:
        raise RuntimeError(f"DDS probe {args[0]} failed (exit {proc.returncode}): {proc.stderr.strip()[-400:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def ros_missing() -> str | None:
    """Why the ROS figures cannot run here, or None when they can."""
    if importlib.util.find_spec("rclpy") is None or importlib.util.find_spec("sensor_msgs") is None:
        return "rclpy / sensor_msgs not installed; install the 'ros' extra"
    if not PROBES.exists():
        return f"{PROBES} not found: the DDS probes run from a source checkout"
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
    if not _DOMAIN:  # one no other pusher-rl process on this machine holds
        _DOMAIN.append(claim_free_domain(101, 200))
    os.environ["ROS_DOMAIN_ID"] = str(_DOMAIN[0])
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    return _DOMAIN[0]


def bench_node(argv: list[str], log_path: Path) -> RosProcess:
    """A node process on the bench's domain, started at once (stopped by its pid on leaving
    its ``with`` block, as every ``RosProcess``)."""
    return RosProcess(argv, isolated_ros_env(isolate()), log_path).start()


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
