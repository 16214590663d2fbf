"""Writing rosbag2 bags: whole datasets of transitions, or a stream of recorded messages.

Both write through rosbags' rosbag2 Writer (format version 9) into a staged directory and
publish it atomically (see ``paths``). Message definitions come from the ROS 2 Kilted
typestore, so the bag carries the definitions and RIHS01 hashes real ROS tools expect.
"""

from __future__ import annotations

import os
import threading
from contextlib import suppress
from functools import lru_cache

import numpy as np
from rosbags.rosbag2 import Writer, WriterError
from rosbags.typesys import Stores, get_typestore

from ..errors import UserError
from ..transitions import LAYOUT_SLICES, TRANSITION_LAYOUT, TRANSITION_WIDTH, Transitions
from .cdr import TRANSITION_MESSAGE_SIZE, TRANSITION_MSGTYPE, TRANSITION_TOPIC, encode_transition_blob
from .paths import STORAGE_PLUGIN, StagedBag, resolve_target

# Deterministic stamps make `offline-rl collect` bit-reproducible: transition i is stamped
# TRANSITION_START_NS + i * TRANSITION_PERIOD_NS (2025-01-01T00:00:00Z, then 50 Hz).
TRANSITION_START_NS = 1_735_689_600 * 10**9
TRANSITION_PERIOD_NS = 20_000_000

ROSBAG2_VERSION = 9


@lru_cache(maxsize=1)
def typestore():
    """The message definitions bags are written with (ROS 2 Kilted, else Jazzy)."""
    store = getattr(Stores, "ROS2_KILTED", None) or Stores.ROS2_JAZZY
    return get_typestore(store)


def _check_rows(path, rows: np.ndarray) -> None:
    if rows.ndim != 2 or rows.shape[1] != TRANSITION_WIDTH:
        raise UserError(f"{path}: expected ({TRANSITION_WIDTH},)-wide transition rows, got shape {rows.shape}")
    if rows.shape[0] == 0:
        raise UserError(f"{path}: no transitions to write")
    bad = ~np.isfinite(rows)
    if bad.any():
        column = int(np.flatnonzero(bad.any(axis=0))[0])
        raise UserError(f"{path}: {int(bad.any(axis=1).sum())} transition rows hold NaN or inf (first in field {field_of_column(column)!r}); not writing them")


def field_of_column(column: int) -> str:
    """The layout label of a column of the (N, 25) transition matrix."""
    return next(label for label, _ in TRANSITION_LAYOUT if column < LAYOUT_SLICES[label].stop)


def write_transitions(
    path: str | os.PathLike,
    transitions: Transitions | np.ndarray,
    storage: str | None = None,
    custom_data: dict[str, str] | None = None,
) -> None:
    """Write transitions as a rosbag2 bag with one ``/pusher/transition`` message per row.

    ``path``: ``x.db3`` or ``x.mcap`` gives a single self-describing storage file, any other
    path a bag directory whose storage is ``storage`` ('sqlite3', the default, or 'mcap').
    An existing bag at ``path`` is replaced atomically; on any error it is left untouched and
    nothing half-written remains. Stamps are TRANSITION_START_NS + i * 20 ms.
    """
    rows = transitions.to_rows() if isinstance(transitions, Transitions) else np.asarray(transitions, np.float32)
    target = resolve_target(path, storage)
    _check_rows(target.path, rows)
    blob = encode_transition_blob(rows)
    size = TRANSITION_MESSAGE_SIZE
    staged = StagedBag(target, overwrite=True)
    try:
        writer = Writer(staged.bag_dir, version=ROSBAG2_VERSION, storage_plugin=STORAGE_PLUGIN[target.storage])
        with writer:
            for key, value in (custom_data or {}).items():
                writer.set_custom_data(key, value)
            conn = writer.add_connection(TRANSITION_TOPIC, TRANSITION_MSGTYPE, typestore=typestore())
            write = writer.write
            for i, offset in enumerate(range(0, len(blob), size)):
                write(conn, TRANSITION_START_NS + i * TRANSITION_PERIOD_NS, blob[offset : offset + size])
        staged.publish()
    except OSError as exc:
        raise UserError(f"{target.path}: cannot write the bag: {exc}") from exc
    finally:
        staged.discard()


class BagWriter:
    """A streaming rosbag2 writer for already-serialized CDR messages (the recorder node).

    ``with BagWriter("bags/run.db3") as bag: bag.add_topic("/pusher/state",
    "sensor_msgs/msg/JointState"); bag.write("/pusher/state", stamp_ns, cdr_bytes)``.
    Messages go to a staged bag beside ``path``; ``close()`` (idempotent, also on leaving
    the ``with`` block, even by an exception such as KeyboardInterrupt) finalizes it and
    moves it onto ``path``, so every message written before close is in the bag. ``abort()``
    discards it. An existing ``path`` is refused unless ``overwrite=True``, as
    ``ros2 bag record`` refuses an existing output.
    """

    def __init__(self, path: str | os.PathLike, storage: str | None = None, *, overwrite: bool = False):
        self.target = resolve_target(path, storage)
        self.path = self.target.path
        self._lock = threading.RLock()
        self._staged = StagedBag(self.target, overwrite=overwrite)
        self._connections: dict[str, object] = {}
        self.message_count = 0
        self.closed = False
        try:
            self._writer = Writer(
                self._staged.bag_dir, version=ROSBAG2_VERSION, storage_plugin=STORAGE_PLUGIN[self.target.storage]
            )
            self._writer.open()
        except BaseException:
            self._staged.discard()
            raise

    def add_topic(self, topic: str, msgtype: str, *, msgdef: str | None = None, rihs01: str | None = None) -> None:
        """Declare a topic; ``msgtype`` like 'sensor_msgs/msg/JointState'. Idempotent per topic."""
        with self._lock:
            self._check_open()
            if topic in self._connections:
                if self._connections[topic].msgtype != msgtype:
                    raise UserError(f"{self.path}: topic {topic} was added as {self._connections[topic].msgtype}, not {msgtype}")
                return
            store = None
            if msgdef is None or rihs01 is None:
                if msgtype not in typestore().fielddefs:
                    raise UserError(f"{self.path}: message type {msgtype} of {topic} is not a known ROS 2 type; pass msgdef and rihs01")
                store = typestore()
            self._connections[topic] = self._writer.add_connection(
                topic, msgtype, typestore=store, msgdef=msgdef, rihs01=rihs01
            )

    def write(self, topic: str, timestamp_ns: int, data: bytes | bytearray | memoryview) -> None:
        """Append one serialized (CDR) message of a topic added with ``add_topic``."""
        with self._lock:
            self._check_open()
            conn = self._connections.get(topic)
            if conn is None:
                raise UserError(f"{self.path}: topic {topic} was not added; call add_topic first")
            self._writer.write(conn, int(timestamp_ns), bytes(data))
            self.message_count += 1

    def close(self) -> None:
        """Finalize the bag and move it onto ``path``. Safe to call more than once."""
        with self._lock:
            if self.closed:
                return
            self.closed = True
            try:
                self._writer.close()
                self._staged.publish()
            except (OSError, WriterError) as exc:
                with suppress(Exception):
                    self._writer.abort()
                raise UserError(f"{self.path}: cannot finalize the bag: {exc}") from exc
            finally:
                self._staged.discard()

    def abort(self) -> None:
        """Discard everything written; ``path`` is left as it was."""
        with self._lock:
            if self.closed:
                return
            self.closed = True
            with suppress(Exception):
                self._writer.abort()
            self._staged.discard()

    def _check_open(self) -> None:
        if self.closed:
            raise UserError(f"{self.path}: the bag is closed")

    def __enter__(self) -> "BagWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        self.close()
        return False

    def __del__(self):
        # A writer dropped without close() keeps what it recorded rather than a staging dir.
        if not getattr(self, "closed", True):
            with suppress(Exception):
                self.close()
