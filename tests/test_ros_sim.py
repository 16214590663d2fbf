"""The sim node's lockstep protocol: stamps, command validation, source tags, reset."""

from __future__ import annotations

import json

import numpy as np
import pytest

from offline_rl_core.env import PusherReachEnv

from ros_helpers import probe_node, ros2, ros_env, spawn  # noqa: F401 - fixtures

pytestmark = pytest.mark.ros

TICK = 20_000_000  # ns


def stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def test_lockstep_validates_commands_tags_sources_and_resets(spawn, tmp_path):
    from geometry_msgs.msg import PointStamped
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float32MultiArray
    from std_srvs.srv import Trigger

    summary = tmp_path / "summary.json"
    params = tmp_path / "sim.yaml"  # settings from a params file, as a launch file passes them
    params.write_text(f"/**:\n  ros__parameters:\n    mode: lockstep\n    seed: 11\n    summary: '{summary}'\n")
    sim = spawn(ros2("run", "sim", "node", "--ros-args", "--params-file", params), "sim")
    states, targets, transitions = [], [], []
    with probe_node() as node:
        node.create_subscription(JointState, "/pusher/state", states.append, 10)
        node.create_subscription(PointStamped, "/pusher/target", targets.append, 10)
        node.create_subscription(Float32MultiArray, "/pusher/transition", transitions.append, 100)
        command_pub = node.create_publisher(JointState, "/pusher/command", 10)
        reset = node.create_client(Trigger, "/pusher/reset")

        # The first state is republished until answered, so a late subscriber gets it.
        assert node.spin_until(lambda: states and targets and command_pub.get_subscription_count(), 30), sim.output()
        first = states[-1]
        assert stamp_ns(first) == 0 and list(first.name) == ["shoulder", "elbow"]
        env = PusherReachEnv()
        env.reset(seed=11)
        assert np.array_equal(np.array(first.position), env.qpos) and np.array_equal(np.array(first.velocity), env.qvel)
        assert stamp_ns(targets[-1]) == 0 and targets[-1].point.x == env.target[0]

        def command(effort, stamp_of=first, tag=""):
            msg = JointState(name=["shoulder", "elbow"], effort=effort)
            msg.header.stamp = stamp_of.header.stamp
            msg.header.frame_id = tag
            command_pub.publish(msg)

        command([float("nan"), 0.0])
        command([0.5])
        node.spin_for(0.5)
        assert not transitions  # rejected: nothing stepped
        assert "effort is not finite" in sim.output() or "effort has 1 values" in sim.output()

        command([3.0, -0.25], tag="human")  # clipped to [-1, 1]
        assert node.spin_until(lambda: len(transitions) == 1 and any(stamp_ns(s) == TICK for s in states), 10)
        row = np.array(transitions[0].data, np.float32)
        assert [d.label for d in transitions[0].layout.dim][:3] == ["obs", "action", "reward"]
        obs, reward = env.observation(), None
        _, reward, _, _ = env.step(np.array([1.0, -0.25], np.float32))
        assert row[8] == 1.0 and row[9] == -0.25 and row[10] == np.float32(reward)
        assert row[24] == 3.0 and row[22] == 0 and row[23] == 0  # source human, episode 0, step 0
        assert np.allclose(row[:8], obs)

        command([0.0, 0.0], tag="human")  # answers the old stamp: stale, ignored
        node.spin_for(0.3)
        assert len(transitions) == 1

        future = reset.call_async(Trigger.Request())
        assert node.spin_until(future.done, 10) and future.result().success
        assert node.spin_until(lambda: any(stamp_ns(s) == 100 * TICK for s in states), 10)  # episode 1, step 0

    assert sim.stop() == 0
    data = json.loads(summary.read_text())
    assert data == {"episodes": 0, "success_rate": 0.0, "mean_final_dist": None, "mean_return": None}


def test_a_bad_parameter_is_one_line_and_exit_2(spawn):
    sim = spawn(ros2("run", "sim", "node", "--ros-args", "-p", "mode:=fast"), "sim")
    assert sim.wait(timeout=60) == 2
    lines = sim.output().strip().splitlines()
    assert lines == ["sim: error: parameter mode: must be one of realtime, lockstep; got 'fast'"], lines
