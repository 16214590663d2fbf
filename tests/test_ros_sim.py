"""The sim node's lockstep protocol: stamps, command validation, source tags, reset."""

from __future__ import annotations

import json

import numpy as np
import pytest

from offline_rl_core.task.pusher_reach import PusherReachEnv

from ros_helpers import probe_node, ros2, ros_env, spawn  # noqa: F401 - fixtures

pytestmark = pytest.mark.ros

TICK = 20_000_000  # ns
START = 1_700_000_000  # s: the sim time of the first state (start_time)


def stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def stamp_ns_of_clock(msg) -> int:
    return msg.clock.sec * 1_000_000_000 + msg.clock.nanosec


def test_lockstep_validates_commands_tags_sources_and_resets(spawn, tmp_path):
    from geometry_msgs.msg import PointStamped
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float32MultiArray
    from std_srvs.srv import Trigger

    summary = tmp_path / "new" / "summary.json"  # a new directory is made on writing, as the CLI's outputs
    params = tmp_path / "sim.yaml"  # settings from a params file, as a launch file passes them
    params.write_text(f"/**:\n  ros__parameters:\n    mode: lockstep\n    seed: 11\n    summary: '{summary}'\n"
                      f"    start_time: {START}.0\n")
    sim = spawn(ros2("run", "sim", "node", "--ros-args", "--params-file", params), "sim")
    states, targets, transitions, clocks, joint_states = [], [], [], [], []
    with probe_node() as node:
        node.create_subscription(JointState, "/pusher/state", states.append, 10)
        node.create_subscription(JointState, "/joint_states", joint_states.append, 10)
        node.create_subscription(Clock, "/clock", clocks.append, 10)
        node.create_subscription(PointStamped, "/pusher/target", targets.append, 10)
        node.create_subscription(Float32MultiArray, "/pusher/transition", transitions.append, 100)
        command_pub = node.create_publisher(JointState, "/pusher/command", 10)
        human_pub = node.create_publisher(JointState, "/pusher/command/human", 10)
        reset = node.create_client(Trigger, "/pusher/reset")

        # The first state is republished until answered, so a late subscriber gets it.
        assert node.spin_until(lambda: states and targets and command_pub.get_subscription_count()
                               and human_pub.get_subscription_count(), 30), sim.output()
        first = states[-1]
        t0 = START * 1_000_000_000
        assert stamp_ns(first) == t0 and list(first.name) == ["shoulder", "elbow"]
        env = PusherReachEnv()
        env.reset(seed=11)
        assert np.array_equal(np.array(first.position), env.qpos) and np.array_equal(np.array(first.velocity), env.qvel)
        assert stamp_ns(targets[-1]) == t0 and targets[-1].point.x == env.target[0]
        assert targets[-1].header.frame_id == "world"

        def command(effort, stamp_of=first, tag="", publisher=command_pub):
            msg = JointState(name=["shoulder", "elbow"], effort=effort)
            msg.header.stamp = stamp_of.header.stamp
            msg.header.frame_id = tag
            publisher.publish(msg)

        command([float("nan"), 0.0])
        command([0.5])
        node.spin_for(0.5)
        assert not transitions  # rejected: nothing stepped
        assert "effort is not finite" in sim.output() or "effort has 1 values" in sim.output()

        command([3.0, -0.25], publisher=human_pub)  # beyond [-1, 1]: refused and counted, never clipped
        assert node.spin_until(lambda: "beyond limits" in sim.output(), 10), sim.output()
        assert not transitions
        command([1.0, -0.25], publisher=human_pub)  # who acted: the topic
        assert node.spin_until(lambda: len(transitions) == 1 and any(stamp_ns(s) == t0 + TICK for s in states), 10)
        row = np.array(transitions[0].data, np.float32)
        assert [d.label for d in transitions[0].layout.dim][:3] == ["obs", "action", "reward"]
        obs, reward = env.observation(), None
        _, reward, _, _ = env.step(np.array([1.0, -0.25], np.float32))
        assert row[8] == 1.0 and row[9] == -0.25 and row[10] == np.float32(reward)
        assert row[24] == 3.0 and row[22] == 0 and row[23] == 0  # source human, episode 0, step 0
        assert np.allclose(row[:8], obs)
        # /clock is the sim time of the newest state; joint_states carries the same state
        # (two topics: neither waits for the other; the first clock may predate discovery)
        assert node.spin_until(lambda: joint_states and stamp_ns(joint_states[-1]) == t0 + TICK
                               and clocks and stamp_ns_of_clock(clocks[-1]) == t0 + TICK, 10), \
            ([stamp_ns_of_clock(c) for c in clocks[-3:]], [stamp_ns(j) for j in joint_states[-3:]])

        command([0.0, 0.0], publisher=human_pub)  # answers the old stamp: stale, ignored
        node.spin_for(0.3)
        assert len(transitions) == 1
        second = next(s for s in states if stamp_ns(s) == t0 + TICK)
        command([0.5, 0.5], stamp_of=second)  # plain pusher/command: the policy
        command([0.5, 0.5], stamp_of=second, tag="expert")  # the same stamp again: stale
        assert node.spin_until(lambda: len(transitions) == 2, 10)
        assert transitions[1].data[24] == 2.0
        third = None
        assert node.spin_until(lambda: any(stamp_ns(s) == t0 + 2 * TICK for s in states), 10)
        third = next(s for s in states if stamp_ns(s) == t0 + 2 * TICK)
        command([0.5, 0.5], stamp_of=third, tag="expert")  # an older publisher's frame_id tag still counts
        assert node.spin_until(lambda: len(transitions) == 3, 10), (len(transitions), sim.output())
        assert transitions[2].data[24] == 0.0 and "deprecated" in sim.output()

        future = reset.call_async(Trigger.Request())
        assert node.spin_until(future.done, 10) and future.result().success
        assert node.spin_until(lambda: any(stamp_ns(s) == t0 + 100 * TICK for s in states), 10)  # episode 1, step 0

    assert sim.stop() == 0
    data = json.loads(summary.read_text())
    # the episode the reset cut short is counted: no reset can hide a failing episode
    assert data == {"episodes": 0, "success_rate": 0.0, "mean_final_dist": None, "mean_return": None,
                    "abandoned": 1}


@pytest.mark.parametrize("ros_args, error", [
    (["-p", "mode:=fast"], "parameter mode: must be one of realtime, lockstep; got 'fast'"),
    # stamps are int32 seconds (builtin_interfaces/Time): a later start would wrap negative
    (["-p", "start_time:=3000000000.0"], "parameter start_time: Parameter start_time out of range"),
    # the summary is written after the whole run: where it cannot be, that is said at start
    (["-p", "summary:=/proc/none/s.json"], "parameter summary: /proc/none/s.json: cannot write in /proc"),
    (["-r", "badremap"], "cannot parse --ros-args: Couldn't parse remap rule: '-r badremap'."),
])
def test_a_bad_parameter_is_one_line_and_exit_2(spawn, tmp_path, ros_args, error):
    sim = spawn(ros2("run", "sim", "node", "--ros-args", *(a.format(tmp=tmp_path) for a in ros_args)), "sim")
    assert sim.wait(timeout=60) == 2
    lines = sim.output().strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("sim: error: " + error.format(tmp=tmp_path)), lines


def test_realtime_sim_takes_torques_as_an_effort_controller_does(spawn):
    """``effort_topic``: Float64MultiArray torques in N·m, the action times the motor gear (0.5)."""
    from std_msgs.msg import Float32MultiArray, Float64MultiArray

    sim = spawn(ros2("run", "sim", "node", "--ros-args", "-p", "effort_topic:=effort_controller/commands"), "sim")
    transitions = []
    with probe_node() as node:
        node.create_subscription(Float32MultiArray, "/pusher/transition", transitions.append, 100)
        torques = node.create_publisher(Float64MultiArray, "/effort_controller/commands", 10)
        assert node.spin_until(lambda: torques.get_subscription_count() and transitions, 30), sim.output()

        def held(row):
            return list(row.data[8:10]) == [0.5, -1.0] and row.data[24] == 2.0  # the action, source policy

        # held like a zero-order hold until replaced: every tick after it steps with it
        assert node.spin_until(lambda: torques.publish(Float64MultiArray(data=[0.25, -0.5])) or
                               sum(held(t) for t in transitions) >= 3, 20), sim.output()
        # torques beyond the motors' are refused and counted, never clipped to full
        assert node.spin_until(lambda: torques.publish(Float64MultiArray(data=[0.25, -3.0])) or
                               "beyond limits" in sim.output(), 20), sim.output()
    assert sim.stop() == 0
    # its timing report comes after Ctrl-C has shut the context (and rosout) down: printed, not lost
    assert "sim: realtime timing:" in sim.output() and "Failed to publish" not in sim.output(), sim.output()
