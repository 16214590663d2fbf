"""pusher-reach as a Gymnasium env: ``gymnasium.make("offline_rl_core/PusherReach-v0")``.

A thin wrapper over :class:`offline_rl_core.task.pusher_reach.PusherReachEnv`: the same physics,
observation, reward and episode end, with Gymnasium's 5-tuple ``step`` and
``reset(seed=None, options=None) -> (obs, info)``. ``reset(seed=s)`` starts the
episode ``PusherReachEnv().reset(s)`` starts, so datasets and evaluations keyed by
reset seed carry over; ``reset()`` draws the episode seed from ``self.np_random``.

The env truncates at ``env.MAX_STEPS`` (100) itself, so the registration adds no
``TimeLimit`` wrapper. Gymnasium 1.x has no plugin entry points: the env is
registered by :func:`register_gym_envs` (idempotent), which runs when this module
is imported; ``gymnasium.make("offline_rl_core.task.gym_env:offline_rl_core/PusherReach-v0")``
imports it on the fly.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

from .pusher_reach import ACT_DIM, OBS_DIM, PusherReachEnv

ENV_ID = "offline_rl_core/PusherReach-v0"
_SEED_HIGH = 2**63  # episode seeds drawn by reset() lie in [0, 2**63)


class PusherReachGymEnv(gymnasium.Env):
    """The chapter's pusher-reach task behind Gymnasium's API.

    ``info`` holds ``success`` (latched), ``dist`` (fingertip to target, m) and
    ``episode_seed`` (the ``PusherReachEnv`` reset seed of this episode).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 50}

    def __init__(self, render_mode: str | None = None, terminate_on_success: bool = False, width: int = 480, height: int = 480):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, got {render_mode!r}")
        self.render_mode = render_mode
        self.env = PusherReachEnv(terminate_on_success=terminate_on_success)
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(OBS_DIM,), dtype=np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(ACT_DIM,), dtype=np.float32)
        self.width, self.height = width, height
        self._renderer = None

    @property
    def model(self):
        return self.env.model

    @property
    def data(self):
        return self.env.data

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        episode_seed = int(seed) if seed is not None else int(self.np_random.integers(_SEED_HIGH))
        obs = self.env.reset(episode_seed)
        return obs, {"success": False, "dist": self.env.distance(), "episode_seed": episode_seed}

    def step(self, action):
        obs, reward, _, info = self.env.step(action)
        out = {"success": info["success"], "dist": info["dist"], "episode_seed": self.env.seed}
        return obs, reward, info["terminated"], info["truncated"], out

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        if self._renderer is None:
            from .render import TopDownRenderer

            self._renderer = TopDownRenderer(self.env.model, self.width, self.height)
        return self._renderer.render(self.env.data)

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def register_gym_envs() -> None:
    """Register ``offline_rl_core/PusherReach-v0`` with Gymnasium (once; later calls do nothing)."""
    if ENV_ID not in gymnasium.registry:
        # max_episode_steps=None: the env truncates at MAX_STEPS itself; a TimeLimit on
        # top would only duplicate it.
        gymnasium.register(id=ENV_ID, entry_point="offline_rl_core.task.gym_env:PusherReachGymEnv", max_episode_steps=None)


register_gym_envs()
