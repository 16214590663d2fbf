"""Build the chapter's fixed dataset: expert episodes first, then uniform-random ones."""

from __future__ import annotations

from typing import Callable

import numpy as np

from .env import ACT_DIM, MAX_STEPS, OBS_DIM, PusherReachEnv
from .expert import reach_action
from .transitions import SOURCE_EXPERT, SOURCE_RANDOM, Transitions


def expert_episode_count(episodes: int, expert_frac: float) -> int:
    """The first round(expert_frac * episodes) episodes are the expert's (Python's round)."""
    return int(round(expert_frac * episodes))


def collect_transitions(
    episodes: int,
    expert_frac: float,
    seed: int,
    progress: Callable[[int, int], None] | None = None,
) -> Transitions:
    """Roll out ``episodes`` episodes; episode ``ep`` resets with ``seed + ep``.

    Random actions come from one numpy Generator seeded by ``seed``, drawn only on
    random episodes, so the same arguments always give the same bytes.
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if not 0.0 <= expert_frac <= 1.0:
        raise ValueError(f"expert_frac must be in [0, 1], got {expert_frac}")
    env = PusherReachEnv()
    rng = np.random.default_rng(seed)
    n_expert = expert_episode_count(episodes, expert_frac)
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
        is_expert = ep < n_expert
        done = False
        t = 0
        while not done:
            a = reach_action(env) if is_expert else rng.uniform(-1, 1, size=ACT_DIM).astype(np.float32)
            o2, r, done, info = env.step(a)
            obs[i], action[i], reward[i], next_obs[i] = o, a, r, o2
            terminated[i], truncated[i], success[i] = info["terminated"], info["truncated"], info["success"]
            episode[i], step[i] = ep, t
            source[i] = SOURCE_EXPERT if is_expert else SOURCE_RANDOM
            o = o2
            i += 1
            t += 1
        if progress is not None:
            progress(ep + 1, episodes)
    return Transitions(
        obs[:i], action[:i], reward[:i], next_obs[:i], terminated[:i], truncated[:i], success[:i],
        episode[:i], step[:i], source[:i],
    )
