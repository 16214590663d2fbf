"""Roll policies out in pusher-reach on held-out reset seeds and score them.

``rollout`` runs N episodes either batched (N MuJoCo ``MjData`` on one shared
``MjModel``, one policy call per control step for all of them) or sequentially
(the plain one-env loop, kept as the reference). For a policy that treats rows
independently both modes give the same per-episode numbers, bit for bit: they share
the reset, the physics and the observation/reward code of ``offline_rl_core.env``.
"""

from __future__ import annotations

import contextlib
import ctypes
import glob
import os
from dataclasses import dataclass
from typing import Callable, Sequence

import mujoco
import numpy as np

from .atomic import atomic_path
from .env import (  # batch_observations is re-exported: part of this module's API
    ACT_DIM,
    PusherReachEnv,
    apply_action,
    batch_observations,
    build_model,
    clip_actions,
    score_steps,
)
from .stats import wilson_ci

ActFn = Callable[[np.ndarray], np.ndarray]


@dataclass
class RolloutResult:
    """Per-episode outcomes, in the order of ``seeds``."""

    seeds: np.ndarray  # int64 (N,) reset seeds
    success: np.ndarray  # bool (N,) latched info['success'] at episode end
    final_dist: np.ndarray  # float64 (N,) info['dist'] of the last step
    returns: np.ndarray  # float64 (N,) undiscounted return
    lengths: np.ndarray  # int64 (N,) steps taken

    @property
    def successes(self) -> int:
        return int(self.success.sum())

    @property
    def episodes(self) -> int:
        return int(len(self.seeds))

    @property
    def success_rate(self) -> float:
        return self.successes / self.episodes

    @property
    def mean_final_dist(self) -> float:
        return float(self.final_dist.mean())

    @classmethod
    def concatenate(cls, parts: Sequence["RolloutResult"]) -> "RolloutResult":
        return cls(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("seeds", "success", "final_dist", "returns", "lengths")))


_POOL: dict[int, list[PusherReachEnv]] = {}
_MODEL: list[mujoco.MjModel] = []


def _shared_model() -> mujoco.MjModel:
    if not _MODEL:
        _MODEL.append(build_model())
    return _MODEL[0]


def _pooled_envs(model: mujoco.MjModel, n: int) -> list[PusherReachEnv]:
    """n envs on ``model``, reused across calls: an ``MjData`` costs ~0.4 ms to
    allocate, as much as the physics of a short evaluation. Every episode starts
    with ``mj_resetData``, so nothing carries over from the previous user."""
    pool = _POOL.setdefault(id(model), [])
    while len(pool) < n:
        pool.append(PusherReachEnv(model=model))
    return pool[:n]


class BatchedPusherEnv:
    """N pusher-reach episodes stepped together, one ``MjData`` each on one model.

    Resets go through ``PusherReachEnv.reset`` (the one place randomness is drawn);
    actions, physics, observation, reward, success latch and truncation are the
    batch functions of ``offline_rl_core.env`` that ``PusherReachEnv.step`` calls
    with N = 1.
    """

    def __init__(self, n: int, terminate_on_success: bool = False, model: mujoco.MjModel | None = None):
        self.model = model if model is not None else _shared_model()
        self.envs = _pooled_envs(self.model, n)
        self.terminate_on_success = terminate_on_success
        self.n = n
        for env in self.envs:
            env.terminate_on_success = terminate_on_success
        fid = self.envs[0]._fingertip
        mocap = self.envs[0]._mocap
        # Views into each MjData, taken once: reading them costs no attribute lookups per step.
        self._qpos = [e.data.qpos for e in self.envs]
        self._qvel = [e.data.qvel for e in self.envs]
        self._tip = [e.data.site_xpos[fid] for e in self.envs]
        self._target = [e.data.mocap_pos[mocap] for e in self.envs]
        self.steps = np.zeros(n, np.int64)
        self.success = np.zeros(n, bool)

    def _gather(self, idx) -> np.ndarray:
        qpos = np.array([self._qpos[i][:2] for i in idx])
        qvel = np.array([self._qvel[i][:2] for i in idx])
        tip = np.array([self._tip[i][:2] for i in idx])
        target = np.array([self._target[i][:2] for i in idx])
        return qpos, qvel, tip, target

    def reset(self, seeds: Sequence[int]) -> np.ndarray:
        if len(seeds) != self.n:
            raise ValueError(f"{len(seeds)} seeds for {self.n} envs")
        for env, seed in zip(self.envs, seeds):
            env.reset(int(seed))
        self.steps[:] = 0
        self.success[:] = False
        qpos, qvel, tip, target = self._gather(range(self.n))
        return batch_observations(qpos, qvel, target, tip)

    def step(self, actions: np.ndarray, idx: np.ndarray):
        """Step the envs ``idx`` (an int array) with ``actions`` (len(idx), 2).

        Returns ``(obs, reward, done, success, dist)`` arrays for those envs.
        """
        actions = clip_actions(actions, len(idx))
        for row, i in enumerate(idx):
            apply_action(self.model, self.envs[i].data, actions[row])
        self.steps[idx] += 1
        qpos, qvel, tip, target = self._gather(idx)
        score = score_steps(target, tip, self.steps[idx], self.success[idx], self.terminate_on_success)
        self.success[idx] = score.success
        done = score.terminated | score.truncated
        return batch_observations(qpos, qvel, target, tip), score.reward, done, score.success.copy(), score.dist


def _openblas_thread_controls():
    """numpy's bundled OpenBLAS set/get-threads functions, or None where not found."""
    libs = glob.glob(os.path.join(os.path.dirname(np.__file__) + ".libs", "*openblas*"))
    for path in libs:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for suffix in ("64_", "_64_", ""):
            get = getattr(lib, f"scipy_openblas_get_num_threads{suffix}", None) or getattr(lib, f"openblas_get_num_threads{suffix}", None)
            put = getattr(lib, f"scipy_openblas_set_num_threads{suffix}", None) or getattr(lib, f"openblas_set_num_threads{suffix}", None)
            if get is not None and put is not None:
                return get, put
    return None


@contextlib.contextmanager
def single_threaded_blas():
    """Run numpy's BLAS on one thread inside the block.

    A rollout makes ~100 small matmuls per episode batch; handing each to a thread
    pool costs more than the maths, and on a busy machine it made evaluation 10x
    slower. Where the BLAS cannot be reached this does nothing.
    """
    controls = _openblas_thread_controls()
    if controls is None:
        yield
        return
    get, put = controls
    before = int(get())
    put(1)
    try:
        yield
    finally:
        put(before)


def _rollout_sequential(act_fn: ActFn, seeds: np.ndarray, terminate_on_success: bool) -> RolloutResult:
    env = PusherReachEnv(terminate_on_success=terminate_on_success)
    n = len(seeds)
    success = np.zeros(n, bool)
    final_dist = np.zeros(n)
    returns = np.zeros(n)
    lengths = np.zeros(n, np.int64)
    for k, seed in enumerate(seeds):
        obs = env.reset(int(seed))
        done = False
        while not done:
            action = np.asarray(act_fn(obs[None, :]))[0]
            obs, reward, done, info = env.step(action)
            returns[k] += reward
            lengths[k] += 1
        success[k] = info["success"]
        final_dist[k] = info["dist"]
    return RolloutResult(seeds.copy(), success, final_dist, returns, lengths)


def _rollout_batched(act_fn: ActFn, seeds: np.ndarray, terminate_on_success: bool) -> RolloutResult:
    n = len(seeds)
    venv = BatchedPusherEnv(n, terminate_on_success)
    obs = venv.reset(seeds)
    final_dist = np.zeros(n)
    returns = np.zeros(n)
    active = np.arange(n)
    while len(active):
        actions = np.asarray(act_fn(obs))
        next_obs, reward, done, _, dist = venv.step(actions, active)
        returns[active] += reward
        final_dist[active] = dist
        keep = ~done
        active = active[keep]
        obs = next_obs[keep]
    return RolloutResult(seeds.copy(), venv.success.copy(), final_dist, returns, venv.steps.copy())


def rollout(
    act_fn: ActFn,
    reset_seeds: Sequence[int],
    terminate_on_success: bool = False,
    batched: bool = True,
) -> RolloutResult:
    """Run one episode per reset seed with ``act_fn(obs (N, 8) float32) -> (N, 2)``.

    ``batched`` steps all episodes together with one ``act_fn`` call per control
    step; ``batched=False`` is the plain loop, one env and one call per step.
    """
    seeds = np.asarray(list(reset_seeds), dtype=np.int64)
    if seeds.size == 0:
        raise ValueError("rollout needs at least one reset seed")
    run = _rollout_batched if batched else _rollout_sequential
    with single_threaded_blas():
        return run(act_fn, seeds, terminate_on_success)


def expert_act_fn() -> ActFn:
    """The scripted expert as a batch ``act_fn``, from the observation alone.

    The observation carries (cos, sin) of the joint angles, the joint velocities and
    target - fingertip; ``expert.expert_action`` needs angles and the target, which
    we recover exactly enough (atan2 and planar forward kinematics) for it to reach.
    """
    from .env import fingertip_from_joints
    from .expert import expert_action

    def act(obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float64)
        out = np.empty((obs.shape[0], ACT_DIM), np.float32)
        for row, o in enumerate(obs):
            q = np.array([np.arctan2(o[1], o[0]), np.arctan2(o[3], o[2])])
            target = fingertip_from_joints(q) + o[6:8]
            out[row] = expert_action(q, o[4:6], target)
        return out

    return act


def round6(x: float) -> float:
    return round(float(x), 6)


def evaluate_policy(policy, episodes: int, seed: int, batched: bool = True, checkpoint: str | None = None) -> dict:
    """Score ``policy`` (anything with ``act(obs)``, or a callable) on reset seeds
    ``seed .. seed + episodes - 1``; the dict ``offline-rl eval`` prints and writes."""
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    act_fn = policy.act if hasattr(policy, "act") else policy
    result = rollout(act_fn, range(seed, seed + episodes), batched=batched)
    lo, hi = wilson_ci(result.successes, result.episodes)
    return {
        "checkpoint": checkpoint if checkpoint is not None else getattr(policy, "source", None),
        "algorithm": getattr(policy, "algorithm", None),
        "episodes": result.episodes,
        "seed": int(seed),
        "successes": result.successes,
        "success_rate": round6(result.success_rate),
        "wilson_ci_lo": round6(lo),
        "wilson_ci_hi": round6(hi),
        "mean_final_dist": round6(result.mean_final_dist),
        "mean_return": round6(result.returns.mean()),
    }


def write_json_atomic(path, payload) -> "os.PathLike":
    """``json.dumps(indent=2, sort_keys=True)`` + newline, via a temp file and rename,
    so a reader never sees half a file and equal payloads give equal bytes."""
    import json
    from pathlib import Path

    text = json.dumps(payload, indent=2, sort_keys=True) + "\n"
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def format_rate(successes: int, episodes: int) -> str:
    """'27/100 = 0.270 [0.193, 0.363]': a success rate with its Wilson 95 % CI."""
    lo, hi = wilson_ci(successes, episodes)
    return f"{successes}/{episodes} = {successes / episodes:.3f} [{lo:.3f}, {hi:.3f}]"
