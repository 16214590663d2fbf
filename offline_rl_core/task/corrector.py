"""The scripted corrector's decision rule: a stand-in for the person in the HIL stage
(the corrections node, the in-process online loop and the tests use it).

A stand-in for a person watching the arm: it takes over with the scripted expert when
the fingertip has not got closer to the target for ``patience`` steps, and hands back
after ``hold_steps`` steps or on success. Progress is judged only after the first
``grace_steps`` states of an episode: setting off from rest, even the expert's joint-space
swing first takes the fingertip away from the target in a third of the resets, and a
person would not grab the arm for that. Optional Gaussian action noise (a shaky hand)
and a reaction delay (steps between deciding to take over and acting) make it less
perfect. Everything random comes from one numpy Generator seeded by ``seed``.

One call of :meth:`ScriptedCorrector.decide` per state; the answer is the correction
action (float32, one value per command joint) or None (the policy keeps control). On a state
it leaves to the policy, :meth:`ScriptedCorrector.label` gives the action it would have taken:
a label (DAgger's), learnt from without moving the arm.

Any task: the rule judges the task's reward distance and takes over with the task's
scripted expert (:func:`task_rule`, from joint positions and the goal, as the corrector node
has them; or :meth:`ScriptedCorrector.for_task`, which also reads the tracked points a robot
publishes: progress is every reward distance, weighted, so the fingertip nearing the puck
counts as much as the puck nearing the goal, and success is not latched where the task judges
it at the episode's end: a puck pushed off the goal again is worth a takeover). pusher_reach's
are the chapter's (the fingertip's planar distance to the target, ``expert.expert_action``).
``steer="stick"`` takes over as a person steering the fingertip with a Cartesian stick
would instead (``STEERS``; a reach task's only).
Another task's expert comes with its env (``offline_rl_core.task.envs.task_expert``); without
it, a corrector for that task is refused in one line.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..common.errors import UserError
from .pusher_reach import SUCCESS_TOL, fingertip_from_joints
from .expert import expert_action
from .spec import DEFAULT_TASK, TaskSpec, load_task

# expert(qpos, qvel, goal[, points]) -> action in [-1, 1]; distance(qpos, goal[, points]) -> the
# reward's distance (points: the tracked points' vectors, for the tasks that track any)
Expert = Callable[..., np.ndarray]
Distance = Callable[..., float]


def pusher_distance(qpos, target_xy, points=None) -> float:
    """pusher_reach: the fingertip's planar distance to the target."""
    return float(np.linalg.norm(np.asarray(target_xy, np.float64)[:2] - fingertip_from_joints(qpos)))


def pusher_expert(qpos, qvel, target_xy, points=None) -> np.ndarray:
    return expert_action(qpos, qvel, np.asarray(target_xy, np.float64)[:2])


def task_rule(task: TaskSpec, distance: Distance | None = None, steer: str = "expert") -> tuple[Expert, Distance]:
    """The expert and the distance a corrector of ``task`` uses. ``distance``: the task's
    reward distance from joint positions and goal (e.g. ``ObservationBuilder.distance``),
    for tasks other than pusher_reach; ``steer``: how it takes over (``STEERS``)."""
    chapter = task.digest == load_task(DEFAULT_TASK).digest
    if chapter and steer == "expert":
        return pusher_expert, pusher_distance
    try:
        from .envs import task_expert, task_stick
    except ImportError:  # the task envs are not part of this build
        raise UserError(f"the scripted corrector knows pusher_reach's expert only; task {task.name} "
                        f"({task.source_file()}) has none in this build (offline_rl_core.task.envs)") from None
    if chapter:
        return task_stick(task), pusher_distance
    if distance is None:
        raise ValueError(f"a corrector of task {task.name} needs its reward distance")
    return (task_stick(task) if steer == "stick" else task_expert(task)), distance


# How a takeover moves the arm. expert: the task's scripted expert (a joint-space swing to an
# inverse-kinematics pose); stick: the reward's point jogged straight at the goal every state
# (envs.task_stick), as a person steers with a Cartesian stick (HIL-SERL's SpaceMouse): a
# proportional law in the point's space, its actions following the error (reach tasks only)
STEERS = ("expert", "stick")


@dataclass
class CorrectorParams:
    patience: int = 8  # k: steps without getting closer before taking over
    grace_steps: int = 20  # states at an episode's start before progress is judged (the arm sets off)
    hold_steps: int = 25  # m: steps of a takeover before handing back (success ends it early)
    min_progress: float = 0.002  # m: "closer" means the best distance shrank by this much
    noise: float = 0.0  # std of Gaussian noise added to the expert's torque (then clipped)
    reaction_delay: int = 0  # steps between deciding to take over and the first correction
    seed: int = 0
    steer: str = "expert"  # how a takeover moves the arm (STEERS)

    def __post_init__(self) -> None:
        if self.grace_steps < 0:
            raise ValueError(f"grace_steps must be >= 0, got {self.grace_steps}")
        if self.patience < 1 or self.hold_steps < 1:
            raise ValueError(f"patience and hold_steps must be >= 1, got {self.patience}, {self.hold_steps}")
        if self.reaction_delay < 0 or self.noise < 0 or self.min_progress < 0:
            raise ValueError("reaction_delay, noise and min_progress must be >= 0")
        if self.steer not in STEERS:
            raise ValueError(f"steer must be one of {', '.join(STEERS)}, got {self.steer!r}")


class TaskDistances:
    """A task's progress (its reward's distances, weighted) and success distance from what a
    robot publishes: joint positions, the goal vector and the tracked points' vectors."""

    def __init__(self, task: TaskSpec):
        from . import features

        self.task, self.features = task, features

    def vectors(self, qpos, goal, points) -> tuple[np.ndarray, dict]:
        positions = np.asarray(qpos, np.float64)[None]
        vectors = {"goal": np.asarray(goal, np.float64)[None]}
        vectors.update({k: np.asarray(v, np.float64)[None] for k, v in (points or {}).items()})
        return positions, vectors

    def success(self, qpos, goal, points=None) -> float:
        """The success distance (``reward.distance``)."""
        positions, vectors = self.vectors(qpos, goal, points)
        return float(self.features.distances(*self.features.pair(self.task, *self.task.reward.distance,
                                                                 positions, vectors))[0])

    def progress(self, qpos, goal, points=None) -> float:
        """Every reward distance, weighted (the reward less its bonus, negated)."""
        positions, vectors = self.vectors(qpos, goal, points)
        weights = (1.0, *(t.weight for t in self.task.reward.terms))
        return float(sum(w * self.features.distances(*self.features.pair(self.task, a, b, positions, vectors))[0]
                         for w, (a, b) in zip(weights, self.task.reward.distances)))


class ScriptedCorrector:
    """``expert`` and ``distance`` (progress; ``task_rule``, ``for_task``): the task's; default
    pusher_reach's; ``success_distance`` (default ``distance``) and ``success_within``: the
    task's success threshold on it; ``latch``: success latches for the episode (else it is
    each state's)."""

    def __init__(self, params: CorrectorParams | None = None, expert: Expert = pusher_expert,
                 distance: Distance = pusher_distance, success_within: float = SUCCESS_TOL,
                 success_distance: Distance | None = None, latch: bool = True):
        self.p = params or CorrectorParams()
        self.expert, self.distance, self.success_within = expert, distance, float(success_within)
        self.success_distance = success_distance or distance
        self.latch = latch
        self.rng = np.random.default_rng(self.p.seed)
        self.takeovers = 0
        self.corrections = 0  # states answered with a correction
        self.target: np.ndarray | None = None
        self.new_episode(None)

    @classmethod
    def for_task(cls, task: TaskSpec | str | None, params: CorrectorParams | None = None) -> "ScriptedCorrector":
        """The corrector of ``task``: pusher_reach's is the chapter's; another task's judges its
        reward distances and acts with its scripted expert (``task.envs.task_expert``)."""
        task = load_task(task)
        params = params or CorrectorParams()
        if task.digest == load_task(DEFAULT_TASK).digest:
            return cls(params, *task_rule(task, steer=params.steer))
        measure = TaskDistances(task)
        expert, _ = task_rule(task, measure.progress, params.steer)
        return cls(params, expert, measure.progress, task.reward.success_within, measure.success,
                   latch=task.reward.success_at != "end")

    def new_episode(self, goal) -> None:
        self.target = None if goal is None else np.array(goal, np.float64).reshape(-1)
        self.best = np.inf
        self.stalled = 0
        self.delay_left = -1  # >= 0: a takeover is decided, this many states to wait
        self.held = 0  # steps of the current takeover so far
        self.intervening = False
        self.succeeded = False
        self.step = -1  # index of the current state in the episode

    def is_new_episode(self, goal) -> bool:
        goal = np.asarray(goal, np.float64).reshape(-1)
        return self.target is None or goal.shape != self.target.shape or not np.allclose(self.target, goal, atol=1e-9)

    def decide(self, qpos, qvel, goal, points=None) -> np.ndarray | None:
        """Decide the correction for this state (``goal``: the task's goal vector, pusher_reach's
        the target's x, y; ``points``: the tracked points' vectors, for a task that tracks any),
        or None. Call once per state, in order."""
        if self.is_new_episode(goal):
            self.new_episode(goal)
        self.step += 1
        tracked = () if points is None else (points,)
        dist = self.distance(qpos, self.target, *tracked)
        at_goal = (dist if self.success_distance is self.distance else
                   self.success_distance(qpos, self.target, *tracked)) < self.success_within
        # latched for the episode, as the env's success is; or this state's, as the task's
        self.succeeded = (self.succeeded or at_goal) if self.latch else at_goal
        if self.intervening:
            if self.succeeded or self.held >= self.p.hold_steps:
                self.hand_back(dist)
                return None
            return self.act(qpos, qvel, points)
        if self.succeeded:
            return None
        if self.step < self.p.grace_steps:
            self.best = dist  # judged from the end of the grace period
            return None
        if self.delay_left < 0:
            if dist < self.best - self.p.min_progress:
                self.best, self.stalled = dist, 0
            else:
                self.best, self.stalled = min(self.best, dist), self.stalled + 1
            if self.stalled < self.p.patience:
                return None
            self.delay_left = self.p.reaction_delay  # decided: act after the reaction delay
        if self.delay_left > 0:
            self.delay_left -= 1
            return None
        self.delay_left = -1
        self.intervening = True
        self.takeovers += 1
        return self.act(qpos, qvel, points)

    def label(self, qpos, qvel, points=None) -> np.ndarray:
        """The expert's action on the state just decided (after ``decide``), without taking
        over: a label for a state the policy acts on (DAgger's), the corrector's state and random
        stream untouched (no noise: the label is what it would steer, not a shaky hand)."""
        if self.target is None:
            raise ValueError("label() before decide(): no goal yet")
        tracked = () if points is None else (points,)
        action = np.asarray(self.expert(qpos, qvel, self.target, *tracked), np.float64)
        return np.clip(action, -1.0, 1.0).astype(np.float32)

    def act(self, qpos, qvel, points=None) -> np.ndarray:
        tracked = () if points is None else (points,)
        action = np.asarray(self.expert(qpos, qvel, self.target, *tracked), np.float64)
        if self.p.noise > 0:
            action = action + self.rng.normal(0.0, self.p.noise, size=action.shape)
        self.held += 1
        self.corrections += 1
        return np.clip(action, -1.0, 1.0).astype(np.float32)

    def hand_back(self, dist: float) -> None:
        self.intervening = False
        self.held = 0
        self.stalled = 0
        self.best = dist
