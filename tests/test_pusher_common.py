"""pusher_common: node settings as parameters with descriptors and flag aliases."""

from __future__ import annotations

import argparse

import pytest

from offline_rl_core.common.errors import UserError

from ros_helpers import require_ros, ros_env  # noqa: F401 - a fixture

pytestmark = pytest.mark.ros


@pytest.fixture
def make_node():
    """``make_node(name, overrides)``: a node in its own context (no traffic needed)."""
    require_ros()
    import rclpy
    from rclpy.node import Node

    context = rclpy.Context()
    rclpy.init(context=context)
    nodes = []

    def make(name="settings_test", overrides=()):
        node = Node(name, context=context, parameter_overrides=list(overrides), start_parameter_services=False)
        nodes.append(node)
        return node

    yield make
    for node in nodes:
        node.destroy_node()
    rclpy.try_shutdown(context=context)


def specs():
    from pusher_common.params import Param

    return (
        Param("mode", "a", "the mode", choices=("a", "b"), read_only=True, flag="--mode"),
        Param("count", 3, "how many", low=1, flag="--count"),
        Param("rate", 0.5, "how fast", low=0.0, high=1.0),
        Param("path", None, "optional path", kind=str, read_only=True),
        Param("bags", [], "bags", kind=list, read_only=True, flag="--bag"),
    )


def test_flags_are_aliases_and_win_over_other_sources(make_node):
    from rclpy.parameter import Parameter

    from pusher_common.params import Settings, add_flags, overrides_from_flags

    parser = argparse.ArgumentParser()
    add_flags(parser, specs())
    args = parser.parse_args(["--count", "7", "--bag", "x.db3", "--bag", "y.db3"])
    overrides = overrides_from_flags(specs(), args)
    assert {p.name: p.value for p in overrides} == {"count": 7, "bags": ["x.db3", "y.db3"]}  # only given flags
    # a -p / params-file value for the same parameter comes first in the list; the flag wins
    node = make_node(overrides=[Parameter("count", value=2), Parameter("rate", value=1), *overrides])
    s = Settings(node, specs(), on_change=lambda name, value: None)
    assert (s.mode, s.count, s.rate, s.path, s.bags) == ("a", 7, 1.0, None, ["x.db3", "y.db3"])
    assert isinstance(s.rate, float)  # an int given for a float parameter is taken as a float
    d = node.describe_parameter("count")
    assert d.description == "how many" and d.integer_range[0].from_value == 1 and not d.read_only
    assert node.describe_parameter("mode").read_only


@pytest.mark.parametrize("name, value, why", [
    ("mode", "c", "parameter mode: must be one of a, b; got 'c'"),
    ("count", 0, "parameter count: Parameter count out of range. Min: 1, "),  # rclpy's range check
    ("rate", 1.5, "parameter rate: Parameter rate out of range Min: 0.0, Max: 1.0, value: 1.5"),
    ("rate", "fast", "parameter rate: expected a number, got 'fast'"),
])
def test_a_bad_starting_value_is_a_user_error_naming_the_parameter(make_node, name, value, why):
    from rclpy.parameter import Parameter

    from pusher_common.params import Settings

    node = make_node(overrides=[Parameter(name, value=value)])
    with pytest.raises(UserError) as err:
        Settings(node, specs(), on_change=lambda n, v: None)
    assert str(err.value).startswith(why) and "\n" not in str(err.value)


def test_a_misspelt_parameter_is_refused_naming_it_and_the_nodes_parameters(make_node):
    from rclpy.parameter import Parameter

    from pusher_common.params import Settings

    node = make_node(overrides=[Parameter("use_sim_time", value=True), Parameter("cuont", value=2)])
    with pytest.raises(UserError) as err:
        Settings(node, specs(), on_change=lambda n, v: None)
    assert str(err.value) == ("unknown parameter 'cuont' for node settings_test; did you mean count? "
                              "(its parameters: mode, count, rate, path, bags)")
    node = make_node(overrides=[Parameter("use_sim_time", value=True)])  # rclpy's own parameters are known
    assert Settings(node, specs(), on_change=lambda n, v: None).count == 3


def test_run_time_changes_take_effect_or_are_refused(make_node):
    from rclpy.parameter import Parameter

    from pusher_common.params import Settings

    changes = []
    node = make_node()
    s = Settings(node, specs(), on_change=lambda name, value: changes.append((name, value)),
                 check=lambda name, value: "too many" if name == "count" and value > 100 else None)
    results = node.set_parameters([Parameter("count", value=5), Parameter("rate", value=1), Parameter("mode", value="b"),
                                   Parameter("count", value=500), Parameter("count", value=0)])
    assert [r.successful for r in results] == [True, True, False, False, False]
    assert "read-only" in results[2].reason and results[3].reason == "parameter count: too many"
    assert changes == [("count", 5), ("rate", 1.0)] and (s.count, s.rate, s.mode) == (5, 1.0, "a")


def test_a_setting_that_can_change_needs_a_handler(make_node):
    from pusher_common.params import Param, Settings

    with pytest.raises(TypeError, match="handles no change"):
        Settings(make_node(), (Param("gain", 1.0, "gain"),))


def test_train_flags_become_read_only_parameters():
    require_ros()
    from pusher_common.params import params_from_parser

    from offline_rl_core.runs.training_run import add_train_arguments

    parser = argparse.ArgumentParser()
    add_train_arguments(parser)
    params = {p.name: p for p in params_from_parser(parser)}
    assert params["bag"].kind is list and params["bag"].flag == "--bag"
    assert params["algo"].choices and params["algo"].default == "awac"
    assert params["steps"].type is int and params["lr"].type is float
    assert params["deterministic"].type is bool and params["deterministic"].flag == "--deterministic"
    assert params["init"].default is None and params["init"].type is str
    assert all(p.read_only for p in params.values())


def test_thread_priority_puts_every_thread_under_fifo_or_says_why_not():
    """Where SCHED_FIFO is permitted every thread of the process (those started before
    too) runs under it; where it is not, one warning says how to permit it and nothing
    changes. Run in a child process: pytest itself must not become real-time."""
    import subprocess
    import sys

    require_ros()
    code = r"""
import os, threading
from pusher_common.scheduling import apply_thread_priority
DROP
class Log:
    def info(self, text): print("info:", text)
    def warn(self, text): print("warn:", text)
started = threading.Event(); stop = threading.Event()
def other():
    started.set(); stop.wait()
t = threading.Thread(target=other); t.start(); started.wait()
assert apply_thread_priority(0, Log()) is False
done = apply_thread_priority(20, Log())
policies = {os.sched_getscheduler(int(tid)) for tid in os.listdir("/proc/self/task")}
stop.set(); t.join()
print("done", done, "policies", sorted(policies))
"""
    import os

    def check(drop: str) -> None:
        out = subprocess.run([sys.executable, "-c", code.replace("DROP", drop)], capture_output=True, text=True,
                             timeout=60)
        assert out.returncode == 0, out.stderr
        if "done True" in out.stdout:
            assert f"policies [{os.SCHED_FIFO}]" in out.stdout and "SCHED_FIFO priority 20" in out.stdout
        else:
            assert "not permitted" in out.stdout and "rtprio" in out.stdout
            assert f"policies [{os.SCHED_OTHER}]" in out.stdout

    check("")
    if os.geteuid() == 0:  # as an unprivileged user too (no rtprio limit: refused)
        check("import resource; resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0)); os.setuid(65534)")


STALLED_TEARDOWN = """
import threading, sys
import rclpy.task
from rclpy.node import Node
from pusher_common import node_main

node_main.TEARDOWN_LIMIT_S = 1.0

class Done(Node):
    def __init__(self, overrides):
        super().__init__("stalled_teardown", parameter_overrides=list(overrides))
        self.finished = rclpy.task.Future()
        self.finished.set_result(True)
        self.exit_code = 3

    def close(self):
        print("closed", flush=True)
        threading.Thread(target=threading.Event().wait).start()  # never ends: the exit would wait on it

sys.exit(node_main.run_node(Done, prog="stalled", argv=[sys.argv[0]]))
"""


def test_a_node_whose_teardown_hangs_still_ends_after_its_close_with_its_status(ros_env):
    """Once ``close`` has kept what the node had to keep, a hang in what follows (destroying
    rclpy's objects, the interpreter waiting on a thread) ends the process anyway, with the
    node's exit status and where every thread was."""
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", STALLED_TEARDOWN], env=ros_env, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 3, done.stderr
    assert done.stdout.startswith("closed")
    assert "stalled: shutting down took over 1 s" in done.stderr and "Thread" in done.stderr
