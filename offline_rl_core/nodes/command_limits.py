"""The mux's slew limit, as a plain class (no ROS).

A command's values are checked where they are read (``joint_messages``: outside the
controller's range or the task's joint limits is refused and counted, never clipped); what
passes may still jump from one end of the range to the other between two control periods
(a takeover, a policy switched by a new checkpoint). ``SlewLimiter`` lets each value move at
most the task's ``safety.slew`` (action units per command sent) from the one sent before,
so the arm ramps toward a far command instead of jerking to it. Without ``slew`` it passes
everything as it is.
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
