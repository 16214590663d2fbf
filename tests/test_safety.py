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

    bag = BagWriter(path, flush_interval=1.0)
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
            os.kill(os.getpid(), signal.SIGINT)  # Python runs the handler at the next bytecode
        return flush(self, topics, messages, metadata_text)

    bag = _bag_with_pending(tmp_path / "cut.db3")
    monkeypatch.setattr(storage_sqlite.SqliteFileWriter, "flush", interrupted_flush)
    with pytest.raises(KeyboardInterrupt):
        bag.close()
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
