"""The arm's joint messages as plain values: reading commands and states, torques (no ROS).

The nodes hand over a message's fields (``name``, ``effort``, ``position``, ...) as
sequences and get back arrays or a one-line reason to ignore the message, so the
validation is written once and tested without DDS.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from .env import ACT_DIM, JOINT_NAMES


def _in_joint_order(names, values: np.ndarray) -> np.ndarray:
    """``values`` reordered to (shoulder, elbow) when ``names`` lists the joints otherwise."""
    names = list(names)
    if len(names) == ACT_DIM and names != list(JOINT_NAMES) and set(names) == set(JOINT_NAMES):
        return values[[names.index(j) for j in JOINT_NAMES]]
    return values


def action_from_effort(names, effort, allow_empty: bool = False) -> tuple[np.ndarray | None, str | None]:
    """A command's action in [-1, 1] (float32), or (None, why it is ignored).

    An empty effort is (None, None) where ``allow_empty`` (a teleop *yield*).
    """
    if len(effort) == 0 and allow_empty:
        return None, None
    if len(effort) != ACT_DIM:
        return None, f"effort has {len(effort)} values, expected {ACT_DIM} ({', '.join(JOINT_NAMES)})"
    action = _in_joint_order(names, np.array(effort, dtype=np.float64))
    if not np.all(np.isfinite(action)):
        return None, "effort is not finite"
    return np.clip(action, -1.0, 1.0).astype(np.float32), None


def joints_from_state(names, position, velocity) -> tuple[tuple[np.ndarray, np.ndarray] | None, str | None]:
    """(position, velocity) of shoulder and elbow from a JointState's fields, or (None, why)."""
    position, velocity = np.asarray(position, np.float64), np.asarray(velocity, np.float64)
    if len(position) < ACT_DIM or len(velocity) < ACT_DIM:
        return None, f"needs {ACT_DIM} positions and velocities, got {len(position)} and {len(velocity)}"
    names = list(names)
    if len(names) >= ACT_DIM and set(JOINT_NAMES) <= set(names):
        index = [names.index(j) for j in JOINT_NAMES]
        if max(index) >= min(len(position), len(velocity)):
            return None, "names and values differ in length"
        position, velocity = position[index], velocity[index]
    position, velocity = position[:ACT_DIM], velocity[:ACT_DIM]
    if not (np.all(np.isfinite(position)) and np.all(np.isfinite(velocity))):
        return None, "position or velocity is not finite"
    return (position, velocity), None


@lru_cache(maxsize=1)
def actuator_gear() -> np.ndarray:
    """N·m of torque per unit of action, per joint (the model's motor gear)."""
    from .env import build_model

    return np.array(build_model().actuator_gear[:ACT_DIM, 0], np.float64)


def torques_from_action(action) -> np.ndarray:
    """The joint torques (N·m) an action in [-1, 1] commands: what an effort controller takes."""
    return np.clip(np.asarray(action, np.float64), -1.0, 1.0) * actuator_gear()


def action_from_torques(torques) -> tuple[np.ndarray | None, str | None]:
    """The action (float32, clipped to [-1, 1]) for commanded torques (N·m), or (None, why)."""
    torques = np.asarray(torques, np.float64)
    if torques.shape != (ACT_DIM,):
        return None, f"expected {ACT_DIM} torques ({', '.join(JOINT_NAMES)}), got {torques.size}"
    if not np.all(np.isfinite(torques)):
        return None, "torques are not finite"
    return np.clip(torques / actuator_gear(), -1.0, 1.0).astype(np.float32), None
