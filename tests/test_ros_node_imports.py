"""The serving nodes load only what they use: once the policy node and the mux have answered
over DDS, none of the training, bag, benchmark or orchestration layers is in either process."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from ros_helpers import probe_node, require_ros, ros_env, spawn  # noqa: F401 - fixtures

pytestmark = pytest.mark.ros

# The node's own main, with the project modules it has loaded written out when it exits.
WITH_MODULE_LIST = """
import atexit, importlib, json, sys
listing, module = sys.argv.pop(1), sys.argv.pop(1)
atexit.register(lambda: open(listing, "w").write(json.dumps(sorted(m for m in sys.modules if m.startswith("offline_rl_core")))))
sys.exit(importlib.import_module(module).main())
"""
# No layer a serving node needs: training, data sets and bags, benchmarks, orchestration.
NOT_FOR_SERVING = ("learners", "runs", "fast", "evaluation", "data", "benchmarks", "pipelines", "commands")


def loaded_layers(modules: list[str]) -> set[str]:
    return {m.split(".")[1] for m in modules if m.count(".") >= 1}


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    require_ros()
    from offline_rl_core.data.collect import collect_transitions
    from offline_rl_core.learners import TrainConfig, train
    from offline_rl_core.serving.checkpoint import save_checkpoint

    result = train(collect_transitions(2, 1.0, 0), TrainConfig(algo="bc", steps=20, hidden=16, batch_size=16), 0)
    return save_checkpoint(tmp_path_factory.mktemp("ckpt") / "policy.pt", result.checkpoint)


def test_the_policy_node_serves_without_the_training_or_bag_layers(spawn, checkpoint, tmp_path):
    from geometry_msgs.msg import PointStamped
    from sensor_msgs.msg import JointState

    listing = tmp_path / "modules.json"
    node_proc = spawn([sys.executable, "-c", WITH_MODULE_LIST, listing, "pusher_policy.node",
                       "--checkpoint", checkpoint], "policy")
    with probe_node() as node:
        actions = []
        node.create_subscription(JointState, "/policy/action", actions.append, 10)
        state_pub = node.create_publisher(JointState, "/pusher/state", 10)
        target_pub = node.create_publisher(PointStamped, "/pusher/target", 10)
        assert node.spin_until(lambda: state_pub.get_subscription_count() and target_pub.get_subscription_count(), 60), \
            node_proc.output()

        def publish() -> None:
            target = PointStamped()
            target.header.stamp.sec = 7
            target.point.x, target.point.y = 0.1, 0.05
            target_pub.publish(target)
            state = JointState(name=["shoulder", "elbow"], position=[0.2, -0.4], velocity=[0.0, 0.0])
            state.header.stamp.sec = 7
            state_pub.publish(state)

        for _ in range(50):
            publish()
            if node.spin_until(lambda: actions, 0.5):
                break
        assert actions and np.all(np.abs(actions[-1].effort) <= 1.0), node_proc.output()
    assert node_proc.stop() == 0, node_proc.output()
    modules = json.loads(listing.read_text())
    assert "offline_rl_core.serving.policy" in modules  # the listing is of a process that served
    assert not loaded_layers(modules) & set(NOT_FOR_SERVING), modules


def test_the_mux_forwards_without_the_training_or_bag_layers(spawn, tmp_path):
    from sensor_msgs.msg import JointState

    listing = tmp_path / "modules.json"
    mux = spawn([sys.executable, "-c", WITH_MODULE_LIST, listing, "pusher_corrections.mux"], "mux")
    with probe_node() as node:
        commands = []
        node.create_subscription(JointState, "/pusher/command/policy", commands.append, 10)
        action_pub = node.create_publisher(JointState, "/policy/action", 10)
        assert node.spin_until(lambda: action_pub.get_subscription_count(), 60), mux.output()
        for _ in range(50):
            action = JointState(name=["shoulder", "elbow"], effort=[0.25, -0.5])
            action.header.stamp.sec = 3
            action_pub.publish(action)
            if node.spin_until(lambda: commands, 0.5):
                break
        assert commands and list(commands[-1].effort) == [0.25, -0.5], mux.output()
    assert mux.stop() == 0, mux.output()
    modules = json.loads(listing.read_text())
    assert "offline_rl_core.nodes.arbiter" in modules
    assert not loaded_layers(modules) & set(NOT_FOR_SERVING), modules
