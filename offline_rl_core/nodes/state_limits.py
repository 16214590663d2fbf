"""Soft joint limits on the measured state, for an effort-controlled arm (no ROS).

A position or velocity command is checked against the task's joint limits as it is read
(``joint_messages``); an effort command says nothing of where the arm will go, so the limits
are checked against where it is. As ros2_control's soft joint limits do: when a joint's
measured position is beyond ``safety.position_limits`` (or its speed beyond
``safety.velocity_limits``), a command whose effort on that joint pushes it further out
(the same sign as the way out) is refused and counted as ``beyond limits``; one that
pushes it back, or applies none, is taken, so the arm can always be brought back inside.
"""

from __future__ import annotations

import numpy as np

from ..common.rejections import Rejection


class StateLimits:
    def __init__(self, task):
        command, safety, state = task.command, task.safety, task.state
        self.joints = tuple(command.joints)
        index = {joint: i for i, joint in enumerate(state.joints)}
        self.state_index = np.array([index.get(j, -1) for j in self.joints])
        n = len(self.joints)
        self.low, self.high, self.speed = np.full(n, -np.inf), np.full(n, np.inf), np.full(n, np.inf)
        effort = command.interface == "effort"
        for i, j in enumerate(self.state_index):
            if j < 0:
                continue
            if effort and safety.position_limits:
                self.low[i], self.high[i] = safety.position_limits[j]
            if effort and safety.velocity_limits:
                self.speed[i] = safety.velocity_limits[j]
        self.scale = np.asarray(command.scale, np.float64)
        self.offset = np.asarray(command.offset, np.float64)
        self.active = bool(np.isfinite(self.low).any() or np.isfinite(self.high).any() or np.isfinite(self.speed).any())

    def check(self, action: np.ndarray, positions, velocities) -> Rejection | None:
        """None where ``action`` may be applied at the measured ``positions``/``velocities``
        (per state joint); else why it is refused."""
        if not self.active:
            return None
        effort = self.offset + self.scale * np.asarray(action, np.float64)
        known = self.state_index >= 0
        at = np.where(known, self.state_index, 0)
        q = np.where(known, np.asarray(positions, np.float64)[at], 0.0)
        v = np.where(known, np.asarray(velocities, np.float64)[at], 0.0)
        for i, joint in enumerate(self.joints):
            if q[i] > self.high[i] and effort[i] > 0 or q[i] < self.low[i] and effort[i] < 0:
                return Rejection("beyond limits", f"effort {effort[i]:.6g} on {joint} pushes it further beyond its "
                                                  f"position limits [{self.low[i]:g}, {self.high[i]:g}] (at {q[i]:.6g}; "
                                                  "safety.position_limits): refused; one back inside is taken")
            if abs(v[i]) > self.speed[i] and effort[i] * v[i] > 0:
                return Rejection("beyond limits", f"effort {effort[i]:.6g} on {joint} speeds it up beyond ±{self.speed[i]:g} "
                                                  f"(at {v[i]:.6g}; safety.velocity_limits): refused; one that slows "
                                                  "it is taken")
        return None
