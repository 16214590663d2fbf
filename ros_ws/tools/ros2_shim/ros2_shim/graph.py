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
    """Spin at least ``spin_time``, then until other nodes are known and ``snapshot()`` is quiet.

    Without a daemon every call starts discovery from scratch; on a busy machine the
    first remote endpoints can take over a second to show, so a lone graph (only this
    node) keeps waiting up to ``max(6 * spin_time, 3 s)``. Another node shows as a second
    /rosout publisher (endpoint discovery; node names arrive later, so ``complete(snapshot)``
    can ask to wait for them). The graph counts as settled when every node seen so far has
    shown its /rosout publisher and nothing has changed for as long as it took to get there
    (``quiet_enough``): a loaded machine that discovers slowly is waited for longer.
    Returns the last snapshot.
    """
    import rclpy

    start = time.monotonic()
    limit = max(6 * spin_time, 3.0)
    last = None
    last_change = start
    while True:
        rclpy.spin_once(node, timeout_sec=0.05)
        now = time.monotonic()
        current = snapshot()
        if current != last:
            last, last_change = current, now
        others = node.count_publishers("/rosout") > 1
        settled = (others and quiet_enough(start, last_change, now) and complete(current)
                   and endpoints_seen(node))
        if now - start >= limit or (now - start >= spin_time and settled):
            return current


QUIET_S = 0.5  # the least time without a change before a graph counts as settled


def quiet_enough(start: float, last_change: float, now: float) -> bool:
    """No change for ``QUIET_S``, and for as long as discovery took until its last change."""
    return now - last_change >= max(QUIET_S, last_change - start)


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
