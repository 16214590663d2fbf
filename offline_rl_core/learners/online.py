"""The online learner of the HIL-SERL stage: the prior fine-tuned from a live stream.

Transitions arrive one by one (the arm's own steps and a person's takeovers) and are
appended to an online buffer that sits beside the offline bag; every gradient step
draws ``offline_ratio`` of its batch from the offline rows and the rest from the online
ones (RLPD / HIL-SERL's symmetric sampling), and ``utd`` steps are owed per environment
step. New weights are cut every ``publish_every`` environment steps.

An environment step is a transition, except where a stream of raw topics holds a step
whose transition cannot be built (an episode's last, when the state after it is never
published): it is counted (``add(empty, steps=1)``), so versions stay in step with the
arm (a paced actor waits for version ``n // publish_every`` at its n-th state).

Everything is scheduled by counts, not by clocks: update j samples only among the
online transitions of the first ``j // utd + 1`` environment steps, and weights version v
is cut after exactly ``utd * v * publish_every`` updates. So a run that receives the same transitions gives
the same weights however fast or slow the learner was, and an actor that waits for
version v (lockstep over ROS) makes the whole procedure reproducible.

The online buffer never fills up: it keeps the newest ``capacity`` live transitions,
the oldest evicted first (FIFO), while the offline rows stay whole, so a session of any
length runs (at 50 Hz the default ``capacity`` is a little over an hour of the arm's own
steps). Update j samples among the newest ``capacity`` of the first ``j // utd + 1``
online transitions. Those are still held while the learner lags the stream by at most
``LAG_VERSIONS * publish_every`` transitions (the ring has that much room beyond
``capacity``); a learner further behind samples some newer transitions in place of
evicted ones, which changes its weights but never stops it.

With ``normalize_obs`` (``TrainConfig``) the networks learn on z-scored observations, the
statistics of the offline data fixed for the whole stage (statistics that moved with the
stream would move every input under the networks' feet): the prior is unfolded into that
form, live rows are z-scored as they arrive, and every weights version folds the statistics
back into the first layers, so what is served takes raw observations as every checkpoint does.

``state()`` / ``OnlineLearner.restore`` hold everything (networks, optimisers, random
generators, counters and the online buffer), so a learner killed mid-run resumes where
it last saved.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace

import numpy as np
import torch

from ..serving.checkpoint import CHECKPOINT_FORMAT, CHECKPOINT_VERSION, task_field
from ..data.transitions import SOURCE_EXPERT, SOURCE_HUMAN, Transitions
from .config import TrainConfig
from .data import MemberData
from .loop import LEARNERS, seed_generators, torch_threads
from .normalize import fold, normalized, obs_stats, unfold
from .resume import learner_training_state, load_learner_training_state
from .schedule import LearningRates
from .stepper import EagerStep, intra_op_threads, make_step

LAG_VERSIONS = 16  # weights versions the learner may lag the stream with its samples intact


@dataclass
class OnlineSettings:
    utd: int = 2  # gradient steps per environment step
    offline_ratio: float = 0.5  # share of each batch drawn from the offline data
    publish_every: int = 50  # environment steps between weights versions (1 s at 50 Hz)
    capacity: int = 200_000  # online transitions sampled from: the newest, older ones evicted
    # the actor's BC term (sac's bc_weight) also on the offline data's expert rows (its
    # demonstrations), as TD3+BC keeps an actor near them; off: only on a person's corrections
    imitate_expert: bool = False
    # gradient steps of the critic alone on the offline data, with the prior's actor, before
    # the first update: the actor's first gradients then follow a critic of the prior, not a
    # random one (a prior without a critic, the filtered BC of --algo auto, is otherwise pulled
    # off its demonstrations in the stage's first thousands of steps)
    critic_warmup: int = 0
    # environment steps over which the learning rates fall along a cosine to zero (0: constant):
    # the stage's budget, so the last weights are the settled end of the run, not one draw of
    # versions that swing by 0.1 success from one to the next
    lr_decay_steps: int = 0

    def __post_init__(self) -> None:
        if self.utd < 1 or self.publish_every < 1 or self.capacity < 1:
            raise ValueError("utd, publish_every and capacity must be >= 1")
        if self.critic_warmup < 0:
            raise ValueError(f"critic_warmup must be >= 0, got {self.critic_warmup}")
        if self.lr_decay_steps < 0:
            raise ValueError(f"lr_decay_steps must be >= 0, got {self.lr_decay_steps}")
        if not 0.0 <= self.offline_ratio <= 1.0:
            raise ValueError(f"offline_ratio must be in [0, 1], got {self.offline_ratio}")


class OnlineSampler:
    """(1, B) row indices: ``offline_ratio`` of them uniform over the offline rows, the
    rest uniform over the newest ``window`` of the first ``bound`` online transitions
    (all offline while there are none), each online transition in its ring slot."""

    def __init__(self, n_offline: int, batch_size: int, offline_ratio: float, generator: torch.Generator,
                 window: int, ring: int):
        self.n_offline, self.batch_size, self.gen = n_offline, batch_size, generator
        self.window, self.ring = window, ring
        self.n_online_rows = batch_size - int(round(offline_ratio * batch_size))
        if n_offline == 0:
            self.n_online_rows = batch_size

    def next(self, bound: int) -> torch.Tensor:
        n_on = self.n_online_rows if bound > 0 else 0
        parts = []
        if n_on < self.batch_size:
            parts.append(torch.randint(0, self.n_offline, (self.batch_size - n_on,), generator=self.gen))
        if n_on:
            k = torch.randint(max(0, bound - self.window), bound, (n_on,), generator=self.gen)
            parts.append(k % self.ring + self.n_offline)
        return torch.cat(parts).unsqueeze(0)


class PriorMismatch(ValueError):
    """The prior's critic weights cannot initialise this learner."""


class OnlineLearner:
    """One learner (``cfg.algo``, SAC by default) trained on offline + live transitions."""

    def __init__(self, offline: Transitions, cfg: TrainConfig, settings: OnlineSettings, seed: int,
                 prior: dict | None = None, task=None):
        """``task`` (a ``TaskSpec``): the task of the data, recorded in every weights version."""
        if len(offline) == 0 and settings.offline_ratio > 0:
            raise ValueError("no offline transitions to sample from (set offline_ratio 0 to learn from scratch)")
        if prior is not None and prior.get("hidden") and int(prior["hidden"]) != cfg.hidden:
            cfg = replace(cfg, hidden=int(prior["hidden"]))  # the prior's networks are what is fine-tuned
        self.cfg, self.settings, self.seed = cfg, settings, int(seed)
        obs_dim, act_dim = offline.obs.shape[1], offline.action.shape[1]
        if task is not None and (obs_dim, act_dim) != (task.obs_dim, task.act_dim):
            raise ValueError(f"the offline data has obs {obs_dim}, action {act_dim}; task {task.name} has obs "
                             f"{task.obs_dim}, action {task.act_dim}")
        self.task = None if task is None else task_field(task)
        init_gen, sample_gen = seed_generators(seed)
        # z-scored inputs (normalize_obs): the offline data's statistics, for the whole stage
        if cfg.normalize_obs and len(offline) == 0:
            raise ValueError("normalize_obs: no offline transitions to take the observations' statistics from")
        self.norm = obs_stats(offline) if cfg.normalize_obs else None
        if self.norm is not None:
            offline = normalized(offline, *self.norm)
        with torch_threads(intra_op_threads(cfg.threads)):
            self.learner = LEARNERS[cfg.algo](cfg, 1, [init_gen], obs_dim, act_dim)
            if prior is not None:
                policy_state, learner_state = prior["policy_state"], prior.get("learner_state") or {}
                if self.norm is not None:  # a checkpoint's networks take raw observations
                    policy_state, learner_state = unfold(policy_state, *self.norm), unfold(learner_state, *self.norm)
                self.learner.policy.load_member_state(0, policy_state)  # validated with the checkpoint
                try:  # the critic's weights are the trainer's own: checked by loading them
                    self.learner.load_learner_state(0, learner_state)
                except (RuntimeError, KeyError, TypeError, AttributeError) as exc:
                    reason = str(exc).strip().splitlines()[0][:160] if str(exc).strip() else type(exc).__name__
                    raise PriorMismatch(f"the prior's learner_state does not fit a {cfg.algo} learner "
                                        f"of hidden width {cfg.hidden} ({reason})") from None
        self.prior_algorithm = None if prior is None else prior.get("algorithm")
        ring = settings.capacity + LAG_VERSIONS * settings.publish_every
        self.data = MemberData([offline], capacity=len(offline) + ring, fifo_from=len(offline))
        if settings.imitate_expert:  # the demonstrations are imitated as a person's corrections are
            expert = torch.from_numpy(offline.source == SOURCE_EXPERT).to(self.data.human.dtype)
            self.data.human[0, :len(offline), 0] = torch.maximum(self.data.human[0, :len(offline), 0], expert)
        self.n_offline = len(offline)
        self.sample_gen = sample_gen
        self.sampler = OnlineSampler(self.n_offline, cfg.batch_size, settings.offline_ratio, sample_gen,
                                     settings.capacity, ring)
        self.rates = self._rates()
        self.step_once = make_step(self.learner.update, self.data, (1, cfg.batch_size), cfg.device, cfg.cuda_graph,
                                   cfg.threads)
        self.n_online = 0  # online transitions
        self.n_human_seen = 0  # live transitions a person chose, evicted ones included
        self.n_labelled_seen = 0  # live transitions the policy chose and a person labelled
        self.n_steps = 0  # environment steps (transitions, and steps that made none)
        self.step_rows: list[int] | None = None  # online transitions through each step, once they differ
        self.updates = 0
        self.warmup_done = 0  # critic-alone steps taken (critic_warmup)
        if settings.critic_warmup and not hasattr(self.learner, "critic_alone_update"):
            raise ValueError(f"critic_warmup: the {cfg.algo} learner has no critic to warm up alone")
        if settings.critic_warmup and self.n_offline == 0:
            raise ValueError("critic_warmup: no offline transitions to warm the critic up on")
        self.version = 0
        self.losses: dict[str, float] = {}
        self.train_seconds = 0.0

    # ------------------------------------------------------------------ data
    def add(self, rows: Transitions, steps: int | None = None, labels: np.ndarray | None = None) -> None:
        """Append live transitions (already checked: finite, known layout), the transitions
        of the last of ``steps`` environment steps (default: one step per transition).
        ``labels`` (one row of actions per transition, NaN where none): the corrector's action
        on each state the policy acted on, imitated by the actor's BC term in place of the
        executed action, which the critic still learns from (DAgger's labels)."""
        steps = len(rows) if steps is None else int(steps)
        if steps < len(rows):
            raise ValueError(f"{len(rows)} transitions cannot come from {steps} steps")
        if len(rows):
            self.data.append(rows if self.norm is None else normalized(rows, *self.norm), labels)
            self.n_online += len(rows)
            self.n_human_seen += int((rows.source == SOURCE_HUMAN).sum())
            if labels is not None:
                given = np.isfinite(np.asarray(labels, np.float32).reshape(len(rows), -1)).all(axis=1)
                self.n_labelled_seen += int((given & (rows.source != SOURCE_HUMAN)).sum())
        if self.step_rows is None and steps != len(rows):
            self.step_rows = list(range(1, self.n_steps + 1))  # one transition per step so far
        if self.step_rows is not None:
            self.step_rows += [self.n_online - len(rows)] * (steps - 1) + [self.n_online] * min(steps, 1)
        self.n_steps += steps

    def rows_through(self, steps: int) -> int:
        """Online transitions of the first ``steps`` environment steps (those that arrived)."""
        if self.step_rows is None:
            return min(steps, self.n_online)
        return self.step_rows[min(steps, self.n_steps) - 1] if steps > 0 else 0

    @property
    def n_human(self) -> int:
        """Live transitions a person chose (source human): their takeovers' steps."""
        return self.n_human_seen

    @property
    def n_labelled(self) -> int:
        """Live transitions the policy chose and a person labelled with an action (``add``'s labels)."""
        return self.n_labelled_seen

    @property
    def n_evicted(self) -> int:
        """Live transitions no longer held (the oldest, replaced by newer ones)."""
        return max(0, self.n_online - self.data.ring_rows)

    def held_online(self) -> range:
        """The online transitions still held, by index (oldest first)."""
        return range(self.n_evicted, self.n_online)

    @property
    def updates_owed(self) -> int:
        return self.settings.utd * self.n_steps - self.updates

    # ------------------------------------------------------------------ training
    def train(self, max_updates: int | None = None, until_version: bool = True) -> int:
        """Take the updates owed (at most ``max_updates``), stopping where a weights
        version is due (``until_version``) so the caller can cut it. Returns how many."""
        todo = self.updates_owed if max_updates is None else min(self.updates_owed, max_updates)
        if until_version:
            todo = min(todo, self.next_version_updates() - self.updates)
        if todo <= 0:
            return 0
        t0 = time.perf_counter()
        with torch_threads(intra_op_threads(self.cfg.threads)):
            self._warm_up_critic()
            for _ in range(todo):
                self.rates.at(min(self.updates + 1, self.rates.total))
                bound = self.rows_through(self.updates // self.settings.utd + 1)
                losses = self.step_once(self.sampler.next(bound))
                self.updates += 1
            self.losses = {k: float(v.float().mean()) for k, v in losses.items()}
        self.train_seconds += time.perf_counter() - t0
        return todo

    def _rates(self) -> LearningRates:
        """The optimisers' rates along the decay (its total in updates), or left constant."""
        decay = self.settings.lr_decay_steps
        return LearningRates(self.learner, "cosine" if decay else "constant", self.settings.utd * decay)

    def _warm_up_critic(self) -> None:
        """The critic alone, ``critic_warmup`` steps on offline batches, before the first update
        (eager: a few thousand steps once; the same bytes on every runner)."""
        if self.warmup_done >= self.settings.critic_warmup:
            return
        step = EagerStep(self.learner.critic_alone_update, self.data)
        for _ in range(self.settings.critic_warmup - self.warmup_done):
            step(self.sampler.next(0))  # no online row is held before the first update
        self.warmup_done = self.settings.critic_warmup

    def next_version_updates(self) -> int:
        """Updates after which the next weights version is cut."""
        return self.settings.utd * (self.version + 1) * self.settings.publish_every

    def version_due(self) -> bool:
        return self.updates >= self.next_version_updates()

    def cut_version(self) -> dict:
        """The next weights version (call when ``version_due``): a servable checkpoint."""
        self.version += 1
        return self.weights()

    def weights(self) -> dict:
        """The current policy as a checkpoint the policy node serves (``policy.py``),
        with the exploration std and which version this is."""
        learner = self.learner
        state, policy_state = learner.learner_state(0), learner.policy.member_state(0)
        if self.norm is not None:  # served networks take raw observations
            state, policy_state = fold(state, *self.norm), fold(policy_state, *self.norm)
        return {
            "format": CHECKPOINT_FORMAT,
            "version": CHECKPOINT_VERSION,
            "algorithm": learner.name,
            "obs_dim": learner.obs_dim,
            "act_dim": learner.act_dim,
            "hidden": self.cfg.hidden,
            "policy_state": policy_state,
            "obs_mean": None,
            "obs_std": None,
            "learner_state": state,
            "exploration_log_std": state.get("log_std"),
            "weights_version": self.version,
            "trained_through": self.n_online_at_version(self.version),
            "updates": self.updates,
            "config": self.cfg.to_dict(),
            "online": asdict(self.settings),
            "seed": self.seed,
            "prior_algorithm": self.prior_algorithm,
            **({"task": self.task} if self.task is not None else {}),
        }

    def n_online_at_version(self, version: int) -> int:
        return version * self.settings.publish_every

    # ------------------------------------------------------------------ resume
    def state(self) -> dict:
        """Everything needed to resume: tensors, generators, counters, the online rows."""
        return {
            "format": "pusher-rl/online-learner",
            "version": 1,
            "seed": self.seed,
            "config": self.cfg.to_dict(),
            "online": asdict(self.settings),
            "learner": learner_training_state(self.learner),
            "sample_generator": self.sample_gen.get_state(),
            "n_online": self.n_online,
            "n_human": self.n_human_seen,
            "n_labelled": self.n_labelled_seen,
            "n_steps": self.n_steps,
            "step_rows": None if self.step_rows is None else torch.tensor(self.step_rows, dtype=torch.int64),
            "updates": self.updates,
            "critic_warmup_done": self.warmup_done,
            "train_version": self.version,
            # the online rows still held, oldest first (the first is transition n_online - len)
            "online_rows": {name: getattr(self.data, name)[0, self._held_slots()].clone()
                            for name in MemberData.FIELDS},
        }

    def restore(self, state: dict) -> None:
        """Load ``state()`` into this freshly built learner (before its first update)."""
        if state.get("format") != "pusher-rl/online-learner":
            raise ValueError("not an online learner state")
        if self.updates:
            raise ValueError("restore into a learner that has not trained yet")
        load_learner_training_state(self.learner, state["learner"])
        self.rates = self._rates()  # the optimisers' groups were loaded anew
        self.sample_gen.set_state(state["sample_generator"])
        n = int(state["n_online"])
        rows = state["online_rows"]
        self.data.appended = n
        self.n_online = n
        slots = self._held_slots()
        if len(rows["obs"]) < len(slots):
            raise ValueError(f"the saved state holds {len(rows['obs'])} online transitions, this learner's buffer "
                             f"{len(slots)} (resume with the capacity it was saved with)")
        for name in MemberData.FIELDS:  # a state saved with a larger buffer: its newest rows
            saved = rows["action"] if name == "label" and name not in rows else rows[name]  # saved before labels
            getattr(self.data, name)[0, slots] = saved[len(saved) - len(slots):]
        self.data.sizes = [self.n_offline + min(n, self.data.ring_rows)]
        human = state.get("n_human")  # saved since the buffer became a ring; before, every row was held
        self.n_human_seen = int(rows["human"].sum()) if human is None else int(human)
        self.n_labelled_seen = int(state.get("n_labelled", 0))
        self.updates, self.version = int(state["updates"]), int(state["train_version"])
        # saved before the option: a learner that trained had nothing to warm up
        self.warmup_done = int(state.get("critic_warmup_done", self.settings.critic_warmup if self.updates else 0))
        self.n_steps = int(state.get("n_steps", n))  # states saved before steps were counted: one per row
        steps = state.get("step_rows")
        self.step_rows = None if steps is None else [int(v) for v in steps]

    def _held_slots(self) -> torch.Tensor:
        held = self.held_online()
        return torch.arange(held.start, held.stop) % self.data.ring_rows + self.n_offline
