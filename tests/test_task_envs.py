"""Any task's env (task.envs, task.mujoco_task): pusher7_reach on Gymnasium's Pusher model, a
velocity-controlled arm of a task file's own model, the scripted expert, the sim loop's
headerless commands, and the sim section's one-line errors. Real MuJoCo throughout."""

from __future__ import annotations

import textwrap

import numpy as np
import pytest

from offline_rl_core.common.errors import UserError
from offline_rl_core.common.seeds import HELD_OUT
from offline_rl_core.data.transitions import SOURCE_EXPERT
from offline_rl_core.nodes.joint_messages import action_from_command
from offline_rl_core.nodes.sim_loop import SimLoop
from offline_rl_core.task.envs import expert_action, make_env, point_vectors, task_expert, task_model
from offline_rl_core.task.expert import reach_action
from offline_rl_core.task.kinematics import PointKinematics
from offline_rl_core.task.mujoco_task import MujocoTaskEnv
from offline_rl_core.task.pusher_reach import PusherReachEnv
from offline_rl_core.task.corrector import CorrectorParams, ScriptedCorrector
from offline_rl_core.task.spec import load_task

PUSHER7 = load_task("pusher7_reach")


@pytest.fixture(scope="module")
def env7() -> MujocoTaskEnv:
    return make_env(PUSHER7)


def test_pusher7_is_gymnasiums_seven_joint_pusher_as_a_ros2_control_arm(env7):
    assert (PUSHER7.obs_dim, PUSHER7.act_dim) == (20, 7)
    assert PUSHER7.state.topic == "joint_states" and PUSHER7.command.topic == "velocity_controller/commands"
    assert PUSHER7.command.interface == "velocity"  # the joints' own loop closed by the controller
    model = task_model(PUSHER7)
    assert model.nu == 7 and model.site("fingertip").bodyid == model.body("tips_arm").id
    assert env7.frame_skip * model.opt.timestep == pytest.approx(PUSHER7.control_period)
    assert PUSHER7.command.limits == ((-2.0, 2.0),) * 7  # rad/s


def test_a_reset_is_its_seed_alone(env7):
    obs = env7.reset(5)
    goal, start = env7.goal.copy(), env7.joint_positions.copy()
    env7.step(np.ones(7, np.float32))
    assert np.array_equal(env7.reset(5), obs) and np.array_equal(env7.goal, goal)
    fresh = make_env(PUSHER7)
    assert np.array_equal(fresh.reset(5), obs) and np.array_equal(fresh.joint_positions, start)
    assert not np.array_equal(fresh.reset(6), obs)
    for seed in range(20):  # the sampler's promises: in the box, away from the start, starts untouched
        fresh.reset(seed)
        low, high = np.array(fresh.settings.goal_low), np.array(fresh.settings.goal_high)
        assert np.all(fresh.goal >= low) and np.all(fresh.goal <= high) and fresh.distance() >= 0.1
        ranges = fresh.index.ranges
        assert np.all(fresh.joint_positions >= ranges[:, 0]) and np.all(fresh.joint_positions <= ranges[:, 1])
        assert not fresh.index.arm_touches(fresh.model, fresh.data)


def test_the_expert_reaches_held_out_goals_and_the_fingertip_is_forward_kinematics(env7):
    kinematics = PointKinematics(PUSHER7, task_model(PUSHER7))
    fingertip = PUSHER7.point("fingertip")
    for seed in range(HELD_OUT, HELD_OUT + 3):
        obs = env7.reset(seed)
        done = False
        while not done:
            # the expert acts from the joint state and the goal alone, as a node that only hears topics
            action = expert_action(env7)
            state = env7.joint_positions.copy(), env7.joint_velocities.copy(), env7.goal.copy()
            assert np.array_equal(action, task_expert(PUSHER7)(*state))
            assert np.all(np.abs(action) <= 1.0)
            obs, reward, done, info = env7.step(action)
        assert info["success"] and info["dist"] < PUSHER7.reward.success_within / 10
        # what a policy node computes from joint_states is the env's fingertip, bit for bit
        assert np.array_equal(kinematics.point(fingertip, env7.joint_positions), env7.point_positions()["fingertip"])
        difference = env7.goal - env7.point_positions()["fingertip"]
        assert np.array_equal(obs[14:17], difference.astype(np.float32))
        assert np.array_equal(obs[17:], (difference / np.sqrt((difference ** 2).sum())).astype(np.float32))


@pytest.mark.parametrize("name", ["pusher7_reach", "pusher_reach"])
def test_the_stick_corrector_steers_the_fingertip_straight_in_and_hands_back_on_success(name):
    """--steer stick: a takeover jogs the fingertip along what separates it from the goal until
    it is reached, and the corrector then hands back."""
    task = load_task(name)
    env = make_env(task, terminate_on_success=False)
    corrector = ScriptedCorrector.for_task(task, CorrectorParams(patience=1, hold_steps=200, grace_steps=0,
                                                                 steer="stick"))
    assert corrector.expert is not task_expert(task)  # not the expert's joint-space swing
    for seed in range(HELD_OUT, HELD_OUT + 3):
        env.reset(seed)
        corrections, dists, handed_back = 0, [], False
        for _ in range(task.episodes.max_steps):
            points = point_vectors(task, env.point_positions())  # as a robot's tracker or kinematics has them
            action = corrector.decide(env.joint_positions.copy(), env.joint_velocities.copy(), env.goal.copy(), points)
            if action is None:
                handed_back = corrections > 0
                action = np.zeros(task.act_dim, np.float32)  # the policy: a still arm
            else:
                assert handed_back is False and np.all(np.abs(action) <= 1.0)
                corrections += 1
            _, _, _, info = env.step(action)
            dists.append(info["dist"])
        assert info["success"] and handed_back and corrections > 5
        assert min(dists) < task.reward.success_within


def test_a_stick_for_a_task_that_is_no_reach_is_refused_in_one_line():
    with pytest.raises(UserError, match="pusher_push.*reach task.*goal - puck"):
        ScriptedCorrector.for_task("pusher_push", CorrectorParams(steer="stick"))
    with pytest.raises(ValueError, match="steer must be one of expert, stick"):
        CorrectorParams(steer="joystick")


def test_the_push_correctors_label_is_its_experts_action_and_leaves_its_decisions_alone():
    """``label`` (``--action-labels``): on a state it leaves to the policy, the push corrector's
    label is the task's expert's action for that state, and asking for labels changes none of
    its decisions (no state, no random draw of its own)."""
    task = load_task("pusher_push")
    runs = {}
    for labelled in (False, True):
        env = make_env(task)
        corrector = ScriptedCorrector.for_task(task, CorrectorParams(patience=2, hold_steps=5, noise=0.1, seed=3))
        env.reset(HELD_OUT)
        decisions, labels = [], []
        for _ in range(60):
            state = env.joint_positions.copy(), env.joint_velocities.copy()
            points = point_vectors(task, env.point_positions())
            action = corrector.decide(*state, env.goal.copy(), points)
            if action is None and labelled:
                labels.append(corrector.label(*state, points))
                assert np.array_equal(labels[-1], np.clip(expert_action(env), -1, 1).astype(np.float32))
            decisions.append(None if action is None else action.tobytes())
            env.step(np.zeros(task.act_dim, np.float32) if action is None else action)
        runs[labelled] = decisions
    assert runs[True] == runs[False] and any(d is None for d in runs[True]) and any(d for d in runs[True])
    assert labels and all(np.all(np.abs(a) <= 1) for a in labels)


def test_pusher_reach_is_the_chapters_env_and_expert():
    env = make_env("pusher_reach")
    assert type(env) is PusherReachEnv
    env.reset(3)
    env.step(np.array([0.3, -0.2], np.float32))
    assert np.array_equal(expert_action(env), reach_action(env))
    assert env.joint_efforts.shape == (2,) and np.array_equal(env.goal, env.target[:2])


ARM_XML = """
<mujoco model="three_joint_arm">
  <compiler angle="radian"/>
  <option timestep="0.005" integrator="implicitfast"/>
  <default>
    <joint type="hinge" axis="0 0 1" damping="0.005" armature="0.01" range="-2 2"/>
    <geom type="capsule" size="0.02" contype="0" conaffinity="0"/>
  </default>
  <worldbody>
    <body name="l1"><joint name="j1"/><geom fromto="0 0 0 0.2 0 0"/>
      <body name="l2" pos="0.2 0 0"><joint name="j2"/><geom fromto="0 0 0 0.2 0 0"/>
        <body name="l3" pos="0.2 0 0"><joint name="j3"/><geom fromto="0 0 0 0.1 0 0"/>
          <site name="tip" pos="0.1 0 0"/></body></body></body>
  </worldbody>
  <actuator>{actuators}</actuator>
</mujoco>
"""


def velocity_arm(tmp_path, actuators: str, gains: str = "", interface: str = "velocity") -> MujocoTaskEnv:
    """A task file of a 3-joint arm (velocity-controlled unless ``interface`` says otherwise), its
    model beside it, a joint-space goal."""
    (tmp_path / "arm.xml").write_text(ARM_XML.format(actuators=actuators))
    (tmp_path / "arm.yaml").write_text(textwrap.dedent(f"""\
        name: velocity_arm
        control_period: 0.02
        robot:
          state: {{joints: [j3, j1, j2]}}
          command: {{interface: {interface}, joints: [j1, j2, j3], scale: 2.0}}
        goal: {{type: sensor_msgs/JointState}}
        points: {{tip: {{kinematics: "site:tip"}}}}
        observation: [{{positions: [j1, j2, j3]}}, {{velocities: [j1, j2, j3]}}, {{difference: [goal, joints]}}]
        reward: {{distance: [goal, joints], success_within: 0.05}}
        episodes: {{max_steps: 150}}
        sim: {{model: arm.xml, goal: {{min_distance: 0.5}}, expert: {{kp: 25, kd: 5}}{gains}}}
        """))
    return make_env(tmp_path / "arm.yaml")


@pytest.mark.parametrize("actuators, gains", [
    # MuJoCo's own velocity actuators: ctrl is the commanded velocity
    ('<velocity joint="j1" kv="5"/><velocity joint="j2" kv="5"/><velocity joint="j3" kv="5"/>', ""),
    # motors: the PD stand-in for the hardware's velocity loop
    ('<motor joint="j3" ctrlrange="-5 5" ctrllimited="true"/><motor joint="j1" ctrlrange="-5 5" ctrllimited="true"/>'
     '<motor joint="j2" ctrlrange="-5 5" ctrllimited="true"/>', ", gains: {kd: 0.5}"),
])
def test_a_velocity_interface_moves_the_joints_at_the_commanded_speed(tmp_path, actuators, gains):
    env = velocity_arm(tmp_path, actuators, gains)
    assert env.drive.direct == (not gains)
    env.reset(0)
    state_order = ["j3", "j1", "j2"]
    action = np.array([0.25, -0.1, 0.05], np.float32)  # rad/s = 2 * action, command-joint order (j1, j2, j3)
    for _ in range(25):
        env.step(action)
    speed = dict(zip(state_order, env.joint_velocities))
    assert [speed["j1"], speed["j2"], speed["j3"]] == pytest.approx(2 * action, abs=0.02)
    # the joint-space goal's expert: the velocity law toward the goal joints
    for seed in range(2):
        env.reset(seed)
        done = False
        while not done:
            _, _, done, info = env.step(expert_action(env))
        assert info["success"]


def test_headerless_commands_answer_the_state_last_published():
    loop = SimLoop("lockstep", seed=1, task=PUSHER7)
    state = loop.start_episode()
    assert state.stamp_ns == 0 and loop.tick_ns == 50_000_000 and list(state.target) == list(loop.env.goal_position)
    action, problem = action_from_command(PUSHER7, [1.0] * 7)
    assert problem is None and np.array_equal(action, np.full(7, 0.5, np.float32))
    assert action_from_command(PUSHER7, [1.0] * 6)[1].reason == "wrong length"
    assert loop.command_unstamped(action, SOURCE_EXPERT)[1].reason == "unpaired"  # not yet published
    loop.published()
    step, problem = loop.command_unstamped(action, SOURCE_EXPERT)
    assert problem is None and step.next_state.stamp_ns == 50_000_000 and len(step.transition) == loop.layout.width
    assert loop.command_unstamped(action, SOURCE_EXPERT)[1].reason == "unpaired"  # the new state: not yet published
    loop.published()
    assert loop.command(loop.current.stamp_ns, action, SOURCE_EXPERT) is not None  # a stamped command...
    loop.published()
    assert loop.command_unstamped(action, SOURCE_EXPERT)[1].reason == "unpaired"  # ...and stamps pair from now on


def write_task(tmp_path, sim: str) -> str:
    """pusher7_reach's task file with another sim section."""
    path = tmp_path / "t.yaml"
    path.write_text(PUSHER7.path.read_text().split("\nsim:")[0] + "\nsim: " + sim + "\n")
    return str(path)


SITES = "sites: {fingertip: {body: tips_arm, pos: [0.1, 0, 0]}}"


@pytest.mark.parametrize("sim, error", [
    ("{model: nowhere.xml}", "field sim.model: 'nowhere.xml': no model file at"),
    ("{model: 'no_such_package_here:x.xml'}", "names package 'no_such_package_here', which is not installed"),
    (f"{{model: 'gymnasium:envs/mujoco/assets/pusher_v5.xml', {SITES}, frame_skip: 2}}",
     "field sim.frame_skip: 2 physics steps of the model's 0.01 s are 0.02 s, but control_period is 0.05 s"),
    (f"{{model: 'gymnasium:envs/mujoco/assets/pusher_v5.xml', {SITES}, wind: 3}}", "unknown field sim.wind"),
    ("{model: 'gymnasium:envs/mujoco/assets/pusher_v5.xml', sites: {fingertip: {body: hand}}}",
     "field sim.sites.fingertip.body: the model pusher_v5.xml has no body 'hand'"),
    ("{model: 'gymnasium:envs/mujoco/assets/pusher_v5.xml'}", "the sim's model has no site 'fingertip'"),
    (f"{{model: 'gymnasium:envs/mujoco/assets/pusher_v5.xml', {SITES}, goal: {{low: [0, 0]}}}}",
     "field sim.goal.low: expected a list of 3 numbers"),
])
def test_a_bad_sim_section_is_one_line_naming_the_field(tmp_path, sim, error):
    with pytest.raises(UserError) as info:
        make_env(write_task(tmp_path, sim))
    assert error in str(info.value) and "\n" not in str(info.value) and "t.yaml" in str(info.value)


def test_a_task_without_a_sim_is_refused_in_one_line(tmp_path):
    path = tmp_path / "nosim.yaml"
    path.write_text(load_task("pusher7_reach").path.read_text().split("\nsim:")[0])
    with pytest.raises(UserError, match="has no sim section: no simulator hosts it"):
        make_env(path)
    assert task_model(path) is None


def test_realtime_holds_a_headerless_command_until_the_next():
    loop = SimLoop("realtime", seed=2, task=PUSHER7)
    loop.start_episode()
    action = np.linspace(-1, 1, 7).astype(np.float32)
    assert loop.command_unstamped(action, SOURCE_EXPERT) == (None, None)  # held, not stepped
    rows = [loop.tick().transition for _ in range(3)]
    at = loop.layout.slices["action"]
    assert all(np.array_equal(row[at], action) for row in rows) and loop.current.stamp_ns == 3 * loop.tick_ns


@pytest.mark.parametrize("actuators, gains", [
    # MuJoCo's own position actuators: ctrl is the commanded position
    ('<position joint="j1" kp="2" kv="0.3"/><position joint="j2" kp="2" kv="0.3"/>'
     '<position joint="j3" kp="2" kv="0.3"/>', ""),
    # motors: the PD stand-in
    ('<motor joint="j1"/><motor joint="j2"/><motor joint="j3"/>', ", gains: {kp: 2.0, kd: 0.3}"),
])
def test_a_position_interface_holds_the_commanded_pose(tmp_path, actuators, gains):
    env = velocity_arm(tmp_path, actuators, gains, interface="position")
    env.reset(1)
    target = np.array([0.3, -0.4, 0.2], np.float32)  # rad = 2 * action, command-joint order
    for _ in range(200):
        env.step(target)
    pose = dict(zip(["j3", "j1", "j2"], env.joint_positions))
    assert [pose["j1"], pose["j2"], pose["j3"]] == pytest.approx(2 * target, abs=0.01)
