"""The gate a lockstep sim and mux hold their first message behind (pusher_common.readers),
over real DDS between two participants: it opens once the named node reads the topic and
the writer has matched it, so what is published next reaches that node; a listed reader the
writer can never match (a QoS it cannot serve) holds it no longer than its grace."""

from __future__ import annotations

import time

from ros_helpers import probe_node, ros_env  # noqa: F401 - fixtures


def test_the_gate_opens_when_the_writer_has_matched_the_named_reader(ros_env):
    from pusher_common.readers import ReadersGate
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String

    heard = []
    with probe_node("gate_writer") as writer, probe_node("gate_reader") as reader:
        pub = writer.create_publisher(String, "gate_test", QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        gate = ReadersGate(writer, ["gate_reader"], match_grace_s=60.0)
        assert gate.waiting and not gate.open([pub])  # nobody reads it yet
        reader.create_subscription(String, "gate_test", heard.append,
                                   QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        assert writer.spin_until(lambda: gate.open([pub]), timeout=30)
        assert pub.get_subscription_count() >= 1 and not gate.waiting
        pub.publish(String(data="first"))  # the message the gate held: it reaches the reader
        assert reader.spin_until(lambda: heard, timeout=10) and heard[0].data == "first"

    with probe_node("gate_writer2") as writer, probe_node("gate_reader2") as reader:
        pub = writer.create_publisher(String, "gate_test2", QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        gate = ReadersGate(writer, ["gate_reader2"], match_grace_s=1.0)
        # a reader asking for history a volatile writer does not keep: listed, never matched
        reader.create_subscription(String, "gate_test2", heard.append, QoSProfile(
            depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        assert writer.spin_until(lambda: "gate_reader2" in {
            i.node_name for i in writer.get_subscriptions_info_by_topic(pub.topic_name)}, timeout=30)
        listed = time.monotonic()
        assert not gate.open([pub]) and pub.get_subscription_count() == 0  # listed, not matched: it waits
        assert writer.spin_until(lambda: gate.open([pub]), timeout=30)
        assert time.monotonic() - listed >= 0.9  # ... for its grace, then goes on
