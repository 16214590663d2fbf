"""Build a task's fixed dataset: expert episodes first, then uniform-random ones (the chapter's
rule; on pusher_reach, the chapter's dataset)."""

from __future__ import annotations

from typing import Callable

import numpy as np

from ..task.envs import make_env, point_vectors, task_expert
from ..task.spec import TaskSpec, load_task
from .transitions import SOURCE_EXPERT, SOURCE_RANDOM, Layout, Transitions


def expert_episode_count(episodes: int, expert_frac: float) -> int:
    """The first round(expert_frac * episodes) episodes are the expert's (Python's round)."""
    return int(round(expert_frac * episodes))


class EpisodePlan:
    """Who acts in each episode of a collection, and what it does.

    The first ``expert_episode_count`` episodes are the task's scripted expert's
    (``task.envs.task_expert``), the rest take uniform random actions from one numpy
    Generator seeded by ``seed``, drawn only on random episodes. ``collect_transitions`` and
    the recorder node (driving the sim over ROS, see collect_driver) both act through it,
    so they record the same transitions.
    """

    def __init__(self, episodes: int, expert_frac: float, seed: int, task: TaskSpec | str | None = None):
        self.task = load_task(task)
        self.expert = task_expert(self.task)
        self.n_expert = expert_episode_count(episodes, expert_frac)
        self.rng = np.random.default_rng(seed)

    def source(self, episode: int) -> int:
        return SOURCE_EXPERT if episode < self.n_expert else SOURCE_RANDOM

    def action(self, episode: int, position, velocity, goal, points=None) -> np.ndarray:
        """The float32 action for a state of ``episode``: joint positions and velocities (in
        the state's joint order), the task's goal vector (pusher_reach: the target's x, y) and
        the tracked points' vectors (a pushed object's, for the experts that need one)."""
        if episode < self.n_expert:
            return self.expert(position, velocity, goal, points)
        return self.rng.uniform(-1, 1, size=self.task.act_dim).astype(np.float32)


def collect_transitions(
    episodes: int,
    expert_frac: float,
    seed: int,
    progress: Callable[[int, int], None] | None = None,
    task: TaskSpec | str | None = None,
) -> Transitions:
    """Roll out ``episodes`` episodes of ``task`` (default pusher_reach); episode ``ep``
    resets with ``seed + ep``.

    Who acts is ``EpisodePlan``'s rule, so the same arguments always give the same bytes.
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if not 0.0 <= expert_frac <= 1.0:
        raise ValueError(f"expert_frac must be in [0, 1], got {expert_frac}")
    task = load_task(task)
    env = make_env(task, terminate_on_success=False)
    plan = EpisodePlan(episodes, expert_frac, seed, task)
    n = episodes * env.max_steps
    data = Transitions.empty(n, Layout(task.obs_dim, task.act_dim))
    obs, action, reward, next_obs = data.obs, data.action, data.reward, data.next_obs
    terminated, truncated, success = data.terminated, data.truncated, data.success
    episode, step, source = data.episode, data.step, data.source
    i = 0
    for ep in range(episodes):
        o = env.reset(seed=seed + ep)
        episode_source = plan.source(ep)
        done = False
        t = 0
        while not done:
            points = point_vectors(task, env.point_positions()) if ep < plan.n_expert else None
            a = plan.action(ep, env.joint_positions, env.joint_velocities, env.goal, points)
            o2, r, done, info = env.step(a)
            obs[i], action[i], reward[i], next_obs[i] = o, a, r, o2
            terminated[i], truncated[i], success[i] = info["terminated"], info["truncated"], info["success"]
            episode[i], step[i] = ep, t
            source[i] = episode_source
            o = o2
            i += 1
            t += 1
        if progress is not None:
            progress(ep + 1, episodes)
    return Transitions(
        obs[:i], action[:i], reward[:i], next_obs[:i], terminated[:i], truncated[:i], success[:i],
        episode[:i], step[:i], source[:i],
    )
