"""Where ROS engineers look, over real DDS: /diagnostics from running nodes, the arm's markers
(the sim's and ``viz markers``' from joint states), a recording that keeps them, the
gamepad corrector through the mux (joint and Cartesian mode), and the Foxglove live view on loopback."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from ros_helpers import Diagnostics, level, probe_node, require_ros, ros2, ros_env, spawn  # noqa: F401 - fixtures

pytestmark = pytest.mark.ros


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    require_ros()
    from offline_rl_core.data.collect import collect_transitions
    from offline_rl_core.learners import TrainConfig, train
    from offline_rl_core.serving.checkpoint import save_checkpoint

    result = train(collect_transitions(2, 1.0, 0), TrainConfig(algo="bc", steps=20, hidden=16, batch_size=16), 0)
    return save_checkpoint(tmp_path_factory.mktemp("ckpt") / "policy.pt", result.checkpoint)


def test_sim_and_policy_report_on_diagnostics_and_warn_on_refused_states(spawn, checkpoint):
    from sensor_msgs.msg import JointState

    sim = spawn(ros2("run", "sim", "node"), "sim")
    policy = spawn(ros2("run", "policy", "node", "--checkpoint", checkpoint), "policy")
    with probe_node("diag_probe") as node:
        diag = Diagnostics(node)
        assert node.spin_until(lambda: {"/sim", "/policy"} <= set(diag.latest), 60), (sim.output(), policy.output())
        # a healthy pipeline: both OK, the policy answering the sim's states
        assert node.spin_until(lambda: level(diag.latest["/policy"]) == 0
                               and int(diag.values("/policy").get("answered", 0)) > 0, 30), diag.seen[-5:]
        sim_entry = diag.latest["/sim"]
        assert level(sim_entry) == 0 and sim_entry.hardware_id == "pusher_reach"
        assert sim_entry.message.startswith("realtime, episode ")
        assert {"episode", "episodes_done"} <= set(diag.values("/sim"))
        values = diag.values("/policy")
        assert values["weights_version"] == "0" and values["weights_age_s"] == "none"
        assert diag.latest["/policy"].message.startswith("serving weights version 0")

        # states the policy must refuse: WARN with the reason, then OK again once they stop
        bad = node.create_publisher(JointState, "/pusher/state", 10)
        assert node.spin_until(lambda: bad.get_subscription_count() > 0, 30)
        for _ in range(3):
            msg = JointState(name=["shoulder", "elbow"], position=[math.nan, 0.0], velocity=[0.0, 0.0])
            msg.header.stamp.sec = 1
            bad.publish(msg)
        assert node.spin_until(lambda: level(diag.latest["/policy"]) == 1, 30), diag.seen[-5:]
        warned = diag.latest["/policy"]
        assert "messages refused since the last report" in warned.message and "non-finite" in warned.message
        assert diag.values("/policy")["rejected/non-finite"] == "3"
        assert node.spin_until(lambda: level(diag.latest["/policy"]) == 0, 30), diag.seen[-5:]
        assert diag.values("/policy")["rejected/non-finite"] == "3"  # the count stays; the warning goes


def test_sim_markers_draw_the_arm_where_its_fingertip_is(spawn):
    from geometry_msgs.msg import PointStamped
    from visualization_msgs.msg import Marker, MarkerArray

    sim = spawn(ros2("run", "sim", "node", "--ros-args", "-p", "marker_period:=0.0"), "sim")
    with probe_node("markers_probe") as node:
        markers, tips, goals = {}, {}, {}
        key = lambda m: (m.header.stamp.sec, m.header.stamp.nanosec)  # noqa: E731
        node.create_subscription(MarkerArray, "/markers", lambda m: markers.setdefault(key(m.markers[0]), m), 10)
        node.create_subscription(PointStamped, "/pusher/fingertip", lambda m: tips.setdefault(key(m), m), 50)
        node.create_subscription(PointStamped, "/pusher/target", lambda m: goals.setdefault(key(m), m), 50)
        assert node.spin_until(lambda: len(set(markers) & set(tips) & set(goals)) >= 5, 60), sim.output()
        for stamp in sorted(set(markers) & set(tips) & set(goals))[:5]:
            by_ns = {m.ns: m for m in markers[stamp].markers}
            assert all(m.header.frame_id == "world" and m.action == Marker.ADD for m in by_ns.values())
            links = by_ns["links"]
            assert links.type == Marker.LINE_LIST and len(links.points) == 4
            tip, end = tips[stamp].point, links.points[-1]
            assert (end.x, end.y) == pytest.approx((tip.x, tip.y), abs=1e-9)
            tip_marker = by_ns["points/fingertip"].pose.position
            assert (tip_marker.x, tip_marker.y) == pytest.approx((tip.x, tip.y), abs=1e-12)
            goal, target = by_ns["goal"].pose.position, goals[stamp].point
            assert (goal.x, goal.y) == pytest.approx((target.x, target.y), abs=1e-6)


def test_viz_markers_of_a_real_arm_from_joint_states_alone(spawn):
    from sensor_msgs.msg import JointState
    from visualization_msgs.msg import MarkerArray

    # pusher7_reach: the task file's model, 3-D; joint_states in another order, with more joints
    viz = spawn(ros2("run", "viz", "markers", "--ros-args", "-p", "task:=pusher7_reach",
                     "-p", "marker_period:=0.0"), "viz")
    from offline_rl_core.nodes.arm_markers import ArmMarkers
    from offline_rl_core.task.envs import task_model
    from offline_rl_core.task.spec import load_task

    task = load_task("pusher7_reach")
    q = np.linspace(-0.4, 0.4, len(task.state.joints))
    expected = {m.ns: m for m in ArmMarkers(task, task_model(task)).markers(q)}
    with probe_node("viz_probe") as node:
        got: list = []
        node.create_subscription(MarkerArray, "/markers", got.append, 10)
        pub = node.create_publisher(JointState, "/joint_states", 10)
        assert node.spin_until(lambda: pub.get_subscription_count() > 0, 60), viz.output()
        names = list(reversed(task.state.joints)) + ["gripper"]
        msg = JointState(name=names, position=[float(v) for v in reversed(q)] + [0.0])  # no velocities
        msg.header.stamp.sec = 5
        assert node.spin_until(lambda: (pub.publish(msg), got)[1], 20), viz.output()
        by_ns = {m.ns: m for m in got[-1].markers}
        points = [(p.x, p.y, p.z) for p in by_ns["links"].points]
        np.testing.assert_allclose(points, expected["links"].points, atol=1e-12)
        assert got[-1].markers[0].header.stamp.sec == 5
        tip = by_ns["points/fingertip"].pose.position
        np.testing.assert_allclose((tip.x, tip.y, tip.z), expected["points/fingertip"].position, atol=1e-12)


def test_a_passive_recording_of_every_topic_keeps_markers_and_diagnostics_and_every_reader_reads_it(
        spawn, tmp_path):
    """Recordings keep the arm's markers and /diagnostics (sqlite3 and MCAP), the bag's readers
    read such a bag as any other, and --exclude-topic-types leaves them out."""
    from sensor_msgs.msg import JointState

    from offline_rl_core.data.bag import read_transitions
    from offline_rl_core.data.bag.info import bag_info
    from offline_rl_core.data.raw_topics import transitions_from_topics
    from rosbags.highlevel import AnyReader

    bags = {"db3": tmp_path / "session.db3", "mcap": tmp_path / "session.mcap", "lean": tmp_path / "lean.db3"}
    excluded = ["--exclude-topic-types", "visualization_msgs/msg/MarkerArray", "diagnostic_msgs/msg/DiagnosticArray"]
    recorders = [spawn(ros2("run", "recorder", "node", "--passive", "--episodes", "1", "--out", bag,
                            *(excluded if name == "lean" else ()), "--ros-args", "-r", f"__node:=rec_{name}"),
                       f"recorder_{name}") for name, bag in bags.items()]
    with probe_node("rec_probe") as node:
        commands = node.create_publisher(JointState, "/pusher/command/policy", 10)

        def answer(state):  # a policy, so the raw topics join into transitions
            out = JointState(name=["shoulder", "elbow"], effort=[0.3, -0.2])
            out.header.stamp = state.header.stamp
            commands.publish(out)
        node.create_subscription(JointState, "/pusher/state", answer, 10)
        # the recorders subscribe to what discovery finds: every one has this policy's topic
        # before the sim starts, and the sim's first tick waits until each reads the state, so
        # the episode (two seconds) is not over before they hear its commands and markers
        assert node.spin_until(lambda: commands.get_subscription_count() >= 3, 60), [r.output() for r in recorders]
        sim = spawn(ros2("run", "sim", "node", "--ros-args", "-p", "mode:=realtime", "-p", "episodes:=1",
                         "-p", "wait_for_subscribers:=3", "-p", "wait_for_readers:=[rec_db3, rec_mcap, rec_lean]"),
                    "sim")
        assert node.spin_until(lambda: all(r.poll() is not None for r in recorders), 120), \
            [r.output() for r in recorders]
    assert [r.poll() for r in recorders] == [0, 0, 0], [r.output() for r in recorders]
    assert sim.wait(timeout=30) == 0

    for name in ("db3", "mcap"):
        bag = bags[name]
        with AnyReader([bag]) as reader:
            topics = {c.topic: c for c in reader.connections}
            assert {"/pusher/transition", "/markers", "/diagnostics"} <= set(topics), (name, sorted(topics))
            markers = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages([topics["/markers"]])]
        assert markers and {m.ns for m in markers[-1].markers} >= {"links", "joints", "goal"}, name
        assert len(read_transitions(bag)) == 100, name
        info = {t.name: t for t in bag_info(bag).topics}
        assert info["/markers"].msgtype == "visualization_msgs/msg/MarkerArray"
        assert info["/markers"].count == len(markers)
        data, report = transitions_from_topics(bag, "pusher_reach")
        assert len(data) > 0 and report.episodes >= 1, (name, report.format())
    with AnyReader([bags["lean"]]) as reader:
        topics = {c.topic for c in reader.connections}
    assert "/pusher/transition" in topics and "/sim/status" in topics, topics
    assert "/markers" not in topics and "/diagnostics" not in topics, topics
    assert len(read_transitions(bags["lean"])) == 100


def test_gamepad_takes_over_through_the_mux_and_labels_episodes(spawn):
    from sensor_msgs.msg import JointState, Joy
    from std_msgs.msg import Float32MultiArray, String

    from offline_rl_core.data.transitions import SOURCE_HUMAN, SOURCE_POLICY, Layout

    lock = ["-p", "mode:=lockstep"]
    sim = spawn(ros2("run", "sim", "node", "--ros-args", *lock), "sim")
    mux = spawn(ros2("run", "corrections", "mux", "--ros-args", *lock, "-p", "require_teleop:=true"), "mux")
    corrector = spawn(ros2("run", "corrections", "corrector", "--mode", "gamepad"), "corrector")
    layout = Layout(8, 2)
    with probe_node("pad_probe") as node:
        human, policy_cmds, labels, sources = [], [], [], []
        node.create_subscription(JointState, "/pusher/command/human", human.append, 50)
        node.create_subscription(JointState, "/pusher/command/policy", policy_cmds.append, 50)
        node.create_subscription(String, "/episode_label", lambda m: labels.append(json.loads(m.data)), 10)
        node.create_subscription(Float32MultiArray, "/pusher/transition",
                                 lambda m: sources.append(int(m.data[layout.slices["source"]][0])), 100)
        joy_pub = node.create_publisher(Joy, "/joy", 10)
        action_pub = node.create_publisher(JointState, "/policy/action", 10)

        # the probe is the policy: it answers every state with a small fixed action
        def answer(state):
            out = JointState(name=["shoulder", "elbow"], effort=[0.1, 0.1])
            out.header.stamp = state.header.stamp
            action_pub.publish(out)
        node.create_subscription(JointState, "/pusher/state", answer, 10)

        def pad(axes, buttons):
            msg = Joy(axes=[float(a) for a in axes], buttons=list(buttons))
            joy_pub.publish(msg)

        assert node.spin_until(lambda: joy_pub.get_subscription_count() > 0 and len(policy_cmds) >= 5, 60), \
            (sim.output(), mux.output(), corrector.output())
        assert human == [] and list(policy_cmds[-1].effort) == pytest.approx([0.1, 0.1])

        # LB held, left stick right, right stick left: the person drives
        axes, held = [-0.5, 0.0, 0.75, 0.0, 0.0, 0.0], [0] * 9 + [1, 0]
        assert node.spin_until(lambda: (pad(axes, held), len(human) >= 5)[1], 30), corrector.output()
        assert list(human[-1].effort) == pytest.approx([0.5, -0.75])
        assert node.spin_until(lambda: SOURCE_HUMAN in sources, 10)

        # released: the policy has the arm again
        n_policy = len(policy_cmds)
        assert node.spin_until(lambda: (pad(axes, [0] * 11), len(policy_cmds) >= n_policy + 5)[1], 30)
        # the sim's transitions come a step behind the mux's commands, on another topic
        assert node.spin_until(lambda: sources[-1] == SOURCE_POLICY, 10), sources[-10:]

        # A, then B: one label per press
        for buttons in ([1] + [0] * 10, [0] * 11, [0, 1] + [0] * 9, [0] * 11):
            pad(axes, buttons)
            node.spin_for(0.1)
        assert node.spin_until(lambda: len(labels) >= 2, 10), corrector.output()
        assert labels == [{"label": "success"}, {"label": "failure"}]

        # the corrector's /diagnostics entry says what the pad did
        diag = Diagnostics(node)
        assert node.spin_until(lambda: "/corrector" in diag.latest, 10)
        values = diag.values("/corrector")
        assert values["mode"] == "gamepad" and values["labels/success"] == "1" and values["labels/failure"] == "1"


def test_gamepad_in_cartesian_mode_moves_the_fingertip_the_sticks_way_through_the_mux(spawn):
    from geometry_msgs.msg import PointStamped
    from sensor_msgs.msg import JointState, Joy

    from ros_helpers import REPO

    mapping = REPO / "ros_ws" / "src" / "corrections" / "config" / "gamepad_xbox_cartesian.yaml"
    lock = ["-p", "mode:=lockstep"]
    sim = spawn(ros2("run", "sim", "node", "--ros-args", *lock), "sim")
    mux = spawn(ros2("run", "corrections", "mux", "--ros-args", *lock, "-p", "require_teleop:=true"), "mux")
    corrector = spawn(ros2("run", "corrections", "corrector", "--mode", "gamepad", "--gamepad", mapping), "corrector")
    with probe_node("cartesian_probe") as node:
        human, tips = [], []
        node.create_subscription(JointState, "/pusher/command/human", human.append, 50)
        node.create_subscription(PointStamped, "/pusher/fingertip", lambda m: tips.append((m.point.x, m.point.y)), 50)
        joy_pub = node.create_publisher(Joy, "/joy", 10)
        action_pub = node.create_publisher(JointState, "/policy/action", 10)

        def answer(state):  # the probe is the policy: no torque
            out = JointState(name=["shoulder", "elbow"], effort=[0.0, 0.0])
            out.header.stamp = state.header.stamp
            action_pub.publish(out)
        node.create_subscription(JointState, "/pusher/state", answer, 10)

        def pad(axes, buttons):
            joy_pub.publish(Joy(axes=[float(a) for a in axes], buttons=list(buttons)))

        assert node.spin_until(lambda: joy_pub.get_subscription_count() > 0 and len(tips) >= 5, 60), \
            (sim.output(), mux.output(), corrector.output())
        # LB held, left stick right: the fingertip goes +x
        axes, held = [-1.0, 0.0, 0.0, 0.0, 0.0, 0.0], [0] * 9 + [1, 0]
        assert node.spin_until(lambda: (pad(axes, held), len(human) >= 1)[1], 30), corrector.output()
        start = np.array(tips[-1])
        assert node.spin_until(lambda: (pad(axes, held), len(human) >= 20)[1], 30), corrector.output()
        moved = np.array(tips[-1]) - start
    assert moved[0] > 0.01 and abs(moved[1]) < 0.5 * moved[0], moved
    efforts = np.array([m.effort for m in human])
    assert np.all(np.isfinite(efforts)) and np.all(np.abs(efforts) <= 1.0)


def test_live_view_streams_markers_and_state_to_a_websocket_client_on_loopback(spawn):
    pytest.importorskip("foxglove", reason="the viz extra (foxglove-sdk) is not installed")
    ws_client = pytest.importorskip("websockets.sync.client")
    import re
    import struct
    import time

    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import JointState
    from visualization_msgs.msg import MarkerArray

    sim = spawn(ros2("run", "sim", "node"), "sim")
    view = spawn(ros2("run", "viz", "live_view", "--port", "0"), "live_view")
    assert view.wait_for_output("live view on ws://", 60), view.output()
    url = re.search(r"live view on (ws://127\.0\.0\.1:\d+)", view.output()).group(1)
    wanted = {"/markers": MarkerArray, "/pusher/state": JointState}
    # connect once the view streams both: a channel the SDK adds while a client connects can be
    # advertised to it and yet unknown to its subscribe
    for topic in wanted:
        assert view.wait_for_output(f"streaming {topic} (", 60), view.output()
    # the SDK speaks the protocol as foxglove.sdk.v1 (foxglove.websocket.v1 before it)
    with ws_client.connect(url, subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"], open_timeout=30) as ws:
        channels, got, statuses = {}, {}, []

        def subscribe(advertised):  # subscription id = channel id
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": c["id"], "channelId": c["id"]} for c in advertised]}))

        deadline = time.monotonic() + 60
        while len(got) < len(wanted) and time.monotonic() < deadline:
            frame = ws.recv(timeout=max(deadline - time.monotonic(), 0.1))
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg["op"] == "unadvertise":  # as any client must: a channel re-advertised is subscribed again
                    for topic in [t for t, c in channels.items() if c["id"] in msg["channelIds"]]:
                        del channels[topic]
                elif msg["op"] == "status":
                    statuses.append(msg.get("message"))
                    # the SDK can answer a subscribe that raced its own advertise as if the channel
                    # were unknown (it is advertised, not unadvertised): subscribe to it again
                    unknown = re.search(r"Unknown channel ID: (\d+)", msg.get("message", ""))
                    ours = [c for c in channels.values() if unknown and c["id"] == int(unknown.group(1))]
                    if ours:
                        subscribe(ours)
                elif msg["op"] == "advertise":
                    new = [c for c in msg["channels"] if c["topic"] in wanted and c["topic"] not in channels]
                    for c in new:
                        assert c["encoding"] == "cdr" and c["schemaEncoding"] == "ros2msg"
                        channels[c["topic"]] = c
                    if new:
                        subscribe(new)
                continue
            assert frame[0] == 0x01  # message data
            sub_id, _stamp = struct.unpack_from("<IQ", frame, 1)
            topic = next(t for t, c in channels.items() if c["id"] == sub_id)
            got[topic] = deserialize_message(bytes(frame[13:]), wanted[topic])
    assert set(got) == set(wanted), (sorted(channels), statuses, view.output()[-2000:], sim.output()[-2000:])
    assert channels["/markers"]["schemaName"] == "visualization_msgs/msg/MarkerArray"
    assert "MSG: geometry_msgs/Point" in channels["/markers"]["schema"]  # with its dependencies, as MCAP has it
    assert {m.ns for m in got["/markers"].markers} >= {"links", "joints", "points/fingertip", "goal"}
    assert list(got["/pusher/state"].name) == ["shoulder", "elbow"]
