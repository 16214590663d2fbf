"""The one safe order of a node's way out after Ctrl-C or SIGTERM.

rclpy's signal handler wakes a thread of its own that triggers every registered sigint
guard condition, walking their list without a lock, and only then shuts the context down.
So while that thread runs, a guard condition destroyed on the main thread (the spin's own,
or the node's with it) can be triggered after it is freed: a SIGSEGV while the node closes
(its bag, its summary), about one Ctrl-C in ten with a busy core beside it.

``quiet_signals()`` comes before anything is torn down: SIGINT and SIGTERM are ignored from
then on (a second Ctrl-C cannot interrupt a bag's last transaction either), and
``rclpy.signals.uninstall_signal_handlers()`` joins rclpy's signal thread, so nothing
triggers a guard condition any more. SIGKILL still ends a node that hangs on its way out.
"""

from __future__ import annotations

import signal
import threading

from rclpy.signals import uninstall_signal_handlers

_QUIET = (signal.SIGINT, signal.SIGTERM)


def quiet_signals() -> None:
    """Ignore SIGINT/SIGTERM and stop rclpy's signal thread (idempotent; main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in _QUIET:
        signal.signal(sig, signal.SIG_IGN)
    uninstall_signal_handlers()  # joins the signal thread; puts back the handlers it replaced
    for sig in _QUIET:
        signal.signal(sig, signal.SIG_IGN)
