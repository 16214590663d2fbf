"""Safety without DDS: session keys, checkpoint files that are no files, a bag's close that a
Ctrl-C cannot cut short, the disk-space stop, abandoned episodes counted, the loads kept off
the serving thread, and the SROS2 permissions the project writes."""

from __future__ import annotations

import os
import signal
import stat
import threading
import time
from xml.etree import ElementTree as ET

import numpy as np
import pytest

from offline_rl_core.common.errors import UserError


def test_a_session_key_pair_is_private_and_a_key_others_can_read_is_refused(tmp_path):
    from offline_rl_core.commands.cli import main
    from offline_rl_core.serving.signing import load_signer, load_verifier

    assert main(["weights-key", str(tmp_path / "keys")]) == 0
    key, pub = tmp_path / "keys" / "weights.key", tmp_path / "keys" / "weights.pub"
    assert stat.S_IMODE(key.stat().st_mode) == 0o600
    signer, verifier = load_signer(key), load_verifier(pub)
    assert signer.session == verifier.session and verifier.verify(b"w", signer.sign(b"w"))
    first = key.read_bytes()
    assert main(["weights-key", str(tmp_path / "keys")]) == 0  # a new session: a new pair
    assert key.read_bytes() != first and not load_verifier(pub).verify(b"w", signer.sign(b"w"))
    os.chmod(key, 0o640)
    with pytest.raises(UserError, match="readable by no one else"):
        load_signer(key)
    (tmp_path / "x.pub").write_text("no key")
    with pytest.raises(UserError, match="not a PEM public key"):
        load_verifier(tmp_path / "x.pub")


def test_a_checkpoint_that_is_a_fifo_is_refused_without_blocking(tmp_path):
    from offline_rl_core.serving.checkpoint import load_checkpoint, regular_file_problem

    fifo = tmp_path / "policy.pt"
    os.mkfifo(fifo)
    assert "not a regular file" in regular_file_problem(fifo)
    done = threading.Event()

    def load():
        with pytest.raises(UserError, match="not a regular file"):
            load_checkpoint(fifo)
        done.set()

    worker = threading.Thread(target=load, daemon=True)
    worker.start()
    worker.join(10)  # a blocking open would wait here for a writer that never comes
    assert done.is_set()
    assert "not a regular file" in regular_file_problem("/dev/null")


def test_loads_run_on_the_worker_in_order_and_what_waits_is_bounded():
    from offline_rl_core.nodes.background_loads import BackgroundLoads

    ready = threading.Event()
    gate = threading.Event()
    loads = BackgroundLoads(ready.set, max_pending=2)
    started = threading.Event()
    loads.submit("weights", lambda: started.set() or (gate.wait(10) and "first"))
    assert started.wait(10)
    for i in range(5):  # the worker is busy: only the newest two wait
        loads.submit("weights", lambda i=i: i)
    loads.submit("checkpoint", lambda: 1 / 0)  # a job's failure is its result
    gate.set()
    deadline = time.monotonic() + 10
    results = []
    while len(results) < 4 and time.monotonic() < deadline:
        ready.wait(0.1)
        ready.clear()
        results += loads.drain()
    assert results[:3] == ["first", 3, 4] and isinstance(results[3], ZeroDivisionError)
    assert loads.dropped == {"weights": 3}
    loads.stop()


def _bag_with_pending(path, n=20_000):
    from offline_rl_core.data.bag import BagWriter

    # the background flusher must not empty the buffer first (a loaded machine takes over a
    # second to write 20,000 messages): every message is pending when the test closes the bag
    bag = BagWriter(path, flush_interval=3600.0)
    bag.add_topic("/notes", "std_msgs/msg/String")
    payload = bytes([0, 1, 0, 0, 6, 0, 0, 0]) + b"hello\x00"
    for i in range(n):
        bag.write("/notes", i + 1, payload)
    return bag


def test_a_ctrl_c_during_close_loses_nothing_and_acts_after(tmp_path, monkeypatch):
    """The signal comes in the middle of the bag's last transaction: it waits until the
    bag is whole, then interrupts as it would have."""
    from rosbags.rosbag2 import Reader

    from offline_rl_core.data.bag import storage_sqlite

    flush = storage_sqlite.SqliteFileWriter.flush

    def interrupted_flush(self, topics, messages, metadata_text):
        if messages:
            # to the main thread itself: sent to the process, any of its threads (DDS's, left
            # by earlier tests) may take it, later; Python runs the handler at the next bytecode
            signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)
        return flush(self, topics, messages, metadata_text)

    bag = _bag_with_pending(tmp_path / "cut.db3")
    monkeypatch.setattr(storage_sqlite.SqliteFileWriter, "flush", interrupted_flush)
    # Ctrl-C as a plain Python process takes it, whatever an earlier test in this process set
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            bag.close()
    finally:
        signal.signal(signal.SIGINT, previous)
    with Reader(tmp_path / "cut.db3") as reader:
        assert reader.message_count == 20_000


def test_a_bag_stops_cleanly_below_its_free_space_minimum(tmp_path):
    from rosbags.rosbag2 import Reader

    from offline_rl_core.data.bag import BagWriter
    from offline_rl_core.data.bag.recording import OutOfSpace, free_space

    with pytest.raises(UserError, match="below the minimum"):
        BagWriter(tmp_path / "never.db3", min_free_space=free_space(tmp_path) + (1 << 40))
    assert not (tmp_path / "never.db3").exists()
    bag = _bag_with_pending(tmp_path / "low.db3", n=100)
    bag.min_free_space = free_space(tmp_path) + (1 << 40)  # as a disk filling up
    bag.flush()
    assert bag.low_space is not None
    with pytest.raises(OutOfSpace):
        bag.write("/notes", 10**6, b"\x00\x01\x00\x00\x01\x00\x00\x00\x00")
    bag.close()
    with Reader(tmp_path / "low.db3") as reader:
        assert reader.message_count == 100


def test_a_reset_counts_the_episode_it_abandons_as_a_failure():
    from offline_rl_core.nodes.sim_loop import SimLoop
    from offline_rl_core.task.pusher_reach import ACT_DIM

    loop = SimLoop("lockstep", seed=3, episodes=2)
    loop.start_episode()
    for _ in range(5):
        loop.command(loop.current.stamp_ns, np.zeros(ACT_DIM, np.float32), 2)
    loop.reset()
    assert loop.summary()["abandoned"] == 1 and loop.summary()["episodes"] == 0
    while not loop.finished:
        loop.command(loop.current.stamp_ns, np.zeros(ACT_DIM, np.float32), 2)
    summary = loop.summary()
    successes = sum(s for s, _, _ in loop.results)
    assert summary["episodes"] == 2 and summary["abandoned"] == 1
    assert summary["success_rate"] == successes / 3


# ---------------------------------------------------------------------------- SROS2
def test_sros2_permissions_follow_the_schemas_and_grant_only_what_each_node_uses(tmp_path):
    """The shapes of sros2's policy.xsd and the OMG DDS-Security permissions schema, checked
    element by element (the schemas are not shipped here; the PyPI Fast DDS has no
    DDS-Security, so the files cannot be loaded by a secured participant in this test)."""
    from offline_rl_core.commands.cli import main
    from offline_rl_core.nodes.sros2_policy import NODE_GRAPH

    assert main(["sros2", "--keystore", str(tmp_path), "--domain-id", "7"]) == 0
    policy = ET.parse(tmp_path / "policy.xml").getroot()
    assert policy.tag == "policy" and policy.get("version") and [c.tag for c in policy] == ["enclaves"]
    enclaves = {e.get("path"): e for e in policy.find("enclaves")}
    assert set(enclaves) == {f"/pusher_rl/{n}" for n in NODE_GRAPH}
    for path, enclave in enclaves.items():
        assert [c.tag for c in enclave] == ["profiles"]
        for profile in enclave.find("profiles"):
            assert profile.tag == "profile" and profile.get("ns") == "/" and profile.get("node")
            for group in profile:
                item = {"topics": "topic", "services": "service"}[group.tag]
                assert set(group.attrib) <= {"publish", "subscribe", "reply", "request"}
                assert set(group.attrib.values()) == {"ALLOW"} and len(group) >= 1
                assert all(c.tag == item and c.text for c in group)
    for node in NODE_GRAPH:
        dds = ET.parse(tmp_path / "enclaves" / node / "permissions.xml").getroot()
        assert dds.tag == "dds" and [c.tag for c in dds] == ["permissions"]
        (grant,) = dds.find("permissions")
        assert grant.get("name") == f"/pusher_rl/{node}"
        assert [c.tag for c in grant] == ["subject_name", "validity", "allow_rule", "default"]
        assert grant.find("subject_name").text == f"CN=/pusher_rl/{node}" and grant.find("default").text == "DENY"
        validity = grant.find("validity")
        assert [c.tag for c in validity] == ["not_before", "not_after"]
        before, after = (np.datetime64(validity.find(t).text) for t in ("not_before", "not_after"))
        assert before < after
        rule = grant.find("allow_rule")
        assert [c.tag for c in rule][0] == "domains" and rule.find("domains/id").text == "7"
        assert all(c.tag in ("domains", "publish", "subscribe") for c in rule)
        for criteria in rule.findall("publish") + rule.findall("subscribe"):
            assert [c.tag for c in criteria] == ["topics"] and all(t.tag == "topic" for t in criteria.find("topics"))

    def topics(node, what):
        grant = ET.parse(tmp_path / "enclaves" / node / "permissions.xml").getroot().find("permissions/grant")
        return {t.text for t in grant.findall(f"allow_rule/{what}/topics/topic")}

    # least privilege: only the learner publishes weights, only the mux and the driving recorder command the arm
    assert [n for n in NODE_GRAPH if "rt/learner/weights" in topics(n, "publish")] == ["learner"]
    assert {n for n in NODE_GRAPH if "rt/pusher/command/policy" in topics(n, "publish")} == {"mux"}
    assert "rt/learner/weights" in topics("policy", "subscribe")
    assert "rr/pusher/resetReply" in topics("sim", "publish") and "rq/pusher/resetRequest" in topics("sim", "subscribe")
    assert "rq/pusher/resetRequest" in topics("operator", "publish")
    assert not any(t.endswith("Request") for t in topics("policy", "publish"))


# ---------------------------------------------------------------- watchdog, e-stop, limits

def _position_task(**safety):
    """pusher_reach's arm behind a position interface (hold the position is its safe command)."""
    from offline_rl_core.task.spec import load_task, task_from_dict

    doc = load_task("pusher_reach").describe()
    doc["command"] = {**doc["command"], "interface": "position", "scale": [3.0, 3.0], "offset": [0.0, 0.0]}
    if safety:
        doc["safety"] = safety
    return task_from_dict(doc)


def test_the_watchdog_arms_on_the_first_command_trips_on_silence_and_latches_until_reset():
    from offline_rl_core.nodes.watchdog import CommandWatchdog

    dog = CommandWatchdog(0.06)
    assert not dog.check(100.0) and dog.fault() is None  # nothing came yet: not a fault
    dog.fed(100.0)
    assert not dog.check(100.05)
    assert dog.check(100.07) and dog.fault() == {"trips": 1, "silent": True, "timeout_s": 0.06}
    assert dog.check(100.5) and dog.trips == 1  # one silence, one trip
    dog.fed(100.6)
    assert not dog.check(100.61)
    assert dog.fault() == {"trips": 1, "silent": False, "timeout_s": 0.06}  # latched after commands came back
    dog.reset()
    assert dog.fault() is None
    with pytest.raises(ValueError):
        CommandWatchdog(0.0)


def test_a_realtime_sim_applies_zero_torque_when_its_commands_go_silent_and_resumes_on_one():
    from offline_rl_core.nodes.sim_loop import SimLoop
    from offline_rl_core.task.spec import load_task

    task = load_task("pusher_reach")
    assert task.command_timeout == pytest.approx(3 * task.control_period) and task.safe_command == "zero"
    loop = SimLoop("realtime", task=task)
    loop.start_episode()
    loop.command(None, np.float32([1.0, -1.0]), 2, now=0.0)
    period = task.control_period
    torques = [loop.tick(now=k * period).next_state.torque.tolist() for k in range(1, 6)]
    assert torques[:3] == [[0.5, -0.5]] * 3  # within the timeout the command holds (N·m: gear 0.5)
    assert torques[4] == [0.0, 0.0] and loop.faults()["watchdog"]["trips"] == 1 and loop.safe_steps >= 1
    loop.command(None, np.float32([0.2, 0.2]), 2, now=6 * period)
    assert loop.tick(now=6.5 * period).next_state.torque.tolist() == pytest.approx([0.1, 0.1])
    assert loop.faults()["watchdog"]["silent"] is False  # still reported: latched until estop/reset
    loop.reset_faults()
    assert loop.faults() == {}


def test_without_a_clock_the_sim_steps_as_before_so_lockstep_runs_keep_their_bytes():
    from offline_rl_core.nodes.sim_loop import SimLoop

    loop = SimLoop("lockstep")
    state = loop.start_episode()
    step = loop.command(state.stamp_ns, np.float32([1.0, 1.0]), 2)
    assert step is not None and step.next_state.torque.tolist() == [0.5, 0.5] and loop.faults() == {}


def test_the_safe_command_holds_the_position_for_a_position_interface():
    from offline_rl_core.nodes.watchdog import safe_action

    task = _position_task()
    assert task.safe_command == "hold"
    assert safe_action(task, [0.3, -1.5]).tolist() == pytest.approx([0.1, -0.5])  # position / scale
    assert safe_action(task) is None  # no state heard: nothing to hold
    assert _position_task(safe_command="zero").safe_command == "zero"


def test_the_estop_engages_on_true_and_only_a_reset_releases_it_once_the_button_is_up():
    from offline_rl_core.nodes.estop import EStopLatch

    latch = EStopLatch()
    assert latch.reset() == (True, "not engaged")
    assert latch.on_estop(True) and not latch.on_estop(True) and latch.engaged
    ok, message = latch.reset()
    assert not ok and "still held" in message and latch.engaged
    assert not latch.on_estop(False) and latch.engaged  # the topic never releases it
    assert latch.reset() == (True, "released") and not latch.engaged
    assert latch.as_dict() == {"engaged": False, "held": False, "engagements": 1, "resets_refused": 1}


def test_a_sim_under_estop_applies_the_safe_command_and_does_not_resume_the_old_one_after_reset():
    from offline_rl_core.nodes.sim_loop import SimLoop

    loop = SimLoop("realtime")
    loop.start_episode()
    loop.command(None, np.float32([1.0, 1.0]), 2, now=0.0)
    assert loop.tick(now=0.01).next_state.torque.tolist() == [0.5, 0.5]
    loop.estop.on_estop(True)
    loop.estop_engaged()
    assert loop.tick(now=0.02).next_state.torque.tolist() == [0.0, 0.0]
    loop.estop.on_estop(False)
    assert loop.estop.reset()[0]
    # released: the safe command holds until a fresh command comes; no fault for the e-stop's silence
    assert [loop.tick(now=0.02 * k).next_state.torque.tolist() for k in (2, 10)] == [[0.0, 0.0]] * 2
    assert loop.faults() == {}


def test_commands_beyond_the_controllers_range_or_the_joint_limits_are_refused_not_clipped():
    from offline_rl_core.nodes.joint_messages import action_from_command, action_from_effort
    from offline_rl_core.task.spec import load_task

    task = load_task("pusher_reach")
    assert action_from_command(task, [0.5, -0.5])[0].tolist() == [1.0, -1.0]  # the bounds themselves
    for torques in ([1e300, 0.0], [0.5001, 0.0]):
        action, problem = action_from_command(task, torques)
        assert action is None and problem.reason == "beyond limits", problem
    assert action_from_effort([], [1.0 + 1e-9, -1.0])[1] is None  # float rounding is no command beyond the range
    limited = _position_task(position_limits={"shoulder": [-1.0, 1.0]})
    assert action_from_command(limited, [0.9, 2.5])[1] is None  # the elbow has no limit but the range
    action, problem = action_from_command(limited, [1.2, 0.0])
    assert action is None and problem.reason == "beyond limits" and "shoulder" in problem


def test_a_task_safety_section_is_checked_and_a_task_without_one_keeps_its_digest():
    from offline_rl_core.task.spec import load_task, task_from_dict

    task = load_task("pusher_reach")
    assert "safety" not in task.describe()
    doc = task.describe()
    doc["safety"] = {"command_timeout": 0.1, "velocity_limits": {"elbow": 5.0}, "slew": 0.25}
    safe = task_from_dict(doc)
    assert safe.command_timeout == 0.1 and safe.safety.velocity_limits == (float("inf"), 5.0)
    assert safe.digest != task.digest and task_from_dict(safe.describe()) == safe  # bags and checkpoints keep it
    for field, value, expected in (("command_timeout", 0, "a number > 0"), ("safe_command", "brake", "one of"),
                                   ("position_limits", {"wrist": [0, 1]}, "'wrist', not one of"),
                                   ("position_limits", {"elbow": [1, 0]}, "low < high")):
        with pytest.raises(UserError, match=f"safety.{field}.*{expected}|{expected}"):
            task_from_dict({**task.describe(), "safety": {field: value}})


def test_the_slew_limiter_ramps_a_far_command_and_passes_near_ones():
    from offline_rl_core.nodes.command_limits import SlewLimiter

    ramp = SlewLimiter(0.25)
    assert ramp.limit([0.0, 0.0]).tolist() == [0.0, 0.0]
    assert ramp.limit([1.0, -0.1]).tolist() == pytest.approx([0.25, -0.1])
    assert ramp.limit([1.0, -0.1]).tolist() == pytest.approx([0.5, -0.1]) and ramp.limited == 2
    ramp.restart(np.zeros(2))  # after an e-stop: from the safe command
    assert ramp.limit([-1.0, 0.0]).tolist() == pytest.approx([-0.25, 0.0])
    assert SlewLimiter(None).limit([1.0, -1.0]).tolist() == [1.0, -1.0]


def test_a_producers_actions_are_kept_inside_the_joint_limits_so_none_is_refused():
    from offline_rl_core.nodes.command_limits import action_bounds, within_limits
    from offline_rl_core.nodes.joint_messages import action_from_command, command_from_action
    from offline_rl_core.task.spec import load_task

    task = _position_task(position_limits={"shoulder": [-1.5, 0.3]})
    low, high = action_bounds(task)
    assert low.tolist() == pytest.approx([-0.5, -1.0]) and high.tolist() == pytest.approx([0.1, 1.0])
    rng = np.random.default_rng(0)
    for action in np.tanh(rng.normal(0, 2, (200, 2))).astype(np.float32):  # exploration's samples
        kept = within_limits(task, action)
        assert action_from_command(task, command_from_action(task.command, kept))[1] is None
    assert within_limits(load_task("pusher_reach"), np.float32([0.9, -1.0])).tolist() == pytest.approx([0.9, -1.0])


# ---------------------------------------------------------------- soft limits on the measured state

def _limited_effort_task(**safety):
    """pusher_reach (an effort interface) with joint limits on its measured state."""
    from offline_rl_core.task.spec import load_task, task_from_dict

    doc = load_task("pusher_reach").describe()
    doc["safety"] = safety
    return task_from_dict(doc)


def test_an_effort_beyond_the_measured_limits_is_refused_outward_and_taken_back_inward():
    from offline_rl_core.nodes.state_limits import StateLimits

    limits = StateLimits(_limited_effort_task(position_limits=[[-1.0, 1.0], [-2.0, 2.0]], velocity_limits=[5.0, 5.0]))
    inside, beyond_high = [0.0, 0.0], [1.2, 0.0]
    assert limits.check(np.float32([1.0, 1.0]), inside, [0.0, 0.0]) is None
    refused = limits.check(np.float32([0.3, 0.0]), beyond_high, [0.0, 0.0])
    assert refused.reason == "beyond limits" and "shoulder" in refused and "position limits" in refused
    assert limits.check(np.float32([-0.3, 1.0]), beyond_high, [0.0, 0.0]) is None  # back inside: taken
    assert limits.check(np.float32([0.0, 0.0]), beyond_high, [0.0, 0.0]) is None  # no effort: taken
    assert limits.check(np.float32([0.0, -0.5]), [0.0, -2.5], [0.0, 0.0]).reason == "beyond limits"
    too_fast = limits.check(np.float32([0.0, 0.5]), inside, [0.0, 6.0])
    assert too_fast.reason == "beyond limits" and "velocity_limits" in too_fast
    assert limits.check(np.float32([0.0, -0.5]), inside, [0.0, 6.0]) is None  # braking: taken
    assert not StateLimits(_limited_effort_task()).active  # pusher_reach as shipped: no limits, nothing checked


def test_a_realtime_sim_stops_pushing_a_joint_past_its_limit_and_takes_a_command_back():
    from offline_rl_core.nodes.sim_loop import SimLoop

    probe = SimLoop("realtime", task=_limited_effort_task())
    probe.start_episode()
    start = float(probe.env.joint_positions[0])  # the same seed resets the arm to the same pose
    high = start + 0.2
    loop = SimLoop("realtime", task=_limited_effort_task(position_limits=[[start - 1.0, high], [-9.0, 9.0]]))
    loop.start_episode()
    outward = np.float32([1.0, 0.0])
    assert loop.beyond_state_limits(outward) is None  # the reset pose is inside
    loop.command(None, outward, 2, now=None)
    tick, state = 0, None
    # no clock: the watchdog is not in this test
    while loop.limit_steps == 0:  # full torque until the shoulder passes its high limit
        tick += 1
        assert tick < 200, "the shoulder never reached its limit under full torque"
        state = loop.tick(now=None).next_state
    assert state.position[0] > high and loop.beyond_state_limits(outward).reason == "beyond limits"
    assert loop.tick(now=None).next_state.torque.tolist() == [0.0, 0.0]  # held outward: safe applied
    back = np.float32([-1.0, 0.0])
    assert loop.beyond_state_limits(back) is None
    loop.command(None, back, 2, now=None)
    assert loop.tick(now=None).next_state.torque.tolist() == [-0.5, 0.0]
