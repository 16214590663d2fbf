"""The spec of a raw-topic dataset: which topics of a bag hold the arm's state, its
commands and its goal, and how to join them into transitions.

A YAML file (see ``bags/pusher_topics.yaml``, whose values are the defaults here); every
field is optional. ``load_spec(path)`` checks it and raises UserError, one line naming the
file and the field, for anything unknown or out of range.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

from ...task.pusher_reach import CONTROL_HZ, JOINT_NAMES
from ...common.errors import UserError
from ..transitions import SOURCE_NAMES

SOURCE_AUTO = "auto"
MATCH_MODES = ("exact", "nearest")
STAMP_SOURCES = ("header", "receive")
REWARD_RULES = ("pusher",)
SOURCE_CHOICES = (SOURCE_AUTO, *SOURCE_NAMES.values())
# The sim's command inputs: plain, and one per source (who acted is the topic).
SIM_COMMAND_TOPICS = ("/pusher/command", *(f"/pusher/command/{name}" for name in SOURCE_NAMES.values()))


@dataclass(frozen=True)
class TopicSpec:
    """What to read from a bag and how to turn it into transitions (times in seconds)."""

    # Where the stamps come from: each message's header, or the bag's receive times
    # (needed when the command type has no header, e.g. std_msgs/Float64MultiArray).
    stamps: str = "header"
    state_topic: str = "/pusher/state"  # sensor_msgs/msg/JointState
    joints: tuple[str, ...] = JOINT_NAMES  # the state's joints, in the observation's order
    # JointState (effort) or std_msgs/msg/Float64MultiArray; those of them the bag holds
    command_topics: tuple[str, ...] = SIM_COMMAND_TOPICS
    # The order of a Float64MultiArray's values (a forward_command_controller's `joints`);
    # also of a JointState command that names no joints.
    command_joints: tuple[str, ...] = JOINT_NAMES
    command_scale: float = 1.0  # action = scale * command value (1 / gear for torques in N·m)
    # auto: as the sim reads it, the command topic's last name when that names a source
    # (pusher/command/expert ...), else a source named in header.frame_id (older bags), else
    # policy; or a fixed source name for every command
    source: str = SOURCE_AUTO
    target_topic: str = "/pusher/target"  # geometry_msgs/msg/PointStamped
    fingertip_topic: str | None = "/pusher/fingertip"  # PointStamped; planar kinematics when absent
    match: str = "nearest"  # exact: same stamp; nearest: the nearest within `tolerance`
    tolerance: float = 0.005
    control_period: float = 1.0 / CONTROL_HZ  # next_obs: the state one period after obs ...
    period_tolerance: float = 0.005  # ... give or take this
    reset_topic: str | None = None  # any type: a message starts a new episode
    target_change: float = 0.0  # m: a target moved further than this starts a new episode
    max_gap: float = 1.0  # s between consecutive states: a longer gap starts a new episode
    reward: str = "pusher"  # offline_rl_core.task.pusher_reach.score_steps
    terminate_on_success: bool = False
    path: Path | None = field(default=None, compare=False)  # the file it came from

    @property
    def join_tolerance_ns(self) -> int:
        return 0 if self.match == "exact" else round(self.tolerance * 1e9)

    @property
    def period_ns(self) -> int:
        return round(self.control_period * 1e9)

    @property
    def period_tolerance_ns(self) -> int:
        return round(self.period_tolerance * 1e9)

    @property
    def max_gap_ns(self) -> int:
        return round(self.max_gap * 1e9)

    def describe(self) -> dict:
        """The spec as plain values (for reports and metadata)."""
        return {f.name: (list(v) if isinstance(v, tuple) else v) for f in fields(self) if f.name != "path"
                for v in [getattr(self, f.name)]}


# YAML layout: section -> {key: dataclass field}; top-level keys map to fields directly.
_SECTIONS: dict[str, dict[str, str]] = {
    "state": {"topic": "state_topic", "joints": "joints"},
    "command": {"topic": "command_topics", "joints": "command_joints", "scale": "command_scale", "source": "source"},
    "target": {"topic": "target_topic"},
    "fingertip": {"topic": "fingertip_topic"},
    "join": {"match": "match", "tolerance": "tolerance"},
    "control": {"period": "control_period", "period_tolerance": "period_tolerance"},
    "episodes": {"reset_topic": "reset_topic", "target_change": "target_change", "max_gap": "max_gap"},
    "reward": {"rule": "reward", "terminate_on_success": "terminate_on_success"},
}
_TOP_LEVEL = {"stamps": "stamps"}


def load_spec(path: str | os.PathLike | None) -> TopicSpec:
    """The spec in a YAML file (None: the defaults); UserError naming file and field."""
    if path is None:
        return TopicSpec()
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such spec file" if not path.exists() else f"{path}: not a file; expected a YAML spec")
    try:
        from ruamel.yaml import YAML  # a dependency of rosbags

        doc = YAML(typ="safe", pure=True).load(path.read_text())
    except Exception as exc:  # ruamel's parser and scanner errors, bad UTF-8
        raise UserError(f"{path}: not valid YAML ({' '.join(str(exc).split())[:200]})") from exc
    return spec_from_dict({} if doc is None else doc, path)


def spec_from_dict(doc, path: Path | None = None) -> TopicSpec:
    """The spec of a parsed YAML document; UserError naming the field for anything wrong."""
    where = str(path) if path else "spec"
    if not isinstance(doc, dict):
        raise UserError(f"{where}: expected a mapping of sections (state, command, target, ...), got {type(doc).__name__}")
    values: dict = {}
    for key, value in doc.items():
        if key in _TOP_LEVEL:
            values[_TOP_LEVEL[key]] = (key, value)
        elif key in _SECTIONS:
            if value is None:
                continue
            if key == "reward" and isinstance(value, str):
                values["reward"] = ("reward", value)
                continue
            if key == "fingertip" and value is False:
                values["fingertip_topic"] = ("fingertip", None)
                continue
            if not isinstance(value, dict):
                raise UserError(f"{where}: field {key}: expected a mapping, got {value!r}")
            for sub, subvalue in value.items():
                if sub not in _SECTIONS[key]:
                    known = ", ".join(_SECTIONS[key])
                    raise UserError(f"{where}: unknown field {key}.{sub}; {key} takes: {known}")
                values[_SECTIONS[key][sub]] = (f"{key}.{sub}", subvalue)
        else:
            known = ", ".join([*_TOP_LEVEL, *_SECTIONS])
            raise UserError(f"{where}: unknown field {key!r}; a spec takes: {known}")
    spec = TopicSpec(path=path)
    checked = {name: _check(where, name, label, value) for name, (label, value) in values.items()}
    spec = replace(spec, **checked)
    if len(spec.joints) != 2:
        raise UserError(f"{where}: field state.joints: the pusher's observation needs 2 joints, got {len(spec.joints)}")
    if len(set(spec.joints)) != len(spec.joints):
        raise UserError(f"{where}: field state.joints names a joint twice: {list(spec.joints)}")
    missing = [j for j in spec.joints if j not in spec.command_joints]
    if missing:
        raise UserError(f"{where}: field command.joints lacks the state's joint {missing[0]!r} (has {list(spec.command_joints)})")
    if spec.period_tolerance_ns * 2 >= spec.period_ns:
        raise UserError(f"{where}: field control.period_tolerance must be under half of control.period ({spec.control_period} s)")
    return spec


def _check(where: str, name: str, label: str, value):
    def bad(expected: str) -> UserError:
        return UserError(f"{where}: field {label}: expected {expected}, got {value!r}")

    if name == "command_topics":
        names = value if isinstance(value, list) else [value]
        if not names or not all(_is_topic(t) for t in names):
            raise bad("a topic name or a list of them")
        return tuple(dict.fromkeys(_absolute(t) for t in names))
    if name in ("state_topic", "target_topic", "fingertip_topic", "reset_topic"):
        if value is None and name in ("fingertip_topic", "reset_topic"):
            return None
        if not _is_topic(value):
            raise bad("a topic name")
        return _absolute(value)
    if name in ("joints", "command_joints"):
        if not isinstance(value, list) or not value or not all(isinstance(j, str) and j for j in value):
            raise bad("a list of joint names")
        return tuple(value)
    if name in ("command_scale",):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value == 0:
            raise bad("a finite non-zero number")
        return float(value)
    if name in ("tolerance", "period_tolerance", "target_change"):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
            raise bad("a number >= 0")
        return float(value)
    if name in ("control_period", "max_gap"):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
            raise bad("a number of seconds > 0")
        return float(value)
    if name == "terminate_on_success":
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    choices = {"stamps": STAMP_SOURCES, "match": MATCH_MODES, "reward": REWARD_RULES, "source": SOURCE_CHOICES}[name]
    if value not in choices:
        raise bad("one of " + ", ".join(choices))
    return value


def _is_topic(value) -> bool:
    return isinstance(value, str) and bool(value.strip()) and not any(c.isspace() for c in value)


def _absolute(topic: str) -> str:
    return topic if topic.startswith("/") else "/" + topic  # bags store absolute names
