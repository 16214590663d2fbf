"""Task files: the built-in pusher-reach file gives the chapter's observations and rewards bit
for bit, any arm's file loads with its sizes, and a wrong file is one line naming the field."""

from __future__ import annotations

import numpy as np
import pytest

from offline_rl_core.common.errors import UserError
from offline_rl_core.task import features
from offline_rl_core.task.pusher_reach import PusherReachEnv
from offline_rl_core.task.spec import builtin_tasks, load_task, task_from_dict, task_from_yaml

VELOCITY_ARM = """
name: velocity_arm
control_period: 0.02
robot:
  state: {topic: joint_states, joints: [j0, j1, j2], revolute: [j0, j1, j2]}
  command: {interface: velocity, controller: velocity_controller, joints: [j2, j0, j1], scale: 1.5}
goal: {topic: goal_joints, type: sensor_msgs/JointState}
observation:
  - cos_sin: [j0, j1, j2]
  - velocities: [j0, j1, j2]
  - difference: [goal, joints]
reward: {distance: [goal, joints], success_within: 0.05}
episodes: {max_steps: 150}
join: {stamps: receive}
"""


def chapter_observation(qpos, qvel, target, fingertip) -> np.ndarray:
    """The chapter's observation, written out as it states it."""
    angles = (np.asarray(qpos, np.float64) + np.pi) % (2 * np.pi) - np.pi
    obs = np.empty(8, np.float32)
    obs[0], obs[1], obs[2], obs[3] = np.cos(angles[0]), np.sin(angles[0]), np.cos(angles[1]), np.sin(angles[1])
    obs[4:6] = qvel
    obs[6:8] = np.asarray(target[:2], np.float64) - np.asarray(fingertip[:2], np.float64)
    return obs


def test_the_pusher_reach_file_is_the_chapters_observation_and_reward():
    task = load_task("pusher_reach")
    assert task.obs_dim == 8 and task.act_dim == 2 and task.joints == ("shoulder", "elbow")
    env = PusherReachEnv()
    rng = np.random.default_rng(3)
    for seed in range(5):
        env.reset(seed)
        success = False
        for step in range(1, 101):
            env.step(rng.uniform(-1, 1, 2))
            vectors = {"goal": env.target[None, :2], "fingertip": env.fingertip[None, :2]}
            obs = features.observe(task, env.qpos[None], env.qvel[None], vectors)[0]
            assert obs.tobytes() == chapter_observation(env.qpos, env.qvel, env.target, env.fingertip).tobytes()
            assert obs.tobytes() == env.observation().tobytes()
            scored = features.score(task, env.qpos[None], vectors, [step], [success])
            dist = float(np.sqrt((env.target[0] - env.fingertip[0]) ** 2 + (env.target[1] - env.fingertip[1]) ** 2))
            assert scored.dist[0] == pytest.approx(dist, abs=1e-15)
            latched = not success and dist < 0.02
            assert scored.reward[0] == pytest.approx(-dist + (1.0 if latched else 0.0), abs=1e-15)
            success = bool(scored.success[0])
            assert bool(scored.truncated[0]) == (step == 100)


def test_any_arms_task_file_takes_its_sizes_from_the_file():
    task = task_from_yaml(VELOCITY_ARM)
    assert task.obs_dim == 3 * 2 + 3 + 3 and task.act_dim == 3
    assert task.action_labels() == ("velocity(j2)", "velocity(j0)", "velocity(j1)")  # the controller's order
    assert task.command.topic == "velocity_controller/commands" and task.command.scale == (1.5, 1.5, 1.5)
    assert task.command.limits == ((-1.5, 1.5),) * 3
    positions = np.array([[0.1, -0.2, 4.0]])
    goal = np.array([[0.3, 0.2, 0.1]])
    obs = features.observe(task, positions, np.zeros((1, 3)), {"goal": goal})[0]
    wrapped = (positions[0] + np.pi) % (2 * np.pi) - np.pi
    np.testing.assert_allclose(obs[-3:], (goal[0] - wrapped).astype(np.float32))
    scored = features.score(task, positions, {"goal": goal}, [1], [False])
    assert scored.reward[0] == pytest.approx(-np.linalg.norm(goal[0] - wrapped))


def test_a_task_round_trips_through_its_description_with_the_same_digest():
    for name in builtin_tasks():
        task = load_task(name)
        again = task_from_dict(task.describe())
        assert again.digest == task.digest and again.observation_labels() == task.observation_labels()
    changed = task_from_yaml(VELOCITY_ARM.replace("success_within: 0.05", "success_within: 0.04"))
    assert changed.digest != task_from_yaml(VELOCITY_ARM).digest


@pytest.mark.parametrize("edit, message", [
    (lambda t: t.replace("name: velocity_arm\n", ""), "field name: every task needs a name"),
    (lambda t: t.replace("control_period: 0.02", "control_perod: 0.02"), "unknown field control_perod"),
    (lambda t: t.replace("cos_sin: [j0, j1, j2]", "cos_sin: [j0, j9]"),
     "field observation[0].cos_sin names 'j9', not one of robot.state.joints (j0, j1, j2)"),
    (lambda t: t.replace("difference: [goal, joints]", "difference: [goal, tip]"),
     "field observation[2].difference: expected a vector: goal, joints, got 'tip'"),
    (lambda t: t.replace("scale: 1.5", "scale: [1, 2]"), "field robot.command.scale: expected a number or a list of 3"),
    (lambda t: t.replace("interface: velocity", "interface: torque"),
     "field robot.command.interface: expected one of effort, velocity, position, got 'torque'"),
    (lambda t: t.replace("type: sensor_msgs/JointState", "type: std_msgs/Float32"),
     "field goal.type: expected one of geometry_msgs/PointStamped"),
    (lambda t: t.replace("max_steps: 150", "max_steps: 0"), "field episodes.max_steps: expected a whole number >= 1"),
    (lambda t: t.replace("stamps: receive", "stamps: received"), "field join.stamps: expected one of header, receive"),
    (lambda t: t.replace("joints: [j0, j1, j2], revolute", "joints: [j0, j1, j1], revolute"),
     "field robot.state.joints names 'j1' twice"),
])
def test_a_wrong_task_file_is_one_line_naming_the_field(tmp_path, edit, message):
    path = tmp_path / "arm.yaml"
    path.write_text(edit(VELOCITY_ARM))
    with pytest.raises(UserError) as raised:
        load_task(path)
    text = str(raised.value)
    assert "\n" not in text and text.startswith(f"{path}: ") and message in text, text


def test_an_unknown_task_name_lists_the_built_in_ones():
    with pytest.raises(UserError, match="unknown task 'pusher_rech': expected a built-in task \\(.*pusher_reach"):
        load_task("pusher_rech")


def test_a_joint_space_goal_meets_each_joint_in_its_own_order():
    """A JointState goal naming its joints in another order (or a subset) is compared joint by joint."""
    task = task_from_yaml(VELOCITY_ARM.replace("goal: {topic: goal_joints, type: sensor_msgs/JointState}",
                                                "goal: {topic: goal_joints, type: sensor_msgs/JointState, joints: [j2, j0]}"))
    assert task.observation_labels()[-2:] == ("goal(j2)-pos(j2)", "goal(j0)-pos(j0)")
    positions = np.array([[0.1, -0.2, 0.3]])
    goal = np.array([[0.5, 0.4]])  # j2, j0
    obs = features.observe(task, positions, np.zeros((1, 3)), {"goal": goal})[0]
    np.testing.assert_allclose(obs[-2:], np.array([0.5 - 0.3, 0.4 - 0.1], np.float32))
    scored = features.score(task, positions, {"goal": goal}, [1], [False])
    assert scored.dist[0] == pytest.approx(np.hypot(0.2, 0.3))


def test_along_across_is_the_offset_in_the_frame_of_the_line_whichever_way_it_runs():
    """``along_across: [fingertip, puck, goal]``: the fingertip's offset from the puck, along
    the line from the puck to the goal and across it (to its left); the same numbers when the
    whole scene turns, zero where puck and goal meet, and only planar vectors."""
    from pathlib import Path

    import offline_rl_core.task as task_pkg

    shipped = (Path(task_pkg.__file__).parent / "builtin" / "pusher_push.yaml").read_text()
    line = "  - difference: [goal, puck]        # where it should go\n"
    assert line in shipped
    text = shipped.replace(line, line + "  - along_across: [fingertip, puck, goal]\n")
    task = task_from_yaml(text, "push_frame.yaml")
    assert task.obs_dim == load_task("pusher_push").obs_dim + 2
    assert task.observation_labels()[-2:] == ("along(fingertip-puck|goal-puck)", "across(fingertip-puck|goal-puck)")

    def frame(fingertip, puck, goal):
        vectors = {"fingertip": np.array([fingertip]), "puck": np.array([puck]), "goal": np.array([goal])}
        return features.observe(task, np.zeros((1, 2)), np.zeros((1, 2)), vectors)[0, -2:]

    # behind the puck (1 cm) and 2 mm to the right of a line running along +x
    np.testing.assert_allclose(frame([0.09, -0.002], [0.1, 0.0], [0.2, 0.0]), [-0.01, -0.002], atol=1e-7)
    turned = lambda v: [-v[1], v[0]]  # noqa: E731 - the same scene a quarter turn round
    np.testing.assert_allclose(frame(turned([0.09, -0.002]), turned([0.1, 0.0]), turned([0.2, 0.0])),
                               [-0.01, -0.002], atol=1e-7)
    assert frame([0.09, 0.0], [0.1, 0.0], [0.1, 0.0]).tolist() == [0.0, 0.0]
    with pytest.raises(UserError, match="push_frame.yaml: field observation\\[4\\].along_across: "
                                        "expected three vector names"):
        task_from_yaml(shipped.replace(line, line + "  - along_across: [fingertip, puck]\n"), "push_frame.yaml")


def test_a_direction_feature_is_the_unit_vector_and_zero_where_the_two_meet():
    """``direction: [goal, joints]``: (goal - joints) / |goal - joints|, the same at a
    centimetre as at a metre; exactly on the goal it is zero, never NaN."""
    task = task_from_yaml(VELOCITY_ARM.replace("  - difference: [goal, joints]\n",
                                                "  - difference: [goal, joints]\n  - direction: [goal, joints]\n"))
    assert task.obs_dim == 3 * 2 + 3 + 3 + 3
    assert task.observation_labels()[-3:] == ("dir(goal(j0)-pos(j0))", "dir(goal(j1)-pos(j1))", "dir(goal(j2)-pos(j2))")
    positions = np.array([[0.1, -0.2, 0.3], [0.1, -0.2, 0.3], [0.5, 0.5, 0.5]])
    goal = np.array([[0.4, 0.2, 0.3], [0.103, -0.196, 0.3], [0.5, 0.5, 0.5]])  # 0.5 rad, 5 mrad, on it
    obs = features.observe(task, positions, np.zeros((3, 3)), {"goal": goal})
    np.testing.assert_allclose(obs[0, -3:], [0.6, 0.8, 0.0], atol=1e-6)
    np.testing.assert_allclose(obs[1, -3:], [0.6, 0.8, 0.0], atol=1e-4)
    assert obs[2, -3:].tolist() == [0.0, 0.0, 0.0] and np.isfinite(obs).all()
    with pytest.raises(UserError, match="field observation\\[3\\].direction: expected two vector names"):
        task_from_yaml(VELOCITY_ARM.replace("  - difference: [goal, joints]\n",
                                            "  - difference: [goal, joints]\n  - direction: [goal]\n"))
