"""Safety over real DDS: the policy node takes only the session learner's weights, refuses a
checkpoint that is no file and answers every state meanwhile; the recorder survives odd type
names, bounds what waits for /clock, stops cleanly when the disk fills, and a Ctrl-C (or two)
never crashes it or cuts its bag short."""

from __future__ import annotations

import array
import json
import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from ros_helpers import probe_node, ros2, ros_env, spawn  # noqa: F401 - fixtures

pytestmark = pytest.mark.ros
START = 1_800_000_000 * 10**9
TICK = 20_000_000


def _rss_mib(pid: int) -> float:
    with open(f"/proc/{pid}/status") as f:
        return int(next(line for line in f if line.startswith("VmRSS:")).split()[1]) / 1024


def _checkpoint(seed: int, version: int | None = None, hidden: int = 64) -> dict:
    import torch

    from offline_rl_core.serving.policy import policy_sequential

    torch.manual_seed(seed)
    net = policy_sequential(8, hidden, 2)
    ckpt = {"format": "pusher-rl/policy", "version": 1, "algorithm": "sac", "obs_dim": 8, "act_dim": 2,
            "hidden": hidden, "policy_state": {k: v.detach().clone() for k, v in net.state_dict().items()}}
    if version is not None:
        ckpt["weights_version"] = version
    return ckpt


def test_the_policy_node_takes_only_the_sessions_weights_and_answers_every_state(spawn, tmp_path, ros_env):
    from geometry_msgs.msg import PointStamped
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import MultiArrayDimension, String, UInt8MultiArray

    from fuzz_messages import stride0_checkpoint
    from offline_rl_core.serving.checkpoint import save_checkpoint
    from offline_rl_core.serving.policy import LoadedPolicy
    from offline_rl_core.serving.signing import Signer, make_session_keys, load_signer
    from offline_rl_core.serving.weights import encode_weights
    from offline_rl_core.task.pusher_reach import observation_from_joints

    keys = make_session_keys(tmp_path / "keys")
    learner = load_signer(keys.signing_key)
    served = save_checkpoint(tmp_path / "policy.pt", _checkpoint(0))
    fifo = tmp_path / "fifo.pt"
    os.mkfifo(fifo)
    proc = spawn([sys.executable, "-m", "pusher_policy.node", "--ros-args", "-p", f"checkpoint:={served}",
                  "-p", "weights_topic:=learner/weights", "-p", f"weights_key:={keys.public_key}"], "policy")
    v1, v2 = _checkpoint(1, 1), _checkpoint(2, 2)
    rogue = {**_checkpoint(3, 2**62)}
    rogue["policy_state"]["4.bias"][:] = 1e6  # saturates every action
    messages = {"v1": encode_weights(v1, learner), "v2": encode_weights(v2, learner),
                "rogue": encode_weights(rogue, Signer.generate()), "stride-0": stride0_checkpoint(8192)}
    answers, statuses = {}, []
    with probe_node() as node:
        pubs = {t: node.create_publisher(m, f"/{t}", 10) for t, m in (
            ("pusher/target", PointStamped), ("pusher/fingertip", PointStamped), ("pusher/state", JointState))}
        weights = node.create_publisher(UInt8MultiArray, "/learner/weights", QoSProfile(
            depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        node.create_subscription(String, "/policy/provenance", lambda m: answers.setdefault(
            json.loads(m.data)["stamp"], json.loads(m.data)["weights_version"]), 1000)
        actions = {}
        node.create_subscription(JointState, "/policy/action", lambda m: actions.setdefault(
            m.header.stamp.sec * 10**9 + m.header.stamp.nanosec, np.array(m.effort, np.float32)), 1000)
        node.create_subscription(String, "/policy/status", lambda m: statuses.append(json.loads(m.data)), 10)
        assert node.spin_until(lambda: weights.get_subscription_count() and node.count_publishers(
            "/policy/action"), 30), proc.output()
        rng = np.random.default_rng(5)
        obs_of = {}
        stamp = [START]

        def state() -> int:
            stamp[0] += TICK
            s = stamp[0]
            q, qd, target, tip = (rng.uniform(-1, 1, 2) for _ in range(4))
            for topic, xy in (("pusher/target", target), ("pusher/fingertip", tip)):
                msg = PointStamped()
                msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(s, 10**9)
                msg.point.x, msg.point.y = float(xy[0]), float(xy[1])
                pubs[topic].publish(msg)
            msg = JointState(name=["shoulder", "elbow"], position=list(q), velocity=list(qd))
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(s, 10**9)
            pubs["pusher/state"].publish(msg)
            obs_of[s] = observation_from_joints(q, qd, target, tip)
            return s

        def answered(timeout=10.0) -> int:
            s = state()
            assert node.spin_until(lambda: s in answers and s in actions, timeout), proc.output()[-3000:]
            return s

        def send(name: str) -> None:
            msg = UInt8MultiArray(data=array.array("B", messages[name]))
            msg.layout.dim = [MultiArrayDimension(label="pusher-rl/weights", size=len(msg.data), stride=1)]
            weights.publish(msg)

        deadline = time.monotonic() + 20  # discovery can drop the first states
        while not answers and time.monotonic() < deadline:
            state()
            node.spin_until(lambda: bool(answers), 1.0)
        send("v1")
        assert node.spin_until(lambda: answers[answered()] == 1, 20), proc.output()[-3000:]
        rss_before = _rss_mib(proc.pid)
        for i in range(40):  # the rogue's messages among the arm's states: none acts, each state answered
            send("rogue" if i % 2 else "stride-0")
            s = answered()
            assert answers[s] == 1
            assert np.allclose(actions[s], LoadedPolicy(v1).act(obs_of[s]), atol=1e-6)
        assert node.spin_until(lambda: statuses and statuses[-1]["rejected"].get("unsigned weights", 0) == 40, 15), \
            (statuses[-1:], proc.output()[-2000:])
        assert _rss_mib(proc.pid) - rss_before < 50
        # a checkpoint that is no file: refused at once, serving goes on
        refused = subprocess.run(ros2("param", "set", "/policy", "checkpoint", str(fifo)), capture_output=True,
                                 text=True, env=ros_env, timeout=60)
        assert "not a regular file" in refused.stdout + refused.stderr, refused
        send("v2")
        assert node.spin_until(lambda: answers[answered()] == 2, 20), proc.output()[-3000:]
    assert proc.running(), proc.output()[-3000:]


def test_the_recorder_survives_odd_type_names_and_bounds_what_waits_for_the_clock(ros_env, tmp_path, monkeypatch):
    """Discovery may report any type string; sim time may never start."""
    import rclpy
    from rclpy.parameter import Parameter
    from rosbags.rosbag2 import Reader

    from pusher_recorder import node as recorder_node

    for odd in ("Foo", "a/b/c/d", "/msg/X", "pkg/msg/", "no_such_pkg/msg/X", ""):
        assert recorder_node.message_class(odd) is None, odd
    monkeypatch.setattr(recorder_node, "BEFORE_CLOCK_BYTES", 1 << 20)
    monkeypatch.setenv("ROS_DOMAIN_ID", ros_env["ROS_DOMAIN_ID"])
    rclpy.init()  # the recorder node is made in this process, on the default context
    bag = tmp_path / "odd.db3"
    rec = recorder_node.Recorder([Parameter("out", value=str(bag)), Parameter("passive", value=True),
                                  Parameter("use_sim_time", value=True)])
    try:
        odd = [("/x", ["Foo"]), ("/y", ["a/b/c/d"]), ("/z", ["/msg/X"]), ("/w", ["std_msgs/msg/String", "Foo"])]
        rec.get_topic_names_and_types = lambda: odd
        rec.record_all = True
        rec.discover()  # no exception, one warning each, nothing subscribed
        assert {"/x", "/y", "/z", "/w"} <= rec.warned and not {"/x", "/y", "/z", "/w"} & set(rec.subs)
        rec.types["/notes"] = "std_msgs/msg/String"
        payload = bytes([0, 1, 0, 0]) + (60_000).to_bytes(4, "little") + b"n" * 59_999 + b"\x00"
        for _ in range(100):  # 6 MB before any /clock
            rec.write("/notes", payload)
        assert rec.before_clock_bytes <= 1 << 20 and rec.dropped_before_clock == 100 - len(rec.before_clock)
        kept = len(rec.before_clock)
        rec.close()
        with Reader(bag) as reader:
            assert reader.message_count == kept
    finally:
        rec.destroy_node()
        rclpy.try_shutdown()


def _sent_numbers(bag) -> list[int]:
    from rosbags.rosbag2 import Reader

    from offline_rl_core.data.bag import typestore

    with Reader(bag) as reader:
        conns = [c for c in reader.connections if c.topic == "/notes"]
        return [int(typestore().deserialize_cdr(raw, "std_msgs/msg/String").data)
                for _, _, raw in reader.messages(conns)]


def _flushed(bag) -> bool:
    try:
        return bool(_sent_numbers(bag))
    except Exception:  # noqa: BLE001 - nothing flushed yet
        return False


def test_the_recorder_stops_cleanly_when_the_disk_fills(spawn, tmp_path, ros_env):
    """Free space below ``min_free_space`` (here: the minimum raised past what is free, as a
    filling disk does): the recording ends, the bag holds every message before the stop."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String

    from offline_rl_core.data.bag.recording import free_space

    bag = tmp_path / "full.db3"
    refused = spawn(ros2("run", "recorder", "node", "--passive", "--topics", "notes", "--out", tmp_path / "x.db3",
                         "--min-free-space", free_space(tmp_path) + (1 << 40)), "refused")
    assert refused.wait(30) == 2 and "below the minimum" in refused.output(), refused.output()
    recorder = spawn(ros2("run", "recorder", "node", "--passive", "--topics", "notes", "--out", bag,
                          "--flush-interval", "0.05"), "recorder")
    assert recorder.wait_for_output("recording passively", 30), recorder.output()
    with probe_node() as node:
        pub = node.create_publisher(String, "/notes", QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
        assert node.spin_until(lambda: pub.get_subscription_count() > 0, 30), recorder.output()
        sent = 0
        while sent < 50:
            pub.publish(String(data=str(sent)))
            sent += 1
            node.spin_for(0.01)
        done = subprocess.run(ros2("param", "set", "/recorder", "min_free_space", str(free_space(tmp_path) + (1 << 40))),
                              capture_output=True, text=True, env=ros_env, timeout=60)
        assert "successful" in done.stdout.lower(), done
        while recorder.running() and sent < 100_000:
            pub.publish(String(data=str(sent)))
            sent += 1
            node.spin_for(0.005)
    assert recorder.wait(30) == 1, recorder.output()
    assert "recording stopped, the bag holds every message before the stop" in recorder.output()
    numbers = _sent_numbers(bag)
    wrote = int(re.search(r"(\d+) messages\)", recorder.output()).group(1))
    assert numbers == list(range(len(numbers))) and len(numbers) == wrote >= 50


@pytest.mark.slow
def test_ctrl_c_and_a_second_one_never_crash_the_recorder_or_cut_its_bag(spawn, tmp_path):
    """With a core kept busy beside it (the race needs the signal thread and the main thread
    to interleave): every run exits 0 with a whole bag holding what it said it wrote.
    bench/shutdown_sigint.py runs this 200 times."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String

    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        with probe_node() as node:
            # deeper than a run publishes: a full reliable history of samples not yet acknowledged
            # makes Fast DDS's publish block, then fail ("cannot publish data"), the test's not the recorder's
            pub = node.create_publisher(String, "/notes", QoSProfile(depth=4000,
                                                                     reliability=ReliabilityPolicy.RELIABLE))
            for run in range(6):
                bag = tmp_path / f"run{run}.db3"
                recorder = spawn(ros2("run", "recorder", "node", "--passive", "--topics", "notes", "--out", bag),
                                 f"recorder{run}")
                assert recorder.wait_for_output("recording passively", 60), recorder.output()
                i = 0
                while not _flushed(bag):  # recording for real
                    assert recorder.running() and i < 5000, recorder.output()
                    if "subscribed to /notes" in recorder.output():
                        pub.publish(String(data=str(i)))
                        i += 1
                    node.spin_for(0.02)
                for j in range(2000):  # pending in the writer when the signal comes
                    pub.publish(String(data=str(10**6 + j)))
                recorder.proc.send_signal(signal.SIGINT)
                if run % 2:
                    time.sleep(0.005 * run)  # the second Ctrl-C, into the close
                    recorder.proc.send_signal(signal.SIGINT)
                rc = recorder.wait(60)
                assert rc == 0, f"run {run}: exit {rc}\n{recorder.output()[-3000:]}"
                wrote = int(re.search(r"(\d+) messages\)", recorder.output()).group(1))
                numbers = _sent_numbers(bag)  # what it took, in order (DDS may drop some of a burst before)
                assert len(numbers) == wrote > 0 and all(a < b for a, b in zip(numbers, numbers[1:])), run
    finally:
        busy.kill()
        busy.wait()


# ---------------------------------------------------------------- watchdog and e-stop

def _latest_status(node, name: str, seen: list):
    from std_msgs.msg import String

    return node.create_subscription(String, f"/{name}/status", lambda m: seen.append(json.loads(m.data)), 10)


def test_sigkill_of_the_policy_driving_the_controller_zeroes_the_sims_torque(spawn, tmp_path):
    """The policy node drives the realtime sim through its effort controller topic; killed
    with SIGKILL (no goodbye), the sim's watchdog applies zero torque and latches the fault."""
    from sensor_msgs.msg import JointState

    from offline_rl_core.serving.checkpoint import save_checkpoint

    served = save_checkpoint(tmp_path / "policy.pt", _checkpoint(0))
    sim = spawn([sys.executable, "-m", "pusher_sim.node", "--ros-args",
                 "-p", "effort_topic:=effort_controller/commands"], "sim")
    policy = spawn([sys.executable, "-m", "pusher_policy.node", "--ros-args", "-p", f"checkpoint:={served}"], "policy")
    efforts, statuses = [], []
    with probe_node() as node:
        node.create_subscription(JointState, "/pusher/state", lambda m: efforts.append(list(m.effort)), 100)
        _latest_status(node, "sim", statuses)
        # the policy drives: the applied torque is its (nonzero) command
        assert node.spin_until(lambda: sum(any(e) for e in efforts[-5:]) == 5, 60), sim.output() + policy.output()
        os.kill(policy.pid, signal.SIGKILL)
        killed_at = len(efforts)
        assert node.spin_until(lambda: any(not any(e) for e in efforts[killed_at:]), 10), sim.output()
        first_zero = next(i for i in range(killed_at, len(efforts)) if not any(efforts[i]))
        assert node.spin_until(lambda: len(efforts) > first_zero + 5, 10)
        assert all(not any(e) for e in efforts[first_zero:])  # and stays zero: no one commands
        assert node.spin_until(lambda: statuses and statuses[-1]["faults"].get("watchdog", {}).get("trips"), 10), \
            statuses[-1:]
    assert statuses[-1]["faults"]["watchdog"]["silent"] is True
    assert sim.stop() == 0


def test_the_estop_engages_the_sim_and_policy_and_only_estop_reset_releases_them(spawn, tmp_path):
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Bool
    from std_srvs.srv import Trigger

    from offline_rl_core.serving.checkpoint import save_checkpoint

    served = save_checkpoint(tmp_path / "policy.pt", _checkpoint(0))
    sim = spawn([sys.executable, "-m", "pusher_sim.node", "--ros-args",
                 "-p", "effort_topic:=effort_controller/commands"], "sim")
    policy = spawn([sys.executable, "-m", "pusher_policy.node", "--ros-args", "-p", f"checkpoint:={served}"], "policy")
    efforts, actions, sim_status, policy_status = [], [], [], []
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    with probe_node() as node:
        node.create_subscription(JointState, "/pusher/state", lambda m: efforts.append(list(m.effort)), 100)
        node.create_subscription(JointState, "/policy/action", actions.append, 100)
        _latest_status(node, "sim", sim_status)
        _latest_status(node, "policy", policy_status)
        estop = node.create_publisher(Bool, "/estop", latched)
        reset = node.create_client(Trigger, "/estop/reset")
        assert node.spin_until(lambda: sum(any(e) for e in efforts[-5:]) == 5, 60), sim.output() + policy.output()
        estop.publish(Bool(data=True))
        assert node.spin_until(lambda: sim_status and sim_status[-1]["estop"]["engaged"] and policy_status
                               and policy_status[-1]["estop"]["engaged"], 10), (sim_status[-1:], policy_status[-1:])
        engaged_at, answered_at = len(efforts), len(actions)
        assert node.spin_until(lambda: len(efforts) > engaged_at + 10, 10)
        assert all(not any(e) for e in efforts[engaged_at:])  # the safe command, every tick
        assert len(actions) == answered_at  # the policy answers nothing
        assert node.spin_until(lambda: policy_status[-1]["rejected"].get("estop"), 10)

        def call():
            assert reset.wait_for_service(timeout_sec=10)
            future = reset.call_async(Trigger.Request())
            assert node.spin_until(future.done, 10)
            return future.result()

        refused = call()  # the button is still down
        assert not refused.success and "still held" in refused.message
        # the first answer came; both servers must have taken the request before the release
        # (a node that took the release first would grant the reset: the topics are not ordered)
        assert node.spin_until(lambda: sim_status[-1]["estop"]["resets_refused"]
                               and policy_status[-1]["estop"]["resets_refused"], 10), (sim_status[-1], policy_status[-1])
        estop.publish(Bool(data=False))  # released on the topic: still engaged
        assert node.spin_until(lambda: not sim_status[-1]["estop"]["held"] and not policy_status[-1]["estop"]["held"],
                               10), (sim_status[-1], policy_status[-1])
        assert sim_status[-1]["estop"]["engaged"] and policy_status[-1]["estop"]["engaged"] and not any(efforts[-1])
        assert node.spin_until(lambda: call().success and not sim_status[-1]["estop"]["engaged"]
                               and not policy_status[-1]["estop"]["engaged"], 20), (sim_status[-1], policy_status[-1])
        # released: the policy drives again
        assert node.spin_until(lambda: len(actions) > answered_at and any(efforts[-1]), 20), policy.output()
    assert sim.stop() == 0


def test_the_policy_node_sends_its_controller_the_safe_command_when_its_states_stop(spawn, tmp_path):
    """A forward controller holds the last command: when the states stop coming (the arm's
    driver, the network), the policy node driving it sends zero torque once, fault latched."""
    from geometry_msgs.msg import PointStamped
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray

    from offline_rl_core.serving.checkpoint import save_checkpoint

    served = save_checkpoint(tmp_path / "policy.pt", _checkpoint(0))
    policy = spawn([sys.executable, "-m", "pusher_policy.node", "--ros-args", "-p", f"checkpoint:={served}"], "policy")
    torques, statuses = [], []
    with probe_node() as node:
        node.create_subscription(Float64MultiArray, "/effort_controller/commands",
                                 lambda m: torques.append(list(m.data)), 100)
        _latest_status(node, "policy", statuses)
        pubs = {t: node.create_publisher(m, f"/{t}", 10) for t, m in (
            ("pusher/target", PointStamped), ("pusher/fingertip", PointStamped), ("pusher/state", JointState))}
        assert node.spin_until(lambda: all(p.get_subscription_count() for p in pubs.values())
                               and node.count_publishers("/effort_controller/commands"), 60), policy.output()
        stamp = [START]

        def send_state():
            stamp[0] += TICK
            sec, nsec = divmod(stamp[0], 10**9)
            for topic in ("pusher/target", "pusher/fingertip"):
                msg = PointStamped()
                msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nsec
                msg.point.x, msg.point.y = 0.1, 0.05
                pubs[topic].publish(msg)
            msg = JointState(name=["shoulder", "elbow"], position=[0.3, -1.2], velocity=[0.5, -0.1])
            msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nsec
            pubs["pusher/state"].publish(msg)

        while not node.spin_until(lambda: len(torques) >= 3, 0.05):  # the policy drives
            send_state()
        answered = len(torques)
        send_state()  # the last state: answered with a nonzero torque
        assert node.spin_until(lambda: len(torques) > answered, 10) and any(torques[-1]), torques[-3:]
        # the states stop: the controller's next command is zero torque, and the fault is latched
        # (answers to states still in flight may come first)
        last = len(torques)
        assert node.spin_until(lambda: [0.0, 0.0] in torques[last:], 10), (torques[last:], policy.output())
        assert node.spin_until(lambda: statuses and statuses[-1]["faults"].get("watchdog"), 10), statuses[-1:]
        assert torques[-1] == [0.0, 0.0]  # and the zero is what the controller holds


def test_the_mux_refuses_an_effort_that_pushes_a_joint_further_beyond_its_limit(spawn, tmp_path):
    """Soft limits on the measured state: with the shoulder beyond its position limit, an
    action pushing it further out is refused (counted as beyond limits), one back is forwarded."""
    from sensor_msgs.msg import JointState

    from offline_rl_core.task.spec import load_task

    doc = load_task("pusher_reach").describe()
    doc["safety"] = {"position_limits": [[-0.5, 0.5], [-3.0, 3.0]]}
    task_file = tmp_path / "limited.yaml"
    task_file.write_text(json.dumps(doc))
    mux = spawn(ros2("run", "corrections", "mux", "--ros-args", "-p", f"task:={task_file}"), "mux")
    with probe_node() as node:
        commands = []
        node.create_subscription(JointState, "/pusher/command/policy", commands.append, 10)
        action_pub = node.create_publisher(JointState, "/policy/action", 10)
        state_pub = node.create_publisher(JointState, "/pusher/state", 10)
        assert node.spin_until(lambda: action_pub.get_subscription_count() and state_pub.get_subscription_count(), 60), \
            mux.output()

        def send(effort):
            state = JointState(name=["shoulder", "elbow"], position=[0.8, 0.0], velocity=[0.0, 0.0])
            state_pub.publish(state)  # the shoulder 0.3 rad beyond its high limit
            action = JointState(name=["shoulder", "elbow"], effort=effort)
            action.header.stamp.sec = 3
            action_pub.publish(action)

        for _ in range(50):  # until the mux has read a state: then outward is refused
            send([0.25, 0.0])
            if node.spin_until(lambda: "beyond limits" in mux.output(), 0.5):
                break
        assert "further beyond its position limits" in mux.output(), mux.output()
        commands.clear()
        for _ in range(20):
            send([-0.25, 0.0])
            if node.spin_until(lambda: commands, 0.5):
                break
        assert commands and list(commands[-1].effort) == [-0.25, 0.0], mux.output()
    assert mux.stop() == 0, mux.output()


def test_the_sim_refuses_torque_that_pushes_a_joint_further_beyond_its_limit(spawn, tmp_path):
    """The realtime sim, its shoulder starting beyond the task's high limit: full torque
    outward is refused (counted as beyond limits, nothing applied), torque back is applied."""
    from sensor_msgs.msg import JointState

    from offline_rl_core.nodes.sim_loop import SimLoop
    from offline_rl_core.task.spec import load_task

    probe = SimLoop("realtime", seed=0)
    start = float(probe.start_episode().position[0])  # the sim's first pose (reset seed 0)
    doc = load_task("pusher_reach").describe()
    doc["safety"] = {"position_limits": [[start - 3.0, start - 0.2], [-9.0, 9.0]]}
    task_file = tmp_path / "limited.yaml"
    task_file.write_text(json.dumps(doc))
    sim = spawn([sys.executable, "-m", "pusher_sim.node", "--ros-args", "-p", f"task:={task_file}"], "sim")
    efforts, statuses, states = [], [], []  # states: (shoulder position, shoulder effort) of each state
    high = start - 0.2

    def on_state(m):
        efforts.append(list(m.effort))
        states.append((m.position[0], m.effort[0]))

    with probe_node() as node:
        node.create_subscription(JointState, "/pusher/state", on_state, 100)
        _latest_status(node, "sim", statuses)
        command_pub = node.create_publisher(JointState, "/pusher/command/policy", 10)
        assert node.spin_until(lambda: command_pub.get_subscription_count() and efforts, 60), sim.output()

        def drive(effort, until, timeout=10.0):
            deadline = time.monotonic() + timeout
            while time.monotonic() < deadline:
                command_pub.publish(JointState(name=["shoulder", "elbow"], effort=effort))
                if node.spin_until(until, 0.02):
                    return True
            return False

        assert drive([1.0, 0.0], lambda: statuses and statuses[-1]["rejected"].get("beyond limits")), \
            sim.output() + str(statuses[-1:])
        # no outward torque was applied to the shoulder beyond its limit: a state's effort is what
        # the step from the state before it applied (under load the realtime episode may end
        # meanwhile, and the next one's pose, inside the limits, takes any torque)
        outward = [(i, before, effort) for i, ((before, _), (_, effort)) in enumerate(zip(states, states[1:]))
                   if before > high and effort > 0.0]
        assert not outward, outward[:5]
        assert drive([-1.0, 0.0], lambda: efforts[-1] == [-0.5, 0.0]), sim.output()  # back inside: taken
    assert sim.stop() == 0, sim.output()
