"""Nodes survive bad input: the policy node, the sim, the corrections mux and the online
learner each get 10,000 fuzzed messages on every topic they subscribe to, as real
processes on a private DDS domain.

Each test sends its fuzz (tests/fuzz_messages.py, seeded) in rounds of at most 9 messages
per topic, closed by a good message whose answer proves the node has read the round
(DDS keeps messages of one writer in order, and 10 fit the node's queue), then a burst
faster than the node answers. It checks that the node keeps running, publishes nothing
non-finite or out of range, counts every refused message by the reason the fuzz case
names (its ``~/status``), warns about them at a throttled rate, still answers good input
correctly afterwards, and that its memory (VmRSS) stays flat.
"""

from __future__ import annotations

import array
import json
import math
import os
import shutil
import sys
import time
from collections import Counter

import numpy as np
import pytest

from fuzz_messages import (JOINT_KINDS, NS, POINT_KINDS, TRANSITION_KINDS, WEIGHTS_KINDS, bad_stamp,
                           broken_checkpoints, broken_weights, command_case, flip_in_tensor_data, joint_case,
                           point_case, transition_case, weights_case)
from ros_helpers import probe_node, require_ros, ros_env, spawn  # noqa: F401 - fixtures

pytestmark = pytest.mark.ros

MESSAGES = 10_000  # per topic
ROUND = 9  # fuzzed messages per topic before a round's closing message (the node's queue holds 10)
TICK = NS // 50
START = 1_700_000_000 * NS
RSS_SLACK_KIB = 4 * 1024  # growth allowed between the first rounds and the end: a small constant
# the learner trains while it is fuzzed: torch's allocator takes a few more MiB for its pools as it does
LEARNER_RSS_SLACK_KIB = 8 * 1024
DEEP = 5000  # the probe's own queues: it must not drop what the node publishes
# s: a node taking the rounds' messages in, each counted by its reason (a loaded CI machine took over 10)
ROUNDS_COUNTED_S = 30.0


# ------------------------------------------------------------------ shared pieces
@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    """Two tiny checkpoints whose actions differ."""
    require_ros()
    from offline_rl_core.data.bag import write_transitions
    from offline_rl_core.data.collect import collect_transitions
    from offline_rl_core.learners import TrainConfig
    from offline_rl_core.runs.training_run import run_training

    root = tmp_path_factory.mktemp("fuzz_ckpt")
    write_transitions(root / "expert.db3", collect_transitions(2, 1.0, 0))
    cfg = TrainConfig(algo="bc", steps=30, hidden=16, batch_size=32, log_every=10)
    quiet = dict(eval_episodes=0, progress=None, log=lambda s: None)
    return {"bag": root / "expert.db3",
            "a": run_training([str(root / "expert.db3")], cfg, 0, root / "a", **quiet) / "policy.pt",
            "b": run_training([str(root / "expert.db3")], cfg, 1, root / "b", **quiet) / "policy.pt"}


def rss_kib(pid: int) -> int:
    with open(f"/proc/{pid}/status") as f:
        return int(next(line for line in f if line.startswith("VmRSS:")).split()[1])


class Status:
    """A node's ``~/status`` as the probe hears it."""

    def __init__(self, node, name: str):
        from std_msgs.msg import String

        self.node, self.seen = node, []
        node.create_subscription(String, f"/{name}/status", lambda m: self.seen.append(json.loads(m.data)), 10)

    def wait(self, predicate, timeout: float = 10.0) -> dict | None:
        """The first status published from now on that satisfies ``predicate``."""
        start = len(self.seen)
        ok = self.node.spin_until(lambda: any(predicate(s) for s in self.seen[start:]), timeout)
        return next(s for s in self.seen[start:] if predicate(s)) if ok else None


def stamp_msg(header, stamp_ns: int, bad=None) -> None:
    if bad is not None:
        header.stamp.sec, header.stamp.nanosec = bad
    else:
        header.stamp.sec, header.stamp.nanosec = stamp_ns // NS, stamp_ns % NS


def joint_msg(fields: dict, stamp_ns: int, rng):
    from sensor_msgs.msg import JointState

    msg = JointState(name=list(fields["name"]))
    for f in ("position", "velocity", "effort"):
        if f in fields:
            setattr(msg, f, [float(v) for v in fields[f]])
    stamp_msg(msg.header, stamp_ns, bad_stamp(rng) if fields["bad_stamp"] else None)
    return msg


def point_msg(fields: dict, stamp_ns: int, rng):
    from geometry_msgs.msg import PointStamped

    msg = PointStamped()
    msg.point.x, msg.point.y = fields["xy"]
    stamp_msg(msg.header, stamp_ns, bad_stamp(rng) if fields["bad_stamp"] else None)
    return msg


def warning_lines(log: str) -> list[str]:
    return [line for line in log.splitlines() if "ignoring " in line and " so far" in line]


def assert_counted_and_throttled(status: dict, expected: Counter, proc, allowed: dict | None = None) -> None:
    """Every refused message counted by its reason; each reason warned about, not each message."""
    rejected = Counter(status["rejected"])
    allowed = allowed or {}
    for reason, (low, high) in allowed.items():
        assert low <= rejected[reason] <= high, (reason, rejected[reason], low, high)
        rejected[reason] = expected[reason]
    assert rejected == expected, (dict(rejected), dict(expected))
    lines = warning_lines(proc.output())
    for reason in expected:
        assert any(f"({reason}: " in line for line in lines), (reason, lines[-5:])
    assert len(lines) < sum(expected.values()) / 10, len(lines)
    assert any("not shown" in line for line in lines)


class Sender:
    """Publishers that count what they sent, by topic."""

    def __init__(self, node):
        self.node, self.pubs, self.sent = node, {}, Counter()

    def add(self, topic: str, msg_type, qos=10) -> None:
        self.pubs[topic] = self.node.create_publisher(msg_type, "/" + topic, qos)

    def send(self, topic: str, msg) -> None:
        self.pubs[topic].publish(msg)
        self.sent[topic] += 1

    def matched(self) -> bool:
        return all(p.get_subscription_count() > 0 for p in self.pubs.values())


# ------------------------------------------------------------------ the policy node
class StateStamps:
    """The stamps a fuzz round gives states, and what the node's stamp order makes of them
    (``offline_rl_core.nodes.pairing.StampOrder``: stale and far-future stamps are refused unless
    the next state confirms them; here no two refused stamps ever confirm each other)."""

    def __init__(self, newest: int):
        self.newest, self.stale_run, self.jumps = newest, 0, 0

    def admitted(self, stamp: int) -> int:
        self.newest, self.stale_run = stamp, 0
        return stamp

    def next(self) -> int:
        return self.admitted(self.newest + TICK)

    def stale(self) -> int:
        self.stale_run += 1  # each further back than the last: none confirms another
        return self.newest - self.stale_run * TICK

    def far(self, ahead: bool) -> int:
        self.jumps += 1  # 1000 s apart: none confirms another
        return self.newest + (10 + 1000 * self.jumps) * NS if ahead else self.newest - (10 + 1000 * self.jumps) * NS


@pytest.mark.slow
def test_policy_node_survives_fuzzed_states_targets_fingertips_and_weights(spawn, checkpoints, tmp_path):
    from geometry_msgs.msg import PointStamped
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float64MultiArray, MultiArrayDimension, String, UInt8MultiArray

    from offline_rl_core.task.pusher_reach import observation_from_joints
    from offline_rl_core.serving.weights import encode_weights
    from offline_rl_core.serving.checkpoint import load_checkpoint
    from offline_rl_core.serving.policy import load_policy
    from offline_rl_core.serving.signing import load_signer, make_session_keys

    served = tmp_path / "policy.pt"
    shutil.copy(checkpoints["a"], served)
    policy = {"a": load_policy(checkpoints["a"]), "b": load_policy(checkpoints["b"])}
    good = load_checkpoint(checkpoints["a"])
    keys = make_session_keys(tmp_path / "keys")
    signer = load_signer(keys.signing_key)
    weights = {"v1": encode_weights({**good, "weights_version": 1}, signer)}
    broken = broken_weights(good, signer)
    # lockstep: the test paces the states, and counts one controller command per state answered (no watchdog's)
    proc = spawn([sys.executable, "-m", "pusher_policy.node", "--ros-args", "-p", f"checkpoint:={served}",
                  "-p", "weights_topic:=learner/weights", "-p", f"weights_key:={keys.public_key}",
                  "-p", "mode:=lockstep"], "policy")
    rng = np.random.default_rng(13)
    actions, torques, provenance = [], [], {}
    expected = Counter()
    flips = 0
    obs_of: dict[int, np.ndarray] = {}
    with probe_node() as node:
        status = Status(node, "policy")
        node.create_subscription(JointState, "/policy/action", actions.append, DEEP)
        node.create_subscription(Float64MultiArray, "/effort_controller/commands", torques.append, DEEP)
        node.create_subscription(String, "/policy/provenance",
                                 lambda m: provenance.setdefault(json.loads(m.data)["stamp"], []).append(
                                     json.loads(m.data)["weights_version"]), DEEP)
        out = Sender(node)
        out.add("pusher/target", PointStamped)
        out.add("pusher/fingertip", PointStamped)
        out.add("pusher/state", JointState)
        out.add("learner/weights", UInt8MultiArray, QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                                                               durability=DurabilityPolicy.TRANSIENT_LOCAL))
        assert node.spin_until(lambda: out.matched() and node.count_publishers("/policy/action"), 30), proc.output()
        stamps = StateStamps(START)

        def weights_msg(label, data: bytes):
            msg = UInt8MultiArray(data=array.array("B", data))
            if label is not None:
                msg.layout.dim = [MultiArrayDimension(label=label, size=len(data), stride=1)]
            return msg

        def trio(stamp: int):
            """A good state with its target and fingertip; returns the observation it means."""
            q, qd = rng.uniform(-3, 3, 2), rng.uniform(-5, 5, 2)
            target, tip = rng.uniform(-0.2, 0.2, 2), rng.uniform(-0.2, 0.2, 2)
            out.send("pusher/target", point_msg({"xy": list(target), "bad_stamp": False}, stamp, rng))
            out.send("pusher/fingertip", point_msg({"xy": list(tip), "bad_stamp": False}, stamp, rng))
            out.send("pusher/state", joint_msg({"name": ["shoulder", "elbow"], "position": q, "velocity": qd,
                                                "bad_stamp": False}, stamp, rng))
            obs_of[stamp] = observation_from_joints(q, qd, target, tip)

        def close_round(version: int | None, timeout: float = 10.0) -> None:
            """Good states until one is answered (with weights ``version`` or newer)."""
            while True:
                stamp = stamps.next()
                trio(stamp)
                ok = node.spin_until(lambda: stamp in provenance, timeout)
                assert ok, f"no answer to {stamp} (node {'running' if proc.running() else 'dead'}):\n" + \
                    proc.output()[-3000:]
                if version is None or max(provenance[stamp]) >= version:
                    return

        # discovery can drop the very first messages: what the node took so far is the baseline
        deadline = time.monotonic() + 20
        while not provenance and time.monotonic() < deadline:
            stamp = stamps.next()
            trio(stamp)
            node.spin_until(lambda: stamp in provenance, 1.0)
        out.send("learner/weights", weights_msg("pusher-rl/weights", weights["v1"]))
        close_round(1)
        baseline = status.wait(lambda s: True)
        assert baseline is not None and not baseline["rejected"], baseline
        sent_before = Counter(baseline["messages"])
        out.sent = Counter()
        # answered while discovery was still matching topics: a state whose fingertip had not
        # come through yet is answered with forward kinematics (pairing.py), not the sent tip
        before_matched = set(provenance)
        rss_start = None
        version = 1
        rounds = 0
        while min(out.sent["pusher/state"], out.sent["learner/weights"]) < MESSAGES - 1000:
            rounds += 1
            if rounds == 20:
                rss_start = rss_kib(proc.pid)
            states, targets, tips = [], [], []  # (msg, expected reason) in the order sent
            while len(states) < ROUND - 1:
                kind = str(rng.choice(list(JOINT_KINDS) + ["stale", "future", "jump ahead", "jump back"]))
                if kind in ("stale", "future"):
                    case = joint_case(rng, "valid", ("position", "velocity"), 3.0)
                    stamp = stamps.stale() if kind == "stale" else stamps.far(True)
                    states.append((joint_msg(case.fields, stamp, rng), f"{kind} stamp"))
                elif kind.startswith("jump"):  # a restarted source: refused once, confirmed by the next
                    case = joint_case(rng, "valid", ("position", "velocity"), 3.0)
                    stamp = stamps.far(kind == "jump ahead")
                    msg = joint_msg(case.fields, stamp, rng)
                    states += [(msg, "future stamp" if kind == "jump ahead" else "stale stamp"), (msg, None)]
                    stamps.admitted(stamp)
                else:
                    case = joint_case(rng, kind, ("position", "velocity"), 3.0)
                    stamp = stamps.next() if case.expect is None else stamps.newest + 7
                    msg = joint_msg(case.fields, stamp, rng)
                    states.append((msg, case.expect))
                    if case.expect is None:
                        named = dict(zip(case.fields["name"] or ["shoulder", "elbow"],
                                         zip(case.fields["position"], case.fields["velocity"])))
                        q = [named["shoulder"][0], named["elbow"][0]]
                        qd = [named["shoulder"][1], named["elbow"][1]]
                        if rng.random() < 0.6 and len(targets) < ROUND:  # its target and fingertip come too
                            target, tip = rng.uniform(-0.2, 0.2, 2), rng.uniform(-0.2, 0.2, 2)
                            targets.append((point_msg({"xy": list(target), "bad_stamp": False}, stamp, rng), None))
                            tips.append((point_msg({"xy": list(tip), "bad_stamp": False}, stamp, rng), None))
                            obs_of[stamp] = observation_from_joints(q, qd, target, tip)
                    if rng.random() < 0.15:  # the same message twice
                        states.append(states[-1])
            for lst in (targets, tips):
                while len(lst) < ROUND:
                    case = point_case(rng, POINT_KINDS[int(rng.integers(len(POINT_KINDS)))])
                    stray = stamps.newest + int(rng.integers(-10**6, 10**6)) * NS + 7  # never a state's stamp
                    lst.append((point_msg(case.fields, stray, rng), case.expect))
            wmsgs = []
            for _ in range(ROUND):
                case = weights_case(rng, WEIGHTS_KINDS[int(rng.integers(len(WEIGHTS_KINDS)))], weights["v1"], broken)
                wmsgs.append((weights_msg(case.fields["label"], case.fields["data"]), case.expect))
            for i in range(ROUND):
                for topic, lst in (("pusher/target", targets), ("pusher/fingertip", tips), ("pusher/state", states),
                                   ("learner/weights", wmsgs)):
                    if i < len(lst):
                        msg, expect = lst[i]
                        out.send(topic, msg)
                        if expect == "bad weights?":
                            flips += 1
                        elif expect is not None:
                            expected[expect] += 1
            version += 1
            out.send("learner/weights", weights_msg("pusher-rl/weights",
                                                    encode_weights({**good, "weights_version": version}, signer)))
            close_round(version)
            assert proc.running(), proc.output()[-3000:]

        # every message of the rounds taken, every refusal counted by its reason
        st = status.wait(lambda s: Counter(s["messages"]) - sent_before == out.sent, ROUNDS_COUNTED_S)
        assert st is not None, (status.seen[-1], dict(out.sent))
        assert_counted_and_throttled(st, expected, proc, {"bad weights": (expected["bad weights"],
                                                                          expected["bad weights"] + flips)})
        # a burst faster than the node answers: good states, and garbage weights
        for _ in range(MESSAGES - out.sent["pusher/state"]):
            trio(stamps.next())
        for _ in range(MESSAGES - 1 - out.sent["learner/weights"]):
            out.send("learner/weights", weights_msg("pusher-rl/weights", rng.bytes(64)))
        final_version = version + 1  # the next version: weights only move forward a few at a time
        out.send("learner/weights", weights_msg("pusher-rl/weights", encode_weights(
            {**load_checkpoint(checkpoints["b"]), "weights_version": final_version}, signer)))
        close_round(final_version)
        rss_end = rss_kib(proc.pid)
        st = status.wait(lambda s: True)
        node.spin_for(0.2)

    assert proc.running(), proc.output()[-3000:]
    assert min(out.sent.values()) >= MESSAGES
    assert Counter(st["messages"]) - sent_before <= out.sent
    assert set(st["rejected"]) == set(expected)  # the burst's were unsigned weights
    # what it published: finite, in range, for states it took, the right policy's action
    # one controller command per state answered: a state taken twice is answered twice on
    # /policy/action, but a headerless command for it goes once (a lockstep arm would step twice)
    answered = [msg.header.stamp.sec * NS + msg.header.stamp.nanosec for msg in actions]
    assert actions and len(torques) == sum(1 for i, s in enumerate(answered) if i == 0 or s != answered[i - 1])
    for msg in actions:
        stamp = msg.header.stamp.sec * NS + msg.header.stamp.nanosec
        effort = np.array(msg.effort, np.float32)
        assert np.all(np.isfinite(effort)) and np.all(np.abs(effort) <= 1.0)
        assert stamp in obs_of, stamp
        if stamp in before_matched:
            continue
        which = "b" if max(provenance[stamp]) >= final_version else "a"
        assert np.array_equal(effort, policy[which].act(obs_of[stamp])), (stamp, which)
    for msg in torques:
        assert all(math.isfinite(t) and abs(t) <= 0.5 for t in msg.data)
    assert rss_end - rss_start < RSS_SLACK_KIB, (rss_start, rss_end)


# ------------------------------------------------------------------ the sim
COMMAND_TOPICS = {"pusher/command": 2, "pusher/command/expert": 0, "pusher/command/random": 1,
                  "pusher/command/policy": 2, "pusher/command/human": 3}


def _stamp(msg) -> int:
    return msg.header.stamp.sec * NS + msg.header.stamp.nanosec


def _rows(transitions) -> np.ndarray:
    return np.array([m.data for m in transitions], np.float32).reshape(len(transitions), -1)


@pytest.mark.slow
def test_sim_survives_fuzzed_commands_on_every_command_topic(spawn):
    """Lockstep: a command steps the arm only when it answers the current state; anything
    else on any of the five command topics is refused and counted."""
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Float32MultiArray

    from offline_rl_core.data.transitions import LAYOUT_SLICES

    proc = spawn([sys.executable, "-m", "pusher_sim.node", "--ros-args", "-p", "mode:=lockstep",
                  "-p", f"start_time:={START // NS}", "-p", "republish_period:=5.0"], "sim")
    rng = np.random.default_rng(17)
    states, transitions = [], []
    expected, sent_steps = Counter(), []  # sent_steps: (action, source) of every command that steps
    with probe_node() as node:
        status = Status(node, "sim")
        node.create_subscription(JointState, "/pusher/state", states.append, DEEP)
        node.create_subscription(Float32MultiArray, "/pusher/transition", transitions.append, DEEP)
        out = Sender(node)
        for topic in COMMAND_TOPICS:
            out.add(topic, JointState)
        assert node.spin_until(lambda: out.matched() and states, 30), proc.output()

        def step(topic: str, msg, action) -> None:
            """Send the command that answers the current state; wait for the next state."""
            before = _stamp(states[-1])
            out.send(topic, msg)
            sent_steps.append((action, COMMAND_TOPICS[topic]))
            assert node.spin_until(lambda: _stamp(states[-1]) != before, 10), proc.output()[-3000:]

        # discovery can drop the first messages: send until one steps; the baseline is what the node took
        deadline = time.monotonic() + 20
        while not transitions and time.monotonic() < deadline:
            msg = joint_msg({"name": ["shoulder", "elbow"], "effort": [0.0, 0.0], "bad_stamp": False},
                            _stamp(states[-1]), rng)
            out.send("pusher/command", msg)
            node.spin_until(lambda: transitions, 1.0)
        baseline = status.wait(lambda s: True)
        assert baseline is not None and not baseline["rejected"], baseline
        sent_before, out.sent, sent_steps = Counter(baseline["messages"]), Counter(), []
        first_transition = len(transitions)
        rss_start, rounds = None, 0
        topics = list(COMMAND_TOPICS)
        while min(out.sent[t] for t in topics) < MESSAGES - 1000:
            rounds += 1
            if rounds == 100:
                rss_start = rss_kib(proc.pid)
            topic = topics[rounds % len(topics)]
            current = _stamp(states[-1])
            for _ in range(ROUND - 1):
                case = command_case(rng, JOINT_KINDS[int(rng.integers(len(JOINT_KINDS)))])
                if case.expect is None:  # a good command, but for another state than the current one
                    offset = int(rng.integers(1, 500)) * TICK * (1 if rng.random() < 0.5 else -1)
                    out.send(topic, joint_msg(case.fields, current + offset, rng))
                    expected["future stamp" if offset > 0 else "stale stamp"] += 1
                else:
                    out.send(topic, joint_msg(case.fields, current, rng))
                    expected[case.expect] += 1
            case = command_case(rng, str(rng.choice(["valid", "reordered", "unnamed"])))
            named = dict(zip(case.fields["name"] or ["shoulder", "elbow"], case.fields["effort"]))
            action = np.clip(np.float32([named["shoulder"], named["elbow"]]), -1, 1)
            msg = joint_msg(case.fields, current, rng)
            step(topic, msg, action)
            if rng.random() < 0.1:  # the same command again, now for a state already stepped
                out.send(topic, msg)
                expected["stale stamp"] += 1
            assert proc.running(), proc.output()[-3000:]
        st = status.wait(lambda s: Counter(s["messages"]) - sent_before == out.sent, ROUNDS_COUNTED_S)
        assert st is not None, (status.seen[-1], dict(out.sent))
        assert_counted_and_throttled(st, expected, proc)
        # a burst on every topic faster than the sim takes it: commands for states long gone
        burst = {t: MESSAGES - out.sent[t] for t in topics}
        for i in range(max(burst.values())):
            for t in topics:
                if i < burst[t]:
                    out.send(t, joint_msg({"name": [], "effort": [0.1, 0.2], "bad_stamp": False}, START - NS, rng))
        step("pusher/command/human", joint_msg({"name": [], "effort": [0.5, -0.5], "bad_stamp": False},
                                               _stamp(states[-1]), rng), np.float32([0.5, -0.5]))
        rss_end = rss_kib(proc.pid)
        node.spin_until(lambda: len(transitions) - first_transition >= len(sent_steps), 10)
        st = status.wait(lambda s: True)
    assert proc.running(), proc.output()[-3000:]
    assert min(out.sent.values()) >= MESSAGES
    assert Counter(st["messages"]) - sent_before <= out.sent
    rows = _rows(transitions[first_transition:])
    # every step is one of the commands that answered a state, in order, with its source
    assert len(rows) == len(sent_steps)
    assert np.array_equal(rows[:, LAYOUT_SLICES["action"]], np.stack([a for a, _ in sent_steps]))
    assert rows[:, LAYOUT_SLICES["source"]].ravel().tolist() == [float(s) for _, s in sent_steps]
    assert np.all(np.isfinite(rows))
    for msg in states:
        assert all(math.isfinite(v) for v in [*msg.position, *msg.velocity, *msg.effort])
        assert all(abs(t) <= 0.5 for t in msg.effort)  # applied torque (N·m): within the motor gear
    assert rss_end - rss_start < RSS_SLACK_KIB, (rss_start, rss_end)


@pytest.mark.slow
def test_realtime_sim_survives_fuzzed_torques(spawn):
    """Realtime, torques on effort_topic (no stamps): bad ones are refused and counted, the
    held command is always a good one (torques beyond the motors' are refused, never clipped)."""
    from std_msgs.msg import Float32MultiArray, Float64MultiArray

    from offline_rl_core.data.transitions import LAYOUT_SLICES

    proc = spawn([sys.executable, "-m", "pusher_sim.node", "--ros-args",
                  "-p", "effort_topic:=effort_controller/commands"], "sim")
    rng = np.random.default_rng(19)
    transitions, expected = [], Counter()
    topic = "effort_controller/commands"
    with probe_node() as node:
        status = Status(node, "sim")
        node.create_subscription(Float32MultiArray, "/pusher/transition", transitions.append, DEEP)
        out = Sender(node)
        out.add(topic, Float64MultiArray)
        assert node.spin_until(lambda: out.matched() and transitions, 30), proc.output()

        def hold(torques) -> None:
            """Good torques; wait until a step has applied them."""
            action = np.clip(np.float32(np.asarray(torques) / 0.5), -1, 1)
            out.send(topic, Float64MultiArray(data=[float(t) for t in torques]))
            start = len(transitions)
            assert node.spin_until(lambda: any(np.array_equal(np.float32(m.data[8:10]), action)
                                               for m in transitions[start:]), 10), proc.output()[-3000:]

        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            try:
                hold(rng.uniform(-0.4, 0.4, 2))
                break
            except AssertionError:
                continue
        baseline = status.wait(lambda s: True)
        assert baseline is not None and not baseline["rejected"], baseline
        sent_before, out.sent = Counter(baseline["messages"]), Counter()
        rss_start, rounds = None, 0
        while out.sent[topic] < MESSAGES - 1000:
            rounds += 1
            if rounds == 50:
                rss_start = rss_kib(proc.pid)
            for _ in range(ROUND):
                kind = str(rng.choice(["nan", "inf", "huge", "empty", "short", "long"]))
                torques = list(rng.uniform(-0.5, 0.5, {"empty": 0, "short": 1, "long": 3}.get(kind, 2)))
                if kind in ("nan", "inf", "huge"):
                    torques[int(rng.integers(2))] = {"nan": math.nan, "inf": -math.inf, "huge": 1e38}[kind]
                out.send(topic, Float64MultiArray(data=[float(t) for t in torques]))
                expected[{"nan": "non-finite", "inf": "non-finite", "huge": "beyond limits"}.get(kind, "wrong length")] += 1
            hold(rng.uniform(-0.4, 0.4, 2))
        st = status.wait(lambda s: Counter(s["messages"]) - sent_before == out.sent, ROUNDS_COUNTED_S)
        assert st is not None, (status.seen[-1], dict(out.sent))
        assert_counted_and_throttled(st, expected, proc)
        for _ in range(MESSAGES - out.sent[topic]):  # a burst of NaN torques
            out.send(topic, Float64MultiArray(data=[math.nan, 0.0]))
        hold([0.2, -0.2])
        rss_end = rss_kib(proc.pid)
    assert proc.running(), proc.output()[-3000:]
    rows = _rows(transitions)
    assert np.all(np.isfinite(rows)) and np.all(np.abs(rows[:, LAYOUT_SLICES["action"]]) <= 1.0)
    assert rss_end - rss_start < RSS_SLACK_KIB, (rss_start, rss_end)


# ------------------------------------------------------------------ the corrections mux
@pytest.mark.slow
def test_mux_survives_fuzzed_policy_and_teleop_actions(spawn):
    """Lockstep, with a corrector present: only ever an action that came in for its stamp
    (clipped), never a refused one. (Stray stamps by the thousand go beyond the last 256
    decisions the mux remembers, so "one command per stamp" is the unit tests' business.)"""
    from sensor_msgs.msg import JointState

    proc = spawn([sys.executable, "-m", "pusher_corrections.mux", "--ros-args", "-p", "mode:=lockstep"], "mux")
    rng = np.random.default_rng(23)
    commands = []  # (source, msg)
    sent_actions = {"policy": {}, "human": {}}  # stamp -> clipped actions the test sent for it
    expected = Counter()
    with probe_node() as node:
        status = Status(node, "mux")
        for source in ("policy", "human"):
            node.create_subscription(JointState, f"/pusher/command/{source}",
                                     lambda m, s=source: commands.append((s, m)), DEEP)
        out = Sender(node)
        out.add("policy/action", JointState)
        out.add("teleop/action", JointState)
        assert node.spin_until(lambda: out.matched() and node.count_publishers("/pusher/command/policy"), 30), \
            proc.output()
        stamp = [START]

        def send(topic: str, case, stamp_ns: int) -> None:
            out.send(topic, joint_msg(case.fields, stamp_ns, rng))
            if case.expect is None and case.fields["effort"] and not case.fields["bad_stamp"]:
                named = dict(zip(case.fields["name"] or ["shoulder", "elbow"], case.fields["effort"]))
                action = np.clip(np.float32([named["shoulder"], named["elbow"]]), -1, 1)
                source = "policy" if topic == "policy/action" else "human"
                sent_actions[source].setdefault(stamp_ns, []).append(action)

        def close_round() -> None:
            """The policy's action for a new stamp and the corrector's yield: forwarded as the policy's."""
            while True:
                stamp[0] += TICK
                s = stamp[0]
                send("policy/action", command_case(rng, "valid"), s)
                send("teleop/action", command_case(rng, "empty", allow_empty=True), s)
                if node.spin_until(lambda: any(_stamp(m) == s for _, m in commands), 2.0):
                    return

        deadline = time.monotonic() + 20  # discovery can drop the first messages
        while not commands and time.monotonic() < deadline:
            close_round()
        baseline = status.wait(lambda s: True)
        assert baseline is not None and not baseline["rejected"], baseline
        sent_before, out.sent = Counter(baseline["messages"]), Counter()
        rss_start, rounds = None, 0
        while min(out.sent.values(), default=0) < MESSAGES - 1000:
            rounds += 1
            if rounds == 50:
                rss_start = rss_kib(proc.pid)
            for topic in ("policy/action", "teleop/action"):
                for _ in range(ROUND):
                    case = command_case(rng, JOINT_KINDS[int(rng.integers(len(JOINT_KINDS)))],
                                        allow_empty=topic == "teleop/action")
                    # good ones for stamps of their own (stray, stale or future): the rule decides them
                    send(topic, case, stamp[0] + int(rng.integers(-100, 100)) * TICK + 7)
                    if case.expect is not None:
                        expected[case.expect] += 1
            close_round()
            assert proc.running(), proc.output()[-3000:]
        st = status.wait(lambda s: Counter(s["messages"]) - sent_before == out.sent, ROUNDS_COUNTED_S)
        assert st is not None, (status.seen[-1], dict(out.sent))
        assert_counted_and_throttled(st, expected, proc)
        for topic in ("policy/action", "teleop/action"):  # a burst: good actions, each for a stamp of its own
            for _ in range(MESSAGES - out.sent[topic] - 1):
                stamp[0] += TICK
                send(topic, command_case(rng, "valid"), stamp[0])
        close_round()
        rss_end = rss_kib(proc.pid)
    assert proc.running(), proc.output()[-3000:]
    assert min(out.sent.values()) >= MESSAGES
    for source, msg in commands:  # only ever an action sent for that stamp, by that side (clipped)
        action = np.array(msg.effort, np.float32)
        assert np.all(np.isfinite(action)) and np.all(np.abs(action) <= 1.0)
        s = _stamp(msg)
        assert any(np.array_equal(action, a) for a in sent_actions[source].get(s, [])), (source, s, action)
    assert rss_end - rss_start < RSS_SLACK_KIB, (rss_start, rss_end)


# ------------------------------------------------------------------ the online learner
@pytest.mark.slow
def test_learner_survives_fuzzed_transitions(spawn, checkpoints, tmp_path):
    """Bad values, bad layouts, raw garbage: refused and counted, never trained on; the good
    transitions among them are learnt from and the weights it publishes stay finite."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Float32MultiArray, MultiArrayDimension

    from offline_rl_core.data.collect import collect_transitions
    from offline_rl_core.serving.policy import load_policy

    from offline_rl_core.serving.signing import make_session_keys

    rows = collect_transitions(3, 0.5, 1).to_rows()
    keys = make_session_keys(tmp_path / "keys")
    proc = spawn([sys.executable, "-m", "pusher_learner.node", "--bag", str(checkpoints["bag"]), "--out",
                  str(tmp_path / "learner"), "--publish-every", "50", "--batch-size", "32",
                  "--signing-key", str(keys.signing_key)], "learner")
    assert proc.wait_for_output("learning from", 60), proc.output()
    rng = np.random.default_rng(29)
    expected, good = Counter(), 0
    topic = "pusher/transition"
    with probe_node() as node:
        status = Status(node, "learner")
        out = Sender(node)
        out.add(topic, Float32MultiArray, QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
        assert node.spin_until(lambda: out.matched(), 30), proc.output()
        baseline = status.wait(lambda s: True)
        assert baseline is not None and not baseline["rejected"] and baseline["received"] == 0, baseline

        def message(case):
            if "raw" in case.fields:
                return case.fields["raw"]
            msg = Float32MultiArray(data=case.fields["data"])
            msg.layout.dim = [MultiArrayDimension(label=label, size=size, stride=size)
                              for label, size in case.fields["layout"]]
            return serialize_message(msg)[:case.fields["truncate"]] if "truncate" in case.fields else msg

        rss_start = None
        while out.sent[topic] < MESSAGES:
            # bursts the learner cannot answer at once (its queue holds 1000, as the probe's does)
            for _ in range(min(900, MESSAGES - out.sent[topic])):
                case = transition_case(rng, TRANSITION_KINDS[int(rng.integers(len(TRANSITION_KINDS)))], rows)
                out.send(topic, message(case))
                if case.expect is None:
                    good += 1
                else:
                    expected[case.expect] += 1
            st = status.wait(lambda s: s["messages"].get(topic, 0) == out.sent[topic], 30)
            assert st is not None, (status.seen[-1:], out.sent[topic], proc.output()[-3000:])
            if rss_start is None:
                rss_start = rss_kib(proc.pid)
        rss_end = rss_kib(proc.pid)
        assert st["received"] == good  # every good one kept, no bad one
        assert_counted_and_throttled(st, expected, proc)
        # it trains on them: version v is cut after v * 50 updates (utd 1)
        st = status.wait(lambda s: s["owed"] == 0, 60)
        assert st is not None and st["weights_version"] == good // 50, (status.seen[-1:], good)
    assert proc.running(), proc.output()[-3000:]
    load_policy(tmp_path / "learner" / "policy.pt")  # finite weights, or it would not load
    assert rss_end - rss_start < LEARNER_RSS_SLACK_KIB, (rss_start, rss_end)


# ------------------------------------------------------------------ checkpoint swaps under load
@pytest.mark.slow
def test_a_broken_checkpoint_swapped_in_under_load_leaves_the_old_policy_serving(spawn, checkpoints, tmp_path):
    """While states stream in, the served checkpoint is replaced by a truncated, an empty, a
    wrong-dimension, a garbage and a bit-flipped file, and written in place in two halves:
    every state is answered, by the policy that last loaded whole."""
    from geometry_msgs.msg import PointStamped
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String

    from offline_rl_core.task.pusher_reach import observation_from_joints
    from offline_rl_core.serving.checkpoint import load_checkpoint
    from offline_rl_core.serving.policy import load_policy

    served = tmp_path / "policy.pt"
    shutil.copy(checkpoints["a"], served)
    policy = {"a": load_policy(checkpoints["a"]), "b": load_policy(checkpoints["b"])}
    good_b = checkpoints["b"].read_bytes()
    broken = broken_checkpoints(load_checkpoint(checkpoints["a"]))
    flipped = flip_in_tensor_data(good_b)  # other weights: only the zip's CRC tells
    proc = spawn([sys.executable, "-m", "pusher_policy.node", "--ros-args", "-p", f"checkpoint:={served}",
                  "-p", "poll_period:=0.01"], "policy")
    rng = np.random.default_rng(31)
    answers = {}
    with probe_node() as node:
        status = Status(node, "policy")
        node.create_subscription(JointState, "/policy/action",
                                 lambda m: answers.setdefault(_stamp(m), np.array(m.effort, np.float32)), DEEP)
        node.create_subscription(String, "/policy/provenance", lambda m: None, 10)
        out = Sender(node)
        out.add("pusher/target", PointStamped)
        out.add("pusher/fingertip", PointStamped)
        out.add("pusher/state", JointState)
        assert node.spin_until(lambda: out.matched() and node.count_publishers("/policy/action"), 30), proc.output()
        stamps = StateStamps(START)
        obs_of = {}

        def load(n: int = 3, timeout: float = 10.0) -> list[np.ndarray]:
            """``n`` states back to back; the answers (and the observations) once all came."""
            sent = []
            for _ in range(n):
                stamp = stamps.next()
                q, qd, target, tip = (rng.uniform(-1, 1, 2) for _ in range(4))
                out.send("pusher/target", point_msg({"xy": list(target), "bad_stamp": False}, stamp, rng))
                out.send("pusher/fingertip", point_msg({"xy": list(tip), "bad_stamp": False}, stamp, rng))
                out.send("pusher/state", joint_msg({"name": ["shoulder", "elbow"], "position": q, "velocity": qd,
                                                    "bad_stamp": False}, stamp, rng))
                obs_of[stamp] = observation_from_joints(q, qd, target, tip)
                sent.append(stamp)
            assert node.spin_until(lambda: all(s in answers for s in sent), timeout), proc.output()[-3000:]
            return sent

        def serving(which: str, stamps_: list[int]) -> bool:
            return all(np.array_equal(answers[s], policy[which].act(obs_of[s])) for s in stamps_)

        deadline = time.monotonic() + 20  # discovery can drop the first messages
        while not answers and time.monotonic() < deadline:
            try:
                load(1, timeout=1.0)
            except AssertionError:
                pass
        failures = 0

        def swap_in_broken(write, which: str) -> None:
            """Break the file with ``write``; keep the load on until the node has tried it."""
            nonlocal failures
            write()
            failures += 1
            deadline = time.monotonic() + 20
            while proc.output().count("cannot reload") < failures:
                assert serving(which, load()), "a broken checkpoint changed the answers"
                assert time.monotonic() < deadline, "the node never tried the broken file:\n" + proc.output()[-2000:]
            assert serving(which, load())

        def replace(data: bytes) -> None:
            tmp = served.with_name("incoming.pt")
            tmp.write_bytes(data)
            os.replace(tmp, served)

        for data in (good_b[:len(good_b) // 2], b"", broken["wrong dims"], rng.bytes(5000), flipped,
                     broken["non-finite weights"]):
            swap_in_broken(lambda: replace(data), "a")
        # written in place, in two halves, while it is read: the half fails, the whole loads
        with open(served, "wb") as f:
            f.write(good_b[:len(good_b) // 2])
            f.flush()
            deadline = time.monotonic() + 20
            while proc.output().count("cannot reload") <= failures:
                assert serving("a", load())
                assert time.monotonic() < deadline, proc.output()[-2000:]
            failures = proc.output().count("cannot reload")  # one or two reads of the half-written file
            f.write(good_b[len(good_b) // 2:])
        deadline = time.monotonic() + 20
        while not serving("b", load(1)):
            assert time.monotonic() < deadline, proc.output()[-2000:]
        assert serving("b", load())
        served.unlink()  # gone: the loaded policy serves on
        assert proc.wait_for_output("disappeared", 10)
        assert serving("b", load())
        swap_in_broken(lambda: replace(broken["wrong dims"]), "b")
        st = status.wait(lambda s: True)
    assert proc.running(), proc.output()[-3000:]
    assert st["rejected"] == {"bad checkpoint": failures}
