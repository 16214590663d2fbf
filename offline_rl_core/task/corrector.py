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
action (float32, one value per command joint) or None (the policy keeps control).

Any task: the rule judges the task's reward distance and takes over with the task's
scripted expert (:func:`task_rule`); pusher_reach's are the chapter's (the fingertip's
planar distance to the target, ``expert.expert_action``). Another task's expert comes
with its env (``offline_rl_core.task.envs.task_expert``); without it, a corrector for
that task is refused in one line.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..common.errors import UserError
from .pusher_reach import SUCCESS_TOL, fingertip_from_joints
from .expert import expert_action
from .spec import DEFAULT_TASK, TaskSpec, load_task

# expert(qpos, qvel, goal) -> action in [-1, 1]; distance(qpos, goal) -> the reward's distance
Expert = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
Distance = Callable[[np.ndarray, np.ndarray], float]


def pusher_distance(qpos, target_xy) -> float:
    """pusher_reach: the fingertip's planar distance to the target."""
    return float(np.linalg.norm(np.asarray(target_xy, np.float64)[:2] - fingertip_from_joints(qpos)))


def pusher_expert(qpos, qvel, target_xy) -> np.ndarray:
    return expert_action(qpos, qvel, np.asarray(target_xy, np.float64)[:2])


def task_rule(task: TaskSpec, distance: Distance | None = None) -> tuple[Expert, Distance]:
    """The expert and the distance a corrector of ``task`` uses. ``distance``: the task's
    reward distance from joint positions and goal (e.g. ``ObservationBuilder.distance``),
    for tasks other than pusher_reach."""
    if task.digest == load_task(DEFAULT_TASK).digest:
        return pusher_expert, pusher_distance
    try:
        from .envs import task_expert
    except ImportError:  # the task envs are not part of this build
        raise UserError(f"the scripted corrector knows pusher_reach's expert only; task {task.name} "
                        f"({task.source_file()}) has none in this build (offline_rl_core.task.envs)") from None
    if distance is None:
        raise ValueError(f"a corrector of task {task.name} needs its reward distance")
    return task_expert(task), distance


@dataclass
class CorrectorParams:
    patience: int = 8  # k: steps without getting closer before taking over
    grace_steps: int = 20  # states at an episode's start before progress is judged (the arm sets off)
    hold_steps: int = 25  # m: steps of a takeover before handing back (success ends it early)
    min_progress: float = 0.002  # m: "closer" means the best distance shrank by this much
    noise: float = 0.0  # std of Gaussian noise added to the expert's torque (then clipped)
    reaction_delay: int = 0  # steps between deciding to take over and the first correction
    seed: int = 0

    def __post_init__(self) -> None:
        if self.grace_steps < 0:
            raise ValueError(f"grace_steps must be >= 0, got {self.grace_steps}")
        if self.patience < 1 or self.hold_steps < 1:
            raise ValueError(f"patience and hold_steps must be >= 1, got {self.patience}, {self.hold_steps}")
        if self.reaction_delay < 0 or self.noise < 0 or self.min_progress < 0:
            raise ValueError("reaction_delay, noise and min_progress must be >= 0")


class ScriptedCorrector:
    """``expert`` and ``distance`` (``task_rule``): the task's; default pusher_reach's;
    ``success_within``: the task's success threshold on that distance."""

    def __init__(self, params: CorrectorParams | None = None, expert: Expert = pusher_expert,
                 distance: Distance = pusher_distance, success_within: float = SUCCESS_TOL):
        self.p = params or CorrectorParams()
        self.expert, self.distance, self.success_within = expert, distance, float(success_within)
        self.rng = np.random.default_rng(self.p.seed)
        self.takeovers = 0
        self.corrections = 0  # states answered with a correction
        self.target: np.ndarray | None = None
        self.new_episode(None)

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

    def decide(self, qpos, qvel, goal) -> np.ndarray | None:
        """Decide the correction for this state (``goal``: pusher_reach's target xy), or
        None. Call once per state, in order."""
        if self.is_new_episode(goal):
            self.new_episode(goal)
        self.step += 1
        dist = self.distance(qpos, self.target)
        if dist < self.success_within:
            self.succeeded = True  # latched for the episode, as the env's success is
        if self.intervening:
            if self.succeeded or self.held >= self.p.hold_steps:
                self.hand_back(dist)
                return None
            return self.act(qpos, qvel)
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
        return self.act(qpos, qvel)

    def act(self, qpos, qvel) -> np.ndarray:
        action = np.asarray(self.expert(qpos, qvel, self.target), np.float64)
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
