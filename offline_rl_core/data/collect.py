"""Build the chapter's fixed dataset: expert episodes first, then uniform-random ones."""

from __future__ import annotations

from typing import Callable

import numpy as np

from ..task.pusher_reach import ACT_DIM, MAX_STEPS, OBS_DIM, PusherReachEnv
from ..task.expert import expert_action
from .transitions import SOURCE_EXPERT, SOURCE_RANDOM, Transitions


def expert_episode_count(episodes: int, expert_frac: float) -> int:
    """The first round(expert_frac * episodes) episodes are the expert's (Python's round)."""
    return int(round(expert_frac * episodes))


class EpisodePlan:
    """Who acts in each episode of a collection, and what it does.

    The first ``expert_episode_count`` episodes are the scripted expert's, the rest take
    uniform random actions from one numpy Generator seeded by ``seed``, drawn only on
    random episodes. ``collect_transitions`` and the recorder node (driving the sim over
    ROS, see collect_driver) both act through it, so they record the same transitions.
    """

    def __init__(self, episodes: int, expert_frac: float, seed: int):
        self.n_expert = expert_episode_count(episodes, expert_frac)
        self.rng = np.random.default_rng(seed)

    def source(self, episode: int) -> int:
        return SOURCE_EXPERT if episode < self.n_expert else SOURCE_RANDOM

    def action(self, episode: int, position, velocity, target_xy) -> np.ndarray:
        """The float32 action for a state of ``episode`` (joint positions, velocities, target x/y)."""
        if episode < self.n_expert:
            return expert_action(position, velocity, target_xy)
        return self.rng.uniform(-1, 1, size=ACT_DIM).astype(np.float32)


def collect_transitions(
    episodes: int,
    expert_frac: float,
    seed: int,
    progress: Callable[[int, int], None] | None = None,
) -> Transitions:
    """Roll out ``episodes`` episodes; episode ``ep`` resets with ``seed + ep``.

    Who acts is ``EpisodePlan``'s rule, so the same arguments always give the same bytes.
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if not 0.0 <= expert_frac <= 1.0:
        raise ValueError(f"expert_frac must be in [0, 1], got {expert_frac}")
    env = PusherReachEnv()
    plan = EpisodePlan(episodes, expert_frac, seed)
    n = episodes * MAX_STEPS
    obs = np.empty((n, OBS_DIM), np.float32)
    action = np.empty((n, ACT_DIM), np.float32)
    reward = np.empty(n, np.float32)
    next_obs = np.empty((n, OBS_DIM), np.float32)
    terminated = np.zeros(n, bool)
    truncated = np.zeros(n, bool)
    success = np.zeros(n, bool)
    episode = np.empty(n, np.int64)
    step = np.empty(n, np.int64)
    source = np.empty(n, np.int64)
    i = 0
    for ep in range(episodes):
        o = env.reset(seed=seed + ep)
        episode_source = plan.source(ep)
        done = False
        t = 0
        while not done:
            a = plan.action(ep, env.qpos, env.qvel, env.target[:2])
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
