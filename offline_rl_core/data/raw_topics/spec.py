"""What a task file asks of a recording: its topics by role, their types, and the join's times.

The task file (``offline_rl_core.task.spec``, e.g. the built-in ``pusher_reach``) names the
robot's state topic, its command topic and the project's action topics, the goal, the
tracked points and the reset topic; ``plan_for(task)`` turns that into the topics a bag is
read by (absolute names, as a bag stores them) and the join's times in nanoseconds. The
batch join (``build``) and the live one (``live``) both read from it.
"""

from __future__ import annotations

from dataclasses import dataclass

from ...common.errors import UserError
from ...task.spec import JOINT_STATE, TaskSpec


# The scripted corrector's action labels (``--action-labels``): on every state it leaves to the
# policy, the action it would take (JointState of the command joints, effort in [-1, 1], stamped
# with the state's stamp). The project's topic, not the robot's: the arm never reads it.
ACTION_LABEL_TOPIC = "corrections/action_label"


def absolute(topic: str) -> str:
    """A task's relative topic name as a bag stores it (recorded without a namespace)."""
    return topic if topic.startswith("/") else "/" + topic


@dataclass(frozen=True)
class TopicRole:
    """One topic the join reads: what it is for, the task field that names it, the types it may have."""

    topic: str  # absolute
    role: str  # state, command, action, goal, point, reset, label
    field: str  # the task file's field naming it (for messages)
    types: tuple[str, ...] | None  # None: any type (a reset)
    required: bool
    name: str = ""  # a point's name
    given: str = ""  # the name as the task file gives it (relative: a node's namespace applies)


@dataclass(frozen=True)
class JoinPlan:
    """The topics of a task's recording and the join's times (ns)."""

    task: TaskSpec
    roles: tuple[TopicRole, ...]

    @property
    def where(self) -> str:
        return self.task.source_file()

    def of_role(self, *roles: str) -> list[TopicRole]:
        return [r for r in self.roles if r.role in roles]

    def role_of(self, topic: str) -> TopicRole | None:
        return next((r for r in self.roles if r.topic == topic), None)

    @property
    def state_topic(self) -> str:
        return self.of_role("state")[0].topic

    @property
    def goal_topic(self) -> str:
        return self.of_role("goal")[0].topic

    @property
    def receive_stamps(self) -> bool:
        return self.task.join.stamps == "receive"

    @property
    def tolerance_ns(self) -> int:
        return 0 if self.task.join.match == "exact" else round(self.task.join.tolerance * 1e9)

    @property
    def period_ns(self) -> int:
        return round(self.task.control_period * 1e9)

    @property
    def period_tolerance_ns(self) -> int:
        return round(self.task.join.period_tolerance * 1e9)

    @property
    def max_gap_ns(self) -> int:
        return round(self.task.episodes.max_gap * 1e9)


def plan_for(task: TaskSpec, action_labels: bool = False) -> JoinPlan:
    """The topics ``task`` reads from a recording, by role; ``action_labels``: the corrector's
    action labels too (``ACTION_LABEL_TOPIC``, joined to the states they label)."""
    command = task.command
    roles: list[TopicRole] = []

    def add(given: str, role: str, field: str, types, required: bool, name: str = "") -> None:
        other = next((r for r in roles if r.topic == absolute(given)), None)
        if other is None:
            roles.append(TopicRole(absolute(given), role, field, types, required, name, given))
        elif {role, other.role} - {"command", "action"}:  # (an action topic may be the controller's)
            raise UserError(f"{task.source_file()}: field {field} names {given}, which field {other.field} "
                            "names too; one topic holds one thing")

    add(task.state.topic, "state", "robot.state.topic", (JOINT_STATE,), True)
    add(command.topic, "command", "robot.command.topic", (command.type,), False)
    for topic in command.action_topics:
        add(topic, "action", "robot.command.action_topics", (JOINT_STATE,), False)
    add(task.goal.topic, "goal", "goal.topic", (task.goal.type,), True)
    for p in task.points:
        if p.topic is not None:  # a point without kinematics must be heard on its topic
            add(p.topic, "point", f"points.{p.name}.topic", (p.type,), p.kinematics is None, p.name)
    if task.episodes.reset_topic is not None:
        add(task.episodes.reset_topic, "reset", "episodes.reset_topic", None, True)
    if action_labels:
        add(ACTION_LABEL_TOPIC, "label", "the corrector's action labels (--action-labels)", (JOINT_STATE,), False)
    return JoinPlan(task, tuple(roles))

