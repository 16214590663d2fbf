"""Transitions from a bag of raw robot topics: states, commands, a goal and tracked points,
joined by stamp as a task file says.

The steps, each on whole arrays:

1. Read the task's topics (payloads and receive times) and decode them (``streams``).
   Stamps are the header stamps, or the bag's receive times with ``join.stamps: receive``.
2. Duplicates: messages of a topic with the same stamp. The first received is kept, the
   others counted (and how many of them differ from the kept one). Joined by receive
   times, states with the same header stamp are duplicates too (a republished state).
3. States get their goal (the latest at or before the state's stamp, give or take the
   join tolerance) and each tracked point (the one with the state's stamp, nearest within
   the tolerance; the point's forward kinematics when its topic is not in the bag or lacks
   the state's). A state without a goal cannot be observed and is dropped.
4. Episodes: a new one starts where the goal moves (more than ``episodes.goal_change``),
   after a message on the reset topic (by receive order), after a gap over
   ``episodes.max_gap``, or at a state more than ``episodes.max_steps`` periods after the
   episode's first (the time limit).
5. Each command joins one state: the one with its stamp (``join.match: exact``) or the
   nearest within ``join.tolerance``; when several commands join one state the nearest is
   kept. A command with no state, or superseded, is dropped and counted; none is ever
   filled in. Joined by receive times, a command whose header names an earlier state than
   the one it arrived beside (a late re-send) is dropped and counted too. A joined command
   is one environment step of the recording.
6. A joined command makes a transition to the state one control period later (give or take
   ``join.period_tolerance``) in the same episode; without one (the episode's last state,
   a dropped message) it is counted and dropped.
7. Observation, reward, success latch and episode end: the task's (``task.features``), the
   step index from the stamps (``round((t - episode start) / period)``). With a ``judge`` (a
   success classifier of observations, ``learners.success_classifier``) each state's success
   is the judge's instead of the task's success distance: where no tracker says whether the
   puck is at the goal, a classifier trained on a person's labels does. The distance rule is
   still counted beside it (``JoinReport.judged``), never used.

The observation is computed from the joint positions, velocities, goal and points exactly as
published, so a sim bag gives the sim's own transitions bit for bit. ``join(...)`` (steps 2-7
on decoded arrays) is also what the live join (``live``) runs on its window of a stream.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...common.errors import UserError
from ...task import features
from ...task.spec import TaskSpec
from ..bag import TRANSITION_TOPIC, open_bag
from ..bag.estop_spans import bag_engaged_spans, engaged_at
from ..transitions import Transitions
from .messages import MessageDecodeError
from .spec import JoinPlan, plan_for
from .streams import NO_HEADER, Mismatch, Rows, decode_rows, has_header


@dataclass
class JoinReport:
    """What the join found: every message is counted once, in one row of its topic."""

    bag: str
    task: str
    points: dict = field(default_factory=dict)  # point -> where it came from (its topic, kinematics)
    command_topics: dict = field(default_factory=dict)  # topic -> messages
    states: dict = field(default_factory=dict)
    commands: dict = field(default_factory=dict)
    goals: dict = field(default_factory=dict)
    point_topics: dict = field(default_factory=dict)  # point -> counts of its topic
    resets: int = 0
    episodes: int = 0
    episode_starts: dict = field(default_factory=dict)  # what started each new episode
    steps: int = 0  # joined commands: the environment steps the recording holds
    transitions: int = 0
    ignored: dict = field(default_factory=dict)  # topic -> why it was not read
    estop_dropped: int | None = None  # transitions whose state came while the e-stop was engaged; None: no estop topic
    # with a judge: its successes against the task's success distance, per transition
    judged: dict | None = None
    # per episode of the transitions: when the bag received its first state (its log time, ns):
    # what tells which episode a label without an episode number labels
    episode_first_received: list[int] | None = field(default=None, repr=False)

    def as_dict(self) -> dict:
        fields = {k: getattr(self, k) for k in ("bag", "task", "points", "command_topics", "states", "commands",
                                                 "goals", "point_topics", "resets", "episodes", "episode_starts",
                                                 "steps", "transitions", "ignored")}
        if self.estop_dropped is not None:
            fields["estop_dropped"] = self.estop_dropped
        if self.judged is not None:
            fields["judged"] = self.judged
        return fields

    def format(self) -> str:
        """The report as a few lines of text (what `offline-rl dataset` prints)."""
        st, cmd = self.states, self.commands
        lines = [
            f"{self.bag} (task: {self.task})",
            f"  states      {_messages_text(st)}, {st['malformed']} malformed, {st['without_goal']} without a goal"
            + (f", {st['without_point']} without a tracked point" if st.get("without_point") else "")
            + f"; {st['kept']} kept",
            f"  commands    {_messages_text(cmd)}, {cmd['malformed']} malformed ({cmd['wrong_length']} of another "
            f"length); joined {cmd['exact'] + cmd['within_tolerance']} ({cmd['exact']} exact, "
            f"{cmd['within_tolerance']} within tolerance), dropped {cmd['without_state']} without a state, "
            f"{cmd['answering_an_earlier_state']} answering an earlier state (by its header), "
            f"{cmd['superseded']} with another command nearer the same state, {cmd['no_next_state']} without a "
            f"next state, {cmd['after_termination']} after termination; {cmd['clipped']} clipped to [-1, 1]",
            f"              on {', '.join(f'{t} ({n})' for t, n in self.command_topics.items())}"
            + "".join(f"; not {t}: {why}" for t, why in self.ignored.items()),
            f"  goals       {_messages_text(self.goals)}",
        ]
        for name, counts in self.point_topics.items():
            lines.append(f"  {name:<11} {_messages_text(counts)}; {counts['states_without']} states without one")
        for name, source in self.points.items():
            lines.append(f"  {name:<11} from {source}")
        starts = ", ".join(f"{n} by {_START_CAUSE[k]}" for k, n in self.episode_starts.items())
        lines.append(f"  episodes    {self.episodes} (new episodes started: {starts})"
                     + (f"; {self.resets} reset messages" if self.resets else ""))
        if self.estop_dropped is not None:
            lines.append(f"  e-stop      {self.estop_dropped} transitions left out: their state came while it was engaged")
        if self.judged is not None:
            j = self.judged
            lines.append(f"  success     judged by {j['judge']}: {j['successes']} transitions a success, "
                         f"{j['false_successes']} of them not by the task's success distance, {j['missed']} a "
                         f"success by the distance but not judged one")
        lines.append(f"  transitions {self.transitions} of {self.steps} steps")
        return "\n".join(lines)


_START_CAUSE = {"goal": "a goal change", "gap": "a time gap", "reset": "a reset message",
                "time_limit": "the time limit"}


def _messages_text(counts: dict) -> str:
    return (f"{counts['messages']} messages, {counts['duplicates']} duplicate stamps "
            f"({counts['duplicates_differing']} differing)")


def _counts_text(counts: dict) -> str:
    return ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in counts.items())


def transitions_from_topics(bag: str | os.PathLike, task: TaskSpec | str | os.PathLike | None = None,
                            judge=None, end_on_success: bool = False) -> tuple[Transitions, JoinReport]:
    """The transitions of a raw-topic bag as ``task`` says (a TaskSpec, a built-in name or a
    task file; None: the task the bag records, else pusher_reach), and the report of the
    join; ``judge``: a success classifier whose judgement replaces the task's success
    distance; ``end_on_success``: an episode ends at its first success (terminated; the
    steps after it make no transition), whatever the task's reward says. UserError for a missing topic, a wrong type, a joint the messages lack, a
    command of the wrong length, or a bag that yields no transition."""
    from ..task_record import task_of_bag

    bag = Path(bag)
    task = task_of_bag(bag, task)
    plan = plan_for(task)
    streams, report = read_bag(bag, plan)
    try:
        result = join(plan, streams, report, point_kinematics(task), engaged=bag_engaged_spans(bag), judge=judge,
                      terminate_on_success=True if end_on_success else None)
    except JoinEmpty as exc:
        raise UserError(f"{bag}: {exc}") from None
    return result.data, report


# ------------------------------------------------------------------ reading a bag

@dataclass
class Streams:
    """A recording's decoded topics by role (commands of every command topic merged, in
    arrival order)."""

    states: Rows
    commands: Rows
    goal: Rows
    points: dict  # point name -> Rows (points with a topic that was heard)
    resets: np.ndarray  # int64 receive times of reset messages
    labels: Rows | None = None  # the corrector's action labels (a plan with them), in arrival order


def read_bag(bag: Path, plan: JoinPlan) -> tuple[Streams, JoinReport]:
    """The task's topics from the bag, type-checked and decoded (UserError naming the topic
    and the task field for anything that does not fit)."""
    task = plan.task
    report = JoinReport(str(bag), task.source_file())
    with open_bag(bag) as reader:
        types: dict[str, set] = {}
        for c in reader.connections:
            types.setdefault(c.topic, set()).add(c.msgtype)
        have = ", ".join(sorted(types)) or "none"
        hint = ""
        if TRANSITION_TOPIC in types and plan.state_topic not in types:
            hint = f"; it holds {TRANSITION_TOPIC}: train on it without --from-topics"
        commands = plan.of_role("command", "action")
        if not any(r.topic in types for r in commands):
            raise UserError(f"{bag}: no command topic ({', '.join(r.topic for r in commands)}: {plan.where}, fields "
                            f"robot.command.topic and robot.command.action_topics); the bag has: {have}{hint}")
        found = {}
        for role in plan.roles:
            if role.topic not in types:
                if role.required:
                    raise UserError(f"{bag}: no topic {role.topic} ({plan.where}, field {role.field}); "
                                    f"the bag has: {have}{hint}")
                continue
            got = sorted(types[role.topic])
            if role.types is not None and len(got) != 1:
                raise UserError(f"{bag}: {role.topic} has several types ({', '.join(got)}); {plan.where} field "
                                f"{role.field} needs {' or '.join(role.types)}")
            found[role.topic] = got[0]
        headed = [r.topic for r in commands if r.topic in found and has_header(found[r.topic])]
        for role in commands:
            if role.topic in found and not plan.receive_stamps and not has_header(found[role.topic]) and headed:
                # joined by header stamps, a command without one cannot be placed; the
                # action topics (which have one) hold the arm's commands
                report.ignored[role.topic] = f"{found.pop(role.topic)} has no header (join.stamps: header)"
        recv: dict[str, list] = {t: [] for t in found}
        data: dict[str, list] = {t: [] for t in found}
        connections = [c for c in reader.connections if c.topic in found]
        for conn, stamp, raw in reader.messages(connections=connections):
            recv[conn.topic].append(stamp)
            data[conn.topic].append(raw)

    decoded: dict[str, Rows] = {}
    for topic, msgtype in found.items():
        role = plan.role_of(topic)
        try:
            decoded[topic] = decode_rows(plan, role, msgtype, data[topic], recv[topic])
        except MessageDecodeError as exc:
            raise UserError(f"{bag}: {topic}: not a readable {msgtype}: {exc}") from None
        except Mismatch as exc:
            raise UserError(f"{bag}: {exc}") from None
    for role in commands:
        rows = decoded.get(role.topic)
        if rows is not None and len(rows) and rows.wrong_length == len(rows):
            raise UserError(f"{bag}: {role.topic}: every command holds another number of values than the "
                            f"{task.act_dim} joints of {plan.where} field robot.command.joints "
                            f"({', '.join(task.command.joints)})")
    report.command_topics = {r.topic: len(decoded[r.topic]) for r in commands if r.topic in decoded}
    parts = [decoded[r.topic] for r in commands if r.topic in decoded]
    merged = Rows.concat(parts, task.act_dim)
    merged = merged.take(np.argsort(merged.recv, kind="stable"))  # arrival order across topics
    points = {r.name: decoded[r.topic] for r in plan.of_role("point") if r.topic in decoded}
    resets = [decoded[r.topic].recv for r in plan.of_role("reset") if r.topic in decoded]
    return Streams(decoded[plan.state_topic], merged, decoded[plan.goal_topic], points,
                   np.sort(resets[0]) if resets else np.zeros(0, np.int64)), report


def point_kinematics(task: TaskSpec):
    """The task's forward kinematics of its tracked points (None when no point has any);
    ``site:`` / ``body:`` points need the task's MuJoCo model (``task.envs.task_model``)."""
    from ...task.kinematics import PointKinematics

    kinds = [p.kinematics for p in task.points if p.kinematics is not None]
    if not kinds:
        return None
    model = None
    if any(k != "planar_two_link" for k in kinds):
        try:
            from ...task.envs import task_model
        except ImportError:  # the model hosting of task.envs is not in this build
            raise UserError(f"{task.source_file()}: points with site:/body: kinematics need the task's MuJoCo "
                            "model (offline_rl_core.task.envs), which this build lacks") from None
        model = task_model(task)
        if model is None:
            raise UserError(f"{task.source_file()}: points with site:/body: kinematics need a MuJoCo model "
                            "(field sim.model)")
    return PointKinematics(task, model)


# ------------------------------------------------------------------ the join

class JoinEmpty(ValueError):
    """The streams hold no usable state, or no transition."""


@dataclass
class JoinResult:
    """The transitions, and per kept state what the live join needs to tell a final outcome
    from one a later message could change."""

    data: Transitions
    step_of_row: np.ndarray  # int64: the environment step (joined command, from 0) of each transition
    state_t: np.ndarray  # int64 stamps of the kept states (sorted)
    episode_key: np.ndarray  # int64: the stamp of each kept state's episode's first state
    cmd_t: np.ndarray  # int64: the stamp of the command a state kept (-1: none)
    cmd_dist: np.ndarray  # int64 ns from that command to the state (-1: none)
    next_t: np.ndarray  # int64: the state one period later (-1: none), in this episode or not
    next_dist: np.ndarray  # int64 ns from it to one period later
    row_of_state: np.ndarray  # int64: the transition of each kept state (-1: none)
    unobserved_t: np.ndarray  # int64 stamps of states dropped for a missing goal or point
    # with a judge: each transition's success by the task's success distance (None: no judge)
    rule_success: np.ndarray | None = None
    # with action labels: each transition's label (float32, in [-1, 1]; NaN where its state has none)
    labels: np.ndarray | None = None


def first_per_stamp(stamp: np.ndarray, content: np.ndarray) -> tuple[np.ndarray, int, int]:
    """Rows to keep (the first received of each stamp, in stamp order), the number of
    duplicates and how many of those differ (bit for bit) from the row kept."""
    order = np.lexsort((np.arange(stamp.size), stamp))
    s = stamp[order]
    first = np.ones(s.size, bool)
    first[1:] = s[1:] != s[:-1]
    kept = order[first]
    dup = order[~first]
    if dup.size == 0:
        return kept, 0, 0
    ref = kept[(np.cumsum(first) - 1)[~first]]
    bits = np.ascontiguousarray(content).view(np.uint8).reshape(content.shape[0], -1)
    differing = int(np.any(bits[dup] != bits[ref], axis=1).sum())
    return kept, int(dup.size), differing


def nearest(sorted_t: np.ndarray, query: np.ndarray, tolerance_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each query stamp, the index of the nearest stamp in ``sorted_t`` (the earlier on
    a tie), its distance in ns and whether that is within the tolerance."""
    if sorted_t.size == 0:
        zeros = np.zeros(query.shape, np.int64)
        return zeros, zeros, np.zeros(query.shape, bool)
    right = np.searchsorted(sorted_t, query)
    left = np.clip(right - 1, 0, None)
    right = np.clip(right, 0, sorted_t.size - 1)
    d_left = np.abs(query - sorted_t[left])
    d_right = np.abs(sorted_t[right] - query)
    pick = np.where(d_right < d_left, right, left)
    dist = np.minimum(d_left, d_right)
    return pick, dist, dist <= tolerance_ns


def _unique_rows(rows: Rows, section: dict, by_header: bool = False) -> Rows:
    """One row per stamp, usable ones, in stamp order; counted into ``section``. With
    ``by_header`` (receive stamps), also one per header stamp: a copy received later (a
    state republished while the arm waits) is the same message."""
    content = np.hstack([rows.values, rows.source[:, None].astype(np.float64)])
    kept, dups, differing = first_per_stamp(rows.stamp, content)
    if by_header:
        headed = np.flatnonzero(rows.header[kept] != NO_HEADER)
        first, more, more_differing = first_per_stamp(rows.header[kept[headed]], content[kept[headed]])
        keep = np.ones(kept.size, bool)
        keep[headed] = False
        keep[headed[first]] = True  # the earliest received of each header stamp
        kept, dups, differing = kept[keep], dups + more, differing + more_differing
    section.update(messages=len(rows), duplicates=dups, duplicates_differing=differing,
                   malformed=int((~rows.ok[kept]).sum()))
    return rows.take(kept[rows.ok[kept]])


def _episode_starts(plan: JoinPlan, t: np.ndarray, recv: np.ndarray, goal: np.ndarray, resets: np.ndarray
                    ) -> tuple[np.ndarray, dict]:
    """Where each episode starts (bool per state) and the states each cause started."""
    ep = plan.task.episodes
    n = t.size
    starts = {"goal": np.zeros(n, bool), "gap": np.zeros(n, bool)}
    if n > 1:
        if ep.goal_change > 0:
            starts["goal"][1:] = features.distances(goal[1:], goal[:-1]) > ep.goal_change
        else:
            starts["goal"][1:] = (goal[1:] != goal[:-1]).any(axis=1)
        starts["gap"][1:] = np.diff(t) > plan.max_gap_ns
    if plan.task.episodes.reset_topic is not None:
        seen = np.searchsorted(resets, recv, side="right")
        starts["reset"] = np.zeros(n, bool)
        starts["reset"][1:] = seen[1:] != seen[:-1]
    new = np.zeros(n, bool)
    if n:
        new[0] = True
    for mask in starts.values():
        new |= mask
    # the time limit: a state more than max_steps periods after its episode's first starts the next
    limit = np.zeros(n, bool)
    firsts = list(np.flatnonzero(new)) + [n]
    for lo, hi in zip(firsts[:-1], firsts[1:]):
        first = lo
        while True:
            steps = np.rint((t[first:hi] - t[first]) / plan.period_ns)
            over = np.flatnonzero(steps > ep.max_steps)
            if over.size == 0:
                break
            first += int(over[0])
            limit[first] = True
    starts["time_limit"] = limit & ~new
    return new | limit, starts


def join(plan: JoinPlan, s: Streams, report: JoinReport, kinematics=None, allow_empty: bool = False,
         engaged: list[tuple[int, int]] | None = None, judge=None,
         terminate_on_success: bool | None = None) -> JoinResult:
    """Steps 2-7 on decoded streams. JoinEmpty when no state is usable, or (unless
    ``allow_empty``: the live join's window) no transition can be built. ``judge``: an object
    whose ``success(obs)`` (bool per observation) says which states are successes;
    ``terminate_on_success``: whether a success ends its episode (None: as the task's reward says)."""
    task = plan.task
    tol = plan.tolerance_ns
    n_joints = len(task.state.joints)

    # 2. one state per stamp
    states = _unique_rows(s.states, report.states, by_header=plan.receive_stamps)
    goals = _unique_rows(s.goal, report.goals)
    t_state, recv_state = states.stamp, states.recv

    # 3. the goal and points of each state
    k = np.searchsorted(goals.stamp, t_state + tol, side="right") - 1
    observed = k >= 0
    report.states["without_goal"] = int((~observed).sum())
    vectors = {"goal": goals.values[np.clip(k, 0, None)] if len(goals) else np.zeros((k.size, task.goal.size))}
    without_point = np.zeros(t_state.size, bool)
    for p in task.points:
        values = np.full((t_state.size, len(p.axes)), np.nan)
        heard = np.zeros(t_state.size, bool)
        rows = s.points.get(p.name)
        if rows is not None:
            counts = report.point_topics.setdefault(p.name, {})
            rows = _unique_rows(rows, counts)
            j, _, heard = nearest(rows.stamp, t_state, tol)
            values[heard] = rows.values[j[heard]]
            counts["states_without"] = int((~heard & observed).sum())
            report.points[p.name] = p.topic if p.kinematics is None else f"{p.topic}, else {p.kinematics}"
        else:
            report.points[p.name] = p.kinematics
        if p.kinematics is not None:
            for i in np.flatnonzero(~heard & observed):  # the policy node's kinematics, value for value
                values[i] = kinematics.point(p, states.values[i, :n_joints])
        else:
            without_point |= ~heard
        vectors[p.name] = values
    without_point &= observed
    report.states["without_point"] = int(without_point.sum())
    keep = observed & ~without_point
    unobserved_t = t_state[~keep]
    t_state, recv_state = t_state[keep], recv_state[keep]
    positions, velocities = states.values[keep, :n_joints], states.values[keep, n_joints:]
    vectors = {name: v[keep] for name, v in vectors.items()}
    if t_state.size == 0:
        raise JoinEmpty(f"no usable state on {plan.state_topic} (with a goal from {plan.goal_topic}); "
                        f"{_counts_text(report.states)}")

    # 4. episodes
    new, starts = _episode_starts(plan, t_state, recv_state, vectors["goal"], s.resets)
    report.resets = int(s.resets.size)
    episode = np.cumsum(new) - 1
    first_state = np.flatnonzero(new)

    # 5. commands to states
    commands = _unique_rows(s.commands, report.commands)
    report.commands["wrong_length"] = s.commands.wrong_length
    t_cmd, action64, source = commands.stamp, commands.values, commands.source
    report.commands["clipped"] = int((np.abs(action64) > 1.0).any(axis=1).sum())
    action = np.clip(action64, -1.0, 1.0).astype(np.float32)  # as the sim does: clip, then float32
    state_of, dist, joined = nearest(t_state, t_cmd, tol)
    # Joined by receive times, a command that names in its header an earlier state than the
    # one it arrived beside answers a state the arm had left (a re-send for a republished
    # state that came after the next one: the arm ignored it, as the sim does). Joined by
    # header stamps, such a command is never within the tolerance of that state anyway.
    header_state = states.header[keep][state_of] if t_state.size else np.zeros(0, np.int64)
    stale = (joined & (commands.header != NO_HEADER) & (header_state != NO_HEADER)
             & (commands.header < header_state - tol))
    joined &= ~stale
    c = np.flatnonzero(joined)
    # per state: a command of the project's action topics before the controller's (they say
    # who acted: the mux's output, where a policy node also sends its own proposal to the
    # controller), then the nearest, then the earliest
    c = c[np.lexsort((t_cmd[c], dist[c], commands.rank[c], state_of[c]))]
    first = np.ones(c.size, bool)
    first[1:] = state_of[c][1:] != state_of[c][:-1]
    report.commands.update(exact=int((dist[c[first]] == 0).sum()), within_tolerance=int((dist[c[first]] > 0).sum()),
                           without_state=int((~joined & ~stale).sum()), answering_an_earlier_state=int(stale.sum()),
                           superseded=int((~first).sum()))
    c = c[first]
    c = c[np.argsort(state_of[c], kind="stable")]
    a = state_of[c]  # the state each kept command acts on; one step each
    step_index = np.arange(c.size)

    # 6. the state one period later, in the same episode
    b, next_dist, has_next = nearest(t_state, t_state[a] + plan.period_ns, plan.period_tolerance_ns)
    candidate = has_next.copy()
    has_next &= episode[b] == episode[a]
    report.commands["no_next_state"] = int((~has_next).sum())
    live = {"cmd_t": np.full(t_state.size, -1, np.int64), "cmd_dist": np.full(t_state.size, -1, np.int64),
            "next_t": np.full(t_state.size, -1, np.int64), "next_dist": np.zeros(t_state.size, np.int64)}
    # how far a command nearer (or of an action topic, for the controller's) could still come
    live["cmd_t"][a], live["cmd_dist"][a] = t_cmd[c], np.where(commands.rank[c] > 0, tol, dist[c])
    live["next_t"][a[candidate]], live["next_dist"][a[candidate]] = t_state[b[candidate]], next_dist[candidate]
    c, a, b, step_index = c[has_next], a[has_next], b[has_next], step_index[has_next]

    # 7. reward, success latch, episode end: the task's rule on the next state
    obs_all = features.observe(task, positions, velocities, vectors)
    dist_state = features.distances(features.vector(task, task.reward.distance[0], positions, vectors),
                                    features.vector(task, task.reward.distance[1], positions, vectors))
    within = dist_state < task.reward.success_within
    judged = None
    if judge is not None:
        judge = judge if isinstance(judge, StateVerdicts) else StateVerdicts(judge)
        judged = judge(obs_all)
        within, rule_within = judged, within
    # success latches on a step's result, as the sim latches it: at states a command acts on
    # or a step ends in, never at an episode's first (a driver's states between two
    # commands of a slower controller are neither)
    control = np.zeros(t_state.size, bool)
    control[state_of[joined]] = True
    control[b] = True
    def latched_before(hit_now):
        hit = hit_now & ~new & control
        hits_so_far = np.cumsum(hit)
        before_episode = np.where(first_state > 0, hits_so_far[first_state - 1], 0)[episode]
        return hits_so_far[a] - before_episode[a] > 0

    success_before = latched_before(within)
    step = np.rint((t_state[a] - t_state[first_state[episode[a]]]) / plan.period_ns).astype(np.int64)
    next_vectors = {n: v[b] for n, v in vectors.items()}
    terminate = task.reward.terminate_on_success if terminate_on_success is None else terminate_on_success
    score = features.score(task, positions[b], next_vectors, step + 1, success_before, terminate,
                           success_now=None if judged is None else judged[b])
    rule = None if judged is None else features.score(task, positions[b], next_vectors, step + 1,
                                                      latched_before(rule_within)).success
    alive = ~(success_before & terminate)
    report.commands["after_termination"] = int((~alive).sum())
    c, a, b, step, step_index = c[alive], a[alive], b[alive], step[alive], step_index[alive]
    score = features.StepScore._make(f[alive] for f in score)
    rule = None if rule is None else rule[alive]
    if engaged is not None:  # the e-stop's spans (engaged, released): the arm applied the safe command then
        outside = ~engaged_at(recv_state[a], engaged)
        report.estop_dropped = int((~outside).sum())
        c, a, b, step, step_index = c[outside], a[outside], b[outside], step[outside], step_index[outside]
        score = features.StepScore._make(f[outside] for f in score)
        rule = None if rule is None else rule[outside]
    if rule is not None:
        report.judged = judged_counts(getattr(judge, "source", "a classifier"), score.success, rule)
    report.states["kept"] = int(t_state.size)
    report.episode_starts = {key: int(v.sum()) for key, v in starts.items()}
    report.steps = int(report.commands["exact"] + report.commands["within_tolerance"])

    used_episodes, episode_id = np.unique(episode[a], return_inverse=True)
    data = Transitions(
        obs=obs_all[a],
        action=action[c],
        reward=score.reward.astype(np.float32),
        next_obs=obs_all[b],
        terminated=score.terminated,
        truncated=score.truncated,
        success=score.success,
        episode=episode_id.reshape(-1).astype(np.int64),
        step=step,
        source=source[c].astype(np.int64),
    )
    report.episodes = int(used_episodes.size)
    report.episode_first_received = recv_state[first_state[used_episodes]].astype(np.int64).tolist()
    report.transitions = len(data)
    row_of_state = np.full(t_state.size, -1, np.int64)
    row_of_state[a] = np.arange(a.size)
    if c.size == 0 and not allow_empty:
        raise JoinEmpty(f"no transitions could be built from {plan.state_topic} and the commands; "
                        f"commands: {_counts_text(report.commands)}")
    labels = None
    if s.labels is not None:  # a label carries its state's header stamp; joined by receive times, matched by it
        by_header = plan.receive_stamps
        labels = _labels_of(s.labels, states.header[keep][a] if by_header else t_state[a], 0 if by_header else tol,
                            task.act_dim, by_header)
    return JoinResult(data, step_index.astype(np.int64), t_state, t_state[first_state[episode]], live["cmd_t"],
                      live["cmd_dist"], live["next_t"], live["next_dist"], row_of_state, unobserved_t, rule, labels)


def _labels_of(labels: Rows, t: np.ndarray, tol: int, act_dim: int, by_header: bool = False) -> np.ndarray:
    """The action label of each state stamped ``t`` (the one with its stamp, nearest within the
    join tolerance; the first received of a stamp; ``by_header``: ``t`` are the states' header
    stamps, matched to the labels'), clipped into [-1, 1] as a command is; NaN where none was heard."""
    out = np.full((t.size, act_dim), np.nan, np.float32)
    usable = labels.take(np.flatnonzero(labels.ok))
    if by_header:
        usable.stamp = usable.header
    if len(usable) == 0 or t.size == 0:
        return out
    keep, _, _ = first_per_stamp(usable.stamp, usable.values)
    usable = usable.take(keep)
    j, _, heard = nearest(usable.stamp, t, tol)
    out[heard] = np.clip(usable.values[j[heard]], -1.0, 1.0).astype(np.float32)
    return out


class StateVerdicts:
    """A judge's verdicts, one state at a time and remembered: a state's verdict must not
    depend on which states share its batch (a batched matrix product may round otherwise),
    and the live join, which joins a window of the stream again on every poll, judges each
    state once. ``judge.success(obs)``: bool per row of observations."""

    LIMIT = 200_000  # verdicts kept (the live join's window is an episode or two)

    def __init__(self, judge):
        self.judge = judge
        self.source = getattr(judge, "source", "a classifier")
        self.known: dict[bytes, bool] = {}

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        if len(self.known) > self.LIMIT:
            self.known.clear()
        out = np.empty(len(obs), bool)
        for i, row in enumerate(obs):
            key = row.tobytes()
            verdict = self.known.get(key)
            if verdict is None:
                verdict = self.known[key] = bool(self.judge.success(row[None])[0])
            out[i] = verdict
        return out


def judged_counts(judge: str, judged: np.ndarray, rule: np.ndarray) -> dict:
    """A judge's successes against the task's success distance, over the same transitions."""
    judged, rule = np.asarray(judged, bool), np.asarray(rule, bool)
    return {"judge": judge, "successes": int(judged.sum()), "rule_successes": int(rule.sum()),
            "false_successes": int((judged & ~rule).sum()), "missed": int((rule & ~judged).sum())}
