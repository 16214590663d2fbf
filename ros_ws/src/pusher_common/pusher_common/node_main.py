"""Every node's ``main()``: set up rclpy, run the node, shut down cleanly, one-line errors.

    def main(argv=None):
        return run_node(PusherSim, prog="sim", flags=PARAMS, argv=argv)

- The command line's flags (``flags``: :class:`~pusher_common.params.Param` entries with
  a ``flag``) are parsed beside ``--ros-args`` and handed to the node's constructor as
  parameter overrides: ``make_node(overrides)``.
- A :class:`~offline_rl_core.common.errors.UserError` (bad parameter, missing file) prints
  ``PROG: error: ...`` on one line and exits 2; so does a ``--ros-args`` rcl cannot parse
  (``PROG: error: cannot parse --ros-args: REASON``).
- Ctrl-C and SIGTERM end the node cleanly (exit 0 for a node that serves until stopped):
  rclpy's signal handlers shut the context down and the spin returns. A node whose work
  runs in ``main`` itself (``runs_in_main``: ``node.run()``, the trainer) gets Python-level
  handlers instead, so Ctrl-C interrupts that work as a KeyboardInterrupt (also when started
  with SIGINT ignored, as a script's background job is) and is remembered
  (``offline_rl_core.common.interrupts.interrupt_received``); SIGTERM does the same.
- The spin ends when the node's ``finished`` future (if it has one) completes.
- Before spinning, what set-up allocated is moved out of the garbage collector's reach
  (``gc.freeze``), so no collection pauses a node for tens of milliseconds.
- ``node.close()`` (if defined) runs on every way out, before the node is destroyed: the
  place to write a summary or restore a terminal. From then on SIGINT and SIGTERM are
  ignored and rclpy's signal thread is stopped (``pusher_common.shutdown``): a second
  Ctrl-C cannot cut a close short, and nothing triggers a guard condition being destroyed.
  After it, a teardown that hangs ends the process anyway (``TEARDOWN_LIMIT_S``).
"""

from __future__ import annotations

import argparse
import faulthandler
import gc
import os
import re
import signal
import sys
import threading
from typing import Callable, Sequence

import rclpy
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args

from offline_rl_core.common.errors import UserError, caused_by_interrupt
from offline_rl_core.common.interrupts import interrupt_and_remember

from .params import Param, add_flags, overrides_from_flags
from .shutdown import quiet_signals


def spin_executor(executor, node) -> None:
    """Spin until ``node.finished`` completes, or until shutdown when it has none."""
    finished = getattr(node, "finished", None)
    if finished is None:
        executor.spin()
    else:
        executor.spin_until_future_complete(finished)


def run_node(
    make_node: Callable,
    *,
    prog: str,
    command: str | None = None,
    flags: Sequence[Param] = (),
    description: str | None = None,
    argv: list[str] | None = None,
    spin: Callable = spin_executor,
    runs_in_main: bool = False,
) -> int:
    """Run one node process; returns its exit status.

    ``prog`` names the node in error lines; ``command`` is how it is started, for
    ``--help`` (default ``ros2 run PROG node``).
    """
    faulthandler.enable()  # a crash in native code (rclpy, sqlite) leaves the Python stack in the node's log
    argv = list(sys.argv if argv is None else argv)
    parser = argparse.ArgumentParser(prog=command or f"ros2 run {prog} node", description=description,
                                     epilog="Every option is also a ROS parameter: --ros-args -p NAME:=VALUE "
                                            "or --params-file FILE.")
    add_flags(parser, flags)
    try:
        own_args = remove_ros_args(argv)
    except _rclpy.RCLError as exc:  # a params file that does not parse, `-p name` without a value, ...
        print(f"{prog}: error: cannot parse --ros-args: {_rcl_reason(exc)}", file=sys.stderr)
        return 2
    args = parser.parse_args(own_args[1:])
    overrides = overrides_from_flags(flags, args)
    if runs_in_main:
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
        # A handler of our own, also where the shell started this with SIGINT ignored (a
        # background job of a script): Ctrl-C interrupts the work as a KeyboardInterrupt,
        # and the node can ask ``interrupt_received()`` where that exception went astray.
        previous_int = signal.signal(signal.SIGINT, interrupt_and_remember)
        previous_term = signal.signal(signal.SIGTERM, interrupt_and_remember)
    else:
        rclpy.init(args=argv)
    node = None
    try:
        node = make_node(overrides)
        if runs_in_main:
            return int(node.run() or 0)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        # What set-up made (torch, rclpy, the node: ~200,000 objects) lives as long as the
        # process: out of the collector's reach, a full collection takes microseconds, not
        # the 30-40 ms that would hold up an answer to the arm
        gc.freeze()
        spin(executor, node)
        return int(getattr(node, "exit_code", 0) or 0)
    except UserError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except (KeyboardInterrupt, ExternalShutdownException):
        return 0
    except Exception as exc:
        if rclpy.ok() and not caused_by_interrupt(exc):
            raise  # a real error; otherwise a signal shut the context down mid-wait
        return 0
    finally:
        if runs_in_main:
            signal.signal(signal.SIGTERM, previous_term)
            signal.signal(signal.SIGINT, previous_int)
        else:
            quiet_signals()  # before anything is destroyed or closed (``shutdown``)
        if node is not None:
            close = getattr(node, "close", None)
            if close is not None:
                close()
            _end_if_teardown_stalls(prog, int(getattr(node, "exit_code", 0) or 0))
            node.destroy_node()
        rclpy.try_shutdown()


TEARDOWN_LIMIT_S = 30.0  # s: destroying the node and the context, and the interpreter's exit


def _end_if_teardown_stalls(prog: str, status: int) -> None:
    """End the process with ``status`` should its teardown hang.

    What the node had to keep is written (``close`` has run); should destroying rclpy's
    objects or the interpreter's exit hang (seen once on a loaded machine: a recorder that
    had closed its bag never exited), print where every thread is and end the process with
    its status, rather than keep a finished node alive. A C-level watchdog backs this up
    where the hang holds the GIL (its exit status is then 1).
    """

    def stalled() -> None:
        print(f"{prog}: shutting down took over {TEARDOWN_LIMIT_S:g} s; ending the process (its threads "
              "below)", file=sys.stderr, flush=True)
        faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
        sys.stdout.flush()
        os._exit(status)

    timer = threading.Timer(TEARDOWN_LIMIT_S, stalled)
    timer.daemon = True  # never what keeps the process alive
    timer.start()
    faulthandler.dump_traceback_later(2 * TEARDOWN_LIMIT_S, exit=True)


def _rcl_reason(exc: Exception) -> str:
    """Return rcl's reason without its prefix and source locations.

    For example "Couldn't parse remap rule: '-r x'. ...".
    """
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    text = text.removeprefix("Failed to parse ROS arguments: ")
    return re.sub(r", at /\S+:\d+", "", text)
