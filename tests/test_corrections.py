"""The corrections stage (HIL-SERL): mux arbitration, the scripted corrector, source tags,
multi-bag training with a correction ratio, hot reload during a run, and the loop."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from offline_rl_core.data.bag import read_transitions, write_transitions
from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.task.pusher_reach import PusherReachEnv
from offline_rl_core.data.transitions import SOURCE_HUMAN, SOURCE_POLICY, Transitions

from ros_helpers import INDEX, REPO, probe_node, require_ros, ros_env, spawn  # noqa: F401 - fixtures
import ros_install  # noqa: E402 - from ros_ws/tools, on the path ros_helpers sets

CORRECTIONS_SRC = REPO / "ros_ws" / "src" / "corrections"
sys.path.insert(0, str(CORRECTIONS_SRC))  # the pure-Python parts, importable without the install

from offline_rl_core.nodes.arbiter import HUMAN, POLICY, LockstepArbiter, RealtimeArbiter
from offline_rl_core.task.corrector import CorrectorParams, ScriptedCorrector  # noqa: E402


def require_corrections() -> None:
    require_ros()
    if not (INDEX / "corrections").exists() or not (Path(sys.prefix) / "lib" / "corrections" / "mux").exists():
        pytest.skip("the corrections package is not installed: run `make setup`")


A = np.array([0.5, -0.5], np.float32)
B = np.array([-0.25, 0.75], np.float32)


# ---------------------------------------------------------------- packaging
def test_corrections_package_declares_two_executables():
    package = ros_install.read_package(CORRECTIONS_SRC)
    assert package.name == "corrections" and package.modules == ["pusher_corrections"]
    assert package.console_scripts == [("mux", "pusher_corrections.mux", "main"),
                                       ("corrector", "pusher_corrections.corrector", "main")]
    assert "install_scripts=$base/lib/corrections" in (CORRECTIONS_SRC / "setup.cfg").read_text()


def test_ros_install_reads_setup_cfg_entry_points(tmp_path):
    pkg = tmp_path / "demo_pkg"
    (pkg / "demo_pkg").mkdir(parents=True)
    (pkg / "demo_pkg" / "__init__.py").write_text("")
    (pkg / "package.xml").write_text("<package format='3'><name>demo_pkg</name></package>")
    (pkg / "setup.py").write_text("from setuptools import setup\nsetup()\n")
    (pkg / "setup.cfg").write_text(
        "[options.entry_points]\nconsole_scripts =\n    one = demo_pkg.a:main\n    two = demo_pkg.b:run\n"
    )
    package = ros_install.read_package(pkg)
    assert package.console_scripts == [("one", "demo_pkg.a", "main"), ("two", "demo_pkg.b", "run")]
    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True)
    (venv / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages").mkdir(parents=True)
    (venv / "bin" / "python").symlink_to(sys.executable)
    assert ros_install.main(["--venv", str(venv), "--no-shim", str(pkg)]) == 0
    assert "from demo_pkg.b import run" in (venv / "lib" / "demo_pkg" / "two").read_text()
    assert (venv / "lib" / "demo_pkg" / "one").is_file()


# ---------------------------------------------------------------- mux rule
def test_lockstep_human_wins_in_either_order_and_one_command_per_stamp():
    arb = LockstepArbiter()
    # policy first: it waits for the corrector's word
    assert arb.on_policy(1, A, corrector_present=True) is None
    cmd = arb.on_teleop(1, B)
    assert cmd.source == HUMAN and np.array_equal(cmd.action, B) and arb.intervening
    # the corrector first
    cmd = arb.on_teleop(2, B)
    assert cmd.source == HUMAN
    late = arb.on_policy(2, A, corrector_present=True)  # a policy action can't replace the human's
    assert late.resend and late.source == HUMAN and np.array_equal(late.action, B)
    # a yield lets the policy's action through, in either order
    assert arb.on_teleop(3, None) is None
    cmd = arb.on_policy(3, A, corrector_present=True)
    assert cmd.source == POLICY and np.array_equal(cmd.action, A) and not arb.intervening
    assert arb.on_policy(4, A, corrector_present=True) is None
    assert arb.on_teleop(4, None).source == POLICY
    # after the decision a teleop action for the stamp only repeats the decision
    again = arb.on_teleop(4, B)
    assert again.resend and again.source == POLICY
    assert arb.counts == {POLICY: 2, HUMAN: 2}


def test_lockstep_without_corrector_forwards_at_once():
    arb = LockstepArbiter()
    cmd = arb.on_policy(7, A, corrector_present=False)
    assert cmd.source == POLICY and not cmd.resend


def test_realtime_hold_window():
    arb = RealtimeArbiter(hold_s=0.1)
    assert arb.on_policy(0, A, now=0.0).source == POLICY
    assert arb.on_teleop(0, B, now=1.0).source == HUMAN
    assert arb.on_policy(0, A, now=1.05) is None  # inside the hold: the human has the arm
    assert arb.holding(1.09) and not arb.holding(1.11)
    assert arb.on_policy(0, A, now=1.11).source == POLICY  # the hold expired
    arb.on_teleop(0, B, now=2.0)
    assert arb.on_teleop(0, None, now=2.01) is None  # an empty action lets go at once
    assert arb.on_policy(0, A, now=2.02).source == POLICY


# ---------------------------------------------------------------- corrector rule
def still_arm(corrector: ScriptedCorrector, steps: int, qpos=(0.0, 0.0), target=(0.0, 0.15)):
    return [corrector.decide(np.array(qpos), np.zeros(2), np.array(target)) for _ in range(steps)]


def test_corrector_takes_over_after_patience_and_hands_back_after_hold():
    c = ScriptedCorrector(CorrectorParams(patience=4, hold_steps=3, grace_steps=0))
    answers = still_arm(c, 12)
    acted = [a is not None for a in answers]
    # state 0 sets the best distance; the 4th state without progress is taken over;
    # 3 corrections, hand back, and the count starts again
    assert acted == [False] * 4 + [True] * 3 + [False] * 4 + [True]
    assert c.takeovers == 2 and c.corrections == 4


def test_corrector_reaction_delay_and_noise_are_seeded():
    def run(seed):
        c = ScriptedCorrector(CorrectorParams(patience=2, hold_steps=5, reaction_delay=2, noise=0.3, seed=seed, grace_steps=0))
        return still_arm(c, 10)

    a, b, other = run(1), run(1), run(2)
    # decided on state 2 (2 states without progress), 2 states of delay, 5 corrections
    assert [x is None for x in a] == [True] * 4 + [False] * 5 + [True]
    assert all(np.array_equal(x, y) for x, y in zip(a, b) if x is not None)
    assert any(not np.array_equal(x, y) for x, y in zip(a, other) if x is not None)


def test_corrector_hands_back_on_success_and_resets_per_episode():
    env = PusherReachEnv()
    env.reset(3)
    c = ScriptedCorrector(CorrectorParams(patience=1, hold_steps=100, grace_steps=0))
    sources = []
    for _ in range(100):
        action = c.decide(env.qpos.copy(), env.qvel.copy(), env.target[:2].copy())
        sources.append(action is not None)
        env.step(np.zeros(2, np.float32) if action is None else action)
    assert c.takeovers >= 1 and c.succeeded and env.success
    assert not sources[-1]  # handed back once the fingertip reached the target
    # a new target is a new episode: no carry-over of the success latch
    c.decide(np.zeros(2), np.zeros(2), np.array([0.0, -0.15]))
    assert not c.succeeded and not c.intervening


# ---------------------------------------------------------------- training from several bags
def correction_bag(path: Path, n_episodes: int = 2) -> Transitions:
    """A correction-run bag: the expert's data relabelled policy, with human stretches."""
    data = collect_transitions(n_episodes, 1.0, 7)
    source = np.full(len(data), SOURCE_POLICY)
    source[(data.step >= 10) & (data.step < 20)] = SOURCE_HUMAN
    data.source = source
    write_transitions(path, data)
    return data


def test_training_on_several_bags_with_the_correction_ratio(tmp_path):
    import torch

    from offline_rl_core.learners import TrainConfig
    from offline_rl_core.learners.data import IndexSampler, correction_pools, intervention_actor_mask
    from offline_rl_core.runs.training_run import load_bags, run_training

    mix = tmp_path / "mix.db3"
    write_transitions(mix, collect_transitions(4, 0.5, 0))
    corr = tmp_path / "corrections.db3"
    correction_bag(corr)
    quiet = dict(eval_episodes=0, progress=None, log=lambda s: None)
    cfg = TrainConfig(algo="awac", steps=20, hidden=16, batch_size=32, log_every=10)
    prior = run_training([str(mix)], cfg, 0, tmp_path / "prior", **quiet) / "policy.pt"
    cfg = TrainConfig(algo="awac", steps=20, hidden=16, batch_size=32, log_every=10, correction_ratio=0.5)
    out = run_training([str(mix), str(corr)], cfg, 1, tmp_path / "hil", init=str(prior), **quiet)
    metrics = json.loads((out / "metrics.json").read_text())
    assert [b["transitions"] for b in metrics["bags"]] == [400, 200]
    assert metrics["bags"][1]["sources"] == {"policy": 180, "human": 20}
    assert metrics["config"]["correction_ratio"] == 0.5 and metrics["init"] == str(prior)

    data, _ = load_bags([str(mix), str(corr)])
    main, extra = correction_pools(data)
    assert len(extra) == 200 and len(main) == 400
    sampler = IndexSampler([len(data)], 32, [torch.Generator().manual_seed(0)],
                           [(torch.from_numpy(main), torch.from_numpy(extra))], 0.5)
    idx = sampler.next()[0].numpy()
    assert np.sum(np.isin(idx, extra)) == 16  # half of every batch from the correction runs
    # intervention-aware: the policy's last 5 actions before each takeover are not imitated
    mask = intervention_actor_mask(data)
    masked = np.flatnonzero(mask == 0)
    assert len(masked) == 10
    assert set(data.step[masked]) == {5, 6, 7, 8, 9} and set(data.source[masked]) == {SOURCE_POLICY}


# ---------------------------------------------------------------- over ROS
def stamp(node_time):
    from builtin_interfaces.msg import Time

    return Time(sec=0, nanosec=int(node_time))


def joint_msg(effort, stamp_ns: int, frame: str = ""):
    from sensor_msgs.msg import JointState

    msg = JointState(name=["shoulder", "elbow"], effort=[float(e) for e in effort])
    msg.header.stamp = stamp(stamp_ns)
    msg.header.frame_id = frame
    return msg


@pytest.mark.ros
def test_mux_over_ros_lockstep_and_realtime(spawn, ros_env):
    require_corrections()
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Bool

    from ros2_shim.ament_index import ros2_run

    # who acted is the topic a command goes to: pusher/command/policy or pusher/command/human
    lock = spawn(ros2_run("corrections", "mux", "--ros-args", "-p", "mode:=lockstep", "-p", "require_teleop:=true",
                          "-r", "__ns:=/lock", "-r", "policy/action:=/policy/action", "-r", "teleop/action:=/teleop/action"),
                 "mux_lockstep")
    real = spawn(ros2_run("corrections", "mux", "--ros-args", "-p", "mode:=realtime", "-p", "hold_ms:=300",
                          "-r", "__ns:=/real", "-r", "policy/action:=/policy/action", "-r", "teleop/action:=/teleop/action"),
                 "mux_realtime")
    assert lock.wait_for_output("mux lockstep", 60) and real.wait_for_output("mux realtime", 60)
    # its start-up line names the topics it really uses (namespaced, remapped)
    assert ("mux lockstep: /policy/action + /teleop/action -> /lock/pusher/command/policy | "
            "/lock/pusher/command/human") in lock.output(), lock.output()
    with probe_node("mux_probe") as node:
        got = {"lock": [], "real": [], "lock_int": [], "real_int": []}
        from rclpy.qos import DurabilityPolicy, QoSProfile

        latched = QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        for mux in ("lock", "real"):
            for source in ("policy", "human"):
                node.create_subscription(JointState, f"/{mux}/pusher/command/{source}",
                                         lambda m, mux=mux, source=source: got[mux].append((source, m)), 10)
        node.create_subscription(Bool, "/lock/corrections/intervening", lambda m: got["lock_int"].append(m.data), latched)
        node.create_subscription(Bool, "/real/corrections/intervening", lambda m: got["real_int"].append(m.data), latched)
        policy = node.create_publisher(JointState, "/policy/action", 10)
        teleop = node.create_publisher(JointState, "/teleop/action", 10)
        assert node.spin_until(lambda: policy.get_subscription_count() >= 2 and teleop.get_subscription_count() >= 2
                               and len(got["lock_int"]) and len(got["real_int"]), 30)

        # lockstep: stamp 1 policy then human -> one human command; stamp 2 yield -> the policy's
        policy.publish(joint_msg(A, 1, "policy"))
        node.spin_for(0.3)
        assert got["lock"] == []  # waits for the corrector's word
        teleop.publish(joint_msg(B, 1, "human"))
        assert node.spin_until(lambda: len(got["lock"]) >= 1, 10)
        teleop.publish(joint_msg([], 2, "human"))
        policy.publish(joint_msg(A, 2, "policy"))
        assert node.spin_until(lambda: len(got["lock"]) >= 2, 10)
        node.spin_for(0.3)
        lock_cmds = [(m.header.stamp.nanosec, source, list(m.effort)) for source, m in got["lock"]]
        assert lock_cmds == [(1, "human", list(map(float, B))), (2, "policy", list(map(float, A)))], lock_cmds
        assert node.spin_until(lambda: got["lock_int"][-3:] == [False, True, False], 5), got["lock_int"]

        # realtime: the teleop action holds the arm for hold_ms; policy actions inside are dropped
        got["real"].clear()
        teleop.publish(joint_msg(B, 10, "human"))
        assert node.spin_until(lambda: len(got["real"]) >= 1, 10)
        policy.publish(joint_msg(A, 11, "policy"))
        node.spin_for(0.1)
        assert [source for source, _ in got["real"]] == ["human"]
        assert node.spin_until(lambda: got["real_int"][-1] is False and True in got["real_int"], 5)
        policy.publish(joint_msg(A, 12, "policy"))  # hold over: the policy drives again
        assert node.spin_until(lambda: len(got["real"]) >= 2, 10)
        assert got["real"][-1][0] == "policy"


@pytest.mark.ros
def test_the_lockstep_mux_holds_its_first_command_until_the_named_readers_read_the_commands(spawn, ros_env):
    """A raw-topic learner or recorder whose command readers discovery matched late loses
    no step: the lockstep arm waits for the held command, which goes once they read both
    command topics (a re-send for the held stamp adds nothing); later ones go at once."""
    require_corrections()
    from sensor_msgs.msg import JointState

    from ros2_shim.ament_index import ros2_run

    mux = spawn(ros2_run("corrections", "mux", "--ros-args", "-p", "mode:=lockstep", "-p",
                         "wait_for_readers:=[late_reader]", "-r", "__ns:=/held"), "mux_held")
    assert mux.wait_for_output("mux lockstep", 60), mux.output()
    with probe_node("watcher") as node:
        got = []
        for source in ("policy", "human"):
            node.create_subscription(JointState, f"/held/pusher/command/{source}", lambda m: got.append(m), 10)
        policy = node.create_publisher(JointState, "/held/policy/action", 10)
        assert node.spin_until(lambda: policy.get_subscription_count() >= 1, 30)
        policy.publish(joint_msg(A, 1, "policy"))
        policy.publish(joint_msg(A, 1, "policy"))  # the sim republished the state: answered again
        node.spin_for(0.5)
        assert got == [], "a command went before the named reader read the commands"
        with probe_node("late_reader") as late:
            late_got = []
            for source in ("policy", "human"):
                late.create_subscription(JointState, f"/held/pusher/command/{source}", lambda m: late_got.append(m), 10)
            assert node.spin_until(lambda: len(got) >= 1, 30), mux.output()
            assert late.spin_until(lambda: len(late_got) >= 1, 10), mux.output()
            policy.publish(joint_msg(B, 2, "policy"))  # the readers are there: at once
            assert node.spin_until(lambda: len(got) >= 2, 10), mux.output()
            node.spin_for(0.3)
            assert [(m.header.stamp.nanosec, list(m.effort)) for m in got] == [
                (1, list(map(float, A))), (2, list(map(float, B)))]
            assert late.spin_until(lambda: len(late_got) >= 2, 10)
            assert [m.header.stamp.nanosec for m in late_got] == [1, 2]


@pytest.fixture(scope="module")
def weak_prior(tmp_path_factory):
    """An AWAC prior trained briefly on the reference bag (it rarely succeeds)."""
    from offline_rl_core.learners import TrainConfig
    from offline_rl_core.runs.training_run import run_training

    root = tmp_path_factory.mktemp("hil_prior")
    cfg = TrainConfig(algo="awac", steps=300, log_every=100)
    return run_training([str(REPO / "bags" / "mix.db3")], cfg, 0, root / "prior", eval_episodes=0, progress=None,
                        log=lambda s: None) / "policy.pt"


@pytest.mark.ros
@pytest.mark.slow
def test_hil_loop_records_sources_hot_reloads_and_improves(ros_env, weak_prior, tmp_path):
    """Two short rounds over ROS: sim + policy + corrector + mux + recorder, trainer, reload."""
    require_corrections()
    from offline_rl_core.pipelines.hil import HilConfig, run_hil
    from offline_rl_core.serving.policy import load_policy

    out = tmp_path / "hil"
    cfg = HilConfig(out=str(out), rounds=2, episodes=8, prior=str(weak_prior), steps=1500, eval_episodes=100,
                    bags=[str(REPO / "bags" / "mix.db3")])
    lines: list[str] = []
    summary = run_hil(cfg, log=lines.append)
    print(lines[-1])
    assert json.loads((out / "summary.json").read_text())["final_success"] == summary["final_success"]
    assert (out / "rounds.png").stat().st_size > 0
    rows = summary["rounds"]
    assert len(rows) == 2 and all(r["transitions"] == 800 and r["episodes"] == 8 for r in rows)
    # source tags: the bag records who acted; takeovers are followed by hand-backs
    for r in rows:
        data = read_transitions(r["bag"])
        assert set(np.unique(data.source)) == {SOURCE_POLICY, SOURCE_HUMAN}
        assert r["correction_transitions"] == int(np.sum(data.source == SOURCE_HUMAN)) > 0
        for e in np.unique(data.episode):
            src = data.source[data.episode == e]
            runs = np.diff(np.flatnonzero(np.diff(np.r_[0, src == SOURCE_HUMAN, 0])))[::2]
            assert np.all(runs <= cfg.hold_steps)  # every takeover hands back within hold_steps
            first = np.flatnonzero(src == SOURCE_HUMAN)
            # never before the grace period plus k states without progress
            assert len(first) == 0 or first[0] >= cfg.grace_steps + cfg.patience - 1
    # hot reload during the run: the policy node (one process) served round 2 with round 1's checkpoint
    assert (out / "policy.log").read_text().count("reloaded ") == 2
    round2 = read_transitions(rows[1]["bag"])
    pol = round2.source == SOURCE_POLICY
    new, old = load_policy(rows[0]["checkpoint"]), load_policy(weak_prior)
    assert np.allclose(new.act(round2.obs[pol]), round2.action[pol], atol=1e-4)
    assert not np.allclose(old.act(round2.obs[pol]), round2.action[pol], atol=1e-4)
    # the loop improves on its prior
    assert summary["final_success"] > summary["prior_success"]
    assert any("reloaded" in line for line in lines)


@pytest.mark.ros
def test_keyboard_mode_needs_a_terminal(ros_env, tmp_path):
    require_corrections()
    from ros2_shim.ament_index import ros2_run

    from offline_rl_core.pipelines.processes import RosProcess

    # RosProcess gives the node /dev/null as stdin (never the terminal pytest runs in)
    with RosProcess(ros2_run("corrections", "corrector", "--mode", "keyboard"), ros_env, tmp_path / "kb.log") as node:
        assert node.wait(timeout=60) == 2
        assert "corrector: error: --mode keyboard needs an interactive terminal" in node.output()


def test_a_claimed_domain_is_not_drawn_by_another_process_until_its_holder_exits(tmp_path):
    """Two pusher-rl sessions on one machine (a HIL run and the test suite) never draw the same
    DDS domain while both run: the id is held by the process that drew it, and freed when it
    ends, however it ends."""
    env = {**os.environ, "TMPDIR": str(tmp_path)}  # a lock folder of the test's own
    holder = subprocess.Popen([sys.executable, "-c", "from offline_rl_core.pipelines.processes import "
                               "claim_free_domain as c; print(c(1, 3), flush=True); import sys; sys.stdin.read()"],
                              env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        held = int(holder.stdout.readline())
        draw = [sys.executable, "-c", "from offline_rl_core.pipelines.processes import claim_free_domain as c; "
                "print(sorted({c(1, 3) for _ in range(2)}))"]
        others = json.loads(subprocess.run(draw, env=env, capture_output=True, text=True, check=True).stdout)
        assert held in (1, 2, 3) and sorted(others + [held]) == [1, 2, 3]  # the two ids the holder left
    finally:
        holder.kill()
        holder.wait()
    freed = subprocess.run([sys.executable, "-c", "from offline_rl_core.pipelines.processes import claim_free_domain "
                            "as c; print(sorted({c(1, 3) for _ in range(3)}))"], env=env, capture_output=True,
                           text=True, check=True)
    assert json.loads(freed.stdout) == [1, 2, 3]  # a killed holder's id is free again


def test_rosproc_stops_by_pid_with_escalation(tmp_path):
    import signal as _signal

    from offline_rl_core.pipelines.processes import RosProcess, isolated_ros_env

    env = isolated_ros_env(domain_id=42)
    assert env["ROS_DOMAIN_ID"] == "42" and env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert "ROS_LOCALHOST_ONLY" not in env and 1 <= int(isolated_ros_env()["ROS_DOMAIN_ID"]) <= 100
    stubborn = "import signal, time; signal.signal(signal.SIGINT, signal.SIG_IGN); print('up', flush=True); time.sleep(60)"
    proc = RosProcess([sys.executable, "-c", stubborn], env, tmp_path / "stubborn.log").start()
    assert proc.wait_for_output("up", 30)
    started = time.monotonic()
    assert proc.stop(timeout=1.0) == -_signal.SIGTERM  # SIGINT ignored, SIGTERM after 1 s
    assert time.monotonic() - started < 10 and not proc.running()


@pytest.mark.ros
def test_the_realtime_mux_ramps_sends_the_safe_command_when_silent_and_forwards_nothing_under_estop(
        spawn, ros_env, tmp_path):
    require_corrections()
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Bool, String

    from offline_rl_core.common.atomic import write_json_atomic
    from offline_rl_core.task.spec import load_task
    from ros2_shim.ament_index import ros2_run

    task = {**load_task("pusher_reach").describe(), "safety": {"slew": 0.25}}
    write_json_atomic(tmp_path / "task.yaml", task)  # JSON is YAML
    mux = spawn(ros2_run("corrections", "mux", "--ros-args", "-p", f"task:={tmp_path / 'task.yaml'}"), "mux")
    assert mux.wait_for_output("mux realtime", 60), mux.output()
    with probe_node("mux_safety_probe") as node:
        sent, statuses = [], []
        node.create_subscription(JointState, "/pusher/command/policy", lambda m: sent.append(list(m.effort)), 50)
        node.create_subscription(String, "/mux/status", lambda m: statuses.append(json.loads(m.data)), 10)
        policy = node.create_publisher(JointState, "/policy/action", 10)
        estop = node.create_publisher(Bool, "/estop", QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        assert node.spin_until(lambda: policy.get_subscription_count() and estop.get_subscription_count(), 30)
        policy.publish(joint_msg([0.0, 0.0], 1, "policy"))
        policy.publish(joint_msg([1.0, -1.0], 2, "policy"))  # a far jump: ramped by the task's slew
        assert node.spin_until(lambda: len(sent) >= 2, 10), mux.output()
        assert sent[:2] == [[0.0, 0.0], [0.25, -0.25]]
        # then silence: the safe command (zero effort) once, the fault latched on ~/status
        assert node.spin_until(lambda: len(sent) >= 3, 10) and sent[2] == [0.0, 0.0]
        assert node.spin_until(lambda: statuses and statuses[-1]["faults"].get("watchdog"), 10), statuses[-1:]
        assert statuses[-1]["slew_limited"] == 1
        # the e-stop: nothing forwarded, counted
        estop.publish(Bool(data=True))
        assert node.spin_until(lambda: statuses[-1]["estop"]["engaged"], 10), statuses[-1]
        count = len(sent)
        policy.publish(joint_msg([0.1, 0.1], 3, "policy"))
        assert node.spin_until(lambda: statuses[-1]["rejected"].get("estop") == 1, 10), statuses[-1]
        assert all(s == [0.0, 0.0] for s in sent[count:])  # at most the safe command
