"""Spin an executor with a fast path for messages (the lockstep loop's sim and recorder).

rclpy's executor rebuilds its wait set in Python from every entity of its nodes (the
parameter services, QoS event handlers, timers, ...) on each wake-up, and wakes about
twice per callback: that cost per message, not DDS, bounds lockstep recording
(bench/RESULTS.md has the figures). Here one wait set, made once, holds the subscriptions,
timers and services; ready subscriptions are taken and their callbacks called directly,
while a ready timer or service is run by the executor itself (``spin_once``), as is the
rest (guard conditions, clients, QoS events), polled every ``POLL_S``. (rclpy's
EventsExecutor, which does this in C++, hangs with these nodes.)

The wait set comes from rclpy's private C binding (as rclpy's own ``wait_for_message``
does). Where an rclpy lacks it, or with ``PUSHER_RL_SPIN=executor``, the public
``executor.spin_until_future_complete`` runs instead: slower, the same behaviour.
"""

from __future__ import annotations

import os
import time

from rclpy.executors import Executor, ExternalShutdownException
from rclpy.subscription import Subscription
from rclpy.task import Future

from .shutdown import quiet_signals

try:  # private API: kept only while this rclpy has it
    from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
    from rclpy.signals import SignalHandlerGuardCondition

    _FAST_PATH = hasattr(_rclpy, "WaitSet") and hasattr(_rclpy.WaitSet, "get_ready_entities")
except ImportError:
    _FAST_PATH = False

POLL_S = 0.1


def fast_path_available() -> bool:
    """Whether the private wait-set API is here and not switched off (``PUSHER_RL_SPIN=executor``)."""
    return _FAST_PATH and os.environ.get("PUSHER_RL_SPIN", "fast") != "executor"


def spin_until_future_complete(executor: Executor, future: Future) -> None:
    """Spin until ``future`` completes, as the executor's method of that name, fast for messages.

    For nodes whose subscriptions, timers and services all exist when it is called; a
    callback that takes two arguments gets the message's info too (as the executor gives
    it: source and received timestamps). Raises ExternalShutdownException when the context shuts down
    (Ctrl-C, SIGTERM), as the executor does.
    """
    if not fast_path_available():
        executor.spin_until_future_complete(future)
        return
    context = executor.context
    nodes = executor.get_nodes()
    subscriptions = [sub for node in nodes for sub in node.subscriptions]
    timers = [timer for node in nodes for timer in node.timers]
    services = [srv for node in nodes for srv in node.services]
    sigint = SignalHandlerGuardCondition(context)  # a signal wakes the wait
    wait_set = _rclpy.WaitSet(len(subscriptions), 1, len(timers), 0, len(services), 0, context.handle)
    next_poll = 0.0
    try:
        while not future.done():
            wait_set.clear_entities()
            for sub in subscriptions:
                wait_set.add_subscription(sub.handle)
            for timer in timers:
                wait_set.add_timer(timer.handle)
            for srv in services:
                wait_set.add_service(srv.handle)
            wait_set.add_guard_condition(sigint.handle)
            wait_set.wait(int(POLL_S * 1e9))
            if not context.ok():
                raise ExternalShutdownException()
            ready = wait_set.get_ready_entities("subscription")
            for sub in subscriptions:
                # none after the callback that completes the future, as with the executor
                if sub.handle.pointer in ready and not future.done():
                    taken = sub.handle.take_message(sub.msg_type, sub.raw)
                    if taken is not None:  # (message, info), or None if it was gone
                        if getattr(sub, "_callback_type", None) == Subscription.CallbackType.WithMessageInfo:
                            sub.callback(*taken)
                        else:
                            sub.callback(taken[0])
            if future.done():
                return
            now = time.monotonic()
            if wait_set.get_ready_entities("timer") or wait_set.get_ready_entities("service") or now >= next_poll:
                next_poll = now + POLL_S
                executor.spin_once(timeout_sec=0)
    finally:
        if not context.ok():
            # a signal shut the context down: rclpy's signal thread may still be triggering
            # the guard conditions it had registered, this one included (``shutdown``)
            quiet_signals()
        sigint.destroy()


def spin_node_fast(executor: Executor, node) -> None:
    """``run_node``'s ``spin`` for a node with a ``finished`` future, on the fast path."""
    spin_until_future_complete(executor, node.finished)
