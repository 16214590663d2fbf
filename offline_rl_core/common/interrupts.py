"""SIGTERM as Ctrl-C: a process stopped by ``kill`` or a process manager cleans up exactly
as one stopped at the terminal (its ``finally`` blocks stop its children, close its files)."""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from typing import Iterator


def raise_keyboard_interrupt(signum, frame) -> None:
    """A signal handler that turns the signal into KeyboardInterrupt."""
    raise KeyboardInterrupt


_received: list[int] = []  # the signals ``interrupt_and_remember`` has handled in this process


def interrupt_and_remember(signum, frame) -> None:
    """A signal handler that remembers the signal came, then raises KeyboardInterrupt.

    The memory is for where the exception goes astray: raised inside an import's C code,
    CPython can turn it into another error (a TypeError out of ``ImportError``), and a
    library's ``except Exception`` fallback can swallow that. ``interrupt_received()``
    still says a person asked to stop."""
    _received.append(signum)
    raise KeyboardInterrupt


def interrupt_received() -> bool:
    """Whether ``interrupt_and_remember`` has handled a signal in this process."""
    return bool(_received)


@contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Within the block, SIGTERM raises KeyboardInterrupt; the previous handler comes back
    after it. Only the main thread can set handlers: elsewhere nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, raise_keyboard_interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextmanager
def signals_deferred(signals=(signal.SIGINT, signal.SIGTERM)) -> Iterator[None]:
    """Within the block, SIGINT/SIGTERM wait: each one that came is raised again after it,
    with the handlers it had before, so work that must finish (a bag's last transaction) is
    never cut in the middle. Only the main thread can set handlers: elsewhere nothing changes
    (signals are handled on the main thread anyway)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    came: list[int] = []
    previous = {sig: signal.signal(sig, lambda signum, frame: came.append(signum)) for sig in signals}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        for sig in dict.fromkeys(came):
            signal.raise_signal(sig)
