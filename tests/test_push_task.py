"""pusher_push: the chapter's arm pushing a puck (task.pusher_push, task.push_expert), the reward
terms and the success judged at the episode's end (task.features), and the older tasks' digests
kept. Real MuJoCo throughout; a few episodes only (the expert's 100 held-out resets are in
bench/pusher_push_expert.json)."""

from __future__ import annotations

import math
import textwrap

import numpy as np
import pytest

from offline_rl_core.common.errors import UserError
from offline_rl_core.common.seeds import HELD_OUT
from offline_rl_core.nodes.sim_loop import SimLoop
from offline_rl_core.task import features
from offline_rl_core.task.envs import expert_action, make_env, point_vectors, task_expert
from offline_rl_core.task.spec import POSE_STAMPED, load_task, task_from_dict, task_from_yaml

PUSH = load_task("pusher_push")


@pytest.fixture(scope="module")
def env():
    return make_env(PUSH)


def test_tasks_written_before_the_new_reward_fields_keep_their_digests():
    # bags and checkpoints of these tasks record these digests
    assert load_task("pusher_reach").digest == "156662009106bf38"
    assert load_task("pusher7_reach").digest == "338e9695c44c7200"  # since its direction feature
    assert "success_at" not in load_task("pusher_reach").describe()["reward"]
    assert task_from_dict(PUSH.describe()).digest == PUSH.digest  # the JSON form reads back


def test_the_puck_is_a_tracked_point_from_a_topic_and_the_observation_sees_puck_and_goal():
    puck = PUSH.point("puck")
    assert (puck.topic, puck.type, puck.kinematics) == ("puck", POSE_STAMPED, None)
    assert PUSH.observation_labels() == (
        "cos(shoulder)", "sin(shoulder)", "cos(elbow)", "sin(elbow)", "vel(shoulder)", "vel(elbow)",
        "puck.x-fingertip.x", "puck.y-fingertip.y", "goal.x-puck.x", "goal.y-puck.y",
        "dir(puck.x-fingertip.x)", "dir(puck.y-fingertip.y)", "dir(goal.x-puck.x)", "dir(goal.y-puck.y)",
        "along(fingertip-puck|goal-puck)", "across(fingertip-puck|goal-puck)")
    assert (PUSH.control_period, PUSH.episodes.max_steps, PUSH.sim["frame_skip"]) == (0.05, 60, 10)  # 20 Hz, 3 s
    assert PUSH.reward.distances == (("goal", "puck"), ("puck", "fingertip"))
    assert PUSH.reward.success_at == "end"


def test_resets_are_seeded_within_reach_and_clear_of_the_arm(env):
    s = env.push
    starts = set()
    for seed in (HELD_OUT, HELD_OUT + 1, HELD_OUT + 2, 7):
        env.reset(seed)
        puck, goal, q = env.puck.copy(), env.goal.copy(), env.joint_positions.copy()
        again = make_env(PUSH)
        again.reset(seed)
        assert np.array_equal(again.puck, puck) and np.array_equal(again.goal, goal)
        assert np.array_equal(again.joint_positions, q)
        assert s.radius[0] <= math.hypot(*puck) <= s.radius[1] and s.radius[0] <= math.hypot(*goal) <= s.radius[1]
        assert s.distance[0] <= math.hypot(*(goal - puck)) <= s.distance[1]
        assert env.geometry.push_is_clear(puck, goal, s.standoff, s.margin)
        assert not env.index.arm_touches(env.model, env.data)
        assert np.allclose(env.point_positions()["puck"][:2], puck)
        starts.add(tuple(puck))
    assert len(starts) == 4


def test_the_expert_pushes_the_puck_onto_the_goal_and_holds_it_there(env):
    expert = task_expert(PUSH)
    for seed in (HELD_OUT, HELD_OUT + 3):
        obs = env.reset(seed)
        done = False
        rewards = []
        while not done:
            action = expert(env.joint_positions, env.joint_velocities, env.goal,
                            point_vectors(PUSH, env.point_positions()))
            assert action.dtype == np.float32 and np.all(np.abs(action) <= 1.0)
            obs, reward, done, info = env.step(action)
            rewards.append(reward)
        assert info["success"] and info["dist"] < PUSH.reward.success_within
        assert env.steps == PUSH.episodes.max_steps  # judged at the end: the episode runs its length
        # the reward of the last step, from the task file's terms
        vectors = env.vectors()
        expected = -math.dist(vectors["goal"], vectors["puck"]) - 0.5 * math.dist(vectors["puck"], vectors["fingertip"])
        assert rewards[-1] == pytest.approx(expected + PUSH.reward.success_bonus, abs=1e-12)
    with pytest.raises(ValueError, match="puck"):
        expert(env.joint_positions, env.joint_velocities, env.goal)  # no tracker, no push


def test_success_at_the_end_is_this_states_not_latched():
    n = np.zeros((3, 2))
    at_goal = {"goal": np.zeros((3, 2)), "puck": np.array([[0.0, 0.001], [0.05, 0.0], [0.0, 0.0]]),
               "fingertip": np.array([[0.0, 0.03], [0.0, 0.03], [0.0, 0.03]])}
    scored = features.score(PUSH, n, at_goal, [5, 6, 150], [True, True, False])
    assert scored.success.tolist() == [True, False, True]  # the second left the goal: no longer a success
    assert scored.truncated.tolist() == [False, False, True]
    bonus = PUSH.reward.success_bonus
    assert scored.reward[0] == pytest.approx(-0.001 - 0.5 * math.hypot(0.0, 0.029) + bonus)
    assert scored.reward[1] == pytest.approx(-0.05 - 0.5 * math.hypot(0.05, 0.03))
    # someone else's judgement (a label, a classifier) replaces the distance's
    judged = features.score(PUSH, n, at_goal, [5, 6, 7], [False] * 3, success_now=[False, True, False])
    assert judged.success.tolist() == [False, True, False]
    assert judged.reward[1] == pytest.approx(scored.reward[1] + bonus)


def test_the_sim_loop_hosts_the_push_and_hands_out_the_puck(env):
    loop = SimLoop("lockstep", seed=HELD_OUT, episodes=1, task=PUSH)
    state = loop.start_episode()
    assert set(state.points) == {"fingertip", "puck"} and state.target[:2].tolist() == loop.env.goal.tolist()
    step = loop.command(state.stamp_ns, expert_action(loop.env), 0)
    assert step.transition.shape == (loop.layout.width,) and step.next_state is not None


BASE = textwrap.dedent("""\
    name: bad_push
    robot: {state: {joints: [shoulder, elbow]}, command: {scale: 0.5}}
    goal: {axes: [x, y]}
    points: {fingertip: {kinematics: "site:fingertip", axes: [x, y]}, puck: {topic: puck, axes: [x, y]}}
    observation: [{difference: [goal, puck]}]
    """)


@pytest.mark.parametrize("extra, says", [
    ("reward: {distance: [goal, puck], success_at: sometimes}", "field reward.success_at: expected one of latch, end"),
    ("reward: {distance: [goal, puck], terms: [{distance: [puck]}]}", "field reward.terms[0].distance: expected two"),
    ("reward: {distance: [goal, puck], terms: [{distance: [puck, elbow]}]}", "field reward.terms[0].distance: expected a vector"),
    ("reward: {distance: [goal, puck], terms: [{distance: [puck, fingertip], scale: 2}]}", "unknown field reward.terms[0].scale"),
])
def test_bad_reward_fields_are_one_line_naming_the_field(extra, says):
    with pytest.raises(UserError, match=says.replace("[", r"\[").replace("]", r"\]")) as err:
        task_from_yaml(BASE + extra)
    assert "\n" not in str(err.value)


def test_a_push_section_without_the_push_env_and_a_puck_without_its_body_are_refused():
    task = task_from_yaml(BASE + "reward: {distance: [goal, puck]}\nsim: {model: x.xml, push: {}}\n")
    with pytest.raises(UserError, match="field sim.push: only with sim.env: pusher_push"):
        make_env(task)
    doc = PUSH.describe()
    doc["sim"] = {**doc["sim"], "points": {"puck": "body:nothing"}, "model": str(
        load_task("pusher_push").path.parent / "pusher_push.xml")}
    with pytest.raises(UserError, match="field sim.points.puck: the sim's model has no body 'nothing'"):
        make_env(task_from_dict(doc))


def with_approach(approach):
    doc = PUSH.describe()
    doc["sim"] = {**doc["sim"], "push": {**doc["sim"]["push"], "approach": approach},
                  "model": str(PUSH.path.parent / "pusher_push.xml")}
    return task_from_dict(doc)


def test_the_orbit_approach_goes_round_the_puck_and_pushes_it_onto_the_goal():
    """``sim.push.approach: orbit`` (the shipped task's): its expert differs from the wave's (a
    task of its own digest) on the way behind the puck and still ends each episode with the
    puck on the goal."""
    task = PUSH
    assert task.sim["push"]["approach"] == "orbit" and with_approach("wave").digest != PUSH.digest
    env, wave = make_env(task), task_expert(with_approach("wave"))
    orbit = task_expert(task)
    for seed in (HELD_OUT, HELD_OUT + 3):
        env.reset(seed)
        done, differed = False, 0
        while not done:
            args = (env.joint_positions, env.joint_velocities, env.goal, point_vectors(task, env.point_positions()))
            action = orbit(*args)
            assert action.dtype == np.float32 and np.all(np.abs(action) <= 1.0)
            differed += not np.array_equal(action, wave(*args))
            _, _, done, info = env.step(action)
        assert differed > 0 and info["success"] and info["dist"] < task.reward.success_within


def test_an_unknown_approach_is_one_line_naming_the_field():
    with pytest.raises(UserError, match=r"field sim.push.approach: expected one of wave, orbit") as err:
        make_env(with_approach("sideways"))
    assert "\n" not in str(err.value)
