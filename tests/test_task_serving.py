"""Policies of any arm: checkpoints and weights record their task and are refused for another
task in one line naming both layouts, `train --task` refuses a bag of another layout, ONNX
exports a 7-joint policy, and the policy node's logic (observation builder, pairing, commands)
reads any task's messages without DDS."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import arm7
from offline_rl_core.commands import cli
from offline_rl_core.common.errors import UserError
from offline_rl_core.data.bag import write_transitions
from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.learners import TrainConfig, train
from offline_rl_core.nodes.joint_messages import action_from_effort, command_from_action
from offline_rl_core.nodes.observation import ObservationBuilder
from offline_rl_core.nodes.pairing import StatePairing
from offline_rl_core.serving.checkpoint import (
    checkpoint_task, checkpoint_to_bytes, load_checkpoint, save_checkpoint, task_field,
)
from offline_rl_core.serving.policy import load_policy
from offline_rl_core.serving.signing import Signer
from offline_rl_core.serving.weights import encode_weights, policy_from_weights_message
from offline_rl_core.task.pusher_reach import observation_from_joints
from offline_rl_core.task.spec import load_task

TINY = dict(steps=30, hidden=16, batch_size=32, log_every=10)


@pytest.fixture(scope="module")
def arm(tmp_path_factory):
    """The 7-joint task file, a bag of its layout, and a BC run on it by `offline-rl train --task`."""
    root = tmp_path_factory.mktemp("arm7")
    task_file = arm7.write_task(root)
    bag = root / "arm7.db3"
    write_transitions(bag, arm7.synthetic_transitions())
    run = root / "run"
    assert cli.main(["train", "--bag", str(bag), "--task", str(task_file), "--algo", "bc", "--steps", "30",
                     "--hidden", "16", "--batch-size", "32", "--eval-episodes", "0", "--out", str(run)]) == 0
    pusher_bag = root / "pusher.db3"
    write_transitions(pusher_bag, collect_transitions(2, 1.0, 0))
    pusher_ckpt = save_checkpoint(root / "pusher.pt",
                                  train(collect_transitions(2, 1.0, 0), TrainConfig(algo="bc", **TINY), 0).checkpoint)
    return {"task_file": task_file, "task": load_task(task_file), "bag": bag, "run": run,
            "checkpoint": run / "policy.pt", "pusher_bag": pusher_bag, "pusher_ckpt": pusher_ckpt}


def test_a_trained_checkpoint_records_its_task_and_metrics_name_it(arm):
    ckpt = load_checkpoint(arm["checkpoint"])
    task = arm["task"]
    assert ckpt["task"] == {**task.layout(), "spec": task.describe()}
    assert ckpt["task"]["task"] == "test_arm7" and len(ckpt["task"]["observation"]) == arm7.OBS_DIM
    assert checkpoint_task(ckpt).digest == task.digest
    metrics = json.loads((arm["run"] / "metrics.json").read_text())
    assert metrics["task"] == task.layout()
    # pusher_reach's metrics keep the chapter's keys: no task named there
    run = arm["run"].parent / "pusher_run"
    assert cli.main(["train", "--bag", str(arm["pusher_bag"]), "--algo", "bc", "--steps", "2", "--hidden", "8",
                     "--batch-size", "8", "--eval-episodes", "0", "--out", str(run)]) == 0
    assert "task" not in json.loads((run / "metrics.json").read_text())
    assert load_checkpoint(run / "policy.pt")["task"]["task"] == "pusher_reach"


def test_a_checkpoint_is_refused_for_another_task_in_one_line_naming_both(arm):
    task = arm["task"]
    assert load_policy(arm["checkpoint"], task).act_dim == 7
    assert load_policy(arm["checkpoint"]).obs_dim == arm7.OBS_DIM  # no task asked: the checkpoint's own
    with pytest.raises(UserError) as refused:
        load_policy(arm["checkpoint"], "pusher_reach")
    line = str(refused.value)
    pusher = load_task("pusher_reach")
    assert "\n" not in line and line.startswith(f"{arm['checkpoint']}: a checkpoint of task test_arm7")
    for words in (f"digest {task.digest}", "obs_dim=21, act_dim=7", "the task here is pusher_reach",
                  f"digest {pusher.digest}", "obs_dim=8, act_dim=2"):
        assert words in line, line
    # a checkpoint that records no task (written before tasks existed) is pusher_reach's
    old = {k: v for k, v in load_checkpoint(arm["pusher_ckpt"]).items() if k != "task"}
    old_path = save_checkpoint(arm["run"].parent / "old.pt", old)
    assert load_policy(old_path, "pusher_reach").obs_dim == 8
    with pytest.raises(UserError, match=r"a checkpoint of task pusher_reach \(digest \w+, recording none, obs_dim=8, "
                                        r"act_dim=2\); the task here is test_arm7"):
        load_policy(old_path, task)


@pytest.mark.parametrize("edit, message", [
    (lambda t: "pusher_reach", "checkpoint field 'task' must be a mapping of task, digest, observation, action, spec"),
    (lambda t: {k: v for k, v in t.items() if k != "spec"}, "checkpoint field 'task' must be a mapping"),
    (lambda t: {**t, "digest": 7}, "checkpoint field 'task.digest' must be a non-empty string"),
    (lambda t: {**t, "action": t["action"][:3]}, "checkpoint field 'task.action' must be 7 labels"),
    (lambda t: {**t, "spec": {**t["spec"], "observation": "none"}}, "checkpoint field task.spec: field observation"),
    (lambda t: {**t, "task": "other"}, "its spec (task test_arm7, obs 21, action 7) is not the layout it records "
                                       "(task other"),
])
def test_a_malformed_task_field_is_one_line(arm, tmp_path, edit, message):
    ckpt = load_checkpoint(arm["checkpoint"])
    bad = save_checkpoint(tmp_path / "bad.pt", {**ckpt, "task": edit(ckpt["task"])})
    with pytest.raises(UserError) as refused:
        load_checkpoint(bad)
    assert message in str(refused.value) and "\n" not in str(refused.value), str(refused.value)


def test_weights_messages_carry_the_task_and_another_tasks_are_refused(arm):
    signer = Signer.generate()
    ckpt = load_checkpoint(arm["checkpoint"])
    data = encode_weights({**ckpt, "weights_version": 3}, signer)
    policy, problem = policy_from_weights_message("pusher-rl/weights", data, signer.verifier(), "learner/weights",
                                                  arm["task"])
    assert problem is None and policy.weights_version == 3 and policy.checkpoint["task"] == ckpt["task"]
    policy, problem = policy_from_weights_message("pusher-rl/weights", data, signer.verifier(), "learner/weights",
                                                  load_task())
    assert policy is None and problem.reason == "bad weights" and "the task here is pusher_reach" in problem


def test_the_online_learner_records_the_task_in_every_weights_version(arm):
    from offline_rl_core.learners.online import OnlineLearner, OnlineSettings

    learner = OnlineLearner(arm7.synthetic_transitions(), TrainConfig(algo="sac", hidden=16, batch_size=16),
                            OnlineSettings(publish_every=5), 0, task=arm["task"])
    assert learner.weights()["task"] == task_field(arm["task"])
    with pytest.raises(ValueError, match="task pusher_reach has obs 8, action 2"):
        OnlineLearner(arm7.synthetic_transitions(), TrainConfig(algo="sac", hidden=16), OnlineSettings(), 0,
                      task=load_task())


def test_train_refuses_a_bag_whose_layout_is_not_the_tasks(arm, capsys):
    out = arm["run"].parent / "refused"
    code = cli.main(["train", "--bag", str(arm["bag"]), "--task", "pusher_reach", "--algo", "bc", "--steps", "2",
                     "--eval-episodes", "0", "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "Traceback" not in err[0], err
    assert err[0].startswith(f"offline-rl: error: {arm['bag']}: its transitions have obs 21, action 7; "
                             "task pusher_reach (built-in task pusher_reach, digest "), err
    assert err[0].endswith("has obs 8, action 2") and not out.exists()
    # without --task the bag is read as pusher_reach's (it records none): the same refusal
    assert cli.main(["train", "--bag", str(arm["bag"]), "--algo", "bc", "--eval-episodes", "0",
                     "--out", str(out)]) == 2
    assert "its transitions have obs 21, action 7" in capsys.readouterr().err


def test_onnx_export_of_a_seven_joint_policy_names_its_task(arm, tmp_path):
    pytest.importorskip("onnxruntime")
    import onnx

    from offline_rl_core.serving.onnx_export import export_onnx, verify_onnx

    policy = load_policy(arm["checkpoint"])
    path = export_onnx(policy, tmp_path / "arm7.onnx")
    assert verify_onnx(policy, path) <= 1e-5
    model = onnx.load(str(path))
    dims = [d.dim_value for d in model.graph.input[0].type.tensor_type.shape.dim]
    assert dims[1] == arm7.OBS_DIM and [d.dim_value for d in model.graph.output[0].type.tensor_type.shape.dim][1] == 7
    meta = {p.key: p.value for p in model.metadata_props}
    assert json.loads(meta["pusher-rl.task"]) == arm["task"].layout()


# ---------------------------------------------------------------- the policy node's logic
def test_the_observation_builder_picks_the_tasks_joints_by_name(arm):
    task = arm["task"]
    builder = ObservationBuilder(task)
    rng = np.random.default_rng(1)
    q, qd = rng.uniform(-3, 3, 7), rng.uniform(-2, 2, 7)
    order = [4, 0, 6, 2, 1, 5, 3]
    names = [arm7.JOINTS[i] for i in order] + ["gripper"]  # shuffled, and a joint the task does not use
    (pos, vel), problem = builder.state(names, list(q[order]) + [0.7], list(qd[order]) + [9.0])
    assert problem is None and np.array_equal(pos, q) and np.array_equal(vel, qd)
    _, problem = builder.state(names[1:], list(q[order][1:]) + [0.7], list(qd[order][1:]) + [9.0])
    assert problem.reason == "unknown joints" and "lack j5" in problem
    _, problem = builder.state([], list(q[:6]), list(qd[:6]))
    assert problem.reason == "wrong length" and "expected 7" in problem
    _, problem = builder.state(list(arm7.JOINTS), list(q[:6]) + [float("nan")], list(qd))
    assert problem.reason == "non-finite"

    goal, problem = builder.goal_from_point(0.4, -0.1, 0.3)
    tip, _ = builder.point("tip", 0.1, 0.2, 0.25)
    assert problem is None and goal.tolist() == [0.4, -0.1, 0.3]
    obs = builder.observe(q, qd, goal, {"tip": tip})
    assert obs.dtype == np.float32 and obs.shape == (arm7.OBS_DIM,)
    wrapped = (q[:2] + np.pi) % (2 * np.pi) - np.pi
    want = np.concatenate([[np.cos(wrapped[0]), np.sin(wrapped[0]), np.cos(wrapped[1]), np.sin(wrapped[1])], q[2:], qd,
                           goal - tip, [0.3 * np.cos(q[0]) + 0.2 * np.cos(q[0] + q[1]),
                                        0.3 * np.sin(q[0]) + 0.2 * np.sin(q[0] + q[1])]]).astype(np.float32)
    np.testing.assert_allclose(obs, want, atol=1e-6)
    assert builder.topic_only == ("tip",)  # no kinematics stands in for it: states wait for it


def test_the_observation_builder_gives_pusher_reachs_observation():
    builder = ObservationBuilder(load_task())
    rng = np.random.default_rng(2)
    for _ in range(200):
        q, qd, target, tip = rng.uniform(-4, 4, 2), rng.uniform(-5, 5, 2), rng.uniform(-.2, .2, 2), rng.uniform(-.2, .2, 2)
        (pos, vel), _ = builder.state(["elbow", "shoulder"], q[::-1], qd[::-1])
        goal, _ = builder.goal_from_point(*target, 0.0)
        assert builder.observe(pos, vel, goal, {"fingertip": tip}).tobytes() == \
            observation_from_joints(q, qd, target, tip).tobytes()
        # without a fingertip heard: forward kinematics, as the pusher node always did
        np.testing.assert_array_equal(builder.observe(pos, vel, goal, {}), observation_from_joints(q, qd, target))


def test_a_joint_space_goal_is_read_by_name():
    from offline_rl_core.task.spec import task_from_yaml

    velocity_arm = task_from_yaml("""
name: joint_goal_arm
robot:
  state: {joints: [a, b, c]}
  command: {interface: velocity, joints: [c, a, b]}
goal: {topic: goal_joints, type: sensor_msgs/JointState}
observation: [{positions: [a, b, c]}, {difference: [goal, joints]}]
reward: {distance: [goal, joints]}
""")
    builder = ObservationBuilder(velocity_arm)
    assert builder.joint_goal
    goal, problem = builder.goal_from_joints(["c", "x", "a", "b"], [3.0, 9.0, 1.0, 2.0])
    assert problem is None and goal.tolist() == [1.0, 2.0, 3.0]
    assert builder.goal_from_joints(["a", "b"], [1.0, 2.0])[1].reason == "unknown joints"
    # a position-only arm: velocities are not observed, so a state may leave them out
    (pos, vel), problem = builder.state(["b", "a", "c"], [2.0, 1.0, 3.0], [])
    assert problem is None and vel.tolist() == [0.0, 0.0, 0.0]
    obs = builder.observe(pos, vel, goal, {})
    assert obs.tolist() == [1.0, 2.0, 3.0, 0.0, 0.0, 0.0]
    assert builder.distance(pos, np.array([1.0, 2.0, 5.0])) == pytest.approx(2.0)


def test_commands_are_offset_plus_scale_times_the_action_in_the_controllers_order(arm):
    task = arm["task"]
    action = np.array([1.0, -1.0, 0.5, 0.0, -0.5, 2.0, -3.0])
    values = command_from_action(task.command, action)
    clipped = np.clip(action, -1, 1)
    assert values.tolist() == [o + s * a for s, o, a in zip(arm7.SCALE, arm7.OFFSET, clipped)]
    assert np.allclose(command_from_action(load_task().command, [1.0, -0.4]), [0.5, -0.2])  # N·m: gear 0.5
    # the mux reads actions of the task's command joints, named in any order
    named = list(reversed(arm7.CONTROLLER_ORDER))
    got, problem = action_from_effort(named, list(reversed(clipped)), joints=task.command.joints)
    assert problem is None and got.tolist() == pytest.approx(clipped.tolist())
    assert action_from_effort([], [0.1, 0.2], joints=task.command.joints)[1].reason == "wrong length"


def test_pairing_waits_for_a_required_point_and_follows_a_co_stamping_topic():
    p = StatePairing(points=("tip",), required=("tip",))
    p.on_goal(1, [0.1, 0.2, 0.3])
    assert p.on_state(1, "s1") is None  # the tip has no kinematics: wait for it
    done = p.on_point("tip", 1, [0.0, 0.1, 0.2])
    assert done.state == "s1" and done.points["tip"].tolist() == [0.0, 0.1, 0.2]
    # the tip carried a state's stamp: from now on a state waits for the tip of its stamp
    p.on_goal(2, [0.1, 0.2, 0.3])
    p.on_point("tip", 99, [5.0, 5.0, 5.0])  # a stray one
    assert p.on_state(2, "s2") is None and p.on_point("tip", 2, [0.0, 0.0, 0.0]).state == "s2"
    # a point topic that never carries a state's stamp gives its latest point
    q = StatePairing(points=("tip",))
    q.on_point("tip", 500, [1.0, 1.0, 1.0])
    q.on_goal(7, [0.0, 0.0, 0.0])
    assert q.on_state(8, "s").points["tip"].tolist() == [1.0, 1.0, 1.0]


def test_the_corrector_of_another_task_needs_its_expert(arm):
    from offline_rl_core.task import corrector

    expert, distance = corrector.task_rule(load_task())
    assert expert is corrector.pusher_expert and distance is corrector.pusher_distance
    try:
        import offline_rl_core.task.envs  # noqa: F401
    except ImportError:
        with pytest.raises(UserError, match="the scripted corrector knows pusher_reach's expert only; task test_arm7"):
            corrector.task_rule(arm["task"], ObservationBuilder(arm["task"]).distance)
    else:
        pytest.skip("the task envs are here: the corrector of another task is tested with them")


def test_a_checkpoint_written_as_bytes_keeps_its_task(arm):
    from offline_rl_core.serving.checkpoint import checkpoint_from_bytes

    ckpt = load_checkpoint(arm["checkpoint"])
    back = checkpoint_from_bytes(checkpoint_to_bytes(ckpt), "bytes")
    assert back["task"] == ckpt["task"] and torch.equal(back["policy_state"]["0.weight"], ckpt["policy_state"]["0.weight"])


def test_hil_takes_the_task_and_refuses_what_it_cannot_evaluate(arm, tmp_path, capsys):
    out = tmp_path / "hil"
    assert cli.main(["hil", "--task", str(arm["task_file"]), "--bag", str(arm["bag"]), "--out", str(out)]) == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert line == (f"offline-rl: error: task test_arm7 ({arm['task_file']}): offline-rl hil runs the task in a sim "
                    "and scores it on held-out rollouts there; the task has no sim section"), line
    assert not out.exists()  # nothing was written
    # a prior of another task than the run's: one line naming both layouts
    assert cli.main(["hil", "--online", "--bag", str(arm["pusher_bag"]), "--prior", str(arm["checkpoint"]),
                     "--out", str(out)]) == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert "a checkpoint of task test_arm7" in line and "the task here is pusher_reach" in line, line


def test_a_task_only_a_bag_records_reaches_the_nodes_as_a_file(arm, tmp_path):
    from offline_rl_core.pipelines.hil import task_argument
    from offline_rl_core.task.spec import task_from_dict

    recorded = task_from_dict(arm["task"].describe(), tmp_path / "session.db3:/task_description")
    path = task_argument(recorded, tmp_path)
    assert load_task(path).digest == arm["task"].digest
    assert task_argument(load_task(), tmp_path) == "pusher_reach"
    assert task_argument(arm["task"], tmp_path) == str(arm["task_file"])
