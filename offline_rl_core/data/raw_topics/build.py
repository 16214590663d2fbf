"""Transitions from a bag of raw robot topics: states, commands and a goal, joined by stamp.

The steps, each on whole arrays:

1. Read the spec's topics (payloads and receive times) and decode them (``messages``).
   Stamps are the header stamps, or the bag's receive times with ``stamps: receive``.
2. Duplicates: messages of a topic with the same stamp. The first received is kept, the
   others counted (and how many of them differ from the kept one).
3. States get their target (the latest at or before the state's stamp, give or take the
   join tolerance) and fingertip (the one with the state's stamp, nearest within the
   tolerance; planar forward kinematics when the bag has no fingertip topic, or lacks the
   state's). A state without a target cannot be observed and is dropped.
4. Episodes: a new one starts where the target moves (more than ``target_change``), after a
   message on the reset topic (by receive order), or after a gap over ``max_gap``.
5. Each command joins one state: the one with its stamp (``match: exact``) or the nearest
   within ``tolerance``; when several commands join one state the nearest is kept. A
   command with no state, or superseded, is dropped and counted; none is ever filled in.
6. A joined command makes a transition to the state one control period later (give or take
   ``period_tolerance``) in the same episode; without one (the episode's last state, a
   dropped message) it is counted and dropped.
7. Reward, success latch and episode end: ``env.score_steps`` (the pusher's rule), the
   step index from the stamps (``round((t - episode start) / period)``).

Observations use ``env.batch_observations`` on the joint positions, velocities, target and
fingertip exactly as published, so a sim bag gives the sim's own transitions bit for bit.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..bag import TRANSITION_TOPIC, open_bag
from ..bag.estop_spans import bag_engaged_spans, engaged_at
from ...task.pusher_reach import (
    SUCCESS_TOL, StepScore, batch_observations, fingertip_from_joints, planar_distances, score_steps,
)
from ...common.errors import UserError
from ..transitions import SOURCE_BY_NAME, SOURCE_POLICY, Transitions, source_from_tag
from .messages import (
    FLOAT64_MULTI_ARRAY, HAS_HEADER, JOINT_STATE, POINT_STAMPED, Decoded, MessageDecodeError, decode_messages,
)
from .spec import SOURCE_AUTO, TopicSpec, load_spec



def source_of_topic(topic: str) -> int | None:
    """The source a command topic names (``.../command/expert`` ...), None for another."""
    return SOURCE_BY_NAME.get(topic.rstrip("/").rsplit("/", 1)[-1])


@dataclass
class JoinReport:
    """What the join found: every message is counted once, in one row of its topic."""

    bag: str
    spec: str
    fingertip: str = "forward kinematics"  # or the fingertip topic used
    command_topics: dict = field(default_factory=dict)  # topic -> messages
    states: dict = field(default_factory=dict)
    commands: dict = field(default_factory=dict)
    targets: dict = field(default_factory=dict)
    fingertips: dict = field(default_factory=dict)
    resets: int = 0
    episodes: int = 0
    episode_starts: dict = field(default_factory=dict)  # what started each new episode
    transitions: int = 0
    estop_dropped: int | None = None  # transitions whose state came while the e-stop was engaged; None: no estop topic

    def as_dict(self) -> dict:
        return {
            "bag": self.bag, "spec": self.spec, "fingertip": self.fingertip, "command_topics": self.command_topics,
            "states": self.states,
            "commands": self.commands, "targets": self.targets, "fingertips": self.fingertips,
            "resets": self.resets, "episodes": self.episodes, "episode_starts": self.episode_starts,
            "transitions": self.transitions,
            **({} if self.estop_dropped is None else {"estop_dropped": self.estop_dropped}),
        }

    def format(self) -> str:
        """The report as a few lines of text (what `offline-rl dataset` prints)."""
        st, cmd = self.states, self.commands
        lines = [
            f"{self.bag} (spec: {self.spec})",
            f"  states      {_messages_text(st)}, {st['malformed']} malformed, {st['without_target']} without a target; "
            f"{st['kept']} kept",
            f"  commands    {_messages_text(cmd)}, {cmd['malformed']} malformed; "
            f"joined {cmd['exact'] + cmd['within_tolerance']} ({cmd['exact']} exact, {cmd['within_tolerance']} within "
            f"tolerance), dropped {cmd['without_state']} without a state, {cmd['superseded']} with another command "
            f"nearer the same state, {cmd['no_next_state']} without a next state, {cmd['after_termination']} after "
            f"termination; {cmd['clipped']} clipped to [-1, 1]",
            f"              on {', '.join(f'{t} ({n})' for t, n in self.command_topics.items())}",
            f"  targets     {_messages_text(self.targets)}",
        ]
        if self.fingertips:
            lines.append(f"  fingertips  {_messages_text(self.fingertips)}; "
                         f"{self.fingertips['states_without']} states without one (planar kinematics)")
        lines.append(f"  fingertip   from {self.fingertip}")
        starts = ", ".join(f"{n} by {_START_CAUSE[k]}" for k, n in self.episode_starts.items())
        lines.append(f"  episodes    {self.episodes} (new episodes started: {starts})"
                     + (f"; {self.resets} reset messages" if self.resets else ""))
        if self.estop_dropped is not None:
            lines.append(f"  e-stop      {self.estop_dropped} transitions left out: their state came while it was engaged")
        lines.append(f"  transitions {self.transitions}")
        return "\n".join(lines)


_START_CAUSE = {"target": "a target change", "gap": "a time gap", "reset": "a reset message"}


def _messages_text(counts: dict) -> str:
    return (f"{counts['messages']} messages, {counts['duplicates']} duplicate stamps "
            f"({counts['duplicates_differing']} differing)")


def transitions_from_topics(bag: str | os.PathLike, spec: TopicSpec | str | os.PathLike | None) -> tuple[Transitions, JoinReport]:
    """The transitions of a raw-topic bag under ``spec`` (a TopicSpec, a YAML path or None
    for the defaults), and the report of the join. UserError for a missing topic, a wrong
    type, an unknown joint, or a bag that yields no transition."""
    if not isinstance(spec, TopicSpec):
        spec = load_spec(spec)
    bag = Path(bag)
    topics = _read_topics(bag, spec)
    return _Join(bag, spec, topics).run()


@dataclass
class _Topic:
    name: str
    msgtype: str
    recv_ns: np.ndarray  # int64 bag timestamps, in bag order
    payloads: list


def _read_topics(bag: Path, spec: TopicSpec) -> dict[str, _Topic]:
    """The spec's topics from the bag: type-checked, with payloads and receive times."""
    where = spec.path or "the default spec"
    commands = (JOINT_STATE, FLOAT64_MULTI_ARRAY)
    wanted = [  # (spec field, topic, accepted types, required)
        ("state.topic", spec.state_topic, (JOINT_STATE,), True),
        *(("command.topic", topic, commands, False) for topic in spec.command_topics),
        ("target.topic", spec.target_topic, (POINT_STAMPED,), True),
        ("fingertip.topic", spec.fingertip_topic, (POINT_STAMPED,), False),
        ("episodes.reset_topic", spec.reset_topic, None, True),
    ]
    with open_bag(bag) as reader:
        types: dict[str, set] = {}
        for c in reader.connections:
            types.setdefault(c.topic, set()).add(c.msgtype)
        have = ", ".join(sorted(types)) or "none"
        hint = ""
        if TRANSITION_TOPIC in types and spec.state_topic not in types:
            hint = f"; it holds {TRANSITION_TOPIC}: train on it without --from-topics"
        if not any(topic in types for topic in spec.command_topics):
            raise UserError(f"{bag}: no command topic ({', '.join(spec.command_topics)}: spec {where}, field command.topic); "
                            f"the bag has: {have}{hint}")
        found = {}
        for label, topic, accepted, required in wanted:
            if topic is None:
                continue
            if topic not in types:
                if not required:
                    continue
                raise UserError(f"{bag}: no topic {topic} (spec {where}, field {label}); the bag has: {have}{hint}")
            got = sorted(types[topic])
            if accepted is not None and (len(got) != 1 or got[0] not in accepted):
                raise UserError(f"{bag}: {topic} has type {', '.join(got)}; spec field {label} needs {' or '.join(accepted)}")
            if spec.stamps == "header" and accepted is not None and not HAS_HEADER[got[0]]:
                raise UserError(f"{spec.path or 'spec'}: field stamps is header, but {topic} ({got[0]}) has no header; "
                                "set stamps: receive to join by the bag's receive times")
            found[topic] = got[0]
        recv: dict[str, list] = {t: [] for t in found}
        data: dict[str, list] = {t: [] for t in found}
        connections = [c for c in reader.connections if c.topic in found]
        for conn, stamp, raw in reader.messages(connections=connections):
            recv[conn.topic].append(stamp)
            data[conn.topic].append(raw)
    return {t: _Topic(t, found[t], np.array(recv[t], np.int64), data[t]) for t in found}


def _decode(bag: Path, topic: _Topic) -> list[Decoded]:
    try:
        return decode_messages(topic.payloads, topic.msgtype)
    except MessageDecodeError as exc:
        raise UserError(f"{bag}: {topic.name}: not a readable {topic.msgtype}: {exc}") from None


def _nearest(sorted_t: np.ndarray, query: np.ndarray, tolerance_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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


def _first_per_stamp(stamp: np.ndarray, content: np.ndarray) -> tuple[np.ndarray, int, int]:
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


class _Join:
    def __init__(self, bag: Path, spec: TopicSpec, topics: dict[str, _Topic]):
        self.bag, self.spec, self.topics = bag, spec, topics
        self.report = JoinReport(str(bag), str(spec.path) if spec.path else "defaults")

    def stamps(self, topic: _Topic, decoded: list[Decoded]) -> np.ndarray:
        out = np.empty(len(topic.payloads), np.int64)
        for d in decoded:
            out[d.rows] = topic.recv_ns[d.rows] if self.spec.stamps == "receive" else d.stamp_ns
        return out

    # ------------------------------------------------------------------ topics
    def joint_columns(self, topic: _Topic, names: tuple[str, ...], count: int, order: tuple[str, ...], label: str):
        """Column of each spec joint in an array of ``count`` values named ``names`` (or, when
        the message names none, given in ``order``); None if the row does not fit."""
        if names:
            missing = [j for j in self.spec.joints if j not in names]
            if missing:
                raise UserError(f"{self.bag}: {topic.name}: joint {missing[0]!r} (spec field {label}) is not among "
                                f"the message's joint names [{', '.join(names)}]")
            return [names.index(j) for j in self.spec.joints] if count == len(names) else None
        return [order.index(j) for j in self.spec.joints] if count == len(order) else None

    def read_states(self):
        topic = self.topics[self.spec.state_topic]
        decoded = _decode(self.bag, topic)
        n = len(topic.payloads)
        stamp = self.stamps(topic, decoded)
        qpos = np.zeros((n, 2))
        qvel = np.zeros((n, 2))
        ok = np.zeros(n, bool)
        for d in decoded:
            counts = {key: count for key, _, count in d.layout.arrays}
            pos_cols = self.joint_columns(topic, d.layout.names, counts["position"], self.spec.joints, "state.joints")
            vel_cols = self.joint_columns(topic, d.layout.names, counts["velocity"], self.spec.joints, "state.joints")
            if pos_cols is None or vel_cols is None:
                continue
            qpos[d.rows] = d.arrays["position"][:, pos_cols]
            qvel[d.rows] = d.arrays["velocity"][:, vel_cols]
            ok[d.rows] = True
        finite = np.isfinite(qpos).all(axis=1) & np.isfinite(qvel).all(axis=1)
        kept, dups, differing = _first_per_stamp(stamp, np.hstack([qpos, qvel]))
        malformed = kept[~(ok & finite)[kept]]
        self.report.states = {"messages": n, "duplicates": dups, "duplicates_differing": differing,
                              "malformed": int(malformed.size)}
        kept = kept[(ok & finite)[kept]]
        return stamp[kept], topic.recv_ns[kept], qpos[kept], qvel[kept]

    def read_points(self, topic_name: str, section: dict) -> tuple[np.ndarray, np.ndarray]:
        """Stamps (sorted, one per stamp) and xy of a PointStamped topic."""
        topic = self.topics[topic_name]
        decoded = _decode(self.bag, topic)
        stamp = self.stamps(topic, decoded)
        xy = np.zeros((len(topic.payloads), 2))
        for d in decoded:
            xy[d.rows] = d.arrays["point"][:, :2]
        kept, dups, differing = _first_per_stamp(stamp, xy)
        finite = np.isfinite(xy[kept]).all(axis=1)
        section.update(messages=len(topic.payloads), duplicates=dups, duplicates_differing=differing,
                       malformed=int((~finite).sum()))
        kept = kept[finite]
        return stamp[kept], xy[kept]

    def read_command_topic(self, topic: _Topic):
        """Stamps, values (in state.joints order), sources and usability of one command topic."""
        spec = self.spec
        decoded = _decode(self.bag, topic)
        n = len(topic.payloads)
        value = np.zeros((n, 2))
        topic_source = source_of_topic(topic.name)
        source = np.full(n, SOURCE_POLICY if topic_source is None else topic_source)
        if spec.source != SOURCE_AUTO:
            source[:] = SOURCE_BY_NAME[spec.source]
        ok = np.zeros(n, bool)
        for d in decoded:
            if topic.msgtype == FLOAT64_MULTI_ARRAY:
                _, _, count = d.layout.arrays[0]
                data = d.arrays["data"][:, d.layout.data_offset:]
                cols = self.joint_columns(topic, (), count - d.layout.data_offset, spec.command_joints, "command.joints")
            else:
                _, _, count = d.layout.arrays[2]
                data = d.arrays["effort"]
                cols = self.joint_columns(topic, d.layout.names, count, spec.command_joints, "command.joints")
                tagged = source_from_tag(d.layout.frame_id)
                if spec.source == SOURCE_AUTO and topic_source is None and tagged is not None:
                    source[d.rows] = tagged
            if cols is None:
                continue
            value[d.rows] = data[:, cols]
            ok[d.rows] = True
        return self.stamps(topic, decoded), value, source, ok

    def read_commands(self):
        spec = self.spec
        topics = [self.topics[t] for t in spec.command_topics if t in self.topics]
        parts = [self.read_command_topic(topic) for topic in topics]
        stamp, value, source, ok = (np.concatenate([p[i] for p in parts]) for i in range(4))
        arrival = np.argsort(np.concatenate([t.recv_ns for t in topics]), kind="stable")  # across topics
        stamp, value, source, ok = stamp[arrival], value[arrival], source[arrival], ok[arrival]
        n = stamp.size
        action64 = value * spec.command_scale
        ok &= np.isfinite(action64).all(axis=1)
        kept, dups, differing = _first_per_stamp(stamp, np.hstack([value, source[:, None].astype(np.float64)]))
        malformed = int((~ok[kept]).sum())
        kept = kept[ok[kept]]
        clipped = int((np.abs(action64[kept]) > 1.0).any(axis=1).sum())
        self.report.command_topics = {t.name: len(t.payloads) for t in topics}
        self.report.commands = {"messages": n, "duplicates": dups, "duplicates_differing": differing,
                                "malformed": malformed, "clipped": clipped}
        action = np.clip(action64[kept], -1.0, 1.0).astype(np.float32)  # as the sim does: clip, then float32
        return stamp[kept], action, source[kept]

    # ------------------------------------------------------------------ the join
    def run(self) -> tuple[Transitions, JoinReport]:
        spec, report = self.spec, self.report
        tol = spec.join_tolerance_ns
        t_state, recv_state, qpos, qvel = self.read_states()
        t_target, target_xy = self.read_points(spec.target_topic, report.targets)

        # 3. target and fingertip of each state
        k = np.searchsorted(t_target, t_state + tol, side="right") - 1
        has_target = k >= 0
        report.states["without_target"] = int((~has_target).sum())
        t_state, recv_state, qpos, qvel, k = (a[has_target] for a in (t_state, recv_state, qpos, qvel, k))
        target = target_xy[k]
        if t_state.size == 0:
            raise UserError(f"{self.bag}: no usable state on {spec.state_topic} (with a target from {spec.target_topic}); "
                            f"{_counts_text(report.states)}")
        fingertip = np.empty((t_state.size, 2))
        has_tip = np.zeros(t_state.size, bool)
        if spec.fingertip_topic in self.topics:
            report.fingertip = spec.fingertip_topic
            t_tip, tip_xy = self.read_points(spec.fingertip_topic, report.fingertips)
            j, _, has_tip = _nearest(t_tip, t_state, tol)
            fingertip[has_tip] = tip_xy[j[has_tip]]
            report.fingertips["states_without"] = int((~has_tip).sum())
        for i in np.flatnonzero(~has_tip):  # the policy node's planar kinematics, value for value
            fingertip[i] = fingertip_from_joints(qpos[i])

        # 4. episodes
        starts = {"target": np.zeros(t_state.size, bool), "gap": np.zeros(t_state.size, bool)}
        moved = target[1:] - target[:-1]
        if spec.target_change > 0:
            starts["target"][1:] = np.hypot(moved[:, 0], moved[:, 1]) > spec.target_change
        else:
            starts["target"][1:] = (moved != 0).any(axis=1)
        starts["gap"][1:] = np.diff(t_state) > spec.max_gap_ns
        if spec.reset_topic is not None:
            resets = np.sort(self.topics[spec.reset_topic].recv_ns)
            report.resets = int(resets.size)
            seen = np.searchsorted(resets, recv_state, side="right")
            starts["reset"] = np.zeros(t_state.size, bool)
            starts["reset"][1:] = seen[1:] != seen[:-1]
        new = np.zeros(t_state.size, bool)
        new[0] = True
        for mask in starts.values():
            new |= mask
        episode = np.cumsum(new) - 1
        first_state = np.flatnonzero(new)

        # 5. commands to states
        t_cmd, action, source = self.read_commands()
        s, dist, joined = _nearest(t_state, t_cmd, tol)
        c = np.flatnonzero(joined)
        c = c[np.lexsort((t_cmd[c], dist[c], s[c]))]  # per state: nearest first, then earliest
        keep = np.ones(c.size, bool)
        keep[1:] = s[c][1:] != s[c][:-1]
        superseded = int((~keep).sum())
        c = c[keep]
        report.commands.update(exact=int((dist[c] == 0).sum()), within_tolerance=int((dist[c] > 0).sum()),
                               without_state=int((~joined).sum()), superseded=superseded)
        c = c[np.argsort(s[c], kind="stable")]
        a = s[c]  # the state each kept command acts on

        # 6. the state one period later, in the same episode
        b, _, has_next = _nearest(t_state, t_state[a] + spec.period_ns, spec.period_tolerance_ns)
        has_next &= episode[b] == episode[a]
        report.commands["no_next_state"] = int((~has_next).sum())
        c, a, b = c[has_next], a[has_next], b[has_next]

        # 7. reward, success latch, episode end: the pusher's rule on the next state
        dist_state = planar_distances(target, fingertip)
        hit = (dist_state < SUCCESS_TOL) & ~new  # the sim latches success only after a step
        hits_so_far = np.cumsum(hit)
        before_episode = np.where(first_state > 0, hits_so_far[first_state - 1], 0)[episode]
        success_before = hits_so_far[a] - before_episode[a] > 0
        step = np.rint((t_state[a] - t_state[first_state[episode[a]]]) / spec.period_ns).astype(np.int64)
        score = score_steps(target[b], fingertip[b], step + 1, success_before, spec.terminate_on_success)
        alive = ~(success_before & spec.terminate_on_success)
        report.commands["after_termination"] = int((~alive).sum())
        c, a, b, step, score = c[alive], a[alive], b[alive], step[alive], StepScore._make(f[alive] for f in score)
        spans = bag_engaged_spans(self.bag)  # the arm applied the safe command then, not these actions
        if spans is not None:
            outside = ~engaged_at(recv_state[a], spans)
            report.estop_dropped = int((~outside).sum())
            c, a, b, step, score = c[outside], a[outside], b[outside], step[outside], StepScore._make(f[outside] for f in score)
        if c.size == 0:
            raise UserError(f"{self.bag}: no transitions could be built from {spec.state_topic} and the commands; "
                            f"commands: {_counts_text(report.commands)}")

        obs_all = batch_observations(qpos, qvel, target, fingertip)
        used_episodes, episode_id = np.unique(episode[a], return_inverse=True)
        data = Transitions(
            obs=obs_all[a],
            action=action[c],
            reward=score.reward.astype(np.float32),
            next_obs=obs_all[b],
            terminated=score.terminated,
            truncated=score.truncated,
            success=score.success,
            episode=episode_id.astype(np.int64),
            step=step,
            source=source[c].astype(np.int64),
        )
        report.states["kept"] = int(t_state.size)
        report.episodes = int(used_episodes.size)
        report.episode_starts = {k: int(v.sum()) for k, v in starts.items()}
        report.transitions = len(data)
        return data, report


def _counts_text(counts: dict) -> str:
    return ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in counts.items())
