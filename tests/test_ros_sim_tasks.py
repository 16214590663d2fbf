"""The sim node hosting a task other than pusher-reach: Gymnasium's 7-joint Pusher as a
ros2_control arm (joint_states, velocity_controller/commands, the goal on a topic), over DDS."""

from __future__ import annotations

import json

import numpy as np
import pytest

from offline_rl_core.data.transitions import Layout, Transitions
from offline_rl_core.task.envs import make_env
from offline_rl_core.task.spec import load_task, task_from_dict

from ros_helpers import probe_node, ros2, ros_env, spawn  # noqa: F401 - fixtures

pytestmark = pytest.mark.ros

START = 1_700_000_000  # s: sim time of the first state
TICK = 50_000_000  # ns: pusher7_reach's control period


def stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def test_pusher7_in_lockstep_takes_controller_commands_and_publishes_its_task(spawn):
    from geometry_msgs.msg import PointStamped
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float32MultiArray, Float64MultiArray, String

    task = load_task("pusher7_reach")
    sim = spawn(ros2("run", "sim", "node", "--ros-args", "-p", "task:=pusher7_reach", "-p", "mode:=lockstep",
                     "-p", "seed:=3", "-p", f"start_time:={START}.0"), "sim")
    states, goals, transitions, statuses, described = [], [], [], [], []
    with probe_node() as node:
        node.create_subscription(JointState, "/joint_states", states.append, 10)
        node.create_subscription(PointStamped, "/goal", goals.append, 10)
        node.create_subscription(Float32MultiArray, "/pusher/transition", transitions.append, 100)
        node.create_subscription(String, "/sim/status", lambda m: statuses.append(json.loads(m.data)), 10)
        commands = node.create_publisher(Float64MultiArray, "/velocity_controller/commands", 10)
        assert node.spin_until(lambda: states and goals and commands.get_subscription_count(), 60), sim.output()

        # the first state and goal are reset seed 3's, as the env in this process has them
        env = make_env(task)
        env.reset(3)
        first = states[-1]
        assert stamp_ns(first) == START * 1_000_000_000 and stamp_ns(goals[-1]) == stamp_ns(first)
        assert list(first.name) == list(task.state.joints)
        assert np.array_equal(first.position, env.joint_positions) and np.array_equal(first.velocity, np.zeros(7))
        goal = goals[-1].point
        assert [goal.x, goal.y, goal.z] == list(env.goal_position) and goals[-1].header.frame_id == "world"

        # a subscriber that comes late still gets the task (transient local, as robot_description)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        node.create_subscription(String, "/task_description", described.append, latched)
        assert node.spin_until(lambda: described, 20), sim.output()
        assert task_from_dict(json.loads(described[0].data)).digest == task.digest

        # a command of the wrong length is refused and counted, never cut or padded
        commands.publish(Float64MultiArray(data=[0.5] * 6))
        assert node.spin_until(lambda: any(s["rejected"].get("wrong length") for s in statuses), 20), sim.output()
        assert not transitions

        # beyond the controller's limits (-3 rad/s, the task's are [-2, 2]): refused, never clipped
        commands.publish(Float64MultiArray(data=[2.0, -1.0, 0.5, -3.0, 0.0, 1.0, -0.25]))
        assert node.spin_until(lambda: any(s["rejected"].get("beyond limits") for s in statuses), 20), sim.output()
        assert not transitions

        # joint velocities in rad/s in the controller's joint order
        velocities = [2.0, -1.0, 0.5, -1.5, 0.0, 1.0, -0.25]
        commands.publish(Float64MultiArray(data=velocities))
        assert node.spin_until(lambda: transitions and any(stamp_ns(s) == stamp_ns(first) + TICK for s in states),
                               20), sim.output()
        row = Transitions.from_rows(np.array([transitions[0].data], np.float32), Layout(task.obs_dim, 7))
        action = np.clip(np.float32(velocities) / np.float32(2.0), -1, 1)
        obs = env.observation()
        next_obs, reward, _, _ = env.step(action)
        assert np.array_equal(row.action[0], action) and np.array_equal(row.obs[0], obs)
        assert np.array_equal(row.next_obs[0], next_obs) and row.reward[0] == np.float32(reward)
        moved = next(s for s in states if stamp_ns(s) == stamp_ns(first) + TICK)
        assert np.array_equal(moved.position, env.joint_positions)  # the arm moved, as in this process
        # the effort: what the motors applied (N·m) to follow the velocities, as in this process
        assert np.allclose(moved.effort, env.joint_efforts) and np.all(np.abs(moved.effort) <= 2.0)

        assert node.spin_until(lambda: statuses[-1]["messages"].get("velocity_controller/commands") == 3, 20)
        assert statuses[-1]["rejected"] == {"wrong length": 1, "beyond limits": 1}
    assert sim.stop() == 0


@pytest.mark.parametrize("task, error", [
    ("/nowhere/arm.yaml", "sim: error: unknown task '/nowhere/arm.yaml': expected a built-in task"),
    ("{nosim}", "has no sim section: no simulator hosts it"),
])
def test_a_task_the_sim_cannot_host_is_one_line_and_exit_2(spawn, tmp_path, task, error):
    nosim = tmp_path / "nosim.yaml"
    nosim.write_text(load_task("pusher7_reach").path.read_text().split("\nsim:")[0])
    sim = spawn(ros2("run", "sim", "node", "--ros-args", "-p", f"task:={task.format(nosim=nosim)}"), "sim")
    assert sim.wait(timeout=60) == 2
    lines = sim.output().strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("sim: error: ") and error in lines[0], lines
