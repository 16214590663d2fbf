"""What the online learner node does, without ROS: take live transitions, train, cut
weights versions, save, resume.

The node (``ros2 run learner node``) only moves messages: each raw ``/pusher/transition``
goes to :meth:`LearnerService.receive`, a timer calls :meth:`LearnerService.work`, and
every weights version it returns is published for the acting policy node
(:func:`encode_weights`). Files under ``out``:

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

from .atomic import atomic_path
from .bag.cdr import TransitionDecodeError, decode_transition_payloads
from .errors import UserError
from .learners.config import TrainConfig
from .learners.online import OnlineLearner, OnlineSettings
from .policy import checkpoint_from_bytes, checkpoint_to_bytes, load_checkpoint, save_checkpoint
from .transitions import LAYOUT_SLICES, SOURCE_NAMES, Transitions

WEIGHTS_LABEL = "pusher-rl/weights"  # the weights message's layout label: what its bytes are


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
    settings: OnlineSettings = field(default_factory=OnlineSettings)
    train: TrainConfig = field(default_factory=lambda: TrainConfig(algo="sac"))


@dataclass
class Rejections:
    """Live transitions refused, by reason (never trained on)."""

    counts: dict[str, int] = field(default_factory=dict)

    def add(self, reason: str) -> None:
        self.counts[reason] = self.counts.get(reason, 0) + 1

    @property
    def total(self) -> int:
        return sum(self.counts.values())


def check_row(row: np.ndarray) -> str | None:
    """Why a decoded transition row must not be trained on, or None."""
    if not np.all(np.isfinite(row)):
        bad = [label for label, sl in LAYOUT_SLICES.items() if not np.all(np.isfinite(row[sl]))]
        return f"non-finite {', '.join(bad)}"
    action = row[LAYOUT_SLICES["action"]]
    if np.any(np.abs(action) > 1.0 + 1e-6):
        return "action outside [-1, 1]"
    if int(row[LAYOUT_SLICES["source"]][0]) not in SOURCE_NAMES:
        return f"unknown source {row[LAYOUT_SLICES['source']][0]:g}"
    return None


def encode_weights(checkpoint: dict) -> bytes:
    """A weights version as the bytes of a ``std_msgs/UInt8MultiArray`` (a checkpoint,
    ``torch.save`` format, loaded back with ``weights_only``)."""
    return checkpoint_to_bytes(serving_part(checkpoint))


def serving_part(checkpoint: dict) -> dict:
    """What acting needs: the policy, its exploration std, dims and provenance."""
    keep = ("format", "version", "algorithm", "obs_dim", "act_dim", "hidden", "policy_state", "obs_mean", "obs_std",
            "exploration_log_std", "weights_version", "trained_through", "updates", "seed", "cut_unix")
    return {k: checkpoint[k] for k in keep if k in checkpoint}


def decode_weights(data: bytes, source: str = "weights message") -> dict:
    return checkpoint_from_bytes(data, source)


class LearnerService:
    def __init__(self, cfg: LearnerServiceConfig, log=print):
        from .training_run import load_bags

        self.cfg, self.log = cfg, log
        self.out = Path(cfg.out)
        offline, _ = load_bags(cfg.bags)
        prior = load_checkpoint(cfg.prior) if cfg.prior else None
        if prior is not None and int(prior["hidden"]) != cfg.train.hidden:
            raise UserError(f"{cfg.prior}: the prior's hidden width is {prior['hidden']}, the learner's {cfg.train.hidden}")
        self.learner = OnlineLearner(offline, cfg.train, cfg.settings, cfg.seed, prior)
        self.rejected = Rejections()
        self.received = 0  # live transitions accepted since this process started
        self.started = time.monotonic()
        self.last_save = time.monotonic()
        self.out.mkdir(parents=True, exist_ok=True)
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
    def receive(self, raw: bytes) -> str | None:
        """One raw ``/pusher/transition``; returns why it was rejected, or None."""
        try:
            row = decode_transition_payloads([bytes(raw)])[0]
        except TransitionDecodeError as exc:
            reason = f"bad layout: {exc}"
            self.rejected.add("bad layout")
            return reason
        reason = check_row(row)
        if reason is not None:
            self.rejected.add(reason.split(" ")[0] if reason.startswith("non-finite") else reason)
            return reason
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
                "updates": self.learner.updates, "received": self.learner.n_online,
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
            from .bag import read_transitions

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
        return {"received": learner.n_online, "updates": learner.updates, "owed": learner.updates_owed,
                "weights_version": learner.version, "rejected": dict(self.rejected.counts),
                "train_s": round(learner.train_seconds, 2), **{k: round(v, 5) for k, v in learner.losses.items()}}
