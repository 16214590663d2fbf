"""Recording over ROS equals `offline-rl collect`; an interrupted or killed recording is a
readable bag; passive recording takes every topic with its publishers' QoS, in the node's
namespace and on its clock."""

from __future__ import annotations

import re
import signal
import subprocess
import time

import numpy as np
import pytest
from rosbags.rosbag2 import Reader

from offline_rl_core.data.bag import read_transitions, repair_bag
from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.common.errors import UserError

from ros_helpers import probe_node, ros2, ros_env, spawn  # noqa: F401 - fixtures

pytestmark = pytest.mark.ros


def lockstep_sim(spawn, seed: int, episodes: int = 0, *extra):
    return spawn(
        ros2("run", "sim", "node", "--ros-args", "-p", "mode:=lockstep", "-p", f"seed:={seed}", "-p", f"episodes:={episodes}", *extra),
        "sim",
    )


def test_recording_is_bit_identical_to_collect(spawn, tmp_path):
    bag = tmp_path / "mix.db3"
    sim = lockstep_sim(spawn, seed=7, episodes=4)
    recorder = spawn(
        ros2("run", "recorder", "node", "--out", bag, "--episodes", 4, "--expert-frac", 0.5, "--seed", 7), "recorder"
    )
    assert recorder.wait(timeout=90) == 0, recorder.output()
    assert sim.wait(timeout=30) == 0, sim.output()  # the sim exits by itself after its episodes
    assert "wrote 400 transitions (4 episodes" in recorder.output()

    recorded = read_transitions(bag)
    reference = collect_transitions(4, 0.5, 7)
    assert np.array_equal(recorded.to_rows(), reference.to_rows())
    assert list(np.unique(recorded.source)) == [0, 1]
    # who acted is the command topic, as the sim reads it (no deprecated header.frame_id tag)
    assert "deprecated" not in sim.output(), sim.output()
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as reader:
        topics = {c.topic: c.msgcount for c in reader.connections if c.topic.startswith("/pusher/command")}
    assert set(topics) == {"/pusher/command/expert", "/pusher/command/random"} and sum(topics.values()) >= 400, topics


@pytest.mark.slow
@pytest.mark.parametrize("sig, name", [(signal.SIGINT, "cut.db3"), (signal.SIGTERM, "cut.mcap")])
def test_interrupted_recording_leaves_a_readable_bag(spawn, tmp_path, sig, name):
    bag = tmp_path / name
    lockstep_sim(spawn, seed=3)
    recorder = spawn(
        ros2("run", "recorder", "node", "--out", bag, "--episodes", 1000, "--expert-frac", 0.5, "--seed", 3), "recorder"
    )
    assert recorder.wait_for_output("recording 1000 episodes", timeout=30), recorder.output()
    assert wait_for_rows(bag, 150), recorder.output()  # on disk, into the second episode at least
    rc = recorder.stop(sig, timeout=20)
    assert rc == 0, f"exit {rc}: {recorder.output()}"
    match = re.search(r"interrupted; wrote (\d+) transitions", recorder.output())
    assert match, recorder.output()
    n = int(match.group(1))
    assert n > 0
    recorded = read_transitions(bag)
    assert len(recorded) == n  # every transition received is in the bag
    # 1000 episodes at expert-frac 0.5: all expert so far, so the prefix matches collect.
    episodes = int(recorded.episode.max()) + 1
    reference = collect_transitions(episodes, 1.0, 3)
    assert np.array_equal(recorded.to_rows(), reference.to_rows()[:n])


def rosbags_count(bag) -> int:
    """Messages rosbags' own reader sees in a bag being recorded (0 while it cannot open it)."""
    try:
        with Reader(bag) as reader:
            return sum(1 for _ in reader.messages())
    except Exception:  # noqa: BLE001 - any state of a bag being written: not yet readable
        return 0


def wait_until(predicate, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.05)
    return False


@pytest.mark.slow
@pytest.mark.parametrize("passive, name", [(False, "killed.mcap"), (True, "killed_dir")])
def test_sigkilled_recording_keeps_what_it_flushed(spawn, tmp_path, passive, name):
    """SIGKILL: the bag at --out holds a prefix of what was recorded, readable as it is
    (an MCAP cut inside a flush's two system calls after `bag repair`)."""
    bag = tmp_path / name
    if passive:
        lockstep_sim(spawn, 3, 0, "-p", "wait_for_subscribers:=2")
        driver = spawn(ros2("run", "recorder", "node", "--out", tmp_path / "driver.db3", "--episodes", 1000,
                            "--expert-frac", 0.5, "--seed", 3, "--ros-args", "-r", "__node:=driver"), "driver")
        args = ["--passive", "--topics", "pusher/transition", "pusher/state", "--flush-interval", 0.2]
    else:
        lockstep_sim(spawn, 3)
        args = ["--episodes", 1000, "--expert-frac", 0.5, "--seed", 3, "--flush-interval", 0.2]
    recorder = spawn(ros2("run", "recorder", "node", "--out", bag, *args), "recorder")
    assert recorder.wait_for_output("recording", timeout=30), recorder.output()
    assert wait_for_rows(bag, 200), recorder.output()  # two episodes flushed, then a kill at any moment after
    if passive:  # and a flush's checkpoint went through (one can be held back by this test's own reading)
        assert wait_until(lambda: rosbags_count(bag) > 0, 30), recorder.output()
    recorder.stop(signal.SIGKILL)
    try:
        recorded = read_transitions(bag)
    except UserError as exc:
        assert name.endswith(".mcap") and "bag repair" in str(exc), exc
        repair_bag(bag)
        recorded = read_transitions(bag)
    assert len(recorded) > 0
    if passive:
        # a directory opens in rosbags as left, but its metadata.yaml may be a flush behind or
        # ahead of what rosbags reads (rosbags opens sqlite immutable: a commit the kill left in
        # the WAL is not seen until repair folds it in); `bag repair` makes them agree
        with Reader(bag) as reader:
            assert sum(1 for _ in reader.messages()) > 0
        repair_bag(bag)
    with Reader(bag) as reader:
        assert reader.message_count == sum(1 for _ in reader.messages()) >= len(recorded) > 0
    episodes = int(recorded.episode.max()) + 1
    reference = collect_transitions(episodes, 1.0, 3).to_rows()
    rows = recorded.to_rows()
    first = int(np.flatnonzero((reference == rows[0]).all(axis=1))[0])  # passive: joined a little late
    assert np.array_equal(rows, reference[first : first + len(rows)])
    if passive:
        driver.stop(signal.SIGINT)


@pytest.mark.slow
def test_passive_records_every_topic_with_its_qos_namespace_and_clock(spawn, ros_env, tmp_path):
    """No --topics: every topic as it appears, with the publishers' offered QoS; relative
    names in the node's namespace; stamps on the node's clock: the sim's /clock with
    use_sim_time."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Bool, String

    bag = tmp_path / "all"
    ns = ["--ros-args", "-r", "__ns:=/arm2"]
    sim_start = 1_000_000  # s: the sim's clock starts here and counts 20 ms per step
    spawn(ros2("run", "sim", "node", *ns, "-p", "seed:=5", "-p", f"start_time:={sim_start}.0"), "sim")  # realtime
    recorder = spawn(ros2("run", "recorder", "node", *ns, "-p", f"out:={bag}", "-p", "passive:=true",
                          "-p", "use_sim_time:=true"), "recorder")  # settings as parameters, no flags
    with probe_node() as node:
        notes = node.create_publisher(String, "/arm2/notes", QoSProfile(
            depth=1, reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE))
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and "/arm2/notes" not in recorder.output():
            notes.publish(String(data="hello"))
            node.spin_for(0.1)
        for _ in range(10):
            notes.publish(String(data="hello"))
            node.spin_for(0.1)
        # the e-stop is recorded like any topic (reliable, transient local): the bag marks when it engaged
        estop = node.create_publisher(Bool, "/arm2/estop", QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        estop.publish(Bool(data=True))
        assert node.spin_until(lambda: "/arm2/estop" in recorder.output(), 30), recorder.output()
        node.spin_for(0.5)
        refused = subprocess.run(ros2("param", "set", "/arm2/recorder", "max_bag_size", "1000"),
                                 capture_output=True, text=True, env=ros_env)
        assert "sqlite3 minimum" in refused.stdout + refused.stderr, refused
    assert recorder.stop(signal.SIGINT) == 0, recorder.output()
    with Reader(bag) as reader:
        topics = {c.topic: c for c in reader.connections}
        assert {"/arm2/pusher/state", "/arm2/pusher/transition", "/arm2/pusher/target", "/arm2/notes", "/clock"} <= set(topics)
        assert topics["/arm2/notes"].ext.offered_qos_profiles[0].reliability.name == "BEST_EFFORT"
        assert topics["/arm2/pusher/transition"].ext.offered_qos_profiles[0].reliability.name == "RELIABLE"
        stamps = [stamp for _, stamp, _ in reader.messages([topics["/arm2/pusher/transition"]])]
        pressed = [raw for _, _, raw in reader.messages([topics["/arm2/estop"]])]
    assert len(pressed) == 1 and pressed[0][4] == 1  # std_msgs/Bool true, after the CDR header
    assert stamps and all(sim_start * 10**9 <= s < (sim_start + 3600) * 10**9 for s in stamps)  # sim time, not wall
    assert len(read_transitions(bag)) == len(stamps)  # the namespaced transition topic is the dataset


def wait_for_rows(bag, n: int, timeout: float = 60.0) -> bool:
    """Wait until the bag being recorded holds at least ``n`` transitions on disk."""
    def enough() -> bool:
        try:
            return len(read_transitions(bag)) >= n
        except UserError:
            return False  # nothing flushed yet
    return wait_until(enough, timeout)



@pytest.mark.slow
@pytest.mark.parametrize("task_name", ["pusher7_reach", "pusher_push"])
def test_on_sim_time_headerless_commands_are_stamped_in_the_tick_they_answer(spawn, tmp_path, task_name):
    """A task as a ros2_control arm in lockstep, driven by a controller that sends
    Float64MultiArray commands (no header), recorded passively on sim time: each command is
    stamped with the sim time of its arrival, not of the step it caused, so joining the raw
    topics by receive times (`offline-rl dataset`) gives `offline-rl collect`'s rows exactly
    (each episode's last step has no next state on the topics: the sim resets). pusher_push's
    puck, as a tracker publishes it, is recorded by discovery (not given a type): the sim holds
    its first state until the recorder reads it, which on sim time needs the recorder's
    discovery to run on wall time (no /clock comes before that state)."""
    import sys

    from offline_rl_core.data.raw_topics import transitions_from_topics
    from offline_rl_core.task.spec import load_task
    from ros_helpers import REPO

    task = load_task(task_name)
    bag = tmp_path / "raw.db3"
    command = task.command.topic  # the controller's commands topic (velocity_controller/commands)
    tracked = [p.topic for p in task.points if p.topic]
    recorder = spawn(ros2("run", "recorder", "node", "--passive", "--out", bag, "--topics", "joint_states", "goal",
                          command, *tracked, "--types", "joint_states:sensor_msgs/msg/JointState",
                          "goal:geometry_msgs/msg/PointStamped", f"{command}:std_msgs/msg/Float64MultiArray",
                          "--ros-args", "-p", "use_sim_time:=true"), "recorder")
    assert recorder.wait_for_output("recording passively", 60), recorder.output()
    # the controller sees the recorder in its graph, not whether the sim's writers have matched
    # it (on a loaded machine, seconds later): the sim holds its first state until they have
    sim = spawn(ros2("run", "sim", "node", "--ros-args", "-p", f"task:={task_name}", "-p", "mode:=lockstep",
                     "-p", "seed:=0", "-p", "episodes:=2", "-p", "republish_period:=0.2",
                     "-p", "wait_for_readers:=[recorder]"), "sim")
    controller = spawn([sys.executable, REPO / "ros_ws" / "tools" / "bench_probes" / "scripted_controller.py",
                        task_name, "2", "0.5", "0", "2", "0.02"], "controller")
    assert controller.wait(timeout=300) == 0, controller.output()
    assert sim.wait(timeout=60) == 0, sim.output()
    assert recorder.stop(signal.SIGINT) == 0, recorder.output()
    rows, report = transitions_from_topics(bag, task)
    reference = collect_transitions(2, 0.5, 0, task=task)
    kept = ~(reference.truncated | reference.terminated)
    assert len(rows) == int(kept.sum()) == 2 * (task.episodes.max_steps - 1), report
    for field in ("obs", "action", "reward", "next_obs", "episode", "step"):
        assert np.array_equal(getattr(rows, field), getattr(reference, field)[kept]), field
