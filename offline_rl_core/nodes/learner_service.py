"""What the online learner node does, without ROS: take live transitions, train, cut
weights versions, save, resume.

The node (``ros2 run learner node``) only moves messages: each raw ``/pusher/transition``
goes to :meth:`LearnerService.receive`, a timer calls :meth:`LearnerService.work`, and
every weights version it returns is published for the acting policy node
(``serving.weights.encode_weights``). Files under ``out``:

- ``policy.pt``: the latest weights version, a checkpoint any tool loads (atomic);
- ``learner_state.pt``: everything needed to resume (networks, optimisers, generators,
  counters, the online buffer), written atomically every ``save_every`` seconds and at exit;
- ``progress.jsonl``: one line per weights version (counts, losses, timings);
- ``snapshots/policy_NNNNNN.pt``: the weights every ``snapshot_every`` transitions (the
  learning curve is scored from them afterwards, off the critical path).

Resuming (``resume``): the saved state is loaded, and with a ``session_bag`` (the
passive recorder's bag of the same session) the transitions that arrived after the save
are read back from it, so a learner killed mid-run loses nothing of the session and
continues exactly where an uninterrupted one would be.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..common.atomic import atomic_path
from ..data.bag.cdr import TransitionDecodeError, decode_transition_payloads
from ..common.errors import UserError
from ..learners.config import TrainConfig
from ..learners.online import OnlineLearner, OnlineSettings, PriorMismatch
from .joint_messages import VALUE_LIMIT
from ..common.output_paths import check_output_dir
from ..serving.checkpoint import checkpoint_task, load_checkpoint, save_checkpoint
from ..serving.policy import policy_for_task
from ..common.rejections import Rejection, RejectionCounter
from ..data.transitions import LAYOUT_SLICES, SOURCE_NAMES, Transitions


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
    settings: OnlineSettings = field(default_factory=OnlineSettings)
    train: TrainConfig = field(default_factory=lambda: TrainConfig(algo="sac"))


def check_row(row: np.ndarray) -> Rejection | None:
    """Why a decoded transition row must not be trained on, or None."""
    if not np.all(np.isfinite(row)):
        bad = [label for label, sl in LAYOUT_SLICES.items() if not np.all(np.isfinite(row[sl]))]
        return Rejection("non-finite", f"non-finite {', '.join(bad)}")
    action = row[LAYOUT_SLICES["action"]]
    if np.any(np.abs(action) > 1.0 + 1e-6):
        return Rejection("out of range", "action outside [-1, 1]")
    wild = [label for label in ("obs", "reward", "next_obs") if np.any(np.abs(row[LAYOUT_SLICES[label]]) > VALUE_LIMIT)]
    if wild:
        return Rejection("out of range", f"{', '.join(wild)} beyond ±{VALUE_LIMIT:g}")
    flags = [label for label in ("terminated", "truncated", "success")
             if row[LAYOUT_SLICES[label]][0] not in (0.0, 1.0)]
    if flags:
        return Rejection("out of range", f"{', '.join(flags)} not 0 or 1")
    counters = [label for label in ("episode", "step") if not _count(row[LAYOUT_SLICES[label]][0])]
    if counters:
        return Rejection("out of range", f"{', '.join(counters)} not a count")
    source = row[LAYOUT_SLICES["source"]][0]
    if source != int(source) or int(source) not in SOURCE_NAMES:
        return Rejection("unknown source", f"unknown source {source:g}")
    return None


def _count(value: float) -> bool:
    """Whether a float32 field holds a count (a whole number from 0 up, exact in float32)."""
    return 0.0 <= value < 2.0**24 and value == int(value)


class LearnerService:
    def __init__(self, cfg: LearnerServiceConfig, log=print):
        from ..runs.training_run import load_bags, task_of_run

        self.cfg, self.log = cfg, log
        self.out = check_output_dir(cfg.out, "parameter out:")  # before the bags load: a bad path is refused at once
        self.out.mkdir(parents=True, exist_ok=True)
        prior = load_checkpoint(cfg.prior) if cfg.prior else None  # validated as the policy node validates it
        given = cfg.task or (checkpoint_task(prior) if prior is not None and "task" in prior else None)
        self.task = task_of_run(cfg.bags, given)
        offline, _ = load_bags(cfg.bags, task=self.task)
        if prior is not None:
            policy_for_task(prior, cfg.prior, self.task)  # a prior of another task: one line naming both
            if prior["hidden"] != cfg.train.hidden:
                raise UserError(f"{cfg.prior}: the prior's hidden width is {prior['hidden']}, the learner's {cfg.train.hidden}")
        try:
            self.learner = OnlineLearner(offline, cfg.train, cfg.settings, cfg.seed, prior, self.task)
        except PriorMismatch as exc:
            raise UserError(f"{cfg.prior}: {exc}") from None
        self.rejected = RejectionCounter()  # live transitions refused, by reason (never trained on)
        self.received = 0  # live transitions accepted since this process started
        self.started = time.monotonic()
        self.last_save = time.monotonic()
        if cfg.snapshot_every and cfg.snapshot_every % cfg.settings.publish_every:
            raise UserError(f"snapshot_every ({cfg.snapshot_every}) must be a multiple of publish_every "
                            f"({cfg.settings.publish_every})")
        if cfg.resume:
            self._resume()
        else:
            self._write_policy(self.learner.weights())
            self.save()  # a resume point from the start: a learner killed at once restarts too
            if cfg.snapshot_every:
                save_checkpoint(self.out / "snapshots" / "policy_000000.pt", {**self.learner.weights(), "wall_s": 0.0,
                                                                             "train_s": 0.0})
        self.weights = self.learner.weights()  # the version the actor should be acting on

    # ---------------------------------------------------------------- input
    def receive(self, raw: bytes) -> Rejection | None:
        """One raw ``/pusher/transition``; returns why it was rejected (counted), or None."""
        try:
            row = decode_transition_payloads([bytes(raw)])[0]
        except TransitionDecodeError as exc:
            rejection = Rejection("bad layout", f"bad layout: {exc}")
        else:
            rejection = check_row(row)
        if rejection is not None:
            self.rejected.add(rejection)
            return rejection
        self.learner.add(Transitions.from_rows(row[None]))
        self.received += 1
        return None

    # ---------------------------------------------------------------- work
    def work(self, budget_s: float = 0.02) -> list[dict]:
        """Train for about ``budget_s`` seconds (or until nothing is owed); returns the
        weights versions cut meanwhile, oldest first."""
        versions = []
        deadline = time.perf_counter() + budget_s
        while self.learner.updates_owed > 0 and time.perf_counter() < deadline:
            self.learner.train(max_updates=8)
            if self.learner.version_due():
                self.weights = {**self.learner.cut_version(), "cut_unix": time.time()}
                versions.append(self.weights)
                self._on_version(self.weights)
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
                "wall_s": round(time.monotonic() - self.started, 3),
                **{k: round(v, 6) for k, v in self.learner.losses.items() if math.isfinite(v)}}
        with open(self.out / "progress.jsonl", "a", encoding="utf-8") as f:
            f.write(json.dumps(line) + "\n")

    def _write_policy(self, weights: dict) -> None:
        save_checkpoint(self.out / "policy.pt", weights)

    # ---------------------------------------------------------------- persistence
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
        saved = self.learner.n_online
        caught_up = 0
        if self.cfg.session_bag:
            from ..data.bag import read_transitions

            session = read_transitions(self.cfg.session_bag)
            rows = session.to_rows()[saved:]
            for row in rows:
                if check_row(row) is None:
                    self.learner.add(Transitions.from_rows(row[None]))
                    caught_up += 1
        self.log(f"learner: resumed from {path} at {saved} transitions, {self.learner.updates} updates, "
                 f"weights version {self.learner.version}" + (f"; {caught_up} more read back from "
                                                              f"{self.cfg.session_bag}" if self.cfg.session_bag else ""))

    def status(self) -> dict:
        learner = self.learner
        return {"received": learner.n_online, "evicted": learner.n_evicted, "updates": learner.updates, "owed": learner.updates_owed,
                "weights_version": learner.version, "rejected": dict(self.rejected.counts),
                "train_s": round(learner.train_seconds, 2), **{k: round(v, 5) for k, v in learner.losses.items()}}
