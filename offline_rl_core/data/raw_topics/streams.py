"""A recording's topics as arrays by role: states, commands, goal, tracked points, resets, and
the corrector's action labels (read as the project's action topics are).

``decode_rows(plan, role, msgtype, payloads, recv_ns)`` turns the raw payloads of one topic
into ``Rows``: stamps, receive times and float64 values in the task's order (the state's
joint positions and velocities in ``robot.state.joints`` order, the action in
``robot.command.joints`` order, the goal's and a point's axes or joints), with which rows are
usable. The batch join decodes a whole topic at once, the live join one message at a time;
both through here, so they read a message the same way.

A topic whose messages do not fit the task (a joint the task names that a JointState lacks,
a type without a header where the task joins by header stamps) raises ``Mismatch``; a
single message that does not fit (a command of another length, a NaN) is only marked
unusable, and counted by the join.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...task.spec import AXES, FLOAT64_MULTI_ARRAY, JOINT_STATE
from ..transitions import SOURCE_BY_NAME, SOURCE_POLICY, source_from_tag
from .messages import HAS_HEADER, Decoded, decode_messages
from .spec import JoinPlan, TopicRole


class Mismatch(ValueError):
    """A topic's messages do not fit the task file (its text names the topic and the field);
    ``reason``: the node's rejection reason for it (``common.rejections.REASONS``)."""

    def __init__(self, text: str, reason: str = "bad layout"):
        super().__init__(text)
        self.reason = reason


def source_of_topic(topic: str) -> int | None:
    """The source a command topic names (``.../command/expert`` ...), None for another."""
    return SOURCE_BY_NAME.get(topic.rstrip("/").rsplit("/", 1)[-1])


NO_HEADER = -1  # Rows.header of a message whose type has no header


@dataclass
class Rows:
    """The decoded messages of one role, in arrival order."""

    stamp: np.ndarray  # int64 ns: header stamps, or receive times (join.stamps: receive)
    recv: np.ndarray  # int64 ns: when the message was received (the bag's timestamp)
    values: np.ndarray  # float64 (n, width)
    ok: np.ndarray  # bool: decoded, the task's length, finite
    source: np.ndarray  # int64: who acted (commands; 0 otherwise)
    rank: np.ndarray | None = None  # commands: 0 from the project's action topics, 1 from the controller's
    wrong_length: int = 0  # commands refused for holding another number of values
    # int64 ns: the header stamp where the type has one, else NO_HEADER; kept with
    # join.stamps: receive too, where it still names the state a command answers
    header: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.stamp.size)

    def __post_init__(self):
        if self.rank is None:
            self.rank = np.zeros(self.stamp.size, np.int8)
        if self.header is None:
            self.header = np.full(self.stamp.size, NO_HEADER, np.int64)

    @classmethod
    def empty(cls, width: int) -> "Rows":
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, width)), np.zeros(0, bool),
                   np.zeros(0, np.int64))

    @classmethod
    def concat(cls, parts: list["Rows"], width: int) -> "Rows":
        if not parts:
            return cls.empty(width)
        stamp, recv, values, ok, source, rank, header = (
            np.concatenate([getattr(p, f) for p in parts])
            for f in ("stamp", "recv", "values", "ok", "source", "rank", "header"))
        return cls(stamp, recv, values, ok, source, rank, sum(p.wrong_length for p in parts), header)

    def take(self, index) -> "Rows":
        return Rows(self.stamp[index], self.recv[index], self.values[index], self.ok[index], self.source[index],
                    self.rank[index], self.wrong_length, self.header[index])


def role_width(plan: JoinPlan, role: TopicRole) -> int:
    task = plan.task
    if role.role == "state":
        return 2 * len(task.state.joints)
    if role.role in ("command", "action", "label"):
        return task.act_dim
    if role.role == "goal":
        return task.goal.size
    if role.role == "point":
        return len(task.point(role.name).axes)
    return 0


def check_type(plan: JoinPlan, role: TopicRole, msgtype: str) -> None:
    """Mismatch when ``msgtype`` is not one the role takes, or has no header to join by."""
    if role.types is not None and msgtype not in role.types:
        raise Mismatch(f"{role.topic} has type {msgtype}; {plan.where} field {role.field} needs "
                       f"{' or '.join(role.types)}")
    if role.types is not None and not plan.receive_stamps and not has_header(msgtype):
        raise Mismatch(f"{role.topic} ({msgtype}) has no header, but {plan.where} joins by header stamps "
                       "(field join.stamps); set join.stamps: receive to join by receive times", "bad stamp")


def has_header(msgtype: str) -> bool:
    return HAS_HEADER.get(msgtype, True)


def decode_rows(plan: JoinPlan, role: TopicRole, msgtype: str, payloads, recv_ns) -> Rows:
    """The rows of one topic (``payloads`` with their receive times). MessageDecodeError for
    a payload that is not a readable ``msgtype``; Mismatch for messages that do not fit the task."""
    check_type(plan, role, msgtype)
    recv = np.asarray(recv_ns, np.int64)
    n = recv.size
    width = role_width(plan, role)
    decoded = decode_messages(payloads, msgtype) if role.types is not None else []
    rows = Rows(recv.copy(), recv, np.zeros((n, width)), np.zeros(n, bool) if role.types else np.ones(n, bool),
                np.zeros(n, np.int64))
    for d in decoded:
        if d.stamp_ns is not None:
            rows.header[d.rows] = d.stamp_ns
            if not plan.receive_stamps:
                rows.stamp[d.rows] = d.stamp_ns
    read = {"state": _read_state, "command": _read_command, "action": _read_command, "label": _read_command,
            "goal": _read_vector, "point": _read_vector}.get(role.role)
    if read is not None:
        read(plan, role, msgtype, decoded, rows)
        rows.ok &= np.isfinite(rows.values).all(axis=1)
    return rows


def _columns(role: TopicRole, names: tuple[str, ...], count: int, wanted: tuple[str, ...], field: str, where: str):
    """The column of each wanted joint among ``count`` values named ``names`` (or, when the
    message names none, given in ``wanted`` order); None when the values do not fit."""
    if names:
        missing = [j for j in wanted if j not in names]
        if missing:
            raise Mismatch(f"{role.topic}: joint {missing[0]!r} ({where} field {field}) is not among the "
                           f"message's joint names [{', '.join(names)}]", "unknown joints")
        return [names.index(j) for j in wanted] if count == len(names) else None
    return list(range(len(wanted))) if count == len(wanted) else None


def _counts(d: Decoded) -> dict[str, int]:
    return {key: count for key, _, count in d.layout.arrays}


def _read_state(plan: JoinPlan, role: TopicRole, msgtype: str, decoded: list[Decoded], rows: Rows) -> None:
    task = plan.task
    joints = task.state.joints
    k = len(joints)
    needs_velocity = any(f.kind == "velocities" for f in task.observation)
    for d in decoded:
        counts = _counts(d)
        cols = _columns(role, d.layout.names, counts["position"], joints, "robot.state.joints", plan.where)
        if cols is None:
            continue
        rows.values[d.rows, :k] = d.arrays["position"][:, cols]
        if counts["velocity"] == counts["position"]:
            rows.values[d.rows, k:] = d.arrays["velocity"][:, cols]
        elif counts["velocity"] or needs_velocity:
            continue  # velocities the observation needs, or not one per joint
        rows.ok[d.rows] = True


def _read_command(plan: JoinPlan, role: TopicRole, msgtype: str, decoded: list[Decoded], rows: Rows) -> None:
    """Actions in [-1, 1] terms (not yet clipped): the controller's command mapped back,
    (command - offset) / scale; the project's action topics carry the action itself."""
    command = plan.task.command
    joints = command.joints
    controller = role.role == "command"
    topic_source = source_of_topic(role.topic)
    rows.source[:] = SOURCE_POLICY if topic_source is None else topic_source
    rows.rank[:] = 1 if controller else 0
    fixed = command.source != "auto"
    if fixed:
        rows.source[:] = SOURCE_BY_NAME[command.source]
    field = "robot.command.joints"
    for d in decoded:
        if msgtype == FLOAT64_MULTI_ARRAY:
            _, _, count = d.layout.arrays[0]
            count -= d.layout.data_offset
            if count != len(joints):
                rows.wrong_length += d.rows.size
                continue
            values = d.arrays["data"][:, d.layout.data_offset:]
        else:
            counts = _counts(d)
            key = command.interface if controller else "effort"
            cols = _columns(role, d.layout.names, counts[key], joints, field, plan.where)
            if cols is None:
                rows.wrong_length += d.rows.size
                continue
            values = d.arrays[key][:, cols]
            tagged = source_from_tag(d.layout.frame_id)
            if not fixed and topic_source is None and tagged is not None:
                rows.source[d.rows] = tagged
        if controller:
            values = (values - np.asarray(command.offset)) / np.asarray(command.scale)
        rows.values[d.rows] = values
        rows.ok[d.rows] = True


def _read_vector(plan: JoinPlan, role: TopicRole, msgtype: str, decoded: list[Decoded], rows: Rows) -> None:
    task = plan.task
    if msgtype == JOINT_STATE:  # a joint-space goal: its positions of goal.joints
        for d in decoded:
            cols = _columns(role, d.layout.names, _counts(d)["position"], task.goal.joints, "goal.joints", plan.where)
            if cols is not None:
                rows.values[d.rows] = d.arrays["position"][:, cols]
                rows.ok[d.rows] = True
        return
    axes = task.goal.axes if role.role == "goal" else task.point(role.name).axes
    cols = [AXES.index(a) for a in axes]
    for d in decoded:
        rows.values[d.rows] = d.arrays["point"][:, cols]
        rows.ok[d.rows] = True
