"""The arm's joint messages as plain values: reading commands and states, torques (no ROS).

The nodes hand over a message's fields (``name``, ``effort``, ``position``, ...) as
sequences and get back arrays or a :class:`~offline_rl_core.common.rejections.Rejection` (why the
message is ignored), so the validation is written once and tested without DDS.

Joint names: an empty ``name`` means the values are in the arm's order (``joints``: the
task's state or command joints; by default pusher_reach's shoulder, elbow); otherwise every
joint is named once, as many names as values, and all of the arm's joints are among them
(a state may name more joints: the arm's are picked out, in the arm's order).
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


def joint_index(names, n_values: int, what: str,
                joints: tuple[str, ...] = JOINT_NAMES) -> tuple[list[int] | None, Rejection | None]:
    """Where each of ``joints`` is among ``n_values`` values named ``names``."""
    names = list(names)
    if not names:
        if n_values != len(joints):
            return None, Rejection("wrong length",
                                   f"{n_values} {what} without joint names, expected {len(joints)} ({_arm(joints)})")
        return list(range(len(joints))), None
    if len(names) != n_values:
        return None, Rejection("wrong length", f"{len(names)} joint names but {n_values} {what}")
    if len(set(names)) != len(names):
        return None, Rejection("duplicate joints", f"a joint is named twice in {_shown(names)}")
    missing = [j for j in joints if j not in names]
    if missing:
        return None, Rejection("unknown joints", f"joint names {_shown(names)} lack {_arm(missing)}")
    return [names.index(j) for j in joints], None


def _arm(joints) -> str:
    """Joint names as an error line shows them (a few)."""
    joints = list(joints)
    return ", ".join(joints[:8]) + (f", ... ({len(joints)} joints)" if len(joints) > 8 else "")


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
                       joints: tuple[str, ...] = JOINT_NAMES) -> tuple[np.ndarray | None, Rejection | None]:
    """A command's action in [-1, 1] (float32, clipped, in ``joints`` order: the task's
    command joints), or (None, why it is ignored).

    An empty effort is (None, None) where ``allow_empty`` (a teleop *yield*).
    """
    if len(effort) == 0 and allow_empty:
        return None, None
    if len(effort) != len(joints):
        return None, Rejection("wrong length", f"effort has {len(effort)} values, expected {len(joints)} "
                                               f"({_arm(joints)})")
    index, problem = joint_index(names, len(effort), "efforts", joints)
    if problem:
        return None, problem
    action = np.array(effort, dtype=np.float64)[index]
    if not np.all(np.isfinite(action)):
        return None, Rejection("non-finite", "effort is not finite")
    return np.clip(action, -1.0, 1.0).astype(np.float32), None


def joints_from_state(names, position, velocity, joints: tuple[str, ...] = JOINT_NAMES,
                      velocity_optional: bool = False) -> tuple[tuple[np.ndarray, np.ndarray] | None, Rejection | None]:
    """(position, velocity) of ``joints`` (the task's state joints, in that order) from a
    JointState's fields, or (None, why). ``velocity_optional``: a state without velocities
    (a position-only arm) reads as zero velocities."""
    position, velocity = np.asarray(position, np.float64), np.asarray(velocity, np.float64)
    if velocity_optional and len(velocity) == 0:
        velocity = np.zeros_like(position)
    if len(position) != len(velocity):
        return None, Rejection("wrong length", f"{len(position)} positions but {len(velocity)} velocities")
    index, problem = joint_index(names, len(position), "positions", joints)
    if problem:
        return None, problem
    position, velocity = position[index], velocity[index]
    problem = _bad_values(np.concatenate([position, velocity]), "position or velocity is")
    if problem:
        return None, problem
    return (position, velocity), None


def point_xy(x: float, y: float, what: str = "point") -> tuple[np.ndarray | None, Rejection | None]:
    """A target's or fingertip's planar position, or (None, why)."""
    return checked_vector([x, y], what)


def checked_vector(values, what: str = "point") -> tuple[np.ndarray | None, Rejection | None]:
    """A goal's or tracked point's values (float64), or (None, why): finite and within range."""
    vector = np.array(values, np.float64).reshape(-1)
    problem = _bad_values(vector, f"{what} is")
    return (None, problem) if problem else (vector, None)


def command_from_action(command, action) -> np.ndarray:
    """What the controller takes for an action in [-1, 1] (``command``: a task's
    ``CommandSpec``): ``offset + scale * action`` per joint, in the controller's joint order
    (pusher_reach: torques in N·m, the action times the motors' 0.5 N·m gear)."""
    action = np.clip(np.asarray(action, np.float64), -1.0, 1.0)
    return np.asarray(command.scale, np.float64) * action + np.asarray(command.offset, np.float64)


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
                                               f"({_arm(joints)}, the controller's joints)")
    index, problem = joint_index(names, values.size, "values", joints)
    if problem:
        return None, problem
    values = values[index]
    if not np.all(np.isfinite(values)):
        return None, Rejection("non-finite", "command is not finite")
    action = (values - np.asarray(task.command.offset)) / np.asarray(task.command.scale)
    return np.clip(action, -1.0, 1.0).astype(np.float32), None
