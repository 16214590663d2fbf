"""A task file: the robot, its goal, the observation, reward and episodes, as ros2_control has them.

One YAML file says everything the project needs to learn and act on an arm it was not
written for (``offline_rl_core/task/builtin/*.yaml`` are the built-in ones, documented field
by field in ``pusher_reach.yaml``; every field not given takes the default named there):

- ``robot.state``: the ``sensor_msgs/JointState`` topic (joint_state_broadcaster's
  ``joint_states``) and the joints, by name; the message may hold them in any order, and more;
- ``robot.command``: the command interface: a ``forward_command_controller``
  (``<controller>/commands``, ``std_msgs/Float64MultiArray`` in the controller's ``joints``
  order) of position, velocity or effort, or JointState commands; the action's scale;
- ``goal``: a Cartesian point or pose (``PointStamped`` / ``PoseStamped``) or a joint-space
  goal (``JointState``); ``points``: other tracked points, from topics or forward kinematics;
- ``observation``: the features, in order; ``reward``: a negative distance, the success
  threshold and bonus; ``episodes``; ``join`` (how a recording's topics are joined);
  ``control_period``; ``sim``: how the sim node hosts it, when the task has a model.

``load_task(name_or_path)`` reads and checks one; anything wrong is a ``UserError`` of one
line naming the file and the field. ``TaskSpec.digest`` identifies it (checkpoints and bags
record it, so a checkpoint of one task is never silently served on another).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import asdict, dataclass, field
from functools import cached_property
from pathlib import Path

from ..common.errors import UserError

BUILTIN_DIR = Path(__file__).resolve().parent / "builtin"
DEFAULT_TASK = "pusher_reach"

COMMAND_INTERFACES = ("effort", "velocity", "position")
FLOAT64_MULTI_ARRAY = "std_msgs/msg/Float64MultiArray"
JOINT_STATE = "sensor_msgs/msg/JointState"
POINT_STAMPED = "geometry_msgs/msg/PointStamped"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
COMMAND_TYPES = (FLOAT64_MULTI_ARRAY, JOINT_STATE)
GOAL_TYPES = (POINT_STAMPED, POSE_STAMPED, JOINT_STATE)
POINT_TYPES = (POINT_STAMPED, POSE_STAMPED)
AXES = ("x", "y", "z")
FEATURES = ("positions", "cos_sin", "velocities", "vector", "difference", "direction", "along_across")
STAMP_SOURCES = ("header", "receive")
MATCH_MODES = ("exact", "nearest")
SOURCE_CHOICES = ("auto", "expert", "random", "policy", "human")
# The project's own action topics (JointState, effort = the action in [-1, 1]): the mux's output
# to the sim, one topic per source (who acted); the join of a recording reads those it holds.
ACTION_TOPICS = ("pusher/command", "pusher/command/expert", "pusher/command/random", "pusher/command/policy",
                 "pusher/command/human")
# "joints" names the state's joint positions as a vector (a joint-space goal's partner)
JOINTS_VECTOR = "joints"


@dataclass(frozen=True)
class StateSpec:
    topic: str = "joint_states"
    joints: tuple[str, ...] = ()  # in the observation's order
    revolute: tuple[str, ...] = ()  # angles wrapped to [-pi, pi) before cos/sin


@dataclass(frozen=True)
class CommandSpec:
    interface: str = "effort"
    topic: str = "effort_controller/commands"  # <controller>/commands
    type: str = FLOAT64_MULTI_ARRAY
    joints: tuple[str, ...] = ()  # the controller's `joints` order; default: the state's
    scale: tuple[float, ...] = ()  # command = offset + scale * action, per joint; default 1
    offset: tuple[float, ...] = ()  # default 0
    action_topics: tuple[str, ...] = ACTION_TOPICS
    source: str = "auto"  # who acted, for recordings: auto (by topic name), or one name for all

    @property
    def limits(self) -> tuple[tuple[float, float], ...]:
        """The command range of each joint, in the controller's units (action in [-1, 1])."""
        return tuple((o - abs(s), o + abs(s)) for s, o in zip(self.scale, self.offset))


@dataclass(frozen=True)
class GoalSpec:
    topic: str = "goal"
    type: str = POINT_STAMPED
    axes: tuple[str, ...] = AXES  # a point's coordinates used (x, y and/or z)
    joints: tuple[str, ...] = ()  # a JointState goal's joints (default: the state's)

    @property
    def size(self) -> int:
        return len(self.joints) if self.type == JOINT_STATE else len(self.axes)


@dataclass(frozen=True)
class PointSpec:
    name: str
    topic: str | None = None  # PointStamped / PoseStamped; kinematics when absent or not heard
    type: str = POINT_STAMPED
    kinematics: str | None = None  # "planar_two_link", or "site:NAME" / "body:NAME" of the model
    link_lengths: tuple[float, ...] = ()  # planar_two_link
    axes: tuple[str, ...] = AXES


@dataclass(frozen=True)
class Feature:
    kind: str  # one of FEATURES
    args: tuple[str, ...]  # joint names, or vector names


SUCCESS_RULES = ("latch", "end")


@dataclass(frozen=True)
class DistanceTerm:
    """A further reward term: ``-weight * |a - b|`` every step (e.g. fingertip to puck)."""

    distance: tuple[str, str]
    weight: float = 1.0


@dataclass(frozen=True)
class RewardSpec:
    distance: tuple[str, str] = ("goal", "fingertip")  # reward = -|a - b| each step; success is judged on it
    success_within: float = 0.02
    success_bonus: float = 1.0
    terminate_on_success: bool = False
    # latch: success latches the first step the distance is under success_within (the bonus
    # once, then); end: success is whether it is under it now (the bonus every such step), so
    # an episode's last step says whether the episode ended at the goal
    success_at: str = "latch"
    terms: tuple[DistanceTerm, ...] = ()  # further -weight * |a - b| terms, added every step

    @property
    def distances(self) -> tuple[tuple[str, str], ...]:
        """Every pair of vectors the reward measures: the success distance first."""
        return (self.distance, *(t.distance for t in self.terms))


# Fields added after the first task files: left out of ``describe()`` at their defaults, so
# the digests that bags and checkpoints of those tasks record stay what they were.
_LATER_REWARD_DEFAULTS = {"success_at": "latch", "terms": []}


@dataclass(frozen=True)
class EpisodeSpec:
    max_steps: int = 100
    goal_change: float = 0.0  # a recording's goal moving further than this starts an episode
    reset_topic: str | None = None
    max_gap: float = 1.0  # s between states


@dataclass(frozen=True)
class JoinSpec:
    stamps: str = "header"  # or receive: the bag's receive times (commands without a header)
    match: str = "nearest"
    tolerance: float = 0.005  # s
    period_tolerance: float = 0.005  # s


SAFE_COMMANDS = ("auto", "zero", "hold")  # auto: hold for a position interface, zero otherwise
# The watchdog's default: a consumer of commands that heard none for this many control periods
# applies the safe command (one late command is jitter; three in a row is a silent controller).
TIMEOUT_PERIODS = 3


@dataclass(frozen=True)
class SafetySpec:
    """What the nodes that consume commands do when they must not trust them (nodes.watchdog,
    nodes.estop, nodes.command_limits). Every field's default leaves a run as it was without it."""

    command_timeout: float | None = None  # s; None: TIMEOUT_PERIODS control periods
    safe_command: str = "auto"  # zero (effort or velocity), hold (position), or auto by the interface
    position_limits: tuple[tuple[float, float], ...] = ()  # per state joint (low, high); () none
    velocity_limits: tuple[float, ...] = ()  # per state joint, the largest |speed|; () none
    slew: float | None = None  # the mux: the largest change of an action value per control period


@dataclass(frozen=True)
class TaskSpec:
    name: str
    description: str = ""
    control_period: float = 0.02
    state: StateSpec = field(default_factory=StateSpec)
    command: CommandSpec = field(default_factory=CommandSpec)
    goal: GoalSpec = field(default_factory=GoalSpec)
    points: tuple[PointSpec, ...] = ()
    observation: tuple[Feature, ...] = ()
    reward: RewardSpec = field(default_factory=RewardSpec)
    episodes: EpisodeSpec = field(default_factory=EpisodeSpec)
    join: JoinSpec = field(default_factory=JoinSpec)
    sim: dict = field(default_factory=dict)  # read by the task's env (task.envs); opaque here
    safety: SafetySpec = field(default_factory=SafetySpec)
    path: Path | None = field(default=None, compare=False)

    # ------------------------------------------------------------ safety
    @property
    def command_timeout(self) -> float:
        """Seconds without a valid command before a consumer applies the safe command."""
        timeout = self.safety.command_timeout
        return TIMEOUT_PERIODS * self.control_period if timeout is None else timeout

    @property
    def safe_command(self) -> str:
        """``zero`` (no effort, no velocity) or ``hold`` (the current position)."""
        if self.safety.safe_command != "auto":
            return self.safety.safe_command
        return "hold" if self.command.interface == "position" else "zero"

    # ------------------------------------------------------------ sizes and names
    @property
    def joints(self) -> tuple[str, ...]:
        return self.state.joints

    @property
    def act_dim(self) -> int:
        return len(self.command.joints)

    def vector_size(self, name: str, partner: str | None = None) -> int:
        if name == "goal":
            return self.goal.size
        if name == JOINTS_VECTOR:
            return len(self._joint_order(partner))
        return len(self.point(name).axes)

    def _joint_order(self, partner: str | None) -> tuple[str, ...]:
        """The ``joints`` vector's joints: the goal's, facing a joint-space goal (task.features.pair)."""
        return self.goal.joints if partner == "goal" and self.goal.type == JOINT_STATE else self.state.joints

    def point(self, name: str) -> PointSpec:
        for p in self.points:
            if p.name == name:
                return p
        raise KeyError(name)

    def observation_labels(self) -> tuple[str, ...]:
        """One label per observation value (what a checkpoint records as its layout)."""
        labels: list[str] = []
        for f in self.observation:
            if f.kind == "positions":
                labels += [f"pos({j})" for j in f.args]
            elif f.kind == "cos_sin":
                for j in f.args:
                    labels += [f"cos({j})", f"sin({j})"]
            elif f.kind == "velocities":
                labels += [f"vel({j})" for j in f.args]
            elif f.kind == "vector":
                labels += self._vector_labels(f.args[0])
            elif f.kind == "along_across":
                a, b, c = f.args
                labels += [f"along({a}-{b}|{c}-{b})", f"across({a}-{b}|{c}-{b})"]
            else:
                a, b = f.args
                form = "{}-{}" if f.kind == "difference" else "dir({}-{})"
                labels += [form.format(x, y) for x, y in zip(self._vector_labels(a, b), self._vector_labels(b, a))]
        return tuple(labels)

    def _vector_labels(self, name: str, partner: str | None = None) -> list[str]:
        if name == JOINTS_VECTOR:
            return [f"pos({j})" for j in self._joint_order(partner)]
        if name == "goal" and self.goal.type == JOINT_STATE:
            return [f"goal({j})" for j in self.goal.joints]
        axes = self.goal.axes if name == "goal" else self.point(name).axes
        return [f"{name}.{a}" for a in axes]

    @property
    def obs_dim(self) -> int:
        return len(self.observation_labels())

    def action_labels(self) -> tuple[str, ...]:
        return tuple(f"{self.command.interface}({j})" for j in self.command.joints)

    # ------------------------------------------------------------ identity
    def describe(self) -> dict:
        """The spec as plain values (JSON-able; what bags and checkpoints record)."""
        out = asdict(self)
        out.pop("path")
        if self.safety == SafetySpec():  # a task without a safety section keeps the digest it had
            out.pop("safety")
        for key, default in _LATER_REWARD_DEFAULTS.items():
            if out["reward"][key] == default or out["reward"][key] == tuple(default):
                out["reward"].pop(key)
        return json.loads(json.dumps(out))

    @cached_property  # a frozen spec: computed once (every env step of a task asks for its expert by it)
    def digest(self) -> str:
        text = json.dumps(self.describe(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def layout(self) -> dict:
        """What must match between a task and a checkpoint or bag: names and sizes."""
        return {"task": self.name, "digest": self.digest, "observation": list(self.observation_labels()),
                "action": list(self.action_labels())}

    def source_file(self) -> str:
        return str(self.path) if self.path and self.path.parent != BUILTIN_DIR else f"built-in task {self.name}"


# ------------------------------------------------------------------------ loading

def builtin_tasks() -> list[str]:
    return sorted(p.stem for p in BUILTIN_DIR.glob("*.yaml"))


def load_task(name_or_path: str | os.PathLike | None = None) -> TaskSpec:
    """A built-in task by name (default ``pusher_reach``), or a task file."""
    if name_or_path is None:
        name_or_path = DEFAULT_TASK
    if isinstance(name_or_path, TaskSpec):
        return name_or_path
    text = str(name_or_path)
    path = Path(text)
    if not path.suffix and (BUILTIN_DIR / f"{text}.yaml").is_file():
        path = BUILTIN_DIR / f"{text}.yaml"
    elif not path.is_file():
        if path.exists():
            raise UserError(f"{path}: not a file; expected a task file (YAML)")
        raise UserError(f"unknown task {text!r}: expected a built-in task ({', '.join(builtin_tasks())}) "
                        "or the path of a task file")
    return task_from_yaml(path.read_text(), path)


def task_from_yaml(text: str, path: Path | None = None) -> TaskSpec:
    where = str(path) if path else "task"
    try:
        from ruamel.yaml import YAML  # a dependency of rosbags

        doc = YAML(typ="safe", pure=True).load(text)
    except Exception as exc:  # ruamel's parser and scanner errors
        raise UserError(f"{where}: not valid YAML ({' '.join(str(exc).split())[:200]})") from exc
    return task_from_dict(doc, path)


def task_from_dict(doc, path: Path | None = None) -> TaskSpec:
    """The task of a parsed document (also a ``describe()`` dict); UserError naming the field."""
    return _Reader(str(path) if path else "task", path).task(doc)


class _Reader:
    """Checks a document field by field; errors name the file and the dotted field."""

    TOP = ("name", "description", "control_period", "robot", "goal", "points", "observation", "reward", "episodes",
           "join", "sim", "safety",
           # describe()'s flat form
           "state", "command")

    def __init__(self, where: str, path: Path | None):
        self.where, self.path = where, path

    def error(self, label: str, expected: str, value) -> UserError:
        return UserError(f"{self.where}: field {label}: expected {expected}, got {value!r}")

    def mapping(self, label: str, value, keys: tuple[str, ...]) -> dict:
        if value is None:
            return {}
        if not isinstance(value, dict):
            raise self.error(label, "a mapping", value)
        for key in value:
            if key not in keys:
                raise UserError(f"{self.where}: unknown field {label + '.' if label else ''}{key}; "
                                f"{label or 'a task'} takes: {', '.join(keys)}")
        return value

    # -- scalar checks
    def text(self, label, value, default=None):
        if value is None:
            return default
        if not isinstance(value, str) or not value.strip() or any(c.isspace() for c in value):
            raise self.error(label, "a name without spaces", value)
        return value

    def number(self, label, value, default, low=None, low_open=False):
        if value is None:
            return default
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise self.error(label, "a finite number", value)
        if low is not None and (value <= low if low_open else value < low):
            raise self.error(label, f"a number {'>' if low_open else '>='} {low:g}", value)
        return float(value)

    def count(self, label, value, default):
        if value is None:
            return default
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise self.error(label, "a whole number >= 1", value)
        return value

    def flag(self, label, value, default):
        if value is None:
            return default
        if not isinstance(value, bool):
            raise self.error(label, "true or false", value)
        return value

    def choice(self, label, value, choices, default):
        if value is None:
            return default
        aliases = {c.replace("/msg/", "/"): c for c in choices if "/msg/" in c}
        if value in aliases:
            return aliases[value]
        if value not in choices:
            raise self.error(label, "one of " + ", ".join(c.replace("/msg/", "/") for c in choices), value)
        return value

    def names(self, label, value, default=(), allow_empty=False):
        if value is None:
            return tuple(default)
        if not isinstance(value, (list, tuple)) or (not value and not allow_empty) or \
                not all(isinstance(v, str) and v.strip() for v in value):
            raise self.error(label, "a list of names", value)
        if len(set(value)) != len(value):
            raise UserError(f"{self.where}: field {label} names {sorted(v for v in value if value.count(v) > 1)[0]!r} twice")
        return tuple(value)

    def numbers(self, label, value, n, default):
        if value is None:
            return (default,) * n
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            value = [value] * n
        if not isinstance(value, (list, tuple)) or len(value) != n or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value):
            raise self.error(label, f"a number or a list of {n} numbers (one per command joint)", value)
        return tuple(float(v) for v in value)

    def topic(self, label, value, default=None):
        if value is None:
            return default
        if not isinstance(value, str) or not value.strip("/") or any(c.isspace() for c in value):
            raise self.error(label, "a topic name", value)
        return value

    # -- sections
    def task(self, doc) -> TaskSpec:
        if not isinstance(doc, dict):
            raise UserError(f"{self.where}: expected a mapping (name, robot, goal, observation, ...), "
                            f"got {type(doc).__name__}")
        self.mapping("", doc, self.TOP)
        name = self.text("name", doc.get("name"))
        if name is None:
            raise UserError(f"{self.where}: field name: every task needs a name")
        robot = self.mapping("robot", doc.get("robot"), ("state", "command"))
        state = self.state(robot.get("state", doc.get("state")))
        command = self.command(robot.get("command", doc.get("command")), state)
        goal = self.goal(doc.get("goal"), state)
        points = self.points(doc.get("points"))
        spec = TaskSpec(
            name=name,
            description=str(doc.get("description") or ""),
            control_period=self.number("control_period", doc.get("control_period"), 0.02, 0.0, True),
            state=state, command=command, goal=goal, points=points,
            observation=(), reward=self.reward(doc.get("reward")), episodes=self.episodes(doc.get("episodes")),
            join=self.join(doc.get("join")), sim=self.sim(doc.get("sim")),
            safety=self.safety(doc.get("safety"), state), path=self.path,
        )
        spec = _replace(spec, observation=self.observation(doc.get("observation"), spec))
        self.check_vectors(spec)
        if spec.join.period_tolerance * 2 >= spec.control_period:
            raise UserError(f"{self.where}: field join.period_tolerance must be under half of control_period "
                            f"({spec.control_period} s)")
        return spec

    def state(self, doc) -> StateSpec:
        doc = self.mapping("robot.state", doc, ("topic", "joints", "revolute"))
        joints = self.names("robot.state.joints", doc.get("joints"))
        if not joints:
            raise UserError(f"{self.where}: field robot.state.joints: name the robot's joints (in the observation's order)")
        revolute = self.names("robot.state.revolute", doc.get("revolute"), allow_empty=True)
        unknown = [j for j in revolute if j not in joints]
        if unknown:
            raise UserError(f"{self.where}: field robot.state.revolute names {unknown[0]!r}, not one of "
                            f"robot.state.joints ({', '.join(joints)})")
        return StateSpec(self.topic("robot.state.topic", doc.get("topic"), "joint_states"), joints, revolute)

    def command(self, doc, state: StateSpec) -> CommandSpec:
        doc = self.mapping("robot.command", doc, ("interface", "topic", "controller", "type", "joints", "scale",
                                                  "offset", "action_topics", "source", "limits"))
        interface = self.choice("robot.command.interface", doc.get("interface"), COMMAND_INTERFACES, "effort")
        controller = self.text("robot.command.controller", doc.get("controller"))
        topic = self.topic("robot.command.topic", doc.get("topic"),
                           f"{controller}/commands" if controller else f"{interface}_controller/commands")
        kind = self.choice("robot.command.type", doc.get("type"), COMMAND_TYPES, FLOAT64_MULTI_ARRAY)
        joints = self.names("robot.command.joints", doc.get("joints"), state.joints)
        n = len(joints)
        scale = self.numbers("robot.command.scale", doc.get("scale"), n, 1.0)
        if any(s == 0 for s in scale):
            raise self.error("robot.command.scale", "non-zero numbers (command = offset + scale * action)", list(scale))
        offset = self.numbers("robot.command.offset", doc.get("offset"), n, 0.0)
        if doc.get("limits") is not None:
            scale, offset = self.limits(doc["limits"], n)
        topics = doc.get("action_topics")
        action_topics = ACTION_TOPICS if topics is None else tuple(
            self.topic("robot.command.action_topics", t) for t in (topics if isinstance(topics, list) else [topics]))
        source = self.choice("robot.command.source", doc.get("source"), SOURCE_CHOICES, "auto")
        return CommandSpec(interface, topic, kind, joints, scale, offset, action_topics, source)

    def limits(self, value, n):
        """``limits: [[low, high], ...]`` per joint: the action's [-1, 1] spans [low, high]."""
        if not isinstance(value, list) or len(value) != n or not all(
                isinstance(p, list) and len(p) == 2 and all(isinstance(v, (int, float)) and math.isfinite(v) for v in p)
                and p[0] < p[1] for p in value):
            raise self.error("robot.command.limits", f"{n} pairs [low, high] with low < high, one per command joint",
                             value)
        return tuple((hi - lo) / 2.0 for lo, hi in value), tuple((hi + lo) / 2.0 for lo, hi in value)

    def goal(self, doc, state: StateSpec) -> GoalSpec:
        doc = self.mapping("goal", doc, ("topic", "type", "axes", "joints"))
        kind = self.choice("goal.type", doc.get("type"), GOAL_TYPES, POINT_STAMPED)
        axes = self.axes("goal.axes", doc.get("axes"))
        joints = self.names("goal.joints", doc.get("joints") or None, state.joints if kind == JOINT_STATE else ())
        unknown = [j for j in joints if j not in state.joints]
        if unknown:
            raise UserError(f"{self.where}: field goal.joints names {unknown[0]!r}, not one of robot.state.joints "
                            f"({', '.join(state.joints)})")
        return GoalSpec(self.topic("goal.topic", doc.get("topic"), "goal"), kind, axes, joints)

    def axes(self, label, value):
        axes = self.names(label, value, AXES)
        if any(a not in AXES for a in axes):
            raise self.error(label, "axes among x, y, z", list(axes))
        return axes

    def points(self, doc) -> tuple[PointSpec, ...]:
        doc = doc or {}
        if isinstance(doc, list) and all(isinstance(p, dict) and "name" in p for p in doc):  # describe()'s form
            doc = {p["name"]: {k: v for k, v in p.items() if k != "name" and v not in (None, [])} for p in doc}
        if not isinstance(doc, dict):
            raise self.error("points", "a mapping of point names", doc)
        out = []
        for name, value in doc.items():
            label = f"points.{name}"
            if name in ("goal", JOINTS_VECTOR):
                raise UserError(f"{self.where}: field {label}: {name!r} is a reserved name")
            value = self.mapping(label, value, ("topic", "type", "kinematics", "link_lengths", "axes"))
            topic = self.topic(f"{label}.topic", value.get("topic"))
            kinematics = value.get("kinematics")
            if kinematics is not None and not (kinematics == "planar_two_link" or (
                    isinstance(kinematics, str) and kinematics.split(":", 1)[0] in ("site", "body")
                    and kinematics.count(":") == 1 and kinematics.split(":", 1)[1])):
                raise self.error(f"{label}.kinematics", "planar_two_link, site:NAME or body:NAME", kinematics)
            if topic is None and kinematics is None:
                raise UserError(f"{self.where}: field {label}: give a topic, kinematics, or both")
            lengths = value.get("link_lengths")
            if kinematics == "planar_two_link":
                if not (isinstance(lengths, list) and len(lengths) == 2 and all(
                        isinstance(v, (int, float)) and v > 0 for v in lengths)):
                    raise self.error(f"{label}.link_lengths", "two link lengths > 0 (planar_two_link)", lengths)
            out.append(PointSpec(name, topic, self.choice(f"{label}.type", value.get("type"), POINT_TYPES, POINT_STAMPED),
                                 kinematics, tuple(float(v) for v in (lengths or ())),
                                 self.axes(f"{label}.axes", value.get("axes"))))
        return tuple(out)

    def observation(self, doc, spec: TaskSpec) -> tuple[Feature, ...]:
        if not isinstance(doc, list) or not doc:
            raise self.error("observation", "a list of features (" + ", ".join(FEATURES) + ")", doc)
        out = []
        for i, item in enumerate(doc):
            label = f"observation[{i}]"
            if isinstance(item, dict) and set(item) == {"kind", "args"}:  # describe()'s form
                item = {item["kind"]: list(item["args"]) if len(item["args"]) != 1 or item["kind"] != "vector"
                        else item["args"][0]}
            if not isinstance(item, dict) or len(item) != 1:
                raise self.error(label, "one feature, e.g. {cos_sin: [shoulder, elbow]}", item)
            (kind, args), = item.items()
            if kind not in FEATURES:
                raise self.error(label, "one of " + ", ".join(FEATURES), kind)
            if kind in ("positions", "cos_sin", "velocities"):
                joints = self.names(f"{label}.{kind}", args)
                unknown = [j for j in joints if j not in spec.state.joints]
                if unknown:
                    raise UserError(f"{self.where}: field {label}.{kind} names {unknown[0]!r}, not one of "
                                    f"robot.state.joints ({', '.join(spec.state.joints)})")
                out.append(Feature(kind, joints))
            elif kind == "vector":
                self.vector_name(f"{label}.vector", args, spec)
                out.append(Feature(kind, (args,)))
            elif kind == "along_across":  # a - b in the frame of the line from b to c: planar vectors
                field = f"{label}.{kind}"
                names = self.names(field, args)
                if len(names) != 3:
                    raise self.error(field, "three vector names [a, b, c] (a - b along and across c - b)", args)
                for v in names:
                    self.vector_name(field, v, spec)
                for v in names:
                    if spec.vector_size(v) != 2:
                        raise UserError(f"{self.where}: field {field}: {v} has {spec.vector_size(v)} values; "
                                        "along_across takes planar vectors of two (x, y)")
                out.append(Feature(kind, names))
            else:  # difference, direction: a pair of vectors
                field = f"{label}.{kind}"
                pair = self.names(field, args)
                if len(pair) != 2:
                    raise self.error(field, "two vector names [a, b] (a - b)", args)
                for v in pair:
                    self.vector_name(field, v, spec)
                if spec.vector_size(pair[0], pair[1]) != spec.vector_size(pair[1], pair[0]):
                    raise UserError(f"{self.where}: field {field}: {pair[0]} has "
                                    f"{spec.vector_size(pair[0], pair[1])} values, {pair[1]} {spec.vector_size(pair[1], pair[0])}")
                out.append(Feature(kind, pair))
        return tuple(out)

    def vector_name(self, label, name, spec: TaskSpec) -> None:
        known = ["goal", JOINTS_VECTOR, *(p.name for p in spec.points)]
        if name not in known:
            raise self.error(label, "a vector: " + ", ".join(known), name)

    def check_vectors(self, spec: TaskSpec) -> None:
        labels = ["reward.distance"] + [f"reward.terms[{i}].distance" for i in range(len(spec.reward.terms))]
        for label, (a, b) in zip(labels, spec.reward.distances):
            for v in (a, b):
                self.vector_name(label, v, spec)
            if spec.vector_size(a, b) != spec.vector_size(b, a):
                raise UserError(f"{self.where}: field {label}: {a} has {spec.vector_size(a, b)} values, "
                                f"{b} {spec.vector_size(b, a)}")

    def pair(self, label, value, default=None) -> tuple[str, str]:
        pair = self.names(label, value, default or ())
        if len(pair) != 2:
            raise self.error(label, "two vector names [a, b]", list(pair))
        return pair

    def reward(self, doc) -> RewardSpec:
        doc = self.mapping("reward", doc, ("distance", "success_within", "success_bonus", "terminate_on_success",
                                           "success_at", "terms"))
        terms = doc.get("terms")
        if terms is not None and not isinstance(terms, list):
            raise self.error("reward.terms", "a list of {distance: [a, b], weight: w}", terms)
        checked = []
        for i, term in enumerate(terms or []):
            label = f"reward.terms[{i}]"
            term = self.mapping(label, term, ("distance", "weight"))
            if term.get("distance") is None:
                raise self.error(f"{label}.distance", "two vector names [a, b]", None)
            checked.append(DistanceTerm(self.pair(f"{label}.distance", term["distance"]),
                                        self.number(f"{label}.weight", term.get("weight"), 1.0)))
        return RewardSpec(self.pair("reward.distance", doc.get("distance"), RewardSpec.distance),
                          self.number("reward.success_within", doc.get("success_within"), 0.02, 0.0, True),
                          self.number("reward.success_bonus", doc.get("success_bonus"), 1.0),
                          self.flag("reward.terminate_on_success", doc.get("terminate_on_success"), False),
                          self.choice("reward.success_at", doc.get("success_at"), SUCCESS_RULES, "latch"),
                          tuple(checked))

    def episodes(self, doc) -> EpisodeSpec:
        doc = self.mapping("episodes", doc, ("max_steps", "goal_change", "reset_topic", "max_gap"))
        return EpisodeSpec(self.count("episodes.max_steps", doc.get("max_steps"), 100),
                           self.number("episodes.goal_change", doc.get("goal_change"), 0.0, 0.0),
                           self.topic("episodes.reset_topic", doc.get("reset_topic")),
                           self.number("episodes.max_gap", doc.get("max_gap"), 1.0, 0.0, True))

    def join(self, doc) -> JoinSpec:
        doc = self.mapping("join", doc, ("stamps", "match", "tolerance", "period_tolerance"))
        return JoinSpec(self.choice("join.stamps", doc.get("stamps"), STAMP_SOURCES, "header"),
                        self.choice("join.match", doc.get("match"), MATCH_MODES, "nearest"),
                        self.number("join.tolerance", doc.get("tolerance"), 0.005, 0.0),
                        self.number("join.period_tolerance", doc.get("period_tolerance"), 0.005, 0.0))

    def safety(self, doc, state: StateSpec) -> SafetySpec:
        doc = self.mapping("safety", doc, ("command_timeout", "safe_command", "position_limits", "velocity_limits",
                                           "slew"))
        timeout = self.number("safety.command_timeout", doc.get("command_timeout"), None, 0.0, True)
        safe = self.choice("safety.safe_command", doc.get("safe_command"), SAFE_COMMANDS, "auto")
        slew = self.number("safety.slew", doc.get("slew"), None, 0.0, True)
        return SafetySpec(timeout, safe, self.joint_pairs("safety.position_limits", doc.get("position_limits"), state),
                          self.joint_bounds("safety.velocity_limits", doc.get("velocity_limits"), state), slew)

    def joint_pairs(self, label, value, state: StateSpec) -> tuple[tuple[float, float], ...]:
        """``{joint: [low, high]}`` (or describe()'s list, in the state's order); joints not named: unbounded."""
        if value is None or (isinstance(value, (list, dict)) and not value):
            return ()
        if isinstance(value, list):
            value = dict(zip(state.joints, value))
        if not isinstance(value, dict):
            raise self.error(label, "a mapping of state joints to [low, high]", value)
        self.unknown_joints(label, value, state)
        pairs = []
        for joint in state.joints:
            pair = value.get(joint, [-math.inf, math.inf])
            if not (isinstance(pair, (list, tuple)) and len(pair) == 2 and all(
                    isinstance(v, (int, float)) and not isinstance(v, bool) and not math.isnan(v) for v in pair)
                    and pair[0] < pair[1]):
                raise self.error(f"{label}.{joint}", "[low, high] with low < high", pair)
            pairs.append((float(pair[0]), float(pair[1])))
        return tuple(pairs)

    def joint_bounds(self, label, value, state: StateSpec) -> tuple[float, ...]:
        """``{joint: max}`` (or describe()'s list); joints not named: unbounded."""
        if value is None or (isinstance(value, (list, dict)) and not value):
            return ()
        if isinstance(value, list):
            value = dict(zip(state.joints, value))
        if not isinstance(value, dict):
            raise self.error(label, "a mapping of state joints to a largest speed", value)
        self.unknown_joints(label, value, state)
        bounds = []
        for joint in state.joints:
            bound = value.get(joint, math.inf)
            if isinstance(bound, bool) or not isinstance(bound, (int, float)) or not bound > 0:
                raise self.error(f"{label}.{joint}", "a number > 0", bound)
            bounds.append(float(bound))
        return tuple(bounds)

    def unknown_joints(self, label, value: dict, state: StateSpec) -> None:
        unknown = [j for j in value if j not in state.joints]
        if unknown:
            raise UserError(f"{self.where}: field {label} names {unknown[0]!r}, not one of robot.state.joints "
                            f"({', '.join(state.joints)})")

    def sim(self, doc) -> dict:
        if doc is None:
            return {}
        if not isinstance(doc, dict):
            raise self.error("sim", "a mapping (env, model, ...)", doc)
        return json.loads(json.dumps(doc))  # plain values; the env that reads it checks its fields


# The field checks, for the readers of sections this module leaves opaque (``sim``: task.mujoco_task).
FieldReader = _Reader


def _replace(spec: TaskSpec, **changes) -> TaskSpec:
    from dataclasses import replace

    return replace(spec, **changes)
