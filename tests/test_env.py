"""pusher-reach env: reset sampling, observation, reward, latch, episode end, baselines."""

import math

import numpy as np
import pytest

from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.task.pusher_reach import (
    LINK_LEN, MAX_STEPS, SUCCESS_BONUS, SUCCESS_TOL, PusherReachEnv, batch_observations, fingertip_from_joints,
    observation_from_joints, score_steps,
)
from offline_rl_core.task.expert import reach_action
from offline_rl_core.data.transitions import SOURCE_EXPERT, SOURCE_RANDOM


def run_episode(env, seed, policy):
    """(rewards, infos) of one episode; ``policy(env) -> action``."""
    env.reset(seed)
    rewards, infos, done = [], [], False
    while not done:
        _, reward, done, info = env.step(policy(env))
        rewards.append(reward)
        infos.append(info)
    return rewards, infos


def test_reset_is_deterministic_per_seed():
    a, b = PusherReachEnv(), PusherReachEnv()
    assert a.reset(11).tobytes() == b.reset(11).tobytes()
    a.step([1.0, -1.0])
    assert a.reset(11).tobytes() == b.reset(11).tobytes()  # nothing carries over from the last episode
    assert a.reset(12).tobytes() != b.reset(11).tobytes()


@pytest.mark.parametrize("seed", [0, 1, 7, 123456])
def test_reset_follows_the_documented_sampling(seed):
    rng = np.random.Generator(np.random.PCG64(seed))
    shoulder, elbow = rng.uniform(-math.pi, math.pi, size=2)
    radius = rng.uniform(0.05, 0.19)
    phi = rng.uniform(0.0, 2.0 * math.pi)
    env = PusherReachEnv()
    env.reset(seed)
    assert env.qpos.tolist() == [shoulder, elbow]
    assert env.qvel.tolist() == [0.0, 0.0]
    assert env.target.tolist() == [radius * math.cos(phi), radius * math.sin(phi), 0.0]
    assert env.data.ctrl.tolist() == [0.0, 0.0]
    assert env.steps == 0 and env.success is False


def hand_observation(env):
    """The documented formula, from scratch: wrapped angles, velocities, target - fingertip."""
    sh, el = ((float(q) + math.pi) % (2 * math.pi) - math.pi for q in env.qpos)
    tip = env.fingertip
    return np.array(
        [math.cos(sh), math.sin(sh), math.cos(el), math.sin(el), *env.qvel, env.target[0] - tip[0], env.target[1] - tip[1]],
        dtype=np.float32,
    )


def test_observation_matches_the_formula_and_hand_kinematics():
    env = PusherReachEnv()
    rng = np.random.default_rng(3)
    obs = env.reset(5)
    # At reset the fingertip is MuJoCo's forward kinematics of qpos, as planar FK gives it.
    sh, el = env.qpos
    hand_tip = [LINK_LEN * (math.cos(sh) + math.cos(sh + el)), LINK_LEN * (math.sin(sh) + math.sin(sh + el))]
    np.testing.assert_allclose(env.fingertip[:2], hand_tip, rtol=0, atol=1e-15)
    for _ in range(60):
        assert obs.dtype == np.float32 and obs.shape == (8,)
        np.testing.assert_array_equal(obs, hand_observation(env))
        obs, *_ = env.step(rng.uniform(-1, 1, 2))
    # Spinning the arm winds qpos past pi; the observation sees the wrapped angle.
    env.reset(5)
    env.data.qpos[:2] += [4 * math.pi, -6 * math.pi]
    obs = env.observation()
    np.testing.assert_allclose(obs[:4], hand_observation(env)[:4], rtol=0, atol=1e-6)


def test_observation_from_joints_equals_env_observation_at_reset():
    env = PusherReachEnv()
    for seed in range(200):
        obs = env.reset(seed)
        np.testing.assert_array_equal(observation_from_joints(env.qpos, env.qvel, env.target[:2]), obs)


def test_observation_from_joints_with_the_published_fingertip_is_the_env_observation():
    # The ROS policy node builds its observation from /pusher/state, /pusher/target and
    # /pusher/fingertip: it must see exactly what the policy saw in training.
    env = PusherReachEnv()
    rng = np.random.default_rng(0)
    for seed in range(30):
        env.reset(seed)
        for _ in range(30):
            obs, *_ = env.step(rng.uniform(-1, 1, 2))
            np.testing.assert_array_equal(observation_from_joints(env.qpos, env.qvel, env.target[:2], env.fingertip[:2]), obs)


def test_env_fingertip_is_the_kinematics_of_the_last_physics_substep():
    # MuJoCo computes site_xpos at the start of mj_step, so after a control step the
    # env's fingertip (as in the chapter) is the forward kinematics of qpos one 0.01 s
    # physics substep earlier; planar FK of that qpos reproduces the observation.
    import mujoco

    env = PusherReachEnv()
    rng = np.random.default_rng(0)
    worst = 0.0
    for seed in range(30):
        env.reset(seed)
        for _ in range(10):
            env.data.ctrl[:] = np.float32(rng.uniform(-1, 1, 2))
            mujoco.mj_step(env.model, env.data)
            q_before = env.qpos.copy()
            mujoco.mj_step(env.model, env.data)
            lagged = observation_from_joints(env.qpos, env.qvel, env.target[:2], fingertip_from_joints(q_before))
            np.testing.assert_array_equal(lagged, env.observation())
            worst = max(worst, float(np.abs(observation_from_joints(env.qpos, env.qvel, env.target[:2])[6:] - lagged[6:]).max()))
    # an arm that publishes no fingertip gets planar FK of its joints: close, not equal
    assert 0.0 < worst < 0.02


def test_batch_forms_are_the_single_env_maths():
    envs = [PusherReachEnv() for _ in range(4)]
    rng = np.random.default_rng(1)
    for i, env in enumerate(envs):
        env.reset(i)
        for _ in range(int(rng.integers(1, 20))):
            env.step(rng.uniform(-1, 1, 2))
    obs = batch_observations(
        np.stack([e.qpos for e in envs]), np.stack([e.qvel for e in envs]),
        np.stack([e.target[:2] for e in envs]), np.stack([e.fingertip[:2] for e in envs]),
    )
    np.testing.assert_array_equal(obs, np.stack([e.observation() for e in envs]))
    score = score_steps(
        np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]]), np.array([[0.03, 0.04], [0.01, 0.0], [0.01, 0.0]]),
        np.array([5, 99, 100]), np.array([False, True, False]), terminate_on_success=False,
    )
    np.testing.assert_array_equal(score.dist, [0.05, 0.01, 0.01])
    np.testing.assert_array_equal(score.reward, [-0.05, -0.01, -0.01 + SUCCESS_BONUS])
    np.testing.assert_array_equal(score.success, [False, True, True])
    np.testing.assert_array_equal(score.terminated, [False, False, False])
    np.testing.assert_array_equal(score.truncated, [False, False, True])


def test_reward_is_minus_distance_plus_one_bonus_and_success_latches():
    env = PusherReachEnv()
    rewards, infos = run_episode(env, 0, reach_action)
    dists = np.array([i["dist"] for i in infos])
    latch = int(np.argmax(dists < SUCCESS_TOL))
    assert dists[latch] < SUCCESS_TOL and (dists[:latch] >= SUCCESS_TOL).all()
    dx, dy = env.target[:2] - env.fingertip[:2]
    assert infos[-1]["dist"] == math.sqrt(dx * dx + dy * dy)
    for t, (reward, info) in enumerate(zip(rewards, infos)):
        assert reward == (-info["dist"] + SUCCESS_BONUS if t == latch else -info["dist"])
        assert info["success"] == (t >= latch)
    # The latch holds even when the arm is pushed back out of the tolerance.
    env.data.qpos[0] += 1.0
    _, reward, _, info = env.step([0.0, 0.0])
    assert info["dist"] > SUCCESS_TOL and info["success"] and reward == -info["dist"]


def test_truncation_exactly_at_max_steps():
    env = PusherReachEnv()
    env.reset(4)
    for t in range(1, MAX_STEPS + 1):
        _, _, done, info = env.step([0.0, 0.0])
        assert set(info) == {"terminated", "truncated", "success", "dist"}
        assert info["truncated"] == (t == MAX_STEPS) and done == (t == MAX_STEPS) and not info["terminated"]
    assert env.steps == MAX_STEPS


def test_terminate_on_success_ends_the_episode_at_the_latch():
    rewards, infos = run_episode(PusherReachEnv(terminate_on_success=True), 0, reach_action)
    last = infos[-1]
    assert last["terminated"] and last["success"] and not last["truncated"] and len(infos) < MAX_STEPS
    assert not any(i["success"] for i in infos[:-1])
    assert rewards[-1] == -last["dist"] + SUCCESS_BONUS


def test_step_api_and_action_clipping():
    env = PusherReachEnv()
    with pytest.raises(RuntimeError):
        env.step([0.0, 0.0])
    env.reset(9)
    result = env.step(np.array([3.0, -7.0]))
    assert len(result) == 4
    obs, reward, done, info = result
    assert obs.dtype == np.float32 and isinstance(reward, float) and done is False
    assert env.data.ctrl.tolist() == [1.0, -1.0]
    other = PusherReachEnv()
    other.reset(9)
    assert other.step([1.0, -1.0])[0].tobytes() == obs.tobytes()


def test_expert_reaches_every_seed():
    env = PusherReachEnv()
    returns, finals = [], []
    for seed in range(20):
        rewards, infos = run_episode(env, seed, reach_action)
        assert infos[-1]["success"]
        returns.append(sum(rewards))
        finals.append(infos[-1]["dist"])
    assert np.mean(finals) < 0.001
    assert np.mean(returns) == pytest.approx(-2.4, abs=0.1)


def test_random_policy_final_distance():
    rng = np.random.default_rng(0)
    env = PusherReachEnv()
    finals = [run_episode(env, seed, lambda _: rng.uniform(-1, 1, 2))[1][-1]["dist"] for seed in range(100)]
    assert np.mean(finals) == pytest.approx(0.176, abs=0.03)


def test_collected_mix_behaviour_returns():
    t = collect_transitions(200, 0.3, 0)
    for source, expected in ((SOURCE_EXPERT, -2.33), (SOURCE_RANDOM, -16.0)):
        mask = t.source == source
        per_episode = t.reward[mask].astype(np.float64).sum() / len(np.unique(t.episode[mask]))
        assert per_episode == pytest.approx(expected, abs=0.1 if source == SOURCE_EXPERT else 0.5)
