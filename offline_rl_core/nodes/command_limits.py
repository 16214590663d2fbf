"""The mux's slew limit, as a plain class (no ROS).

A command's values are checked where they are read (``joint_messages``: outside the
controller's range or the task's joint limits is refused and counted, never clipped); what
passes may still jump from one end of the range to the other between two control periods
(a takeover, a policy switched by a new checkpoint). ``SlewLimiter`` lets each value move at
most the task's ``safety.slew`` (action units per command sent) from the one sent before,
so the arm ramps toward a far command instead of jerking to it. Without ``slew`` it passes
everything as it is.

A producer keeps its own commands inside the limits (``within_limits``: the policy node,
its exploration included), so what it sends is never refused.
"""

from __future__ import annotations

import numpy as np


class SlewLimiter:
    def __init__(self, max_step: float | None):
        if max_step is not None and not max_step > 0:
            raise ValueError(f"slew must be > 0, got {max_step}")
        self.max_step = max_step
        self.last: np.ndarray | None = None  # the action sent before
        self.limited = 0  # commands that were ramped

    def limit(self, action: np.ndarray) -> np.ndarray:
        """The action to send now for ``action`` (float32)."""
        action = np.asarray(action, np.float32)
        if self.max_step is not None and self.last is not None:
            step = np.clip(action.astype(np.float64) - self.last, -self.max_step, self.max_step)
            ramped = (self.last + step).astype(np.float32)
            if not np.array_equal(ramped, action):
                self.limited += 1
                action = ramped
        self.last = action.astype(np.float64)
        return action

    def restart(self, action: np.ndarray | None = None) -> None:
        """Forget (or set) the action sent before: after an e-stop the ramp starts at the safe command."""
        self.last = None if action is None else np.asarray(action, np.float64)


def action_bounds(task) -> tuple[np.ndarray, np.ndarray]:
    """The action range whose commands the task's joint limits allow, per command joint
    (an action in [-1, 1]; narrower for a position or velocity interface with limits)."""
    command, safety = task.command, task.safety
    low, high = np.full(len(command.joints), -np.inf), np.full(len(command.joints), np.inf)
    if command.interface == "position" and safety.position_limits:
        bounds = dict(zip(task.state.joints, safety.position_limits))
        for i, joint in enumerate(command.joints):
            low[i], high[i] = bounds.get(joint, (-np.inf, np.inf))
    elif command.interface == "velocity" and safety.velocity_limits:
        bounds = dict(zip(task.state.joints, safety.velocity_limits))
        for i, joint in enumerate(command.joints):
            low[i], high[i] = -bounds.get(joint, np.inf), bounds.get(joint, np.inf)
    scale, offset = np.asarray(command.scale, np.float64), np.asarray(command.offset, np.float64)
    a, b = (low - offset) / scale, (high - offset) / scale  # a negative scale swaps them
    return np.clip(np.minimum(a, b), -1.0, 1.0), np.clip(np.maximum(a, b), -1.0, 1.0)


def within_limits(task, action: np.ndarray, bounds: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """What a producer (the policy node, exploring or not) sends for ``action``: kept inside
    the task's limits, so no consumer has to refuse it."""
    low, high = action_bounds(task) if bounds is None else bounds
    return np.clip(np.asarray(action, np.float32), low, high).astype(np.float32)
