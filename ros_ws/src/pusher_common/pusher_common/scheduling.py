"""Real-time scheduling for the nodes that answer the arm at 50 Hz (sim, policy, mux).

With ``thread_priority`` above 0 a node puts every thread of its process — the executor's
and the DDS middleware's — under ``SCHED_FIFO`` at that priority, as ros2_control's
controller manager does with its ``thread_priority``: a learner or any other work on the
machine then waits for them, not the other way round. It needs the permission to (root,
CAP_SYS_NICE, or an ``rtprio`` limit in /etc/security/limits.conf); without it the node
says so once and runs under the normal scheduler. The nodes block in their wait sets
between messages, so a FIFO thread never spins the core away from the rest.
"""

from __future__ import annotations

import os

from .params import Param

THREAD_PRIORITY = Param(
    "thread_priority", 0, "SCHED_FIFO priority of this node's threads, 1-99 (0: the normal scheduler); needs "
    "permission (root, CAP_SYS_NICE or an rtprio limit), else a warning", low=0, high=99, read_only=True)


def apply_thread_priority(priority: int, logger) -> bool:
    """Put this process's threads under SCHED_FIFO at ``priority`` (0: leave them); True when done."""
    if priority <= 0:
        return False
    if not hasattr(os, "sched_setscheduler"):
        logger.warn(f"thread_priority {priority}: this platform has no SCHED_FIFO; running without it")
        return False
    param = os.sched_param(priority)
    try:
        for tid in os.listdir("/proc/self/task"):
            try:
                os.sched_setscheduler(int(tid), os.SCHED_FIFO, param)
            except ProcessLookupError:
                continue  # a thread that ended meanwhile
    except PermissionError:
        logger.warn(f"thread_priority {priority}: not permitted to use SCHED_FIFO (needs root, CAP_SYS_NICE or an "
                    "rtprio limit in /etc/security/limits.conf); running under the normal scheduler")
        return False
    logger.info(f"threads under SCHED_FIFO priority {priority}")
    return True
