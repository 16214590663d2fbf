"""``ros2 launch PKG FILE.launch.yaml [name:=value ...]`` on ``ros2_shim.launch_files``.

Reads the YAML subset this project's launch files use (arg, node; see
``ros2_shim.launch_files``), starts each node as its own process (logs under
``$ROS_LOG_DIR`` or ``~/.ros/log``, echoed here with a ``[exe-N]`` prefix, as ros2 launch
does with ``output: screen``), and ends when a node marked ``on_exit: shutdown`` exits,
when all have exited, or on Ctrl-C / SIGTERM; every process is stopped by its pid.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time
from pathlib import Path

USAGE = "usage: ros2 launch [-h] [-s] package_name [launch_file_name] [launch_arguments ...]"


def launch_command(args: list[str]) -> int:
    from offline_rl_core.common.errors import UserError
    from ros2_shim.launch_files import declared_arguments, find_launch_file, load_launch, parse_launch_arguments

    parser = argparse.ArgumentParser(prog="ros2 launch", usage=USAGE[7:],
                                     description="Run a launch file (YAML format: arg and node actions)")
    parser.add_argument("-s", "--show-args", "--show-arguments", action="store_true",
                        help="Show arguments that may be given to the launch file")
    parser.add_argument("package_name", help="Name of the ROS package which contains the launch file, or a launch file path")
    parser.add_argument("launch_arguments", nargs="*", default=[],  # a default: argparse requires a bare '*' positional
                        help="The launch file name and arguments 'name:=value'")
    opts = parser.parse_args(args)
    rest = list(opts.launch_arguments)
    try:
        if Path(opts.package_name).is_file():
            path = Path(opts.package_name)
        else:
            if not rest or ":=" in rest[0]:
                print(USAGE, file=sys.stderr)
                print("ros2 launch: error: name the launch file", file=sys.stderr)
                return 2
            path = find_launch_file(opts.package_name, rest.pop(0))
        if opts.show_args:
            print("Arguments (pass arguments as '<name>:=<value>'):")
            for arg in declared_arguments(path):
                print(f"\n    '{arg['name']}':\n        {arg.get('description', 'no description given')}")
                if "default" in arg:
                    print(f"        (default: '{arg['default']}')")
            return 0
        nodes = load_launch(path, parse_launch_arguments(rest))
    except UserError as exc:
        print(f"ros2 launch: error: {exc}", file=sys.stderr)
        return 2
    return run_launch(nodes)


def _log_dir() -> Path:
    base = Path(os.environ.get("ROS_LOG_DIR") or Path(os.environ.get("ROS_HOME", Path.home() / ".ros")) / "log")
    path = base / f"{time.strftime('%Y-%m-%d-%H-%M-%S')}-launch-{os.getpid()}"
    path.mkdir(parents=True, exist_ok=True)
    return path


def run_launch(nodes) -> int:
    from offline_rl_core.pipelines.processes import LaunchedProcesses

    log_dir = _log_dir()
    print(f"[INFO] [launch]: All log files can be found below {log_dir}", flush=True)
    previous = signal.signal(signal.SIGTERM, _interrupt)
    launched = LaunchedProcesses(nodes, dict(os.environ), log_dir)
    labels = {proc.name: f"{node.executable}-{i}" for i, (node, proc) in
              enumerate(zip(nodes, launched.processes.values()), start=1)}
    shown = {name: 0 for name in labels}
    reported: set[str] = set()
    try:
        for proc in launched.processes.values():
            proc.start()
            print(f"[INFO] [{labels[proc.name]}]: process started with pid [{proc.pid}]", flush=True)
        while True:
            _echo_new_output(launched, labels, shown)
            for proc in launched.processes.values():
                if proc.name not in reported and not proc.running():
                    reported.add(proc.name)
                    _report_exit(proc, labels[proc.name])
            if launched.finished() is not None:
                break
            time.sleep(0.1)
    except Terminated:
        print("[WARNING] [launch]: stopped by SIGTERM", flush=True)
    except KeyboardInterrupt:
        print("[WARNING] [launch]: user interrupted with ctrl-c (SIGINT)", flush=True)
    finally:
        launched.stop()
        _echo_new_output(launched, labels, shown)
        for proc in launched.processes.values():
            if proc.name not in reported and proc.poll() is not None:
                _report_exit(proc, labels[proc.name])
        signal.signal(signal.SIGTERM, previous)
    done = launched.finished()
    return 0 if done is None or done.poll() in (0, None) else 1


def _echo_new_output(launched, labels, shown) -> None:
    for proc in launched.processes.values():
        text = proc.output()
        end = text.rfind("\n") + 1
        for line in text[shown[proc.name]:end].splitlines():
            print(f"[{labels[proc.name]}] {line}")
        shown[proc.name] = max(shown[proc.name], end)
    sys.stdout.flush()


def _report_exit(proc, label: str) -> None:
    code = proc.poll()
    if code == 0:
        print(f"[INFO] [{label}]: process has finished cleanly [pid {proc.pid}]", flush=True)
    else:
        print(f"[ERROR] [{label}]: process has died [pid {proc.pid}, exit code {code}, "
              f"cmd '{' '.join(proc.cmd)}'].", flush=True)


class Terminated(KeyboardInterrupt):
    """SIGTERM: stopped like Ctrl-C, and said to be SIGTERM."""


def _interrupt(signum, frame):
    raise Terminated
