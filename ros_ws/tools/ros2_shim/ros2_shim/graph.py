"""The shim's own short-lived rclpy node, and waiting for discovery without a daemon."""

from __future__ import annotations

import os
import time
from contextlib import contextmanager

DISCOVERY_SPIN_S = 0.5  # ros2cli's default --spin-time without a daemon


@contextmanager
def cli_node():
    """A hidden node on the user's domain, shut down on the way out (Ctrl-C too)."""
    import rclpy

    rclpy.init(args=[])
    node = rclpy.create_node(f"_ros2cli_shim_{os.getpid()}", start_parameter_services=False)
    try:
        yield node
    finally:
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()


def spin_for_discovery(node, spin_time: float, snapshot, complete=lambda current: True):
    """Spin at least ``spin_time``, then until the graph is whole and quiet; returns the last ``snapshot()``.

    Without a daemon every call starts discovery from scratch. What each participant has
    is known from its announcements on ``ros_discovery_info`` (``discovery_info``): its
    nodes and the gids of their readers and writers. The graph counts as settled when
    - a node that is not hidden is there (another ``ros2`` call's node says nothing of the
      user's), and every node with a /rosout publisher is known by name;
    - every endpoint announced has been discovered: on a loaded machine a node's /rosout
      can show a second before its /clock;
    - no participant has announced a change for ``STABLE_S``, by its own clock: a node
      that is still being built announces each endpoint it adds, with its slow set-up
      between them, so a call made while it starts waits for the rest of it;
    - ``snapshot()`` has not changed for ``QUIET_S``, and for as long as discovery took
      until its last change (``quiet_enough``): a participant not discovered at all yet
      cannot announce anything, and a loaded machine that discovers slowly is waited for;
    - ``complete(snapshot)``, when the caller asks for more;
    - ``ANNOUNCEMENT_FLOOR_S`` has passed: a participant whose first discovery exchange
      with this call's was missed is announced again only by its periodic announcement.
    A lone graph (only this node) is waited on up to ``max(6 * spin_time, 3 s)``; while
    announced endpoints are missing, up to ``max(20 * spin_time, 10 s)``. With another rmw,
    where the announcements cannot be read, the quiet graph alone decides. A node whose
    process has not reached ``rclpy.init`` yet is seen by no wait.
    """
    import rclpy

    from .discovery_info import DiscoveryInfo, last_change_age_s, undiscovered_endpoints

    start = time.monotonic()
    limit = max(6 * spin_time, 3.0)
    announced_limit = max(20 * spin_time, 10.0)
    last = None
    last_change = start
    announcements = DiscoveryInfo.open(node)  # None (another rmw): judged by the quiet graph alone
    try:
        while True:
            rclpy.spin_once(node, timeout_sec=0.05)
            now = time.monotonic()
            current = snapshot()
            if current != last:
                last, last_change = current, now
            if announcements is not None:
                announcements.poll()
            elapsed = now - start
            if elapsed < spin_time:
                continue
            others = other_nodes_there(node)
            settled = (others and quiet_enough(start, last_change, now) and complete(current)
                       and all_node_names_known(node, node_names(node)) and endpoints_seen(node))
            if not settled and elapsed < limit:
                continue
            missing = 0
            if announcements is not None:
                missing = undiscovered_endpoints(node, announcements, node.get_name())
                settled = settled and last_change_age_s(node, announcements, node.get_name()) >= STABLE_S
            if elapsed < ANNOUNCEMENT_FLOOR_S:
                continue
            if (settled and missing == 0) or elapsed >= (announced_limit if missing else limit):
                return current
    finally:
        if announcements is not None:
            announcements.close()


QUIET_S = 0.5  # the least time without a change before a graph counts as settled
# the least time since a participant last announced a change (by its own clock): a node
# being built adds endpoints in bursts, with its slow set-up (loading a model, a checkpoint)
# between them
STABLE_S = 1.0
# Fast DDS repeats each participant's announcement every 3 s. A call's participant can miss
# its first exchange with one that is already running: tried as a user would (a sim and a
# policy node started, then `ros2 topic list`), 2 calls in 4 saw the policy node but none of
# the sim, and every call that spun this long saw both.
ANNOUNCEMENT_FLOOR_S = 3.5


def quiet_enough(start: float, last_change: float, now: float) -> bool:
    """No change for ``QUIET_S``, and for as long as discovery took until its last change."""
    return now - last_change >= max(QUIET_S, last_change - start)


def other_nodes_there(node) -> bool:
    """A /rosout publisher of a node that is not hidden: another shim's call (``_ros2cli_shim_*``)
    says nothing about whether the user's nodes have been discovered."""
    return any(not hidden(info.node_name) for info in node.get_publishers_info_by_topic("/rosout"))


def endpoints_seen(node) -> bool:
    """Every node known by name has shown its /rosout publisher (its endpoints are arriving)."""
    for name, namespace in node.get_node_names_and_namespaces():
        try:
            topics = node.get_publisher_names_and_types_by_node(name, namespace)
        except Exception:  # noqa: BLE001 - a node that left meanwhile
            continue
        if not any(topic == "/rosout" for topic, _ in topics):
            return False
    return True


def hidden(name: str) -> bool:
    return any(part.startswith("_") for part in name.split("/") if part)


def node_names(node) -> list[str]:
    """Fully qualified names of the nodes known now, sorted."""
    return sorted(ns.rstrip("/") + "/" + name for name, ns in node.get_node_names_and_namespaces())


def all_node_names_known(node, names: list[str]) -> bool:
    """Every node with a /rosout publisher (all but a few special ones) has shown its name."""
    return len(names) >= node.count_publishers("/rosout")


def absolute_node_name(name: str) -> str:
    return name if name.startswith("/") else "/" + name


def wait_for_node(node, name: str, timeout: float) -> bool:
    """True once the node ``name`` (absolute) is in the graph, False after ``timeout`` s."""
    import rclpy

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if name in node_names(node):
            return True
        rclpy.spin_once(node, timeout_sec=0.05)
    return name in node_names(node)
