"""A person at a gamepad (``sensor_msgs/Joy``, as the standard ``joy`` node publishes it) as the corrector.

The mapping (a YAML file, :func:`load_mapping`; the defaults: an Xbox pad under the ``joy``
node, ``ros_ws/src/corrections/config/gamepad_xbox.yaml`` documents them):

- ``deadman``: the button that takes over while held; released, the policy has the arm;
- ``mode``: ``joint`` (default) or ``cartesian``;
- ``axes``: joint mode: one entry per command joint, in ``robot.command.joints`` order: the
  axis index and a scale (negative flips it); the action is ``scale * axis`` clipped to the
  task's action range [-1, 1] (efforts or velocities, as the task's command interface is);
  joints past the list, or given ``null``, are held at 0. Cartesian mode: one entry per axis
  of the tracked point ``point`` (default: the task's first, pusher_reach's fingertip: x, y;
  pusher7_reach's: x, y, z), the scale in metres the point is asked to move per state at
  full stick; the action moving it there comes from damped least squares on the task's
  Jacobian (``offline_rl_core.task.envs.task_jog``), clipped to [-1, 1]; a stick at rest
  asks the point to stay, so the arm brakes; ``deadzone``: smaller readings are 0;
- ``success`` / ``failure``: buttons that label the current episode (pressed: one label per
  press, on ``episode_label`` as ``{"label": "success"}``).

A Joy message with too few axes or buttons for the mapping, or a non-finite axis, is
refused (a :class:`~offline_rl_core.common.rejections.Rejection`) and changes nothing.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..common.errors import UserError
from ..common.rejections import Rejection
from ..task.spec import TaskSpec

LABEL_TOPIC = "episode_label"  # std_msgs/String, JSON {"label": "success" | "failure"}
LABELS = ("success", "failure")

# The joy node's layout of an Xbox pad (SDL's game controller order): buttons A=0 B=1 X=2
# Y=3 ... LB=9 RB=10; axes left stick x=0 y=1, right stick x=2 y=3 (left and up positive).
XBOX_DEADMAN = 9  # LB
XBOX_SUCCESS = 0  # A
XBOX_FAILURE = 1  # B
XBOX_AXES = ((0, -1.0), (2, -1.0), (1, 1.0), (3, 1.0))  # stick right -> positive action
MODES = ("joint", "cartesian")
FIELDS = ("deadman", "mode", "point", "axes", "deadzone", "success", "failure")


@dataclass(frozen=True)
class GamepadMapping:
    deadman: int = XBOX_DEADMAN
    axes: tuple[tuple[int, float] | None, ...] = XBOX_AXES
    deadzone: float = 0.05
    success: int | None = XBOX_SUCCESS
    failure: int | None = XBOX_FAILURE
    mode: str = "joint"
    point: str | None = None  # cartesian: the tracked point the sticks move (None: the task's first)
    source: str = "built-in Xbox defaults"

    @property
    def buttons_needed(self) -> int:
        return 1 + max(b for b in (self.deadman, self.success, self.failure) if b is not None)

    @property
    def axes_needed(self) -> int:
        return 1 + max((a[0] for a in self.axes if a is not None), default=-1)


def load_mapping(path: str | Path | None) -> GamepadMapping:
    """The mapping of a YAML file (None or empty: the Xbox defaults); UserError naming the field."""
    if not path:
        return GamepadMapping()
    path = Path(path)
    try:
        import yaml

        doc = yaml.safe_load(path.read_text()) or {}
    except OSError as exc:
        raise UserError(f"{path}: cannot read the gamepad mapping: {exc.strerror or exc}") from None
    except yaml.YAMLError as exc:
        raise UserError(f"{path}: not YAML: {str(exc).splitlines()[0]}") from None
    if not isinstance(doc, dict):
        raise UserError(f"{path}: expected a mapping of {', '.join(FIELDS)}")
    unknown = sorted(set(doc) - set(FIELDS))
    if unknown:
        raise UserError(f"{path}: unknown field {unknown[0]!r} (known: {', '.join(FIELDS)})")
    defaults = GamepadMapping()
    mode = doc.get("mode", defaults.mode)
    if mode not in MODES:
        raise UserError(f"{path}: mode: expected one of {', '.join(MODES)}, got {mode!r}")
    point = doc.get("point")
    if point is not None and (mode != "cartesian" or not isinstance(point, str) or not point):
        raise UserError(f"{path}: point: expected the name of a tracked point, with mode: cartesian, got {point!r}")

    def button(name, optional=True):
        value = doc.get(name, getattr(defaults, name))
        if value is None and optional:
            return None
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise UserError(f"{path}: {name}: expected a button index (an integer >= 0), got {value!r}")
        return value

    axes = doc.get("axes", defaults.axes)
    if not isinstance(axes, (list, tuple)):
        raise UserError(f"{path}: axes: expected a list, one {{axis: INDEX, scale: S}} (or null) per command joint")
    parsed: list[tuple[int, float] | None] = []
    for i, entry in enumerate(axes):
        if entry is None:
            parsed.append(None)
            continue
        if isinstance(entry, (list, tuple)) and len(entry) == 2:
            entry = {"axis": entry[0], "scale": entry[1]}
        if not isinstance(entry, dict) or set(entry) - {"axis", "scale"} or "axis" not in entry:
            raise UserError(f"{path}: axes[{i}]: expected {{axis: INDEX, scale: S}} or null, got {entry!r}")
        axis, scale = entry["axis"], entry.get("scale", 1.0)
        if isinstance(axis, bool) or not isinstance(axis, int) or axis < 0:
            raise UserError(f"{path}: axes[{i}].axis: expected an axis index (an integer >= 0), got {axis!r}")
        if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not math.isfinite(scale):
            raise UserError(f"{path}: axes[{i}].scale: expected a finite number, got {scale!r}")
        parsed.append((axis, float(scale)))
    deadzone = doc.get("deadzone", defaults.deadzone)
    if isinstance(deadzone, bool) or not isinstance(deadzone, (int, float)) or not 0 <= deadzone < 1:
        raise UserError(f"{path}: deadzone: expected a number in [0, 1), got {deadzone!r}")
    if mode == "cartesian" and "axes" not in doc:
        raise UserError(f"{path}: axes: mode: cartesian needs its axes, one {{axis: INDEX, scale: METRES}} per "
                        "axis of the point")
    return GamepadMapping(deadman=button("deadman", optional=False), axes=tuple(parsed), deadzone=float(deadzone),
                          success=button("success"), failure=button("failure"), mode=mode, point=point,
                          source=str(path))


@dataclass
class JoyEvents:
    """What one Joy message did: labels to publish (one per button press)."""

    labels: list[str] = field(default_factory=list)


class GamepadTeleop:
    """The held action from the latest Joy message; ``decide`` answers a state as the corrector asks.

    Cartesian mode: ``jog(positions, velocities, delta) -> action`` and ``dims`` (the point's
    axes) turn the sticks' ``delta`` into each state's action (:meth:`for_task` builds them).
    """

    def __init__(self, mapping: GamepadMapping, act_dim: int, jog=None, dims: int = 0):
        if (mapping.mode == "cartesian") != (jog is not None):
            raise ValueError("a cartesian mapping needs a jog, a joint mapping none")
        self.mapping = mapping
        self.act_dim = act_dim
        self.jog, self.dims = jog, dims
        self.action = np.zeros(act_dim, np.float32)
        self.delta = np.zeros(dims, np.float64)  # cartesian: the step asked of the point
        self.active = False
        self.labels_sent = {label: 0 for label in LABELS}
        self._pressed: dict[str, bool] = {label: False for label in LABELS}

    def on_joy(self, axes, buttons) -> tuple[JoyEvents | None, Rejection | None]:
        m = self.mapping
        axes, buttons = np.asarray(axes, np.float64), list(buttons)
        if len(axes) < m.axes_needed:
            return None, Rejection("wrong length", f"{len(axes)} axes, the gamepad mapping ({m.source}) reads "
                                                   f"axis {m.axes_needed - 1}")
        if len(buttons) < m.buttons_needed:
            return None, Rejection("wrong length", f"{len(buttons)} buttons, the gamepad mapping ({m.source}) "
                                                   f"reads button {m.buttons_needed - 1}")
        if not np.all(np.isfinite(axes)):
            return None, Rejection("non-finite", "a Joy axis is not finite")
        values = np.zeros(self.dims if self.jog else self.act_dim, np.float64)
        for k, entry in enumerate(m.axes[: len(values)]):
            if entry is not None:
                value = float(axes[entry[0]])
                values[k] = 0.0 if abs(value) < m.deadzone else entry[1] * value
        if self.jog:
            self.delta = values
        else:
            self.action = np.clip(values, -1.0, 1.0).astype(np.float32)
        self.active = bool(buttons[m.deadman])
        events = JoyEvents()
        for label, index in (("success", m.success), ("failure", m.failure)):
            pressed = index is not None and bool(buttons[index])
            if pressed and not self._pressed[label]:  # a press, not a hold
                events.labels.append(label)
                self.labels_sent[label] += 1
            self._pressed[label] = pressed
        return events, None

    @classmethod
    def for_task(cls, mapping: GamepadMapping, task: TaskSpec) -> "GamepadTeleop":
        """The teleop of ``task``'s arm; cartesian: UserError when the task has no Jacobian for the point."""
        if mapping.mode != "cartesian":
            return cls(mapping, task.act_dim)
        from ..task.envs import task_jog

        jog, dims = task_jog(task, mapping.point)
        return cls(mapping, task.act_dim, jog, dims)

    def decide(self, qpos=None, qvel=None, goal=None) -> np.ndarray | None:
        """The action while the dead-man button is held, else None (the policy keeps the arm).
        Cartesian: the action that moves the point by the sticks' step from this state
        (zero where the state gives no finite answer: never NaN)."""
        if not self.active:
            return None
        if not self.jog:
            return self.action.copy()
        action = np.asarray(self.jog(qpos, qvel, self.delta), np.float32)
        if not np.all(np.isfinite(action)):
            return np.zeros(self.act_dim, np.float32)
        return np.clip(action, -1.0, 1.0)


def label_json(label: str) -> str:
    """The ``episode_label`` message's text (``offline_rl_core.data.episode_labels`` reads it)."""
    if label not in LABELS:
        raise ValueError(f"unknown label {label!r}")
    return json.dumps({"label": label})
