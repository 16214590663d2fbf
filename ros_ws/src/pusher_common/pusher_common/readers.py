"""Hold a node's first message until the nodes that must hear it can.

A lockstep session starts its recorder and learner beside the sim and the mux; a message
published before a reader is matched never reaches it (volatile topics keep no history), so
the sim holds its first state and the mux its first command until the named readers are there.

The names come from the ROS graph (``get_subscriptions_info_by_topic``). With Fast DDS the
graph is filled from each participant's discovery-info topic, apart from the writer's own
matching of the reader's endpoint: under load a reader can be listed a moment before the
writer has matched it, and a message sent then is lost to it (seen: a learner one state short
of its session's recording). So a writer must also have matched as many readers as the graph
lists for its topic (``get_subscription_count``, rmw's matched count). A listed reader it never
matches (a QoS it cannot serve) holds it ``match_grace_s`` at most.
"""

from __future__ import annotations

import time
from typing import Iterable


class ReadersGate:
    """Whether the nodes of ``names`` can hear each of a node's publishers.

    ``open(publishers)``: every node of ``names`` reads each publisher's topic and each writer
    has matched the readers its graph lists. Once open, it stays open.
    """

    def __init__(self, node, names: Iterable[str], match_grace_s: float = 5.0):
        self.node = node
        self.names = set(names)
        self.match_grace_s = match_grace_s
        self.listed_at: float | None = None  # when the graph first listed every name on every topic

    @property
    def waiting(self) -> bool:
        """Whether it is still closed."""
        return bool(self.names)

    def open(self, publishers) -> bool:
        """Check again; True once it is open."""
        if not self.names:
            return True
        listed = {}
        for pub in publishers:
            listed[pub] = self.node.get_subscriptions_info_by_topic(pub.topic_name)
            if not self.names <= {info.node_name for info in listed[pub]}:
                return False
        now = time.monotonic()
        if self.listed_at is None:
            self.listed_at = now
        unmatched = any(pub.get_subscription_count() < len(readers) for pub, readers in listed.items())
        if unmatched and now - self.listed_at < self.match_grace_s:
            return False
        self.names = set()
        return True
