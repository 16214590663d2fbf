"""The policy node (answers, rejects, hot reload), the trainer node, and the closed loop."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import time

import numpy as np
import pytest
import torch

from offline_rl_core.data.bag import write_transitions
from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.task.pusher_reach import observation_from_joints
from offline_rl_core.serving.checkpoint import checkpoint_to_bytes, save_checkpoint
from offline_rl_core.serving.policy import load_policy

from ros_helpers import REPO, probe_node, require_ros, ros2, ros_env, spawn  # noqa: F401 - fixtures

pytestmark = pytest.mark.ros


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """A tiny bag and two tiny checkpoints (different seeds: different actions)."""
    require_ros()
    from offline_rl_core.learners import TrainConfig
    from offline_rl_core.runs.training_run import run_training

    root = tmp_path_factory.mktemp("policy_data")
    bag = root / "expert.db3"
    write_transitions(bag, collect_transitions(2, 1.0, 0))
    cfg = TrainConfig(algo="bc", steps=30, hidden=16, batch_size=32, log_every=10)
    quiet = dict(eval_episodes=0, progress=None, log=lambda s: None)
    a = run_training([str(bag)], cfg, 0, root / "a", **quiet) / "policy.pt"
    b = run_training([str(bag)], cfg, 1, root / "b", **quiet) / "policy.pt"
    return {"bag": bag, "a": a, "b": b}


def replace_atomically(src_bytes: bytes, dest) -> None:
    tmp = dest.with_name(dest.name + ".incoming")
    tmp.write_bytes(src_bytes)
    os.replace(tmp, dest)


@pytest.mark.parametrize("args, error", [
    ([], "{tmp}/none.pt: no such checkpoint file"),
    (["--explore", "--seed", "-1"], "parameter seed: Parameter seed out of range. Min: 0"),  # not at the first state
    (["--ros-args", "-p", "pol_period:=5"], "unknown parameter 'pol_period' for node policy; did you mean poll_period?"),
    (["--ros-args", "-p", "poll_period"], "cannot parse --ros-args: Couldn't parse parameter override rule: "
                                          "'-p poll_period'."),
])
def test_a_bad_start_is_one_line_and_exit_2(spawn, tmp_path, args, error):
    node = spawn(ros2("run", "policy", "node", "--checkpoint", tmp_path / "none.pt", *args), "policy")
    assert node.wait(timeout=60) == 2
    lines = node.output().strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("policy: error: " + error.format(tmp=tmp_path)), lines


def test_ctrl_c_while_the_node_is_still_loading_exits_quietly(spawn, data):
    from ros2_shim.ament_index import ros2_run

    node = spawn(ros2_run("policy", "node", "--checkpoint", data["a"]), "policy")  # the node's own pid
    # the moment torch's library is mapped, the node is still importing it (seconds): Ctrl-C
    # there was a KeyboardInterrupt traceback
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and node.running() and not _maps_torch(node.pid):
        time.sleep(0.005)
    assert node.stop() in (0, 130)
    assert "Traceback" not in node.output() and "serving" not in node.output(), node.output()


def _maps_torch(pid: int) -> bool:
    try:
        return "libtorch_cpu" in open(f"/proc/{pid}/maps").read()
    except OSError:
        return False


def test_policy_answers_rejects_and_hot_reloads(spawn, data, tmp_path):
    from geometry_msgs.msg import PointStamped
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    served = tmp_path / "policy.pt"
    shutil.copy(data["a"], served)
    policy_a, policy_b = load_policy(data["a"]), load_policy(data["b"])
    # lockstep: this test sends a state at a time (a pause between them is no fault to the watchdog)
    node_proc = spawn(ros2("run", "policy", "node", "--ros-args", "-p", f"checkpoint:={served}",
                           "-p", "mode:=lockstep"), "policy")
    actions, torques = [], []
    with probe_node() as node:
        node.create_subscription(JointState, "/policy/action", actions.append, 10)
        node.create_subscription(Float64MultiArray, "/effort_controller/commands", torques.append, 10)
        state_pub = node.create_publisher(JointState, "/pusher/state", 10)
        target_pub = node.create_publisher(PointStamped, "/pusher/target", 10)
        assert node.spin_until(
            lambda: state_pub.get_subscription_count() and target_pub.get_subscription_count()
            and node.count_publishers("/policy/action"), 30
        ), node_proc.output()
        stamp = [0]

        def send(position, velocity, target=(0.1, 0.05)):
            stamp[0] += 1
            t = PointStamped()
            t.header.stamp.sec = stamp[0]
            t.point.x, t.point.y = target
            s = JointState(name=["shoulder", "elbow"], position=position, velocity=velocity)
            s.header.stamp.sec = stamp[0]
            target_pub.publish(t)
            state_pub.publish(s)
            return stamp[0]

        def answer_to(sec, timeout=5.0):
            node.spin_until(lambda: any(a.header.stamp.sec == sec for a in actions), timeout)
            return next((a for a in actions if a.header.stamp.sec == sec), None)

        q, qd = [0.3, -1.2], [0.5, -0.1]
        obs = observation_from_joints(q, qd, (0.1, 0.05))
        # The first messages can race discovery: the probe's writer may see the node's
        # reader matched before the reader has matched the writer, and a reader drops
        # what comes from a writer it does not know yet. A stream recovers on its next
        # message; so does this test, re-sending until the node answers.
        reply, deadline = None, time.monotonic() + 15
        while reply is None and time.monotonic() < deadline:
            reply = answer_to(send(q, qd), timeout=1.0)
        assert reply is not None and reply.header.frame_id == "", node_proc.output()  # frame_id names no source
        assert np.array_equal(np.array(reply.effort, np.float32), policy_a.act(obs))
        # the same action as torques in N·m for an effort controller (motor gear 0.5)
        assert node.spin_until(lambda: torques, 5)
        assert np.allclose(torques[-1].data, 0.5 * np.array(reply.effort), atol=1e-12)

        bad = [send([float("nan"), 0.0], qd), send([0.1], [0.2]), send(q, [float("inf"), 0.0])]
        node.spin_for(0.5)
        assert not any(a.header.stamp.sec in bad for a in actions)
        assert "ignoring pusher/state" in node_proc.output()

        replace_atomically(data["b"].read_bytes(), served)
        want_b = policy_b.act(obs)
        assert not np.array_equal(want_b, policy_a.act(obs))
        deadline = time.monotonic() + 15  # the file is polled every 0.5 s
        while time.monotonic() < deadline:
            reply = answer_to(send(q, qd), timeout=1.0)
            if reply is not None and np.array_equal(np.array(reply.effort, np.float32), want_b):
                break
            node.spin_for(0.1)
        else:
            pytest.fail(f"new checkpoint not picked up (exit {node_proc.proc.poll()}, {len(actions)} actions): " + node_proc.output())
        assert "reloaded" in node_proc.output()

        # A checkpoint whose bias does not fit would load and then fail on every state: refused
        # at reload, and the policy serving goes on.
        ckpt_b = torch.load(data["b"], weights_only=True)
        bad_bias = dict(ckpt_b, policy_state={**ckpt_b["policy_state"], "4.bias": torch.zeros(7)})
        replace_atomically(checkpoint_to_bytes(bad_bias), served)
        assert node.spin_until(lambda: "cannot reload" in node_proc.output(), 10), node_proc.output()
        reply = answer_to(send(q, qd))
        assert reply is not None and np.array_equal(np.array(reply.effort, np.float32), want_b)  # old one serves

        # The checkpoint is a parameter too: setting it switches the policy (loaded off the
        # serving thread); one that does not load is said with the reason, the parameter is
        # set back, and the policy serving goes on.
        def param_set(value):
            return subprocess.run(ros2("param", "set", "/policy", "checkpoint", value), capture_output=True,
                                  text=True, timeout=60)

        switched = param_set(data["a"])
        assert switched.stdout.strip() == "Set parameter successful", switched.stderr
        assert node.spin_until(lambda: f"policy from {data['a']}" in node_proc.output(), 20), \
            node_proc.output()
        reply = answer_to(send(q, qd))
        assert reply is not None and np.array_equal(np.array(reply.effort, np.float32), policy_a.act(obs))
        zero_std = save_checkpoint(tmp_path / "zero_std.pt", dict(ckpt_b, obs_mean=torch.zeros(8), obs_std=torch.zeros(8)))
        param_set(zero_std)
        assert node.spin_until(lambda: "zero_std.pt: obs_std" in node_proc.output(), 20), node_proc.output()
        assert f"still serving {data['a']}" in node_proc.output()
        shown = subprocess.run(ros2("param", "get", "/policy", "checkpoint"), capture_output=True, text=True, timeout=60)
        assert str(data["a"]) in shown.stdout, shown
        refused = param_set("/dev/tty")
        assert "not a regular file" in refused.stderr, refused.stderr
        reply = answer_to(send(q, qd))
        assert reply is not None and np.array_equal(np.array(reply.effort, np.float32), policy_a.act(obs))


@pytest.mark.slow
def test_trainer_node_from_the_card_command_publishes_progress(spawn, data, tmp_path):
    # The type is given so the listener subscribes at once; both topics latch their last
    # reports (transient local), so a reader that matches after a short run's last report,
    # while the trainer is still up, still gets it.
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.qos import DurabilityPolicy, QoSProfile

    echo = spawn(ros2("topic", "echo", "/trainer/progress", "std_msgs/msg/String", "--once", "--full-length"), "echo")
    out = tmp_path / "run"
    with probe_node("trainer_diagnostics") as node:
        seen = []  # the trainer's /diagnostics entries
        node.create_subscription(DiagnosticArray, "/diagnostics",
                                 lambda msg: seen.extend(s for s in msg.status if s.name == "/trainer"),
                                 QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        # the echo listening before the trainer starts: on a loaded machine a short training can
        # be over before a starting `ros2 topic echo` subscribes
        assert node.spin_until(lambda: node.count_subscribers("/trainer/progress") > 0, 60), echo.output()
        trainer = spawn(
            ros2("run", "trainer", "--bag", data["bag"], "--algo", "awac", "--steps", 6000, "--hidden", 16,
                 "--batch-size", 32, "--log-every", 25, "--eval-episodes", 2, "--out", out),
            "trainer",
        )
        assert node.spin_until(lambda: seen or trainer.poll() is not None, 150), trainer.output()
        node.spin_until(lambda: seen, 2)  # what arrived as the trainer exited, still queued
    assert seen, trainer.output()
    entry = seen[-1]
    assert entry.level == b"\x00" and entry.message.startswith("training awac: step "), entry.message
    assert {kv.key for kv in entry.values} >= {"step", "total", "steps_per_s", "scalars/critic_loss"}
    assert trainer.wait(timeout=150) == 0, trainer.output()
    assert (out / "policy.pt").is_file() and json.loads((out / "metrics.json").read_text())["algorithm"] == "awac"
    assert f"wrote {out / 'policy.pt'}" in trainer.output()
    assert echo.wait(timeout=20) == 0, echo.output()
    report = json.loads(echo.output().split("data: ", 1)[1].split("\n---", 1)[0].strip().strip("'"))
    # the first report the echo heard: a step of the run, or (matched as the run ended) its last
    assert report.get("total") == 6000 or report == {"done": True, "out": str(out), "checkpoint": str(out / "policy.pt")}
    # the curves in TensorBoard's event files beside metrics.json, as `offline-rl train` writes them
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    curves = EventAccumulator(str(out))
    curves.Reload()
    assert curves.Scalars("train/critic_loss")[-1].step == 6000 and "eval/success_rate" in curves.Tags()["scalars"]

    bad = spawn(ros2("run", "trainer", "node", "--bag", tmp_path / "none.db3", "--out", tmp_path / "x"), "bad")
    assert bad.wait(timeout=60) == 2
    assert bad.output().strip().splitlines()[-1].startswith("trainer: error:")


def _ctrl_c_stops_the_trainer(ros_env, data, tmp_path, when: str) -> None:
    """Start a long trainer with SIGINT ignored (as a script's background job is), wait
    for a log line matching ``when``, send SIGINT: it must stop with 130 and say so."""
    import signal

    from ros2_shim.ament_index import ros2_run

    log = tmp_path / "trainer.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            ros2_run("trainer", "node", "--bag", data["bag"], "--algo", "bc", "--steps", 10_000_000, "--hidden", 16,
                     "--log-every", 100, "--out", tmp_path / "run"),
            env=ros_env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        deadline = time.monotonic() + 120
        while not re.search(when, log.read_text(), re.M) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        assert proc.poll() is None, log.read_text()
        proc.send_signal(signal.SIGINT)
        try:
            code = proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            # where it is stuck: faulthandler (enabled by every node) writes each thread's stack on SIGABRT
            proc.send_signal(signal.SIGABRT)
            proc.wait(timeout=30)
            pytest.fail("the trainer did not stop within 60 s of SIGINT:\n" + log.read_text()[-6000:])
        assert code == 130, log.read_text()
        assert "interrupted" in log.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.slow
def test_trainer_stops_on_ctrl_c_when_started_with_it_ignored(ros_env, data, tmp_path):
    """A script's background job (`trainer ... &`) starts with SIGINT ignored; Ctrl-C / kill -INT
    still stops it mid-training."""
    _ctrl_c_stops_the_trainer(ros_env, data, tmp_path, when=r"^\s*step\s+\d+/")


@pytest.mark.slow
def test_trainer_stops_on_ctrl_c_during_set_up(ros_env, data, tmp_path):
    """Ctrl-C while the trainer is still setting up (imports, the learner, the fast path)
    stops it with 130 and one line, never a traceback of whatever import it landed in."""
    _ctrl_c_stops_the_trainer(ros_env, data, tmp_path, when=r"^training bc on ")
    assert "Traceback" not in (tmp_path / "trainer.log").read_text()


@pytest.mark.slow
@pytest.mark.parametrize("spin", ["fast", "executor"])
def test_closed_loop_matches_in_process_evaluation(spawn, data, tmp_path, spin):
    """Also both ways the sim can spin: the private wait-set fast path, and rclpy's public
    executor (what runs where an rclpy lacks that API)."""
    from offline_rl_core.evaluation.rollouts import evaluate_policy

    episodes, seed = 6, 500000
    summary = tmp_path / "closed_loop.json"
    spawn(ros2("run", "policy", "node", "--checkpoint", data["a"]), "policy")
    sim = spawn(
        ros2("run", "sim", "node", "--ros-args", "-p", "mode:=lockstep", "-p", f"seed:={seed}",
             "-p", f"episodes:={episodes}", "-p", f"summary:={summary}", "-r", "pusher/command:=policy/action"),
        "sim", env={**os.environ, "PUSHER_RL_SPIN": spin},
    )
    assert sim.wait(timeout=120) == 0, sim.output()
    over_ros = json.loads(summary.read_text())
    in_process = evaluate_policy(load_policy(data["a"]), episodes, seed)
    assert over_ros["episodes"] == episodes
    # Same observation bit for bit (the sim publishes its fingertip); only numpy's
    # 1-row vs N-row float32 rounding of the policy output separates the two.
    assert round(over_ros["success_rate"], 6) == in_process["success_rate"]
    assert abs(over_ros["mean_final_dist"] - in_process["mean_final_dist"]) < 1e-4


@pytest.mark.slow
def test_two_namespaced_pipelines_on_one_domain_stay_apart(spawn, data, tmp_path):
    """serve.launch.yaml with ``namespace:=/armN`` (``-r __ns:=`` on every node): two closed
    loops on one domain, each with its own policy, and no cross-talk.

    Both lockstep sims stamp their states alike, so a policy heard across namespaces
    would answer the other sim's states and its results would no longer be its own."""
    from offline_rl_core.evaluation.rollouts import evaluate_policy

    episodes = 3
    runs = {"arm1": (data["a"], 500000), "arm2": (data["b"], 600000)}
    launches = {}
    for ns, (checkpoint, seed) in runs.items():
        launches[ns] = spawn(ros2("launch", "pusher_bringup", "serve.launch.yaml", f"checkpoint:={checkpoint}",
                                  f"namespace:=/{ns}", f"seed:={seed}", f"episodes:={episodes}",
                                  f"summary:={tmp_path / ns}.json"), f"launch_{ns}",
                             env={**os.environ, "ROS_LOG_DIR": str(tmp_path / "logs")})
    for ns, launch in launches.items():
        assert launch.wait(timeout=120) == 0, launch.output()  # ends when its sim has run its episodes
        assert "[node-2] [INFO]" in launch.output() and "process has finished cleanly" in launch.output()
    for ns, (checkpoint, seed) in runs.items():
        over_ros = json.loads((tmp_path / f"{ns}.json").read_text())
        in_process = evaluate_policy(load_policy(checkpoint), episodes, seed)
        assert over_ros["episodes"] == episodes
        assert round(over_ros["success_rate"], 6) == in_process["success_rate"], ns
        assert abs(over_ros["mean_final_dist"] - in_process["mean_final_dist"]) < 1e-4, ns
