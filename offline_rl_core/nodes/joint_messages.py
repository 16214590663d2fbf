"""The arm's joint messages as plain values: reading commands and states, torques (no ROS).

The nodes hand over a message's fields (``name``, ``effort``, ``position``, ...) as
sequences and get back arrays or a :class:`~offline_rl_core.common.rejections.Rejection` (why the
message is ignored), so the validation is written once and tested without DDS.

Joint names: an empty ``name`` means the values are in the arm's order (shoulder, elbow);
otherwise every joint is named once, as many names as values, and both of the arm's joints
are among them (a state may name more joints: the arm's are picked out).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ..task.pusher_reach import ACT_DIM, JOINT_NAMES
from ..common.rejections import Rejection

# No joint angle (rad), joint speed (rad/s) or planar position (m) of this arm comes near
# it: a finite value beyond it is garbage, and the policy's network would turn it into one.
VALUE_LIMIT = 1e4
_ARM = ", ".join(JOINT_NAMES)


def _joint_index(names, n_values: int, what: str, joints=JOINT_NAMES) -> tuple[list[int] | None, Rejection | None]:
    """Where ``joints`` (default: shoulder and elbow) are among ``n_values`` values named ``names``."""
    names = list(names)
    arm = _ARM if joints is JOINT_NAMES else _listed(joints)
    if not names:
        if n_values != len(joints):
            return None, Rejection("wrong length",
                                   f"{n_values} {what} without joint names, expected {len(joints)} ({arm})")
        return list(range(len(joints))), None
    if len(names) != n_values:
        return None, Rejection("wrong length", f"{len(names)} joint names but {n_values} {what}")
    if len(set(names)) != len(names):
        return None, Rejection("duplicate joints", f"a joint is named twice in {_shown(names)}")
    if not set(joints) <= set(names):
        return None, Rejection("unknown joints", f"joint names {_shown(names)} lack {arm}")
    return [names.index(j) for j in joints], None


def _listed(joints) -> str:
    """A task's joints for a log line: all of a short list, else the first few and a count."""
    joints = list(joints)
    return ", ".join(joints) if len(joints) <= 4 else f"{', '.join(joints[:3])}, ... ({len(joints)} joints)"


def _shown(names: list) -> str:
    """Names as a log line shows them: a few, each cut short (fuzzed names can be anything)."""
    text = ", ".join(repr(str(n)[:24]) for n in names[:4])
    return f"[{text}{', ...' if len(names) > 4 else ''}]"


def _bad_values(values: np.ndarray, what: str) -> Rejection | None:
    if not np.all(np.isfinite(values)):
        return Rejection("non-finite", f"{what} not finite")
    if np.any(np.abs(values) > VALUE_LIMIT):
        return Rejection("out of range", f"{what} beyond ±{VALUE_LIMIT:g}")
    return None


def action_from_effort(names, effort, allow_empty: bool = False,
                       joints=JOINT_NAMES) -> tuple[np.ndarray | None, Rejection | None]:
    """A command's action in [-1, 1] (float32, clipped), or (None, why it is ignored).

    ``joints``: the action's joints, in order (a task's ``command.joints``; default the
    pusher's). An empty effort is (None, None) where ``allow_empty`` (a teleop *yield*).
    """
    if len(effort) == 0 and allow_empty:
        return None, None
    if len(effort) != len(joints):
        arm = _ARM if joints is JOINT_NAMES else _listed(joints)
        return None, Rejection("wrong length", f"effort has {len(effort)} values, expected {len(joints)} ({arm})")
    index, problem = _joint_index(names, len(effort), "efforts", joints)
    if problem:
        return None, problem
    action = np.array(effort, dtype=np.float64)[index]
    if not np.all(np.isfinite(action)):
        return None, Rejection("non-finite", "effort is not finite")
    return np.clip(action, -1.0, 1.0).astype(np.float32), None


def joints_from_state(names, position, velocity) -> tuple[tuple[np.ndarray, np.ndarray] | None, Rejection | None]:
    """(position, velocity) of shoulder and elbow from a JointState's fields, or (None, why)."""
    position, velocity = np.asarray(position, np.float64), np.asarray(velocity, np.float64)
    if len(position) != len(velocity):
        return None, Rejection("wrong length", f"{len(position)} positions but {len(velocity)} velocities")
    index, problem = _joint_index(names, len(position), "positions")
    if problem:
        return None, problem
    position, velocity = position[index], velocity[index]
    problem = _bad_values(np.concatenate([position, velocity]), "position or velocity is")
    if problem:
        return None, problem
    return (position, velocity), None


def point_xy(x: float, y: float, what: str = "point") -> tuple[np.ndarray | None, Rejection | None]:
    """A target's or fingertip's planar position, or (None, why)."""
    xy = np.array([x, y], np.float64)
    problem = _bad_values(xy, f"{what} is")
    return (None, problem) if problem else (xy, None)


@lru_cache(maxsize=1)
def actuator_gear() -> np.ndarray:
    """N·m of torque per unit of action, per joint (the model's motor gear)."""
    from ..task.pusher_reach import build_model

    return np.array(build_model().actuator_gear[:ACT_DIM, 0], np.float64)


def torques_from_action(action) -> np.ndarray:
    """The joint torques (N·m) an action in [-1, 1] commands: what an effort controller takes."""
    return np.clip(np.asarray(action, np.float64), -1.0, 1.0) * actuator_gear()


def action_from_torques(torques) -> tuple[np.ndarray | None, Rejection | None]:
    """The action (float32, clipped to [-1, 1]) for commanded torques (N·m), or (None, why)."""
    torques = np.asarray(torques, np.float64).reshape(-1)
    if torques.shape != (ACT_DIM,):
        return None, Rejection("wrong length", f"expected {ACT_DIM} torques ({_ARM}), got {torques.size}")
    if not np.all(np.isfinite(torques)):
        return None, Rejection("non-finite", "torques are not finite")
    return np.clip(torques / actuator_gear(), -1.0, 1.0).astype(np.float32), None


def action_from_command(task, values, names=()) -> tuple[np.ndarray | None, Rejection | None]:
    """A controller's command as the action: ``(command - offset) / scale``, float32, clipped
    to [-1, 1] (the controller's limits), or (None, why it is refused).

    ``values``: in the task's units (``command.interface``), in ``command.joints`` order, as a
    forward_command_controller takes them (a Float64MultiArray), or named by ``names`` (a
    JointState command). A command of another length is refused, never cut or padded.
    """
    joints = task.command.joints
    values = np.asarray(values, np.float64).reshape(-1)
    if not len(names) and values.size != len(joints):
        return None, Rejection("wrong length", f"{values.size} values, expected {len(joints)} "
                                               f"({_listed(joints)}, the controller's joints)")
    index, problem = _joint_index(names, values.size, "values", joints)
    if problem:
        return None, problem
    values = values[index]
    if not np.all(np.isfinite(values)):
        return None, Rejection("non-finite", "command is not finite")
    action = (values - np.asarray(task.command.offset)) / np.asarray(task.command.scale)
    return np.clip(action, -1.0, 1.0).astype(np.float32), None
