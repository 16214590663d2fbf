"""Roll policies out on held-out reset seeds and score them: pusher-reach fast, any task's env.

Any task with a sim (``task.envs.make_env``): ``rollout_task`` runs its env one episode
after another, one policy call per step (as the policy node asks), and ``rollout_expert``
the task's scripted expert from each state. On pusher_reach ``rollout_task`` is ``rollout``:

``rollout`` runs N episodes either batched (one ``mujoco.batch.Batch`` of N
simulations, one policy call per control step for all of them) or sequentially
(the plain one-env loop, kept as the reference). Both reset from ``sample_reset``
and share the observation and reward code of ``offline_rl_core.task.pusher_reach``, and their
physics is bit-identical: given the same actions, every per-episode number agrees
bit for bit (tests/test_evaluation.py). What can differ is the policy's output:
asked for N rows at once instead of one, a BLAS matmul picks other kernels and
rounds the float32 actions differently in the last bits. For ``LoadedPolicy`` that
leaves ``final_dist`` within a few 1e-8 m and ``returns`` within ~1e-6 of the
sequential loop; ``success`` and ``lengths`` agree unless an episode ends within
that of the 0.02 m threshold (none does in the tests or the benchmark). A policy
whose rows are independent (e.g. the expert) gives identical results in both modes.
"""

from __future__ import annotations

import contextlib
import copy
import ctypes
import functools
import glob
import os
from dataclasses import dataclass
from typing import Callable, Sequence

import mujoco
import mujoco.batch
import numpy as np

from ..task.envs import expert_action, make_env
from ..task.pusher_reach import (
    ACT_DIM, FRAME_SKIP, PusherReachEnv, batch_observations, build_model, clip_actions, sample_reset, score_steps,
)
from ..task.spec import DEFAULT_TASK, TaskSpec, load_task
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


@functools.cache
def _shared_model() -> mujoco.MjModel:
    """The model of every batched rollout: compiling one costs ~1.5 ms."""
    return build_model()


def _unconstrained(model: mujoco.MjModel) -> mujoco.MjModel:
    """``model`` without MuJoCo's collision and constraint stages, where it can have
    no constraint at all (no geom that collides, no pair, equality, flex, limit or
    friction loss): the stages find nothing there but cost ~15 % of an ``mj_step``
    (the collision broadphase diagonalises a 3x3 every substep). Same physics bit for
    bit (tests/test_evaluation.py). Any other model is returned as it is."""
    if (
        (model.geom_contype | model.geom_conaffinity).any() or model.npair or model.neq or model.nflex
        or model.jnt_limited.any() or model.tendon_limited.any()
        or model.dof_frictionloss.any() or model.tendon_frictionloss.any()
    ):
        return model
    model = copy.copy(model)
    model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
    return model


class BatchedPusherEnv:
    """N pusher-reach episodes stepped together in one ``mujoco.batch.Batch``.

    Each episode is a row of the batch's state; a step sets the rows' controls and
    runs ``FRAME_SKIP`` ``mj_step`` substeps per row in C, with no Python per
    episode (on the model less its empty constraint stages, see ``_unconstrained``).
    ``mujoco.batch`` guarantees the result bit-identical to ``mj_step`` on one
    ``MjData`` per episode (``PusherReachEnv.step``), and its ``site_xpos`` is, as
    there, from the start of the last substep. A reset does per row what
    ``PusherReachEnv.reset`` does: ``mj_resetData``, ``sample_reset``'s joints and
    target, ``mj_forward``. Observation, reward, success latch and truncation are the
    batch functions of ``offline_rl_core.task.pusher_reach``. tests/test_evaluation.py checks
    states and fingertips against ``PusherReachEnv`` bit for bit.
    """

    def __init__(self, n: int, terminate_on_success: bool = False, model: mujoco.MjModel | None = None):
        self.model = model if model is not None else _shared_model()
        # nthread=1: the caller's thread only; a thread pool loses on a busy 2-core machine.
        self.batch = mujoco.batch.Batch(_unconstrained(self.model), n, nthread=1)
        self.terminate_on_success = terminate_on_success
        self.n = n
        mocap = self.model.body_mocapid[self.model.body("target").id]
        # Live (n, ...) views of the batch's state rows, and of the fingertip it
        # refreshes after every call.
        self._qpos = self.batch.bind("qpos")[:, :2]
        self._qvel = self.batch.bind("qvel")[:, :2]
        self._ctrl = self.batch.bind("ctrl")[:, :ACT_DIM]
        self._target = self.batch.bind("mocap_pos")[:, mocap]
        self._tip = self.batch.bind("site_xpos")[:, self.model.site("fingertip").id, :2]
        self.steps = np.zeros(n, np.int64)
        self.success = np.zeros(n, bool)

    def reset(self, seeds: Sequence[int]) -> np.ndarray:
        if len(seeds) != self.n:
            raise ValueError(f"{len(seeds)} seeds for {self.n} envs")
        self.batch.reset(stage=mujoco.mjtStage.mjSTAGE_NONE)
        for row, seed in enumerate(seeds):
            self._qpos[row], self._target[row] = sample_reset(int(seed))
        self.batch.forward()
        self.steps[:] = 0
        self.success[:] = False
        return batch_observations(self._qpos, self._qvel, self._target[:, :2], self._tip)

    def step(self, actions: np.ndarray, idx: np.ndarray):
        """Step the envs ``idx`` (a sorted int array) with ``actions`` (len(idx), 2).

        Returns ``(obs, reward, done, success, dist)`` arrays for those envs.
        """
        every = len(idx) == self.n  # the usual case: views instead of copies, no ids for the batch
        sel = slice(None) if every else idx
        self._ctrl[sel] = clip_actions(actions, len(idx))
        self.batch.step(None if every else idx, nstep=FRAME_SKIP)
        self.steps[sel] += 1
        qpos, qvel, tip, target = self._qpos[sel], self._qvel[sel], self._tip[sel], self._target[sel, :2]
        score = score_steps(target, tip, self.steps[sel], self.success[sel], self.terminate_on_success)
        self.success[sel] = score.success
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


@functools.cache
def _mujoco_timer_slot() -> ctypes.c_void_p | None:
    """libmujoco's global ``mjcb_time`` pointer, or None where the library is not found."""
    here = os.path.dirname(mujoco.__file__)
    for pattern in ("libmujoco.so.*", "libmujoco*.dylib", "mujoco.dll"):
        for path in glob.glob(os.path.join(here, pattern)):
            try:
                return ctypes.c_void_p.in_dll(ctypes.CDLL(path), "mjcb_time")
            except (OSError, ValueError):
                continue
    return None


@contextlib.contextmanager
def mujoco_timers_off():
    """Step MuJoCo without its profiling timer inside the block.

    ``import mujoco`` installs a clock_gettime ``mjcb_time`` so that ``MjData.timer``
    profiles every pipeline stage; for this 2-DoF arm the clock reads are a large
    share of an ``mj_step`` (bench/RESULTS.md). Only ``MjData.timer`` reads the callback, never the physics. Where
    libmujoco cannot be reached this does nothing.
    """
    slot = _mujoco_timer_slot()
    if slot is None:
        yield
        return
    before = slot.value
    slot.value = None
    try:
        yield
    finally:
        slot.value = before


@contextlib.contextmanager
def single_threaded_blas():
    """Run numpy's BLAS on one thread inside the block.

    A rollout makes ~100 small matmuls per episode batch; handing each to a thread
    pool costs more than the maths, and on a busy machine far more (bench/RESULTS.md).
    Where the BLAS cannot be reached this does nothing.
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


def _rollout_sequential(act_fn: ActFn, seeds: np.ndarray, terminate_on_success: bool, env=None,
                        choose: Callable[[np.ndarray], np.ndarray] | None = None) -> RolloutResult:
    """One episode after another in ``env`` (default: pusher-reach's); the action of each
    state is ``choose(obs)`` (default: ``act_fn`` on the one-row batch)."""
    env = env if env is not None else PusherReachEnv(terminate_on_success=terminate_on_success)
    choose = choose or (lambda obs: np.asarray(act_fn(obs[None, :]))[0])
    n = len(seeds)
    success = np.zeros(n, bool)
    final_dist = np.zeros(n)
    returns = np.zeros(n)
    lengths = np.zeros(n, np.int64)
    for k, seed in enumerate(seeds):
        obs = env.reset(int(seed))
        done = False
        while not done:
            action = choose(obs)
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
        obs, reward, done, _, dist = venv.step(actions, active)
        returns[active] += reward
        final_dist[active] = dist
        if done.any():
            active, obs = active[~done], obs[~done]
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
    seeds = _seeds(reset_seeds)
    if not batched:  # the reference: MuJoCo as a plain loop runs it, profiling timers included
        with single_threaded_blas():
            return _rollout_sequential(act_fn, seeds, terminate_on_success)
    with single_threaded_blas(), mujoco_timers_off():
        return _rollout_batched(act_fn, seeds, terminate_on_success)


def _seeds(reset_seeds: Sequence[int]) -> np.ndarray:
    seeds = np.asarray(list(reset_seeds), dtype=np.int64)
    if seeds.size == 0:
        raise ValueError("rollout needs at least one reset seed")
    return seeds


def _is_pusher_reach(task: TaskSpec) -> bool:
    return task.sim == {"env": "pusher_reach"}


def rollout_task(task: TaskSpec | str | None, act_fn: ActFn, reset_seeds: Sequence[int],
                 terminate_on_success: bool = False, batched: bool = True) -> RolloutResult:
    """``rollout`` on any task's env: ``act_fn(obs (N, obs_dim)) -> (N, act_dim)``.
    pusher_reach's env is batched (``batched``); another task's runs one episode after
    another, one row per call, as the policy node serves it."""
    task = load_task(task)
    if _is_pusher_reach(task):
        return rollout(act_fn, reset_seeds, terminate_on_success, batched)
    seeds = _seeds(reset_seeds)
    with single_threaded_blas():
        return _rollout_sequential(act_fn, seeds, terminate_on_success, make_env(task, terminate_on_success))


def rollout_expert(task: TaskSpec | str | None, reset_seeds: Sequence[int],
                   terminate_on_success: bool = False) -> RolloutResult:
    """The task's scripted expert (``task.envs.task_expert``) from each state of its env."""
    env = make_env(load_task(task), terminate_on_success)
    return _rollout_sequential(None, _seeds(reset_seeds), terminate_on_success, env, lambda obs: expert_action(env))


def expert_act_fn() -> ActFn:
    """The scripted expert as a batch ``act_fn``, from the observation alone.

    The observation carries (cos, sin) of the joint angles, the joint velocities and
    target - fingertip; ``expert.expert_action`` needs angles and the target, which
    we recover exactly enough (atan2 and planar forward kinematics) for it to reach.
    """
    from ..task.pusher_reach import fingertip_from_joints
    from ..task.expert import expert_action

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


def evaluate_policy(policy, episodes: int, seed: int, batched: bool = True, checkpoint: str | None = None,
                    task: TaskSpec | str | None = None) -> dict:
    """Score ``policy`` (anything with ``act(obs)``, or a callable; None: the task's
    scripted expert) on ``task``'s reset seeds ``seed .. seed + episodes - 1``; the dict
    ``offline-rl eval`` prints and writes (it names the task, but for pusher_reach's)."""
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    task = load_task(task)
    seeds = range(seed, seed + episodes)
    if policy is None:
        result = rollout_expert(task, seeds)
    else:
        act_fn = policy.act if hasattr(policy, "act") else policy
        result = rollout_task(task, act_fn, seeds, batched=batched)
    return scored(result, seed, task, checkpoint if checkpoint is not None else getattr(policy, "source", None),
                  "expert" if policy is None else getattr(policy, "algorithm", None))


def scored(result: RolloutResult, seed: int, task: TaskSpec, checkpoint: str | None, algorithm: str | None) -> dict:
    """The evaluation's dict of a rollout: success with its Wilson interval, distances, return."""
    lo, hi = wilson_ci(result.successes, result.episodes)
    named = {} if task.name == DEFAULT_TASK else {"task": task.name, "task_digest": task.digest}
    return {
        **named,
        "checkpoint": checkpoint,
        "algorithm": algorithm,
        "episodes": result.episodes,
        "seed": int(seed),
        "successes": result.successes,
        "success_rate": round6(result.success_rate),
        "wilson_ci_lo": round6(lo),
        "wilson_ci_hi": round6(hi),
        "mean_final_dist": round6(result.mean_final_dist),
        "mean_return": round6(result.returns.mean()),
    }


def format_rate(successes: int, episodes: int) -> str:
    """'27/100 = 0.270 [0.193, 0.363]': a success rate with its Wilson 95 % CI."""
    lo, hi = wilson_ci(successes, episodes)
    return f"{successes}/{episodes} = {successes / episodes:.3f} [{lo:.3f}, {hi:.3f}]"
