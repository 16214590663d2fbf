"""The command watchdog and the task's safe command, as plain values (no ROS).

A node that consumes commands (the sim in realtime, the mux in realtime, the policy node
when it drives a controller) feeds its :class:`CommandWatchdog` with every valid command and
asks it every control period whether the commands went silent: then it applies the safe
command (``safe_action``) until a valid command comes again. A forward controller, a motor
driver and a zero-order-hold sim all hold the last command for ever; this is what stops
the arm when whoever sent it dies or stalls.

The watchdog arms on the first valid command (before it, the held command is the safe one
already, and a node started before its controller is not at fault). Every silence is a
trip, latched: ``fault()`` reports it on ``~/status`` until ``reset()`` (the ``estop/reset``
service), even after the commands came back.
"""

from __future__ import annotations

import numpy as np

from ..task.spec import TaskSpec


class CommandWatchdog:
    def __init__(self, timeout_s: float):
        if not timeout_s > 0:
            raise ValueError(f"command timeout must be > 0 s, got {timeout_s}")
        self.timeout_s = float(timeout_s)
        self.last_command: float | None = None  # when the latest valid command came; None: not armed
        self.silent = False  # the safe command applies now
        self.trips = 0  # silences since the last reset (latched)
        self.last_trip: float | None = None

    def fed(self, now: float) -> None:
        """A valid command came at ``now`` (seconds on a steady clock)."""
        self.last_command = now
        self.silent = False

    def check(self, now: float) -> bool:
        """Whether the safe command applies at ``now``; a new silence counts as a trip."""
        if self.last_command is None or self.silent:
            return self.silent
        if now - self.last_command > self.timeout_s:
            self.silent = True
            self.trips += 1
            self.last_trip = now
        return self.silent

    def disarm(self) -> None:
        """Wait for the next valid command before watching again (the e-stop engaged: the
        silence that follows is the e-stop's, not a fault)."""
        self.last_command = None
        self.silent = False

    def fault(self) -> dict | None:
        """The latched fault, as ``~/status`` shows it (None: no silence since the last reset)."""
        if not self.trips:
            return None
        return {"trips": self.trips, "silent": self.silent, "timeout_s": self.timeout_s}

    def reset(self) -> None:
        """Clear the latched fault (the safe command still applies while the commands stay silent)."""
        self.trips = 0
        self.last_trip = None


def safe_action(task: TaskSpec, state_position=None) -> np.ndarray | None:
    """The action whose command is the task's safe command (float32, in the command joints' order).

    ``zero``: no effort (or no velocity): ``-offset / scale``, kept inside [-1, 1] where zero
    is outside the controller's range. ``hold``: the command joints' current positions,
    taken from ``state_position`` (the state joints' positions); None when it is not known.
    """
    command = task.command
    if task.safe_command == "hold":
        if state_position is None:
            return None
        index = [task.state.joints.index(j) for j in command.joints]
        values = np.asarray(state_position, np.float64)[index]
    else:
        values = np.zeros(len(command.joints))
    action = (values - np.asarray(command.offset, np.float64)) / np.asarray(command.scale, np.float64)
    return np.clip(action, -1.0, 1.0).astype(np.float32)
