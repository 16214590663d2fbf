"""Messages a node refuses: why, how many, and when to say so (no ROS).

Every check of an incoming message (``joint_messages``, ``pairing``, the learner's
``check_row``) returns a :class:`Rejection`: the one-line detail for the log, carrying a
*reason* from a fixed vocabulary (:data:`REASONS`), so a node's counts stay a small, stable
set of keys however wild its input. A node holds one :class:`RejectionCounter` and reports
its counts on ``~/status`` (``pusher_common.status``).

A flood of bad messages must not flood the log: the counter says when a warning is due,
once per reason at most every ``throttle_s`` seconds, and the warning carries the count.
"""

from __future__ import annotations

import time
from typing import Callable

REASONS = (
    "non-finite",       # NaN or infinity in a value
    "out of range",     # finite, but beyond anything the arm or the task can mean
    "wrong length",     # an array of the wrong size, or names and values that differ in length
    "unknown joints",   # joint names that are not the arm's
    "duplicate joints",  # a joint named twice
    "bad stamp",        # not a valid time (negative, or nanoseconds >= 1 s)
    "stale stamp",      # older than what the node already acts on
    "future stamp",     # a jump ahead that nothing confirmed
    "unpaired",         # a command without a stamp that answers no state (lockstep)
    "bad layout",       # a multi-array whose layout is not the one expected
    "unknown source",   # a transition's source code is none of the known ones
    "bad weights",      # a weights message that is not a loadable policy for this task
    "unsigned weights",  # a weights message not signed by this session's learner
    "weights version",  # signed weights that are unversioned or too far past the acting version
    "bad checkpoint",   # a checkpoint file replaced by one that does not load
    "non-finite action",  # the policy's output for a state was not finite: no answer sent
    "policy error",     # the policy raised on a state (a bug or a checkpoint no check caught): no answer sent
    "beyond limits",    # a command outside the controller's range or the task's joint limits: refused, not clipped
    "estop",            # a command or row that came while the e-stop is engaged: not acted on, not trained on
    "bad label",        # an episode label that is not one, or names no episode that can end (data.episode_labels)
)


class Rejection(str):
    """Why one message was refused: the detail text (it *is* the string) and its ``reason``."""

    reason: str

    def __new__(cls, reason: str, detail: str):
        if reason not in REASONS:
            raise ValueError(f"unknown rejection reason {reason!r}")
        self = super().__new__(cls, detail)
        self.reason = reason
        return self

    def __reduce__(self):
        return Rejection, (self.reason, str(self))


class RejectionCounter:
    """Rejections counted by reason, with a warning line due at most every ``throttle_s`` per reason."""

    def __init__(self, throttle_s: float = 2.0, clock: Callable[[], float] = time.monotonic):
        self.throttle_s = float(throttle_s)
        self.clock = clock
        self.counts: dict[str, int] = {}
        self._last_warned: dict[str, tuple[float, int]] = {}  # reason -> (when, count then)

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def add(self, rejection: Rejection) -> None:
        self.counts[rejection.reason] = self.counts.get(rejection.reason, 0) + 1

    def warning(self, where: str, rejection: Rejection) -> str | None:
        """The log line for a rejection just counted, or None while its reason is throttled."""
        reason, count = rejection.reason, self.counts.get(rejection.reason, 0)
        now = self.clock()
        last = self._last_warned.get(reason)
        if last is not None and now - last[0] < self.throttle_s:
            return None
        unsaid = count - 1 - (last[1] if last is not None else 0)
        self._last_warned[reason] = (now, count)
        more = f", {unsaid} not shown" if unsaid > 0 else ""
        return f"ignoring {where}: {rejection} ({reason}: {count} so far{more})"

    def reject(self, where: str, rejection: Rejection) -> str | None:
        """Count ``rejection``; return its warning line when one is due."""
        self.add(rejection)
        return self.warning(where, rejection)
