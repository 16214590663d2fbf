"""Success labels at run time, over real DDS: a person's key labels the episode, the sim ends
it, and the passive recorder keeps the label in the bag for the episode it labels."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import time

import numpy as np
import pytest

from offline_rl_core.data.bag import read_transitions
from offline_rl_core.data.episode_labels import episode_labels
from offline_rl_core.data.transitions import Layout
from offline_rl_core.task.spec import BUILTIN_DIR, load_task

from ros_helpers import REPO, Diagnostics, probe_node, ros2, ros_env, spawn  # noqa: F401 - fixtures

pytestmark = pytest.mark.ros

LAYOUT = Layout(8, 2)  # pusher_reach
MAX_STEPS = 100


def field(msg, name: str, layout: Layout = LAYOUT) -> float:
    return float(np.asarray(msg.data, np.float32)[layout.slices[name]][0])


def episode_ends(data, episode: int) -> tuple[int, bool, bool]:
    """(steps, terminated, truncated) of an episode's last transition in a bag's data."""
    rows = np.flatnonzero(data.episode == episode)
    last = rows[np.argmax(data.step[rows])]
    return int(data.step[last]) + 1, bool(data.terminated[last]), bool(data.truncated[last])


def recorded(bag, topic: str) -> int:
    """Messages on ``topic`` in the bag being recorded, as flushed so far."""
    from offline_rl_core.common.errors import UserError
    from offline_rl_core.data.bag.reader import open_bag

    try:
        with open_bag(bag) as reader:
            return sum(c.msgcount for c in reader.connections if c.topic == topic)
    except UserError:
        return 0  # nothing flushed yet


def test_a_key_labels_the_episode_the_realtime_sim_ends_it_and_the_bag_keeps_it(spawn, ros_env, tmp_path):
    from std_msgs.msg import Float32MultiArray, String

    bag = tmp_path / "session.db3"
    # the push task with episodes no time limit ends within the test: only the label can end episode 0
    task = tmp_path / "push_long.yaml"
    task.write_text(re.sub(r"max_steps: *\d+", "max_steps: 50000", (BUILTIN_DIR / "pusher_push.yaml").read_text(), 1)
                    .replace("name: pusher_push", "name: push_long", 1)
                    .replace("model: pusher_push.xml", f"model: {BUILTIN_DIR / 'pusher_push.xml'}", 1))
    spec = load_task(task)
    assert spec.episodes.max_steps == 50000
    layout = Layout(spec.obs_dim, spec.act_dim)

    def at(msg, name):
        return field(msg, name, layout)

    # realtime: it steps on its own (the safe command held)
    sim = spawn(ros2("run", "sim", "node", "--ros-args", "-p", f"task:={task}"), "sim")
    recorder = spawn(ros2("run", "recorder", "node", "--passive", "--out", bag), "recorder")  # every topic
    # the person: the keyboard corrector on a pseudo-terminal
    master, slave = os.openpty()
    log = open(tmp_path / "corrector.log", "w")
    corrector = subprocess.Popen(ros2("run", "corrections", "corrector", "--mode", "keyboard", "--task", task),
                                 stdin=slave, stdout=log, stderr=subprocess.STDOUT, env=ros_env, cwd=REPO)
    os.close(slave)
    try:
        with probe_node("label_probe") as node:
            rows, labels = [], []
            node.create_subscription(Float32MultiArray, "/pusher/transition", rows.append, 1000)
            node.create_subscription(String, "/episode_label", lambda m: labels.append(json.loads(m.data)), 10)
            diag = Diagnostics(node)

            def readers() -> int:  # who hears the corrector's labels: the sim, the recorder and this probe
                return int(diag.values("/corrector").get("label_readers", 0)) if "/corrector" in diag.latest else 0

            assert node.spin_until(lambda: readers() >= 3, 60), (readers(), (tmp_path / "corrector.log").read_text())
            # the corrector's writers matched on its side is not the recorder's side matched: wait until the
            # recorder has heard the corrector (its answers in the bag on disk)
            assert node.spin_until(lambda: recorded(bag, "/teleop/action") > 0, 60), recorder.output()
            # and the sim's steps: a label the bag holds before any transition names no episode
            assert node.spin_until(lambda: recorded(bag, "/pusher/transition") > 0, 60), recorder.output()
            assert node.spin_until(lambda: rows, 30), sim.output()
            episode = 0
            os.write(master, b"y")  # success
            assert node.spin_until(lambda: labels and any(at(r, "terminated") for r in rows), 10), \
                (labels, sim.output())
            assert labels == [{"label": "success"}]
            (last,) = [r for r in rows if at(r, "terminated")]
            assert int(at(last, "episode")) == episode
            assert at(last, "success") == 1.0  # the person's word
            # the next episode follows at once
            assert node.spin_until(lambda: int(at(rows[-1], "episode")) == episode + 1, 10)
            assert f"episode {episode} labelled success: it ends at its next step" in sim.output()
    finally:
        os.write(master, b"q")  # the person quits: the terminal is restored
        try:
            assert corrector.wait(timeout=20) == 0
        finally:
            if corrector.poll() is None:
                corrector.kill()
                corrector.wait()
            os.close(master)
            log.close()
    assert recorder.stop(signal.SIGINT) == 0, recorder.output()
    assert episode_labels(bag) == {episode: True}
    assert episode_ends(read_transitions(bag), episode)[1:] == (True, False)


def test_a_lockstep_label_ends_only_the_episode_it_names(spawn, tmp_path):
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float32MultiArray, String

    bag = tmp_path / "labels.db3"
    summary = tmp_path / "sim.json"
    recorder = spawn(ros2("run", "recorder", "node", "--passive", "--episodes", 2, "--out", bag), "recorder")
    sim = spawn(ros2("run", "sim", "node", "--ros-args", "-p", "mode:=lockstep", "-p", "episodes:=2",
                     "-p", "wait_for_subscribers:=2", "-p", f"summary:={summary}"), "sim")
    with probe_node("lockstep_label_probe") as node:
        rows, states = [], []
        node.create_subscription(Float32MultiArray, "/pusher/transition", rows.append, 1000)
        node.create_subscription(JointState, "/pusher/state", states.append, 10)
        command_pub = node.create_publisher(JointState, "/pusher/command/policy", 10)
        label_pub = node.create_publisher(String, "/episode_label", 10)
        answered = set()

        def answer_latest():
            if states and (states[-1].header.stamp.sec, states[-1].header.stamp.nanosec) not in answered:
                state = states[-1]
                answered.add((state.header.stamp.sec, state.header.stamp.nanosec))
                answer((state.header.stamp.sec, state.header.stamp.nanosec))

        def answer(stamp):
            msg = JointState(name=["shoulder", "elbow"], effort=[0.2, -0.1])
            msg.header.stamp.sec, msg.header.stamp.nanosec = stamp
            command_pub.publish(msg)

        def run_until(predicate, timeout=60):
            return node.spin_until(lambda: (answer_latest(), predicate())[1], timeout)

        # the probe is the policy (a recorder and this probe: the sim's two transition readers)
        assert node.spin_until(lambda: states and label_pub.get_subscription_count() >= 2, 60), sim.output()
        # a few steps of episode 0, then the arm waits (lockstep: no new answer, no step) until
        # the recorder has heard this probe (its commands in the bag on disk), so it hears its
        # labels too; meanwhile the last answer goes again, which the sim ignores (stale)
        assert run_until(lambda: len(rows) >= 5), sim.output()
        sent_at = [0.0]

        def repeat_last_answer():
            if time.monotonic() - sent_at[0] > 0.2:
                answer(max(answered))
                sent_at[0] = time.monotonic()
            return recorded(bag, "/pusher/command/policy") > 0
        assert node.spin_until(repeat_last_answer, 60), sim.output()
        label_pub.publish(String(data=json.dumps({"label": "failure", "episode": 0})))
        # waits on the sim's word: 10 s ran out once on a machine loaded to 6
        assert node.spin_until(lambda: "episode 0 labelled failure: it ends" in sim.output(), 30), sim.output()
        assert run_until(lambda: any(int(field(r, "episode")) == 1 for r in rows))
        # episode 0 is over; a late word on it ends nothing (the bag keeps it: the person changed their mind)
        label_pub.publish(String(data=json.dumps({"label": "success", "episode": 0})))
        assert node.spin_until(lambda: "episode 0 labelled success (already over)" in sim.output(), 30)
        assert run_until(lambda: sim.poll() is not None, 120), sim.output()
    assert sim.wait(30) == 0 and recorder.wait(30) == 0, recorder.output()
    data = read_transitions(bag)
    steps0, terminated0, truncated0 = episode_ends(data, 0)
    assert steps0 < MAX_STEPS and (terminated0, truncated0) == (False, True)  # a failure: the person stopped it
    assert episode_ends(data, 1)[0] == MAX_STEPS  # episode 1 ran to its time limit
    assert episode_labels(bag) == {0: True}  # the later label of episode 0 replaces the earlier
    result = json.loads(summary.read_text())
    assert result["episodes"] == 2 and result["labelled"] == 1


def test_a_message_that_is_no_label_is_refused_and_counted_on_the_sims_status(spawn):
    from std_msgs.msg import String

    sim = spawn(ros2("run", "sim", "node", "--ros-args", "-p", "mode:=lockstep"), "sim")
    with probe_node("bad_label_probe") as node:
        statuses = []
        node.create_subscription(String, "/sim/status", lambda m: statuses.append(json.loads(m.data)), 10)
        label_pub = node.create_publisher(String, "/episode_label", 10)
        assert node.spin_until(lambda: label_pub.get_subscription_count() >= 1, 60), sim.output()
        label_pub.publish(String(data="great"))
        label_pub.publish(String(data=json.dumps({"label": "success", "episode": 3})))  # not yet begun
        assert node.spin_until(lambda: statuses and statuses[-1]["rejected"].get("bad label") == 2, 10), \
            (statuses[-1:], sim.output())
        assert statuses[-1]["episode"] == 0 and statuses[-1]["labelled"] == 0
    assert "episode_label: a label is a JSON object" in sim.output()
