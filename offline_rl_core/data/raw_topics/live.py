"""The batch join, live: transitions built from a robot's raw topics as they arrive.

``LiveJoin(task)`` takes each message of the task's topics (``add``) and, when asked
(``poll``), runs the batch join (``build.join``) on a window of the stream (from the first
state of the earliest episode not yet done) and hands out, in the batch's order, every
environment step whose outcome no later message can change: its transition, or that it
has none (an episode's last step, whose next state never comes). So a session's live
transitions are the rows `offline-rl dataset` builds from the session's bag.

When is an outcome final? Each topic's messages are taken to arrive in stamp order (not
across topics), and a step's outcome depends only on messages up to a horizon past it: its
command (the nearest to the state), the next state (one period on, within the period
tolerance), the goal and the tracked points of both states (within the join tolerance). A
topic is known complete up to the latest stamp heard on it; a topic that falls silent (a
goal published once an episode, a person who does not take over) is taken complete up to
``lateness`` before the state stream. When nothing new has come for ``quiet`` seconds while
the caller was idle (a lockstep sim waiting for the learner), everything published so far
is taken to have arrived: up to twice the largest tolerance past the latest state, for
commands up to just before it (the latest state's command may come only once the learner
answers). A state that has no command by then is not yet taken to have none: its command
and the next state come from different writers, in no order between them, and on a busy
machine the command can come after the state it caused and a short silence (a step taken
as commandless there would be one step short for good, and a lockstep session paced on the
steps would wait for it forever). It is taken to have none after ``quiet_missing`` seconds
of silence (a lost message), or when the caller says all has arrived. A message that
comes after a step it could have changed was handed out is counted as late (the live
rows may then differ from the batch's).

With a ``judge`` (a success classifier) each state's success is its verdict, as in the batch
join with that judge, and ``counts.judged`` keeps how often it disagreed with the task's
success distance on the transitions handed out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ...common.rejections import Rejection
from ...task.spec import TaskSpec
from ..transitions import Layout, Transitions
from .build import JoinEmpty, JoinReport, StateVerdicts, Streams, join, judged_counts, point_kinematics
from .messages import MessageDecodeError
from .spec import TopicRole, plan_for
from .streams import Mismatch, Rows, decode_rows, has_header, role_width

NEVER = -(2**62)  # a watermark before any stamp
_GROUP = {"state": "states", "command": "commands", "action": "commands", "goal": "observed", "point": "observed",
          "reset": "resets", "label": "labels"}


@dataclass
class LiveSettings:
    lateness: float = 0.5  # s of stamps: a silent topic is complete up to this before the states
    quiet: float = 0.05  # s with nothing new while idle: all that was published has arrived
    # s with nothing new while idle before a state still without its command is taken to have
    # none (a command only delayed on a busy machine comes well within it)
    quiet_missing: float = 1.0


@dataclass
class LiveSteps:
    """Steps handed out by one ``poll``, oldest first: the transitions, and per step
    whether it made one (the k-th True step is the k-th row)."""

    transitions: Transitions
    has_row: np.ndarray  # bool per step
    labels: np.ndarray | None = None  # with action labels: one per transition (NaN: its state has none)

    def __len__(self) -> int:
        return int(self.has_row.size)


@dataclass
class LiveCounts:
    messages: dict = field(default_factory=dict)  # topic -> messages taken
    late: int = 0  # messages that came after a step they could change was handed out
    late_topics: dict = field(default_factory=dict)  # topic -> late messages
    old: int = 0  # messages from before the window (copies of messages let go of)
    refused: dict = field(default_factory=dict)  # reason -> messages that do not fit the task
    steps: int = 0
    transitions: int = 0
    judged: dict | None = None  # with a judge: its successes against the task's success distance

    def as_dict(self) -> dict:
        out = {"messages": dict(self.messages), "late": self.late, "late_topics": dict(self.late_topics),
               "old": self.old, "refused": dict(self.refused),
               "steps": self.steps, "transitions": self.transitions}
        return out if self.judged is None else {**out, "judged": dict(self.judged)}


class _Buffer:
    """A role's rows, appended one message at a time and joined into one array when read."""

    def __init__(self, width: int):
        self.width = width
        self._rows = Rows.empty(width)
        self._new: list[Rows] = []

    @property
    def rows(self) -> Rows:
        if self._new:
            self._rows = Rows.concat([self._rows, *self._new], self.width)
            self._new = []
        return self._rows

    def append(self, rows: Rows) -> None:
        self._new.append(rows)

    def holds(self, stamp: int) -> bool:
        return bool(np.any(self._rows.stamp == stamp)) or any(int(r.stamp[0]) == stamp for r in self._new)

    def keep(self, mask_of) -> None:
        rows = self.rows
        self._rows = rows.take(mask_of(rows))


class LiveJoin:
    """``judge``: a success classifier (``success(obs)``) whose judgement of each state
    replaces the task's success distance, as in ``build.join``; ``end_on_success``: an
    episode ends at its first success (where the arm's episodes end on it too)."""

    def __init__(self, task: TaskSpec, settings: LiveSettings | None = None, judge=None, action_labels: bool = False,
                 end_on_success: bool = False):
        self.task = task
        self.terminate_on_success = True if end_on_success else None  # None: as the task's reward says
        # verdicts remembered across polls: the window is joined again on each
        self.judge = None if judge is None else StateVerdicts(judge)
        self.plan = plan_for(task, action_labels)
        self.settings = settings or LiveSettings()
        self.kinematics = point_kinematics(task)
        self.roles = {r.topic: r for r in self.plan.roles}
        self.types: dict[str, str] = {}  # topic -> message type, from its first message
        width = {r.topic: role_width(self.plan, r) for r in self.plan.roles}
        self.states = _Buffer(width[self.plan.state_topic])
        self.commands = _Buffer(task.act_dim)
        self.goal = _Buffer(task.goal.size)
        self.points = {r.name: _Buffer(width[r.topic]) for r in self.plan.of_role("point")}
        # the corrector's labels: they gate no step (a label still to come is not waited for; the
        # corrector sends it before its answer, steps before the next state that seals the step)
        self.labels = _Buffer(task.act_dim) if action_labels else None
        self.resets: list[int] = []
        self.watermark = {r.topic: NEVER for r in self.plan.roles}  # latest stamp heard, per topic
        self.window_start = NEVER  # first state of the window (an episode start)
        self.goal_start = NEVER  # the earliest goal the window's states can take
        self.handed_out = NEVER  # every state stamped before this has had its steps handed out
        # how far each group of topics was taken complete when steps were last handed out
        self.sealed = {"states": NEVER, "commands": NEVER, "observed": NEVER, "resets": NEVER, "labels": NEVER}
        self.last_advance = -math.inf  # when a watermark last moved (the caller's clock, s)
        self.changed = False
        self.quiet_used = 0  # the quiet level of the last poll that joined: 0 none, 1 quiet, 2 quiet_missing
        self.episode_key: int | None = None  # the episode of the last transition handed out
        self.episode_id = -1
        self.counts = LiveCounts()
        if self.judge is not None:
            self.counts.judged = judged_counts(self.judge.source, np.zeros(0, bool), np.zeros(0, bool))
        tol, ptol = self.plan.tolerance_ns, self.plan.period_tolerance_ns
        self.quiet_horizon = 2 * max(tol, ptol)
        self.lateness_ns = round(self.settings.lateness * 1e9)

    # ---------------------------------------------------------------- input
    def topics(self) -> list[TopicRole]:
        """The topics to subscribe to (``given``: the task's name for each); joined by header
        stamps, not a command type without a header (the action topics hold the arm's commands)."""
        return [r for r in self.plan.roles if r.types is None or self.plan.receive_stamps
                or any(has_header(t) for t in r.types)]

    def add(self, topic: str, msgtype: str, payload: bytes, recv_ns: int, now: float) -> Rejection | None:
        """One message of ``topic`` (absolute, as ``topics()`` names it) received at
        ``recv_ns`` (the node's clock) at ``now`` (the caller's clock, s). Returns why it was
        refused (counted), or None."""
        role = self.roles[topic]
        try:
            rows = decode_rows(self.plan, role, msgtype, [bytes(payload)], [recv_ns])
        except (MessageDecodeError, Mismatch) as exc:
            return self._refuse(getattr(exc, "reason", "bad layout"), f"{topic}: {exc}")
        self.types.setdefault(topic, msgtype)
        self.counts.messages[topic] = self.counts.messages.get(topic, 0) + 1
        stamp = int(rows.stamp[0])
        group = _GROUP[role.role]
        if role.role == "reset":
            self.resets.append(int(recv_ns))
        elif not self._in_window(role, stamp):
            self.counts.old += 1  # a copy of a message the window let go of, or one far too late
            return None
        elif stamp < self.sealed[group] and not self._held(role).holds(stamp):
            self.counts.late += 1  # it may change a step handed out; kept for the steps to come
            self.counts.late_topics[topic] = self.counts.late_topics.get(topic, 0) + 1
        if role.role != "reset":
            self._held(role).append(rows)
        if stamp > self.watermark[topic]:
            self.watermark[topic] = stamp
            self.last_advance = now
            self.quiet_used = 0
        self.changed = True
        if role.types is not None and rows.wrong_length:
            return self._refuse("wrong length", f"{topic}: a command of another length than the "
                                                f"{self.task.act_dim} joints of robot.command.joints")
        return None

    def _refuse(self, reason: str, text: str) -> Rejection:
        self.counts.refused[reason] = self.counts.refused.get(reason, 0) + 1
        return Rejection(reason, text)

    def heard_stream(self) -> bool:
        """Whether the state and goal topics have been heard (the join can start)."""
        return len(self.states.rows) > 0 and len(self.goal.rows) > 0

    def _held(self, role: TopicRole) -> _Buffer:
        if role.role == "point":
            return self.points[role.name]
        if role.role == "label":
            return self.labels
        return {"state": self.states, "command": self.commands, "action": self.commands, "goal": self.goal}[role.role]

    def _in_window(self, role: TopicRole, stamp: int) -> bool:
        if role.role == "state":
            return stamp >= self.window_start
        if role.role == "goal":
            return stamp >= self.goal_start
        return stamp >= self.window_start - self.plan.tolerance_ns

    # ---------------------------------------------------------------- output
    def poll(self, now: float, idle_since: float = -math.inf, ended: bool = False, quiet: bool | None = None,
             all_arrived: bool = False) -> LiveSteps:
        """The steps that became final since the last poll. ``idle_since``: when the caller
        last finished other work (the quiet rule counts only time it was free to take
        messages); ``quiet``: whether all that was published has arrived but for commands
        still on their way (default: by the quiet rule); ``all_arrived``: commands too (the
        caller knows; otherwise after ``quiet_missing`` of silence); ``ended``: the stream is
        over (nothing more will come), every step is final."""
        silent = now - max(self.last_advance, idle_since)
        missing = all_arrived or silent >= self.settings.quiet_missing
        if quiet is None:
            quiet = silent >= self.settings.quiet
        level = 2 if missing else 1 if quiet else 0
        if not self.changed and level <= self.quiet_used and not ended:
            return self._none()
        self.changed = False
        self.quiet_used = level
        quiet = level > 0
        report = JoinReport("live", self.task.source_file())
        streams = Streams(self.states.rows, self.commands.rows, self.goal.rows,
                          {name: b.rows for name, b in self.points.items()}, np.asarray(self.resets, np.int64),
                          None if self.labels is None else self.labels.rows)
        try:
            result = join(self.plan, streams, report, self.kinematics, allow_empty=True, judge=self.judge,
                          terminate_on_success=self.terminate_on_success)
        except JoinEmpty:
            return self._none()
        seals = (-NEVER, -NEVER, -NEVER, -NEVER) if ended else self._seals(quiet, level == 2)
        cut = self._cut(result, seals)
        if cut <= self.handed_out:
            return self._none()
        # a command below the seal of the states without one could have changed a step handed out
        self.sealed.update(states=seals[0], commands=seals[2], observed=seals[3], labels=cut)
        t = result.state_t
        steps = np.flatnonzero((t >= self.handed_out) & (t < cut) & (result.cmd_dist >= 0))
        rows = result.row_of_state[steps]
        picked = rows[rows >= 0]
        data = result.data.select(picked)
        keys = result.episode_key[steps[rows >= 0]]
        ids = np.empty(keys.size, np.int64)
        for i, key in enumerate(keys):
            if key != self.episode_key:
                self.episode_key = int(key)
                self.episode_id += 1
            ids[i] = self.episode_id
        data.episode = ids
        self.handed_out = cut
        self._prune(result, cut)
        self.counts.steps += int(steps.size)
        self.counts.transitions += int(picked.size)
        if self.judge is not None:
            more = judged_counts(self.judge.source, data.success, result.rule_success[picked])
            for key in ("successes", "rule_successes", "false_successes", "missed"):
                self.counts.judged[key] += more[key]
        labels = None if result.labels is None else result.labels[picked]
        return LiveSteps(data, rows >= 0, labels)

    def _none(self) -> LiveSteps:
        return LiveSteps(Transitions.empty(0, Layout(self.task.obs_dim, self.task.act_dim)), np.zeros(0, bool))

    def _seals(self, quiet: bool, missing: bool = False) -> tuple[int, int, int, int]:
        """How far the states, the commands (for a state that has one, and for one that has
        none yet) and the goal and points are known complete: each topic up to its latest
        stamp, a silent one up to ``lateness`` behind the states; when quiet, all but the
        commands up to twice the largest tolerance past the latest state, and the commands of
        the states that have one up to just before it (those for earlier states were sent
        before it came; the latest state's may come only once the learner answers); with
        ``missing`` (a longer silence) the commands of those that have none too."""
        s_wm = self.watermark[self.plan.state_topic]
        if s_wm == NEVER:
            return NEVER, NEVER, NEVER, NEVER
        silent = s_wm - self.lateness_ns
        states = s_wm + (self.quiet_horizon if quiet else 0)
        read = self.topics()
        commands = min((max(self.watermark[r.topic], silent) for r in read if r.role in ("command", "action")),
                       default=silent)
        without = max(commands, s_wm - 1) if missing else commands
        if quiet:
            commands = max(commands, s_wm - 1)
        seen = min((max(self.watermark[r.topic], silent, states if quiet else NEVER)
                    for r in read if r.role in ("goal", "point")), default=states)
        return states, commands, without, seen

    def _cut(self, r, seals: tuple[int, int, int, int]) -> int:
        """The stamp before which every state's outcome is final."""
        states_seal, commands_seal, without_seal, observed_seal = seals
        if states_seal == NEVER:
            return NEVER
        tol, period, ptol = self.plan.tolerance_ns, self.plan.period_ns, self.plan.period_tolerance_ns
        t = r.state_t
        has_cmd = r.cmd_dist >= 0
        has_next = r.next_t >= 0
        need_commands = np.where(has_cmd, t + r.cmd_dist, t + tol)
        need_states = np.where(has_cmd, np.maximum(r.cmd_t + r.cmd_dist,
                                                   t + period + np.where(has_next, r.next_dist, ptol)), NEVER)
        need_observed = np.where(has_cmd & has_next, r.next_t + tol, t + tol)
        final = (np.where(has_cmd, commands_seal, without_seal) >= need_commands) & (states_seal >= need_states) \
            & (observed_seal >= need_observed)
        cut = min(self.watermark[self.plan.state_topic] + 1, states_seal)  # states not heard yet come later
        if not final.all():
            cut = min(cut, int(t[np.argmin(final)]))
        pending = r.unobserved_t[observed_seal < r.unobserved_t + tol]  # may yet get a goal or point
        if pending.size:
            cut = min(cut, int(pending.min()))
        return max(cut, self.handed_out)

    def _prune(self, r, cut: int) -> None:
        """Drop what no step to come can use: keep from the episode of the last final state."""
        done = np.flatnonzero(r.state_t < cut)
        if done.size == 0:
            return
        start = int(r.episode_key[done[-1]])
        if start <= self.window_start:
            return
        tol = self.plan.tolerance_ns
        goals = self.goal.rows
        goal_ok = goals.stamp[goals.ok & (goals.stamp <= start + tol)]
        self.window_start = start
        if goal_ok.size:
            self.goal_start = int(goal_ok.max())
        self.states.keep(lambda r: r.stamp >= start)
        self.commands.keep(lambda r: r.stamp >= start - tol)
        self.goal.keep(lambda r: r.stamp >= self.goal_start)
        for buffer in [*self.points.values(), *([self.labels] if self.labels is not None else [])]:
            buffer.keep(lambda r: r.stamp >= start - tol)

