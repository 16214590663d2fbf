"""Rollouts: batched == sequential, the expert reaches, observations match the env."""

import mujoco
import numpy as np
import pytest
import torch

from offline_rl_core.task.pusher_reach import PusherReachEnv, build_model
from offline_rl_core.evaluation.rollouts import (
    BatchedPusherEnv, _mujoco_timer_slot, _unconstrained, batch_observations, evaluate_policy, expert_act_fn,
    mujoco_timers_off, rollout,
)
from offline_rl_core.serving.policy import policy_sequential
from offline_rl_core.serving.checkpoint import CHECKPOINT_FORMAT, CHECKPOINT_VERSION
from offline_rl_core.serving.policy import LoadedPolicy

FIELDS = ("seeds", "success", "final_dist", "returns", "lengths")


def random_policy(hidden=32, seed=0) -> LoadedPolicy:
    torch.manual_seed(seed)
    net = policy_sequential(8, hidden, 2)
    return LoadedPolicy({
        "format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "algorithm": "bc",
        "obs_dim": 8, "act_dim": 2, "hidden": hidden, "policy_state": net.state_dict(),
    })


def row_by_row(act_fn):
    """The same policy, evaluated one row at a time: bitwise independent of batch size."""
    return lambda obs: np.stack([act_fn(o[None, :])[0] for o in obs])


@pytest.mark.parametrize("terminate_on_success", [False, True])
def test_expert_batched_equals_sequential_and_reaches(terminate_on_success):
    seeds = range(500000, 500012)
    b = rollout(expert_act_fn(), seeds, terminate_on_success, batched=True)
    s = rollout(expert_act_fn(), seeds, terminate_on_success, batched=False)
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(b, f), getattr(s, f), err_msg=f)
    assert b.success.all()
    if terminate_on_success:
        assert (b.lengths < 100).all()
    else:
        assert (b.lengths == 100).all() and b.final_dist.max() < 0.02


def test_loaded_policy_batched_equals_sequential_exactly_when_rows_are_independent():
    # Row by row, LoadedPolicy is a row-independent function, so the two modes agree bit for bit.
    act = row_by_row(random_policy().act)
    seeds = range(7, 17)
    b = rollout(act, seeds, batched=True)
    s = rollout(act, seeds, batched=False)
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(b, f), getattr(s, f), err_msg=f)


def test_batched_env_steps_bit_for_bit_like_pusher_env():
    # Same seeds, same actions (some outside [-1, 1]), envs dropping out; the batch
    # without MuJoCo's timers as in rollout(), the envs with them: every output, the
    # full integration state and the fingertip agree bit for bit.
    seeds = list(range(40, 46))
    venv = BatchedPusherEnv(len(seeds))
    envs = [PusherReachEnv(model=venv.model) for _ in seeds]
    spec = mujoco.mjtState.mjSTATE_INTEGRATION
    rng = np.random.default_rng(0)

    def check_states(idx):
        for i in idx:
            want = np.empty(mujoco.mj_stateSize(venv.model, spec))
            mujoco.mj_getState(venv.model, envs[i].data, want, spec)
            np.testing.assert_array_equal(venv.batch.state[i], want)
            np.testing.assert_array_equal(venv._tip[i], envs[i].fingertip[:2])

    with mujoco_timers_off():
        obs = venv.reset(seeds)
    np.testing.assert_array_equal(obs, np.stack([e.reset(s) for e, s in zip(envs, seeds)]))
    check_states(range(len(seeds)))
    idx = np.arange(len(seeds))
    for t in range(60):
        if t in (20, 45):
            idx = idx[1::2] if t == 20 else idx[1:]
        actions = rng.uniform(-1.5, 1.5, (len(idx), 2)).astype(np.float32)
        with mujoco_timers_off():
            obs, reward, done, success, dist = venv.step(actions, idx)
        for row, i in enumerate(idx):
            o, r, d, info = envs[i].step(actions[row])
            np.testing.assert_array_equal(obs[row], o)
            assert (reward[row], done[row], success[row], dist[row]) == (r, d, info["success"], info["dist"])
        check_states(idx)


def test_constraint_stages_skipped_only_where_nothing_can_constrain():
    off = mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
    model = build_model()
    assert _unconstrained(model).opt.disableflags & off and not model.opt.disableflags & off
    model.geom_contype[0] = model.geom_conaffinity[0] = 1  # the floor could now touch something
    assert _unconstrained(model) is model


def test_mujoco_timers_off_nulls_and_restores_the_callback():
    slot = _mujoco_timer_slot()
    assert slot is not None, "libmujoco's mjcb_time not found: batched rollouts pay MuJoCo's profiling timers"
    before = slot.value
    with mujoco_timers_off():
        assert slot.value is None
    assert slot.value == before


def test_loaded_policy_batched_matches_sequential_with_batched_matmuls():
    # BLAS picks other kernels for 1 row than for N rows (last-bit differences in the
    # actions), so plain .act agrees to ~1e-8 m, not bit for bit.
    pol = random_policy(hidden=64, seed=1)
    b = rollout(pol.act, range(20), batched=True)
    s = rollout(pol.act, range(20), batched=False)
    np.testing.assert_array_equal(b.success, s.success)
    np.testing.assert_allclose(b.final_dist, s.final_dist, atol=1e-6)
    np.testing.assert_allclose(b.returns, s.returns, atol=1e-4)


def test_batch_observations_equal_env_observations():
    envs = [PusherReachEnv() for _ in range(5)]
    rng = np.random.default_rng(0)
    for i, env in enumerate(envs):
        env.reset(i)
        for _ in range(int(rng.integers(1, 30))):
            env.step(rng.uniform(-1, 1, 2))
    single = np.stack([e.observation() for e in envs])
    batch = batch_observations(
        np.stack([e.qpos for e in envs]), np.stack([e.qvel for e in envs]),
        np.stack([e.target[:2] for e in envs]), np.stack([e.fingertip[:2] for e in envs]),
    )
    np.testing.assert_array_equal(batch, single)


def test_evaluate_policy_dict():
    out = evaluate_policy(expert_act_fn(), episodes=5, seed=123)
    assert out["successes"] == 5 and out["success_rate"] == 1.0 and out["episodes"] == 5 and out["seed"] == 123
    assert out["wilson_ci_hi"] == 1.0 and 0.4 < out["wilson_ci_lo"] < 0.6
    assert out["mean_final_dist"] < 0.02
