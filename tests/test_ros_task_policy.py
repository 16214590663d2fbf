"""The policy node and the mux on an arm nobody here modelled: a 7-joint policy trained with
`offline-rl train --task FILE` is served over DDS on its task's topics (joint states in any
order, the controller's Float64MultiArray out, scaled), and a checkpoint offered for another
task is refused at start in one line naming both layouts."""

from __future__ import annotations

import time

import numpy as np
import pytest

import arm7
from ros_helpers import probe_node, require_ros, ros2, ros_env, spawn  # noqa: F401 - fixtures

pytestmark = pytest.mark.ros


@pytest.fixture(scope="module")
def arm(tmp_path_factory):
    require_ros()
    from offline_rl_core.commands import cli
    from offline_rl_core.data.bag import write_transitions
    from offline_rl_core.data.collect import collect_transitions
    from offline_rl_core.learners import TrainConfig, train
    from offline_rl_core.serving.checkpoint import save_checkpoint

    root = tmp_path_factory.mktemp("ros_arm7")
    task_file = arm7.write_task(root)
    bag = root / "arm7.db3"
    write_transitions(bag, arm7.synthetic_transitions())
    assert cli.main(["train", "--bag", str(bag), "--task", str(task_file), "--algo", "bc", "--steps", "30",
                     "--hidden", "16", "--batch-size", "32", "--eval-episodes", "0", "--out", str(root / "run")]) == 0
    pusher = train(collect_transitions(2, 1.0, 0), TrainConfig(algo="bc", steps=10, hidden=16, batch_size=16), 0)
    return {"task_file": task_file, "checkpoint": root / "run" / "policy.pt",
            "pusher": save_checkpoint(root / "pusher.pt", pusher.checkpoint)}


def test_a_seven_joint_policy_is_served_on_its_tasks_topics(spawn, arm):
    from geometry_msgs.msg import PointStamped
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    from offline_rl_core.nodes.observation import ObservationBuilder
    from offline_rl_core.serving.policy import load_policy
    from offline_rl_core.task.spec import load_task

    task = load_task(arm["task_file"])
    policy = load_policy(arm["checkpoint"], task)
    builder = ObservationBuilder(task)
    # no task given: the node serves the one the checkpoint records; lockstep, as this test
    # sends a state at a time (no watchdog: a pause between states is no fault)
    node_proc = spawn(ros2("run", "policy", "node", "--checkpoint", arm["checkpoint"], "--ros-args",
                           "-p", "mode:=lockstep"), "policy")
    mux = spawn(ros2("run", "corrections", "mux", "--ros-args", "-p", f"task:={arm['task_file']}"), "mux")
    rng = np.random.default_rng(5)
    actions, commands, forwarded = [], [], []
    with probe_node() as node:
        node.create_subscription(JointState, "/policy/action", actions.append, 50)
        node.create_subscription(Float64MultiArray, "/arm_velocity_controller/commands", commands.append, 50)
        node.create_subscription(JointState, "/pusher/command/policy", forwarded.append, 50)
        goal_pub = node.create_publisher(PointStamped, "/arm/goal", 10)
        tip_pub = node.create_publisher(PointStamped, "/arm/tip", 10)
        state_pub = node.create_publisher(JointState, "/arm/joint_states", 10)
        action_pub = node.create_publisher(JointState, "/policy/action", 10)
        assert node.spin_until(lambda: goal_pub.get_subscription_count() and tip_pub.get_subscription_count()
                               and state_pub.get_subscription_count() and node.count_publishers("/policy/action") >= 2
                               and node.count_publishers("/pusher/command/policy")
                               and action_pub.get_subscription_count() >= 2, 60), \
            node_proc.output() + mux.output()
        sent: dict[int, np.ndarray] = {}
        stamp = [0]

        def point(pub, xyz, sec):
            msg = PointStamped()
            msg.header.stamp.sec = sec
            msg.point.x, msg.point.y, msg.point.z = (float(v) for v in xyz)
            pub.publish(msg)

        def send(drop: str | None = None) -> int:
            """A state (shuffled joint order, an extra joint) with its goal and tip; returns its stamp."""
            stamp[0] += 1
            q, qd = rng.uniform(-2, 2, 7), rng.uniform(-1, 1, 7)
            goal, tip = rng.uniform(-0.5, 0.5, 3), rng.uniform(-0.5, 0.5, 3)
            order = list(rng.permutation(7))
            names = [arm7.JOINTS[i] for i in order] + ["gripper"]
            positions, velocities = list(q[order]) + [0.01], list(qd[order]) + [0.0]
            if drop is not None:
                at = names.index(drop)
                del names[at], positions[at], velocities[at]
            point(goal_pub, goal, stamp[0])
            point(tip_pub, tip, stamp[0])
            state = JointState(name=names, position=[float(v) for v in positions],
                               velocity=[float(v) for v in velocities])
            state.header.stamp.sec = stamp[0]
            state_pub.publish(state)
            sent[stamp[0]] = builder.observe(q, qd, builder.goal_from_point(*goal)[0], {"tip": tip})
            return stamp[0]

        def answer(sec, timeout=2.0):
            node.spin_until(lambda: any(a.header.stamp.sec == sec and len(a.effort) == 7 for a in actions), timeout)
            return next((a for a in actions if a.header.stamp.sec == sec), None)

        reply, deadline = None, time.monotonic() + 30  # the first messages can race discovery
        while reply is None and time.monotonic() < deadline:
            reply = answer(send(), timeout=1.0)
        assert reply is not None, node_proc.output()
        for _ in range(3):
            reply = answer(send())
            assert reply is not None, node_proc.output()
            want = policy.act(sent[reply.header.stamp.sec])
            assert list(reply.name) == list(arm7.CONTROLLER_ORDER)
            assert np.array_equal(np.array(reply.effort, np.float32), want)
        # the controller's command: offset + scale * action, in the controller's joint order
        assert node.spin_until(lambda: len(commands) >= 4, 5)
        last = np.array(actions[-1].effort, np.float64)
        assert np.allclose(commands[-1].data, np.array(arm7.OFFSET) + np.array(arm7.SCALE) * last, atol=1e-12)
        # a state lacking one of the task's joints is refused and counted, never answered
        missing = send(drop="j4")
        node.spin_for(0.5)
        assert answer(missing, timeout=0.5) is None
        assert node.spin_until(lambda: "lack j4 (unknown joints: 1 so far)" in node_proc.output(), 5), \
            node_proc.output()
        # the mux forwards the task's actions (its command joints) and refuses another length
        # (the policy node's own discovery of the mux can come after its first answers: more states)
        deadline = time.monotonic() + 30
        while not any(len(c.effort) == 7 for c in forwarded) and time.monotonic() < deadline:
            answer(send(), timeout=1.0)
            node.spin_for(0.2)
        assert any(len(c.effort) == 7 for c in forwarded), mux.output()
        assert list(forwarded[-1].name) == list(arm7.CONTROLLER_ORDER)
        short = JointState(name=["j1", "j2"], effort=[0.1, 0.2])
        short.header.stamp.sec = 10_000
        action_pub.publish(short)
        assert node.spin_until(lambda: "effort has 2 values, expected 7" in mux.output(), 10), mux.output()
        assert not any(c.header.stamp.sec == 10_000 for c in forwarded)
    assert node_proc.stop() == 0, node_proc.output()
    assert mux.stop() == 0, mux.output()


@pytest.mark.parametrize("which, task, words", [
    ("checkpoint", "pusher_reach", ("a checkpoint of task test_arm7", "obs_dim=21, act_dim=7",
                                    "the task here is pusher_reach", "obs_dim=8, act_dim=2")),
    ("pusher", "FILE", ("a checkpoint of task pusher_reach", "recording none", "obs_dim=8, act_dim=2",
                        "the task here is test_arm7", "obs_dim=21, act_dim=7")),
])
def test_a_checkpoint_offered_for_another_task_is_refused_at_start(spawn, arm, which, task, words):
    task = str(arm["task_file"]) if task == "FILE" else task
    node = spawn(ros2("run", "policy", "node", "--checkpoint", arm[which], "--ros-args", "-p", f"task:={task}"),
                 "policy")
    assert node.wait(timeout=60) == 2, node.output()
    lines = node.output().strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"policy: error: {arm[which]}: "), lines
    assert all(w in lines[0] for w in words), lines[0]
