"""Sim time at a message's publication, for a recorder on ``use_sim_time`` (no ROS).

A recorder stamps each message with the node's clock when its callback runs. Under sim
time that clock moves when the recorder takes a /clock message, and neither the order the
callbacks run in nor the order DDS delivers messages of different publishers follows
what caused what: a command answering state t, published before the sim stepped, can be
taken after the /clock of state t + 1, which the sim published once that command had
stepped it, and is then stamped in the next tick. A join by receive times (``join.stamps:
receive``, for commands without a header, e.g. Float64MultiArray) pairs it with the wrong
state.

:class:`PublicationClock` stamps a message with the sim time current when it was
*published* (``MessageInfo['source_timestamp']``: the publisher's wall clock; on one
machine, or clocks kept in sync, publication order follows causality): the newest /clock
published at or before it, plus a nanosecond per microsecond of wall time since (at most
``ORDER_SPAN_NS``), so the stamps of one tick order its messages as they were published,
far inside any join tolerance. A message waits until a /clock published after it has come
(only then is the clock current at its publication known for sure), or until ``flush``.

A message that says its own sim time (a sim's state and goal: their header stamps) is not
flushed into an earlier tick: while it is ahead of the newest /clock taken, that /clock is
still on its way (DDS delivers different writers in no order, and a busy process can fall
quiet between taking the state and taking the /clock published before it), and ``flush``
with ``wait_for_clock`` holds it. Stamped by the previous tick's /clock a state lands a
millisecond after the state before it: that step loses its next state and a lockstep
session paced on the learner's steps waits for a step that never comes. Flushed without
waiting (the stream ended, or its /clock never came), such a message is stamped at the sim
time it says, and what was published after it no earlier.
"""

from __future__ import annotations

import bisect
import heapq
from collections import deque
from typing import Any

KEPT = 4096  # /clock values kept: a message older than all of them gets the oldest
ORDER_SPAN_NS = 999_999  # sim ns: the publication order within one tick, below a millisecond


def published_ns(info) -> int:
    """When a message was published (its MessageInfo's ``source_timestamp``: the
    publisher's clock), else when it was received."""
    return info["source_timestamp"] or info["received_timestamp"]


class PublicationClock:
    def __init__(self, kept: int = KEPT):
        self._published: deque[int] = deque(maxlen=kept)  # wall ns of each /clock, non-decreasing
        self._sim: deque[int] = deque(maxlen=kept)  # its sim ns
        # (published ns, arrival number, the sim time it says or -1, item): a heap
        self._waiting: list[tuple[int, int, int, Any]] = []
        self._arrivals = 0

    def add_clock(self, published_ns: int, sim_ns: int) -> list[tuple[int, Any]]:
        """A /clock message; returns the waiting items it releases, as ``(stamp, item)`` in
        publication order."""
        if self._published and published_ns < self._published[-1]:
            published_ns = self._published[-1]
        self._published.append(int(published_ns))
        self._sim.append(int(sim_ns))
        return self._release(lambda published: published < self._published[-1])

    def add(self, published_ns: int, item: Any, sim_ns: int | None = None) -> list[tuple[int, Any]]:
        """A message published at ``published_ns``; returns what is ready to write.
        ``sim_ns``: the sim time the message says it was published at (a header stamp on
        the sim's clock), if it says one."""
        self._arrivals += 1
        heapq.heappush(self._waiting, (int(published_ns), self._arrivals, -1 if sim_ns is None else int(sim_ns), item))
        if not self._published:
            return []
        return self._release(lambda published: published < self._published[-1])

    def flush(self, wait_for_clock: bool = False) -> list[tuple[int | None, Any]]:
        """Every waiting item (the recording ends, or everything published has arrived),
        stamped by the newest /clock; before any /clock came, with stamp None. With
        ``wait_for_clock``, nothing while a waiting message says a sim time past the newest
        /clock (``clock_behind``)."""
        if wait_for_clock and self.clock_behind:
            return []
        if not self._published:
            items = [(None, item) for *_, item in sorted(self._waiting, key=lambda w: w[:2])]
            self._waiting.clear()
            return items
        # a /clock that never came (unheld): a message is not stamped before the sim time it
        # says, nor before one published ahead of it says (the order of publication kept)
        return self._release(lambda published: True, by_said=True)

    @property
    def clock_behind(self) -> bool:
        """A waiting message says a sim time the /clock taken has not reached: that
        message's /clock is on its way."""
        return bool(self._published) and any(said > self._sim[-1] for _, _, said, _ in self._waiting)

    def stamp(self, published_ns: int) -> int | None:
        """The stamp of a message published at ``published_ns`` (None before any /clock)."""
        i = bisect.bisect_right(self._published, int(published_ns))
        if i == 0:
            if not self._published or len(self._published) < self._published.maxlen:
                return None
            i = 1  # older than every /clock kept: the oldest
        since_ns = max(int(published_ns) - self._published[i - 1], 0)
        return self._sim[i - 1] + min(since_ns // 1000, ORDER_SPAN_NS)

    @property
    def waiting(self) -> int:
        return len(self._waiting)

    def _release(self, ready, by_said: bool = False) -> list[tuple[int, Any]]:
        out, floor = [], -1
        while self._waiting and ready(self._waiting[0][0]):
            published, _, said, item = heapq.heappop(self._waiting)
            stamp = self.stamp(published)
            stamp = self._sim[0] if stamp is None else stamp
            if by_said:
                floor = max(floor, said)
                stamp = max(stamp, floor)
            out.append((stamp, item))
        return out
