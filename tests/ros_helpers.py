"""Shared pieces of the ROS 2 tests: an isolated DDS domain, node processes stopped by pid
(``offline_rl_core.pipelines.processes.RosProcess``), and an in-test rclpy node.

Import the fixtures into a test module with ``from ros_helpers import ros_env, spawn``.
"""

from __future__ import annotations

import os
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import pytest

from offline_rl_core.pipelines.processes import claim_free_domain

REPO = Path(__file__).resolve().parents[1]
# ros_ws/tools (the installer of the ROS packages) is a folder of scripts, not a package
sys.path.insert(0, str(REPO / "ros_ws" / "tools"))
ROS2 = Path(sys.prefix) / "bin" / "ros2"
PACKAGES = ("sim", "recorder", "trainer", "policy", "learner")
# The Python module of each ROS package (PyPI has packages called sim, trainer, policy,
# recorder).
MODULES = {"sim": "pusher_sim", "recorder": "pusher_recorder", "trainer": "pusher_trainer", "policy": "pusher_policy",
           "corrections": "pusher_corrections", "pusher_common": "pusher_common", "learner": "pusher_learner",
           "viz": "pusher_viz"}
INDEX = Path(sys.prefix) / "share" / "ament_index" / "resource_index" / "packages"

# One DDS domain per test session, localhost only, that no other pusher-rl process on this
# machine holds (a HIL session, a benchmark): parallel sessions and other machines on the
# network never see these nodes.
_DOMAIN_ID = str(claim_free_domain())


def rclpy_available() -> bool:
    try:
        import rclpy  # noqa: F401
    except Exception:  # noqa: BLE001 - any failure to load the middleware means no ROS here
        return False
    return True


def require_ros() -> None:
    if not rclpy_available():
        pytest.skip("rclpy is not importable (pip install -e '.[ros]')")
    missing = [p for p in PACKAGES if not (INDEX / p).exists()]
    if missing or not ROS2.exists():
        pytest.skip(f"ROS packages {missing or ''} / ros2 not installed in {sys.prefix}: run `make setup`")


def task_bag_and_prior(tmp_path_factory, task: str, hidden: int | None = None):
    """A 4-episode bag of ``task`` (half expert) and a 50-step AWAC prior trained on it
    (``hidden`` wide, else the default width)."""
    require_ros()
    from offline_rl_core.commands.cli import main

    d = tmp_path_factory.mktemp(task)
    bag, prior = d / f"{task}.db3", d / "prior"
    assert main(["collect", "--task", task, "--episodes", "4", "--expert-frac", "0.5", "--seed", "0",
                 "--out", str(bag)]) == 0
    assert main(["train", "--bag", str(bag), "--algo", "awac", "--steps", "50", "--eval-episodes", "0",
                 *(["--hidden", str(hidden)] if hidden else []), "--out", str(prior)]) == 0
    return bag, prior / "policy.pt"


@pytest.fixture(scope="session")
def ros_env():
    """Environment for node processes (and this process's rclpy) on the session's domain."""
    require_ros()
    overrides = {
        "ROS_DOMAIN_ID": _DOMAIN_ID,
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "ROS_LOCALHOST_ONLY": "",  # deprecated twin of the range; must not contradict it
        "PYTHONUNBUFFERED": "1",
        "RCUTILS_COLORIZED_OUTPUT": "0",
        "RCUTILS_LOGGING_BUFFERED_STREAM": "0",  # node logs reach the log file as they happen
        "OPENBLAS_NUM_THREADS": "1",
    }
    saved = {k: os.environ.get(k) for k in overrides}
    os.environ.update(overrides)
    os.environ.pop("ROS_LOCALHOST_ONLY")
    env = dict(os.environ)
    yield env
    for key, value in saved.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value


@pytest.fixture
def spawn(ros_env, tmp_path):
    """``spawn(cmd, name)`` starts a process on the test domain; all are stopped at teardown."""
    from offline_rl_core.pipelines.processes import RosProcess

    started: list[RosProcess] = []

    def start(cmd: list, name: str, env: dict | None = None) -> RosProcess:
        proc = RosProcess(cmd, env or ros_env, tmp_path / f"{name}.log", cwd=REPO, name=name).start()
        started.append(proc)
        return proc

    yield start
    for proc in reversed(started):
        proc.stop()


def ros2(*args) -> list[str]:
    return [str(ROS2), *map(str, args)]


@contextmanager
def probe_node(name: str = "pytest_probe"):
    """An rclpy node in this process on the test domain, with its own context and executor."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    context = rclpy.Context()
    rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(name, context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    node.spin_for = lambda seconds: _spin_for(executor, seconds)
    node.spin_until = lambda predicate, timeout: _spin_until(executor, predicate, timeout)
    try:
        yield node
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=context)


class Diagnostics:
    """The latest /diagnostics entry of each node, as the probe hears them."""

    def __init__(self, node):
        from diagnostic_msgs.msg import DiagnosticArray

        self.latest: dict[str, object] = {}
        self.seen: list[tuple[str, int, str]] = []
        node.create_subscription(DiagnosticArray, "/diagnostics", self.on_array, 10)

    def on_array(self, msg) -> None:
        for status in msg.status:
            self.latest[status.name] = status
            self.seen.append((status.name, level(status), status.message))

    def values(self, name: str) -> dict[str, str]:
        return {kv.key: kv.value for kv in self.latest[name].values}


def level(status) -> int:
    return status.level[0] if isinstance(status.level, (bytes, bytearray)) else int(status.level)


def _spin_for(executor, seconds: float) -> None:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.02)


def _spin_until(executor, predicate, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        executor.spin_once(timeout_sec=0.02)
    return bool(predicate())
