"""Nothing trained on while the e-stop was engaged, offline too.

A session bag records the ``estop`` topic (std_msgs/Bool; the passive recorder records
every topic). The e-stop is engaged from a ``true`` until it is released: by the first
successful ``estop/reset`` after the button was let go, where the bag records the reset
service's events (``estop/reset/_service_event``), else by the next ``false`` (a bag
without them cannot say when the reset came; the release of the button is the earliest
it can have been). While engaged the arm applied the safe command, not the policy's, so
those steps say nothing of the policy.

``drop_engaged(path, data)``: the transitions of a bag (as ``read_transitions`` returned
them) less those recorded while engaged, judged by each transition message's bag stamp
(the moment its step ended), and how many were dropped; None for a bag without an
``estop`` topic, whose transitions come back untouched. ``bag_engaged_spans`` and
``engaged_at``: the same for transitions joined from raw topics (``raw_topics``), judged by
their state's receive stamp.
"""

from __future__ import annotations

import itertools
import os
from functools import lru_cache
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_types_from_msg

from ...common.errors import UserError
from ..transitions import Transitions
from .reader import one_topic, open_bag, sqlite_storages, transition_topic

ESTOP_TOPIC = "/estop"
ESTOP_MSGTYPE = "std_msgs/msg/Bool"
RESET_EVENT_TOPIC = "/estop/reset/_service_event"
RESET_EVENT_MSGTYPE = "std_srvs/srv/Trigger_Event"
RESPONSE_SENT, RESPONSE_RECEIVED = 2, 3  # service_msgs/ServiceEventInfo event types that carry the answer
FOREVER = 2**63 - 1


@lru_cache(maxsize=1)
def event_typestore():
    """A typestore that also knows std_srvs/Trigger's service event (rosbags' stores hold
    messages only); its own instance, so the shared one stays as bags are written with."""
    from rosbags.typesys import get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    types.update(get_types_from_msg("uint8 structure_needs_at_least_one_member", "std_srvs/msg/Trigger_Request"))
    types.update(get_types_from_msg("bool success\nstring message", "std_srvs/msg/Trigger_Response"))
    event = get_types_from_msg("service_msgs/ServiceEventInfo info\nstd_srvs/Trigger_Request[<=1] request\n"
                               "std_srvs/Trigger_Response[<=1] response", RESET_EVENT_MSGTYPE)
    types.update({RESET_EVENT_MSGTYPE: definition for definition in event.values()})
    store.register(types)
    return store


def _connections(reader: Reader, path: Path, topic: str, msgtype: str) -> list:
    connections = [c for c in reader.connections if c.topic == topic]
    types = sorted({c.msgtype for c in connections})
    if types != [msgtype]:
        raise UserError(f"{path}: {topic} has type {', '.join(types)}; expected {msgtype}")
    return connections


def _estop_words(reader: Reader, path: Path, topic: str) -> list[tuple[int, bool]]:
    words = []
    for _, stamp, raw in reader.messages(_connections(reader, path, topic, ESTOP_MSGTYPE)):
        if len(raw) < 5:
            raise UserError(f"{path}: {topic}: a message of {len(raw)} bytes; expected a {ESTOP_MSGTYPE}")
        words.append((int(stamp), raw[4] != 0))  # CDR: a 4-byte header, then the bool
    return words


def _resets(reader: Reader, path: Path, topic: str) -> list[int]:
    """Stamps of the reset service's successful answers."""
    store, stamps = event_typestore(), []
    for _, stamp, raw in reader.messages(_connections(reader, path, topic, RESET_EVENT_MSGTYPE)):
        try:
            event = store.deserialize_cdr(raw, RESET_EVENT_MSGTYPE)
        except Exception as exc:  # rosbags raises assorted errors on a short or bad payload
            raise UserError(f"{path}: {topic}: a message that is not a {RESET_EVENT_MSGTYPE} ({exc})") from exc
        answered = event.info.event_type in (RESPONSE_SENT, RESPONSE_RECEIVED)
        if answered and event.response and event.response[0].success:
            stamps.append(int(stamp))
    return stamps


def engaged_spans(words: list[tuple[int, bool]], resets: list[int] | None) -> list[tuple[int, int]]:
    """[start, stop) stamps while engaged. ``resets``: the successful resets' stamps, or None
    where the bag does not record them (a ``false`` then releases)."""
    events = sorted([(s, 0, v) for s, v in words] + [(s, 1, None) for s in resets or ()], key=lambda e: e[:2])
    spans, start, held = [], None, False
    for stamp, is_reset, value in events:
        if not is_reset:
            held = value
            if value and start is None:
                start = stamp
            elif not value and start is not None and resets is None:
                spans.append((start, stamp))
                start = None
        elif start is not None and not held:  # the latch refuses a reset while the button is held
            spans.append((start, stamp))
            start = None
    if start is not None:
        spans.append((start, FOREVER))
    return spans


def topic_stamps(reader: Reader, topic: str) -> np.ndarray:
    """Bag stamps of a topic's messages, in the order ``reader.topic_payload_chunks`` yields
    their payloads (so row i of ``read_transitions`` has stamp i)."""
    connections = [c for c in reader.connections if c.topic == topic]
    sqlite_files = sqlite_storages(reader)
    if sqlite_files is None:
        stamps = (stamp for _, stamp, _ in reader.messages(connections))
    else:
        sources = []
        for storage in sqlite_files:
            ids = [c.id for c in storage.connections if c.topic == topic]
            if ids:
                marks = ",".join("?" * len(ids))
                query = f"SELECT timestamp FROM messages WHERE topic_id IN ({marks}) ORDER BY timestamp, id"
                sources.append(row[0] for row in storage.dbconn.execute(query, ids))
        stamps = itertools.chain.from_iterable(sources)
    return np.fromiter(stamps, dtype=np.int64)


def _bag_spans(reader: Reader, path: Path) -> list[tuple[int, int]] | None:
    estop = one_topic(reader, ESTOP_TOPIC)
    if estop is None:
        return None
    reset = one_topic(reader, RESET_EVENT_TOPIC)
    return engaged_spans(_estop_words(reader, path, estop), _resets(reader, path, reset) if reset is not None else None)


def bag_engaged_spans(path: str | os.PathLike) -> list[tuple[int, int]] | None:
    """The [start, stop) bag stamps while the e-stop was engaged; None for a bag without ``estop``."""
    with open_bag(path) as reader:
        return _bag_spans(reader, Path(path))


def engaged_at(stamps: np.ndarray, spans: list[tuple[int, int]]) -> np.ndarray:
    """Which of ``stamps`` fall in a span."""
    stamps = np.asarray(stamps, np.int64)
    engaged = np.zeros(stamps.shape, dtype=bool)
    for start, stop in spans:
        engaged |= (stamps >= start) & (stamps < stop)
    return engaged


def drop_engaged(path: str | os.PathLike, data: Transitions) -> tuple[Transitions, int | None]:
    """``data`` (the bag's transitions) less the rows recorded while the e-stop was engaged,
    and how many were dropped; (data, None) for a bag that records no e-stop."""
    path = Path(path)
    with open_bag(path) as reader:
        spans = _bag_spans(reader, path)
        if not spans:
            return data, None if spans is None else 0
        stamps = topic_stamps(reader, transition_topic(reader))
    if len(stamps) != len(data):  # a recording still growing between the two reads
        raise UserError(f"{path}: {len(stamps)} transition stamps for {len(data)} transitions; "
                        "the bag changed while it was read (read it once its recording has stopped)")
    engaged = engaged_at(stamps, spans)
    dropped = int(engaged.sum())
    if dropped == len(data):
        raise UserError(f"{path}: every one of its {len(data)} transitions was recorded while the e-stop was engaged; "
                        "nothing to train on")
    return (data.select(~engaged) if dropped else data), dropped
