"""Episode labels: a person's word that an episode succeeded or failed, on ``episode_label``.

On a real arm nothing says whether the puck reached the goal; a person does, at the
episode's end. Each label is a ``std_msgs/String`` holding a small JSON object:

    {"label": "success"}        or        {"label": "failure", "episode": 12}

published on ``episode_label`` (a namespaced copy, ``/arm2/episode_label``, is read too) and
recorded in the bag beside the transitions (``bag.writer.write_transitions(labels=...)``
writes them without ROS). ``episode`` is optional: a label without it is of the episode whose
last transition the bag received before it.

``episode_labels(bag)`` reads them back, one per episode (a later label of an episode
replaces an earlier one: the person changed their mind); ``labels_from_success(data)`` is the
simulator's word instead, for simulated data: each episode's success at its last step.
"""

from __future__ import annotations

import json
import os
import struct

import numpy as np

from ..common.errors import UserError
from .transitions import Transitions

LABEL_TOPIC = "episode_label"
LABEL_MSGTYPE = "std_msgs/msg/String"
LABELS = {"success": True, "failure": False}


def label_json(success: bool, episode: int | None = None, source: str | None = None) -> str:
    doc = {"label": "success" if success else "failure"}
    if episode is not None:
        doc["episode"] = int(episode)
    if source is not None:
        doc["source"] = source
    return json.dumps(doc, sort_keys=True)


def parse_label(text: str, where: str = LABEL_TOPIC) -> tuple[bool, int | None]:
    """(success, episode or None) of a label's JSON; a UserError of one line otherwise."""
    try:
        doc = json.loads(text)
    except ValueError:
        raise UserError(f"{where}: a label is a JSON object such as {{\"label\": \"success\"}}, got {text[:80]!r}") \
            from None
    if not isinstance(doc, dict) or doc.get("label") not in LABELS:
        raise UserError(f"{where}: field label: expected success or failure, got "
                        f"{doc.get('label') if isinstance(doc, dict) else doc!r}")
    episode = doc.get("episode")
    if episode is not None and (isinstance(episode, bool) or not isinstance(episode, int) or episode < 0):
        raise UserError(f"{where}: field episode: expected an episode number >= 0, got {episode!r}")
    return LABELS[doc["label"]], episode


def encode_label_message(success: bool, episode: int | None = None, source: str | None = None) -> bytes:
    """The CDR bytes of the std_msgs/String label (for bags written without ROS)."""
    text = label_json(success, episode, source).encode() + b"\x00"
    return b"\x00\x01\x00\x00" + struct.pack("<I", len(text)) + text


def _decode_string(payload: bytes, where: str) -> str:
    try:
        (n,) = struct.unpack_from("<I" if payload[1] == 1 else ">I", payload, 4)
        return bytes(payload[8: 8 + n]).rstrip(b"\x00").decode()
    except (struct.error, IndexError, UnicodeDecodeError) as exc:
        raise UserError(f"{where}: not a std_msgs/String ({exc})") from None


def episode_labels(path: str | os.PathLike, episode_starts: list[int] | None = None) -> dict[int, bool]:
    """The labels a bag holds, by episode (``{}`` when it holds none); a UserError of one line
    naming the bag and topic for a label that is not one. A label without an episode is of the
    episode of the bag's last transition before it; in a bag of raw topics (no transitions),
    of the last episode whose first state came before it: ``episode_starts``, when the bag
    received each episode's first state (the raw join's ``episode_first_received``)."""
    from .bag.reader import open_bag, transition_topic
    from .bag.cdr import decode_transition_payloads

    with open_bag(path) as reader:
        topics = sorted({c.topic for c in reader.connections if c.topic.rstrip("/").endswith(LABEL_TOPIC)})
        if not topics:
            return {}
        labels = [(t, _decode_string(raw, f"{path}: {c.topic}"))
                  for c, t, raw in reader.messages([c for c in reader.connections if c.topic == topics[0]])]
        steps = transition_topic(reader)
        stamps, episodes = [], []
        if steps is not None:
            for c, t, raw in reader.messages([c for c in reader.connections if c.topic == steps]):
                stamps.append(t)
                episodes.append(raw)
    where = f"{path}: {topics[0]}"
    rows = decode_transition_payloads(episodes) if episodes else None
    column = None if rows is None else _episode_column(rows)
    out: dict[int, bool] = {}
    for t, text in sorted(labels, key=lambda x: x[0]):
        success, episode = parse_label(text, where)
        if episode is None and not stamps and episode_starts is not None:  # raw topics: by the episodes' starts
            before = int(np.searchsorted(np.asarray(episode_starts, np.int64), t, side="right")) - 1
            if before < 0:
                raise UserError(f"{where}: a label at {t} ns comes before any episode's first state: which episode "
                                "it labels cannot be told (give it an episode number)")
            episode = before
        elif episode is None:
            before = np.searchsorted(np.asarray(stamps, np.int64), t, side="right") - 1 if stamps else -1
            if before < 0:
                raise UserError(f"{where}: a label at {t} ns comes before any transition: which episode it labels "
                                "cannot be told (give it an episode number)")
            episode = int(column[before])
        out[int(episode)] = success
    return out


def _episode_column(rows: np.ndarray) -> np.ndarray:
    """The episode field of decoded transition rows (any layout: the third field from the end)."""
    return rows[:, -3].astype(np.int64)


def labels_from_success(data: Transitions) -> dict[int, bool]:
    """Each episode's success at its last step: the simulator's label (for simulated data)."""
    order = np.lexsort((data.step, data.episode))
    ep = data.episode[order]
    last = order[np.r_[ep[1:] != ep[:-1], True]] if len(data) else order
    return {int(e): bool(s) for e, s in zip(data.episode[last], data.success[last])}
