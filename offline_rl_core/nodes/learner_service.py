"""What the online learner node does, without ROS: take live transitions, train, cut
weights versions, save, resume.

The node (``ros2 run learner node``) only moves messages: each raw ``/pusher/transition``
goes to :meth:`LearnerService.receive`, a timer calls :meth:`LearnerService.work`, and
every weights version it returns is published for the acting policy node
(``serving.weights.encode_weights``). With ``from_topics`` the transitions are built from the
task's raw topics instead (a robot that publishes only standard topics): each message of
them goes to :meth:`LearnerService.receive_message`, and the live join
(``data.raw_topics.LiveJoin``) hands over the environment steps, with their transitions,
that no later message can change: the rows `offline-rl dataset` builds from the session's
bag. A task that joins by receive times (commands without a header) on a sim's clock
(``sim_time``) has each message stamped by the sim time current at its *publication*
(``publication_clock``, as the recorder on sim time stamps the session's bag): stamped when
the learner got to it, a command answering state t taken after state t + 1's /clock would
join the wrong state, and a lockstep arm, whose wall-clock periods are however long the
policy takes, would join none. Files under ``out``:

- ``policy.pt``: the latest weights version, a checkpoint any tool loads (atomic);
- ``learner_state.pt``: everything needed to resume (networks, optimisers, generators,
  counters, the online buffer), written atomically every ``save_every`` seconds and at exit;
- ``progress.jsonl``: one line per weights version (counts, losses, timings);
- ``snapshots/policy_NNNNNN.pt``: the weights every ``snapshot_every`` transitions (the
  learning curve is scored from them afterwards, off the critical path);
- the ``logger``'s files (``runs.loggers``; TensorBoard event files by default): each
  weights version's losses, counts, age and rates against live transitions.

Resuming (``resume``): the saved state is loaded, and with a ``session_bag`` (the
passive recorder's bag of the same session) the transitions that arrived after the save
are read back from it (raw topics: the bag's messages go through the live join first,
and the steps already trained on are skipped), so a learner killed mid-run loses nothing
of the session and continues exactly where an uninterrupted one would be.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..common.atomic import atomic_path, write_json_atomic
from ..data.bag.cdr import TransitionDecodeError, decode_transition_payloads
from ..common.errors import UserError
from ..learners.config import TrainConfig
from ..learners.online import OnlineLearner, OnlineSettings, PriorMismatch
from .estop import EStopLatch
from .joint_messages import VALUE_LIMIT
from .publication_clock import PublicationClock
from ..common.output_paths import check_output_dir
from ..runs.loggers import DEFAULT_LOGGER, check_logger, online_scalars, open_logger
from ..serving.checkpoint import checkpoint_task, load_checkpoint, save_checkpoint
from ..serving.policy import policy_for_task
from ..common.rejections import Rejection, RejectionCounter
from ..data.raw_topics.live import LiveJoin, LiveSettings
from ..data.raw_topics.messages import header_stamp_ns
from ..data.transitions import PUSHER_LAYOUT, SOURCE_NAMES, Layout, Transitions
from ..task.spec import TaskSpec


LIVE_POLL_PERIOD_S = 0.02


@dataclass
class LearnerServiceConfig:
    bags: list[str]
    out: str = "runs/online"
    prior: str | None = None
    seed: int = 0
    save_every: float = 2.0  # seconds between resume points
    resume: bool = False
    session_bag: str | None = None  # the session's recording: transitions missed while down
    snapshot_every: int = 0  # live transitions between kept copies of the weights (0: none)
    task: str | None = None  # a built-in task or a task file; None: the prior's, else the bags'
    from_topics: bool = False  # build the live transitions from the task's raw topics
    # raw topics: the corrector's action labels too (data.raw_topics.spec.ACTION_LABEL_TOPIC), joined
    # to the states they label and imitated there (the critic learns from the action the arm took)
    action_labels: bool = False
    success: str | None = None  # raw topics: a success classifier judges each state, not the success distance
    # raw topics: an episode ends at its first success, as the arm's do (a policy node's
    # end_on_success classifier labels it, or the sim's terminate_on_success)
    end_on_success: bool = False
    actors: tuple[str, ...] = ()  # the actors' namespaces, when several feed this learner (counted apart)
    live: LiveSettings = field(default_factory=LiveSettings)
    sim_time: bool = False  # raw topics joined by receive times: stamped by the sim time of their publication
    logger: str = DEFAULT_LOGGER  # where each version's losses and rates go besides progress.jsonl
    settings: OnlineSettings = field(default_factory=OnlineSettings)
    train: TrainConfig = field(default_factory=lambda: TrainConfig(algo="sac"))


def actor_transition_topics(actors: tuple[str, ...] | list[str]) -> list[tuple[str | None, str]]:
    """The (actor, topic) pairs a learner subscribes: each actor namespace's
    ``pusher/transition``, or (no actors given) the one in the learner's own namespace."""
    if not actors:
        return [(None, "pusher/transition")]
    bad = [ns for ns in actors if not ns.startswith("/") or ns == "/" or ns.endswith("/") or " " in ns]
    if bad:
        raise UserError(f"parameter actors: {bad[0]!r} is no namespace; expected absolute names such as /arm1")
    if len(set(actors)) != len(actors):
        raise UserError(f"parameter actors: {', '.join(actors)} names an actor twice")
    return [(ns, f"{ns}/pusher/transition") for ns in actors]


def check_row(row: np.ndarray, layout: Layout = PUSHER_LAYOUT) -> Rejection | None:
    """Why a decoded transition row of ``layout`` (the task's) must not be trained on, or None."""
    slices = layout.slices
    if not np.all(np.isfinite(row)):
        bad = [label for label, sl in slices.items() if not np.all(np.isfinite(row[sl]))]
        return Rejection("non-finite", f"non-finite {', '.join(bad)}")
    action = row[slices["action"]]
    if np.any(np.abs(action) > 1.0 + 1e-6):
        return Rejection("out of range", "action outside [-1, 1]")
    wild = [label for label in ("obs", "reward", "next_obs") if np.any(np.abs(row[slices[label]]) > VALUE_LIMIT)]
    if wild:
        return Rejection("out of range", f"{', '.join(wild)} beyond ±{VALUE_LIMIT:g}")
    flags = [label for label in ("terminated", "truncated", "success")
             if row[slices[label]][0] not in (0.0, 1.0)]
    if flags:
        return Rejection("out of range", f"{', '.join(flags)} not 0 or 1")
    counters = [label for label in ("episode", "step") if not _count(row[slices[label]][0])]
    if counters:
        return Rejection("out of range", f"{', '.join(counters)} not a count")
    source = row[slices["source"]][0]
    if source != int(source) or int(source) not in SOURCE_NAMES:
        return Rejection("unknown source", f"unknown source {source:g}")
    return None


def _count(value: float) -> bool:
    """Whether a float32 field holds a count (a whole number from 0 up, exact in float32)."""
    return 0.0 <= value < 2.0**24 and value == int(value)


class LearnerService:
    def __init__(self, cfg: LearnerServiceConfig, log=print):
        from ..runs.training_run import estop_dropped_of, load_bags, task_of_run

        self.cfg, self.log = cfg, log
        self.out = check_output_dir(cfg.out, "parameter out:")  # before the bags load: a bad path is refused at once
        self.transition_topics = actor_transition_topics(cfg.actors)
        if cfg.actors and cfg.from_topics:
            raise UserError("parameter actors: several actors feed the learner on their pusher/transition; "
                            "from_topics joins one robot's raw topics")
        check_logger(cfg.logger, "parameter logger:")
        self.out.mkdir(parents=True, exist_ok=True)
        prior = load_checkpoint(cfg.prior) if cfg.prior else None  # validated as the policy node validates it
        given = cfg.task or (checkpoint_task(prior) if prior is not None and "task" in prior else None)
        self.task = task_of_run(cfg.bags, given)
        self.layout = Layout(self.task.obs_dim, self.task.act_dim)
        offline, bags_read = self._offline(cfg.bags, cfg.from_topics, self.task, load_bags)
        self.offline_estop_dropped = estop_dropped_of(bags_read)  # None: no offline bag records the e-stop
        if self.offline_estop_dropped is not None:
            log(f"offline half: left out {self.offline_estop_dropped} transitions recorded while the e-stop was engaged")
        # the live join of the task's raw topics (None: the transitions come on pusher/transition)
        judge = self._judge(cfg)  # a classifier without from_topics is refused here, not ignored
        if cfg.action_labels and not cfg.from_topics:
            raise UserError("parameter action_labels: only with from_topics (the labels are joined to the raw "
                            "topics' states by stamp)")
        if cfg.end_on_success and not cfg.from_topics:
            raise UserError("parameter end_on_success: only with from_topics (pusher/transition comes with its "
                            "episode's end from the sim)")
        self.live = LiveJoin(self.task, cfg.live, judge, cfg.action_labels, cfg.end_on_success) \
            if cfg.from_topics else None
        # raw topics joined by receive times, on a sim's /clock: each message waits for the
        # /clock that says which tick it was published in (see receive_clock)
        self.publication_clock = PublicationClock() if (
            self.live is not None and cfg.sim_time and self.live.plan.receive_stamps) else None
        self.last_arrival = -math.inf  # when a raw message or /clock last came (the quiet rule)
        self.idle_since = time.monotonic()  # when training last stopped (the live join's quiet rule)
        self.skip_steps = 0  # steps the live join hands over again after a resume (trained on already)
        self.last_poll = -math.inf
        self.live_file_due = False
        if prior is not None:
            policy_for_task(prior, cfg.prior, self.task)  # a prior of another task: one line naming both
        try:
            self.learner = OnlineLearner(offline, cfg.train, cfg.settings, cfg.seed, prior, self.task)
        except PriorMismatch as exc:
            raise UserError(f"{cfg.prior}: {exc}") from None
        self.rejected = RejectionCounter()  # live transitions refused, by reason (never trained on)
        self.estop = EStopLatch()  # while engaged, every live transition is dropped (counted as estop)
        # each actor's own e-stop: while engaged, that actor's transitions are dropped
        self.actor_estops = {ns: EStopLatch() for ns in cfg.actors}
        self.received = 0  # live transitions accepted since this process started
        # accepted transitions by actor namespace, when several actors feed this learner
        self.received_from: dict[str, int] = {ns: 0 for ns in cfg.actors}
        self.started = time.monotonic()
        self.last_save = time.monotonic()
        if cfg.snapshot_every and cfg.snapshot_every % cfg.settings.publish_every:
            raise UserError(f"snapshot_every ({cfg.snapshot_every}) must be a multiple of publish_every "
                            f"({cfg.settings.publish_every})")
        self.curves = open_logger(cfg.logger, self.out, name=self.out.name, resume=cfg.resume, config=self._settings())
        self.curves.drop_previous()  # a fresh session starts anew, as its progress.jsonl does
        if cfg.resume:
            self._resume()
        else:
            self._write_policy(self.learner.weights())
            self.save()  # a resume point from the start: a learner killed at once restarts too
            if cfg.snapshot_every:
                save_checkpoint(self.out / "snapshots" / "policy_000000.pt", {**self.learner.weights(), "wall_s": 0.0,
                                                                             "train_s": 0.0})
        self.weights = self.learner.weights()  # the version the actor should be acting on

    def _judge(self, cfg: LearnerServiceConfig):
        """The success classifier the live join judges states with (None: the task's distance)."""
        if cfg.success is None:
            return None
        if not cfg.from_topics:
            raise UserError(f"parameter success ({cfg.success}): a classifier judges the live join's states; "
                            "pusher/transition comes scored by its sim (set from_topics)")
        from ..learners.success_classifier import load_classifier

        return load_classifier(cfg.success, self.task)

    @staticmethod
    def _offline(bags: list[str], from_topics: bool, task: TaskSpec, load_bags) -> tuple[Transitions, list[dict]]:
        """The offline bags: their transitions, or (raw topics) those joined from a bag
        that holds none; and each bag's summary."""
        if not from_topics:
            return load_bags(bags, task=task)
        from ..data.bag.reader import records_transitions

        parts, summaries = [], []
        for bag in bags:
            data, summary = load_bags([bag], from_topics=not records_transitions(bag) or None, task=task)
            parts.append(data)
            summaries += summary
        if len(parts) == 1:
            return parts[0], summaries
        offset = 0
        for part in parts:  # episode ids unique across bags, as load_bags keeps them
            part.episode = part.episode - part.episode.min() + offset
            offset = int(part.episode.max()) + 1
        return Transitions.concatenate(parts), summaries

    # ---------------------------------------------------------------- input
    def receive(self, raw: bytes, actor: str | None = None) -> Rejection | None:
        """One raw ``/pusher/transition`` (of the actor in namespace ``actor``, when several
        feed the learner); returns why it was rejected (counted), or None."""
        if self.estop.engaged or (actor is not None and self.actor_estops[actor].engaged):
            # the arm applies the safe command: those steps say nothing of the policy
            rejection = Rejection("estop", "a transition while the e-stop is engaged: not trained on")
            self.rejected.add(rejection)
            return rejection
        try:
            row = decode_transition_payloads([bytes(raw)], self.layout)[0]
        except TransitionDecodeError as exc:
            rejection = Rejection("bad layout", f"bad layout: {exc}")
        else:
            rejection = check_row(row, self.layout)
        if rejection is not None:
            self.rejected.add(rejection)
            return rejection
        self.learner.add(Transitions.from_rows(row[None], self.layout))
        self.received += 1
        if actor is not None:
            self.received_from[actor] += 1
        return None

    def receive_message(self, topic: str, msgtype: str, raw: bytes, recv_ns: int,
                        published_ns: int | None = None) -> Rejection | None:
        """One message of the task's raw topics (``topic`` as ``live.topics()`` names it),
        received at ``recv_ns`` (the node's clock) and published at ``published_ns`` (the
        publisher's wall clock: its MessageInfo's source timestamp); returns why it, or a
        message it let through, was refused (counted), or None. With a publication clock the
        message waits for the /clock published after it (``receive_clock``)."""
        if self.publication_clock is None or published_ns is None:
            return self._join(topic, msgtype, raw, recv_ns)
        self.last_arrival = time.monotonic()
        # a sim's state and goal say their tick (header stamps): not flushed before its /clock
        said = header_stamp_ns(raw, msgtype)
        return self._join_released(self.publication_clock.add(published_ns, (topic, msgtype, raw, recv_ns), said))

    def receive_clock(self, published_ns: int, sim_ns: int) -> Rejection | None:
        """A /clock message (``sim_ns``, published at ``published_ns``): the messages published
        before it go to the live join, stamped with the sim time of their publication."""
        if self.publication_clock is None:
            return None
        self.last_arrival = time.monotonic()
        return self._join_released(self.publication_clock.add_clock(published_ns, sim_ns))

    def _join_released(self, released) -> Rejection | None:
        first = None
        for stamp, (topic, msgtype, raw, recv_ns) in released:
            rejection = self._join(topic, msgtype, raw, recv_ns if stamp is None else stamp)
            first = first or rejection
        return first

    def _join(self, topic: str, msgtype: str, raw: bytes, stamp_ns: int) -> Rejection | None:
        rejection = self.live.add(topic, msgtype, raw, stamp_ns, time.monotonic())
        if rejection is not None:
            self.rejected.add(rejection)
        return rejection

    def take_steps(self, ended: bool = False, quiet: bool | None = None) -> int:
        """Hand the environment steps the live join holds as final to the learner (each with
        its transition, or none); returns how many. ``quiet``: everything published has
        arrived (default: the live join's quiet rule)."""
        if self.live is None:
            return 0
        told = quiet is True  # the caller knows all has arrived, commands included
        now = time.monotonic()
        if now - self.last_poll < LIVE_POLL_PERIOD_S and not ended and quiet is None:
            return 0  # a join of the window costs milliseconds: at most once a control period
        self.last_poll = now
        if self.publication_clock is not None:
            # nothing came while idle (a lockstep arm waits for the learner): every /clock
            # published has arrived, so the messages still waiting for a later one (the
            # latest state, its goal) are stamped by the newest
            silent = now - max(self.last_arrival, self.idle_since)
            if quiet is None:
                quiet = silent >= self.cfg.live.quiet
            if (quiet or ended) and self.publication_clock.waiting:
                # a state ahead of the newest /clock: its /clock is still on its way (held
                # for up to quiet_missing: a /clock lost for good must not stop the session)
                wait = not (ended or told or silent >= self.cfg.live.quiet_missing)
                self._join_released(self.publication_clock.flush(wait_for_clock=wait))
        steps = self.live.poll(now, self.idle_since, ended=ended, quiet=quiet, all_arrived=told)
        if len(steps) == 0:
            return 0
        self.live_file_due = True
        rows = steps.transitions.to_rows() if len(steps.transitions) else np.zeros((0, self.layout.width), np.float32)
        k = 0
        for has_row in steps.has_row:
            row = rows[k] if has_row else None
            label = steps.labels[k:k + 1] if has_row and steps.labels is not None else None
            k += bool(has_row)
            if self.skip_steps:
                self.skip_steps -= 1
                continue
            rejection = None if row is None else check_row(row, self.layout)
            if row is not None and self.estop.engaged:  # the arm applied the safe command then
                rejection = Rejection("estop", "a step while the e-stop is engaged: not trained on")
            if rejection is not None:
                self.rejected.add(rejection)
                row = None  # still a step of the arm: the versions stay in step with it
            self.learner.add(Transitions.from_rows(row[None] if row is not None else rows[:0], self.layout), steps=1,
                             labels=label if row is not None else None)
            self.received += row is not None
        return len(steps)

    # ---------------------------------------------------------------- work
    def work(self, budget_s: float = 0.02) -> list[dict]:
        """Train for about ``budget_s`` seconds (or until nothing is owed); returns the
        weights versions cut meanwhile, oldest first."""
        versions = []
        self.take_steps()
        deadline = time.perf_counter() + budget_s
        trained = False
        while self.learner.updates_owed > 0 and time.perf_counter() < deadline:
            trained = True
            self.learner.train(max_updates=8)
            if self.learner.version_due():
                self.weights = {**self.learner.cut_version(), "cut_unix": time.time()}
                versions.append(self.weights)
                self._on_version(self.weights)
        if trained:
            self.idle_since = time.monotonic()
        if self.live is not None and self.live_file_due and not self.learner.updates_owed:
            self._write_live_file()
        if time.monotonic() - self.last_save >= self.cfg.save_every:
            self.save()
        return versions

    def _on_version(self, weights: dict) -> None:
        self._write_policy(weights)
        n, every = weights["trained_through"], self.cfg.snapshot_every
        if every and n % every == 0:
            snap = {**weights, "wall_s": round(time.monotonic() - self.started, 3),
                    "train_s": round(self.learner.train_seconds, 3)}
            save_checkpoint(self.out / "snapshots" / f"policy_{n:06d}.pt", snap)
        line = {"weights_version": weights["weights_version"], "trained_through": weights["trained_through"],
                "updates": self.learner.updates, "received": self.learner.n_online, "human": self.learner.n_human,
                "rejected": self.rejected.total, "train_s": round(self.learner.train_seconds, 3),
                **({"received_from": dict(self.received_from)} if self.received_from else {}),
                "wall_s": round(time.monotonic() - self.started, 3),
                **{k: round(v, 6) for k, v in self.learner.losses.items() if math.isfinite(v)}}
        with open(self.out / "progress.jsonl", "a", encoding="utf-8") as f:
            f.write(json.dumps(line) + "\n")
        arrived_per_s = self.received / max(time.monotonic() - self.started, 1e-9)  # since this process started
        self.curves.scalars(n, {**online_scalars(self.learner, weights, arrived_per_s),
                                "online/rejected": self.rejected.total})

    def _write_policy(self, weights: dict) -> None:
        save_checkpoint(self.out / "policy.pt", weights)

    def _write_live_file(self) -> None:
        """``live.json``: the steps taken from the raw topics and trained on (a pipeline
        waits on it for the learner to have the whole session before stopping it)."""
        self.live_file_due = False
        labelled = {"labelled": self.learner.n_labelled} if self.cfg.action_labels else {}
        write_json_atomic(self.out / "live.json", {"steps": self.learner.n_steps, "transitions": self.learner.n_online,
                                                   **labelled, "updates": self.learner.updates,
                                                   "join": self.live.counts.as_dict()})

    # ---------------------------------------------------------------- persistence
    def close(self) -> Path:
        """On the way out: the steps whose messages have all come (nothing is in flight any
        more; a learner busy training till the end never saw the stream fall quiet), then the
        resume point, and the logger's last scalars and settings."""
        self.take_steps(quiet=True)
        path = self.save()
        if self.live is not None:
            self._write_live_file()  # what close took too: live.json agrees with learner_state.pt
            self.log(f"learner: closed at {self.learner.n_steps} environment steps, {self.learner.n_online} "
                     f"transitions; live join {json.dumps(self.live.counts.as_dict())}")
        self.curves.hparams(self._settings(), {f"train/{k}": v for k, v in self.learner.losses.items()
                                               if math.isfinite(v)})
        self.curves.close()
        return path

    def _settings(self) -> dict:
        cfg = self.cfg
        return {"online": asdict(cfg.settings), "train": cfg.train.to_dict(), "seed": cfg.seed, "prior": cfg.prior,
                "task": self.task.name}

    def save(self) -> Path:
        path = self.out / "learner_state.pt"
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            torch.save(self.learner.state(), f)
            f.flush()
            os.fsync(f.fileno())
        self.last_save = time.monotonic()
        return path

    def _resume(self) -> None:
        path = self.out / "learner_state.pt"
        if not path.exists():
            raise UserError(f"{path}: no saved learner state to resume from")
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
            self.learner.restore(state)
        except (OSError, RuntimeError, ValueError, KeyError) as exc:
            raise UserError(f"{path}: cannot resume from it ({str(exc).splitlines()[0][:160]})") from None
        saved = self.learner.n_steps
        caught_up = 0
        if self.cfg.session_bag and self.live is not None:
            self.skip_steps = saved
            self._feed_session_bag(self.cfg.session_bag)
            before = self.learner.n_steps
            self.take_steps()
            caught_up = self.learner.n_steps - before
        elif self.cfg.session_bag:
            from ..data.bag import read_transitions

            session = read_transitions(self.cfg.session_bag)
            rows = session.to_rows()[saved:]
            for row in rows:
                if check_row(row, self.layout) is None:
                    self.learner.add(Transitions.from_rows(row[None], self.layout))
                    caught_up += 1
        self.log(f"learner: resumed from {path} at {saved} transitions, {self.learner.updates} updates, "
                 f"weights version {self.learner.version}" + (f"; {caught_up} more read back from "
                                                              f"{self.cfg.session_bag}" if self.cfg.session_bag else ""))

    def _feed_session_bag(self, path) -> None:
        """The session's recording into the live join, as if its messages had just arrived."""
        from ..data.bag.reader import open_bag

        wanted = {r.topic for r in self.live.topics()}
        with open_bag(path) as reader:
            connections = [c for c in reader.connections if c.topic in wanted]
            now = time.monotonic()
            for conn, stamp, raw in reader.messages(connections=connections):
                self.live.add(conn.topic, conn.msgtype, bytes(raw), stamp, now)

    def status(self) -> dict:
        learner = self.learner
        live = {"steps": learner.n_steps, "join": self.live.counts.as_dict()} if self.live is not None else {}
        actors = {"received_from": dict(self.received_from)} if self.received_from else {}
        labelled = {"labelled": learner.n_labelled} if self.cfg.action_labels else {}
        return {"received": learner.n_online, **live, **actors, **labelled, "evicted": learner.n_evicted,
                "updates": learner.updates,
                "owed": learner.updates_owed,
                "weights_version": learner.version, "rejected": dict(self.rejected.counts),
                "estop": self.estop.as_dict(),
                **({"actor_estops": {ns: latch.as_dict() for ns, latch in self.actor_estops.items()}}
                   if self.actor_estops else {}),
                **({} if self.offline_estop_dropped is None else {"offline_estop_dropped": self.offline_estop_dropped}),
                "train_s": round(learner.train_seconds, 2), **{k: round(v, 5) for k, v in learner.losses.items()}}
