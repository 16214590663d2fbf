"""Reading transitions from any rosbag2 bag: a directory, a bare ``.db3`` or ``.mcap`` file.

Only ``/pusher/transition`` is read; other topics are ignored and need no definitions. Raw
CDR payloads are fetched without deserializing (for sqlite3 storage, one SQL query on the
``messages`` table) and decoded together by ``decode_transitions``.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager, suppress
from pathlib import Path

import numpy as np
from rosbags.interfaces import MessageDefinitionFormat
from rosbags.rosbag2 import Reader
from rosbags.rosbag2.metadata import ReaderMetadata
from rosbags.rosbag2.reader import DirectoryReader
from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader

from ...common.errors import UserError
from ..transitions import Layout, Transitions
from .cdr import TRANSITION_MSGTYPE, TRANSITION_TOPIC, TransitionDecodeError, decode_transitions
from .mcap_reader import CheckedMcapReader
from .paths import SUFFIX_STORAGE, storage_files
from .storage_sqlite import SQLITE_MAGIC, MessageDigest, WalSqlite3Reader, stored_digest, wal_path

RECORD_HINT = "record one with `offline-rl collect` or `ros2 run recorder node`"


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 300 else text[:297] + "..."


def check_bag_path(path: Path) -> None:
    """Refuse, in one line, a path that cannot be a rosbag2 bag."""
    if not path.exists():
        raise UserError(f"{path}: no such file or directory")
    if path.is_dir():
        if not (path / "metadata.yaml").is_file() and not storage_files(path):
            raise UserError(f"{path} is not a rosbag2 bag: the directory has no metadata.yaml and no .db3 or .mcap files")
    elif path.suffix.lower() not in SUFFIX_STORAGE:
        raise UserError(f"{path} is not a rosbag2 bag: expected a bag directory, or a .db3 or .mcap file")


def check_sqlite_size(path: Path) -> None:
    """Refuse a sqlite3 file shorter than its header says: SQLite would read it silently."""
    with path.open("rb") as f:
        header = f.read(100)
    if len(header) < 100 or not header.startswith(SQLITE_MAGIC):
        return  # not sqlite at all: SQLite itself reports it
    page_size = int.from_bytes(header[16:18], "big")
    page_size = 65536 if page_size == 1 else page_size
    pages = int.from_bytes(header[28:32], "big")
    header_valid = header[24:28] == header[92:96]  # in-header page count is current
    size = path.stat().st_size
    if size % page_size or (header_valid and size < pages * page_size):
        raise UserError(
            f"{path}: the sqlite3 file is truncated ({size} bytes; its header says {pages * page_size}); "
            "the bag may have been copied or recorded incompletely"
        )


def sqlite_storage(path: Path) -> Sqlite3Reader:
    """rosbags' sqlite3 reader, WAL-aware while the file has a WAL (a live recording, or
    one killed): rosbags opens files immutable, which a recorder's next flush would change
    under it, even when its WAL was just emptied into the file."""
    return WalSqlite3Reader(path) if wal_path(Path(path)).exists() else Sqlite3Reader(path)


class BagDirectoryReader(DirectoryReader):
    """rosbags' reader of a bag directory, with the storages above; when metadata.yaml
    lags its files (a recording killed between a flush and the metadata update), the
    counts come from the files, which hold the messages."""

    STORAGE_PLUGINS = {"mcap": CheckedMcapReader, "sqlite3": sqlite_storage}

    def open(self) -> None:
        super().open()
        total = sum(s.metadata.message_count for s in self.storages)
        if total == self.metadata.message_count:
            return
        counts: dict[tuple[str, str], int] = {}
        extra = {}
        for storage in self.storages:
            for conn in storage.connections:
                key = (conn.topic, conn.msgtype)
                counts[key] = counts.get(key, 0) + conn.msgcount
                extra.setdefault(key, conn)
        known = {(c.topic, c.msgtype) for c in self.connections}
        self.connections = [c._replace(msgcount=counts.get((c.topic, c.msgtype), 0)) for c in self.connections]
        for key, conn in extra.items():
            if key not in known:
                self.connections.append(conn._replace(id=len(self.connections) + 1, msgcount=counts[key], owner=self))
        starts = [s.metadata.start_time for s in self.storages if s.metadata.message_count]
        ends = [s.metadata.end_time for s in self.storages if s.metadata.message_count]
        start, end = (min(starts), max(ends)) if starts else (2**63 - 1, 0)
        self.metadata = self.metadata._replace(
            duration=end - start if starts else 0, start_time=start, end_time=end, message_count=total
        )


class StorageFilesReader(DirectoryReader):
    """A bag directory without metadata.yaml (its recorder died before writing it, or it was
    copied without it): the storage files describe themselves, so they are read as they are,
    in split order (what ``ros2 bag reindex`` would list). Topics of split files match by
    name and type."""

    STORAGE_PLUGINS = BagDirectoryReader.STORAGE_PLUGINS

    def __init__(self, path: Path):  # DirectoryReader's own needs metadata.yaml
        self.path = path
        self.connections = []
        self.metadata = ReaderMetadata(0, 2**63 - 1, 0, 0, None, None, None, None)
        self.files = []
        self.storages = []
        self.stack = None

    def open(self) -> None:
        self.stack = ExitStack()
        try:
            paths = storage_files(self.path)
            kinds = {SUFFIX_STORAGE[p.suffix.lower()] for p in paths}
            if len(kinds) != 1:
                raise UserError(f"{self.path}: holds both sqlite3 and MCAP files; expected one storage per bag")
            plugin = self.STORAGE_PLUGINS[kinds.pop()]
            for file in paths:
                storage = plugin(file)
                storage.open()
                self.stack.callback(storage.close)
                self.storages.append(storage)
            self._describe(paths)
        except BaseException:
            with suppress(Exception):
                self.close()
            raise

    def _describe(self, paths: list[Path]) -> None:
        merged: dict[tuple[str, str], object] = {}
        for storage in self.storages:
            for conn in storage.connections:
                key = (conn.topic, conn.msgtype)
                if key not in merged:
                    merged[key] = conn._replace(id=len(merged) + 1, msgcount=0, owner=self)
                old = merged[key]
                if old.msgdef.format == MessageDefinitionFormat.NONE:
                    old = old._replace(msgdef=conn.msgdef)
                merged[key] = old._replace(msgcount=old.msgcount + conn.msgcount)
        self.connections = list(merged.values())
        counted = [s.metadata for s in self.storages if s.metadata.message_count]
        total = sum(m.message_count for m in counted)
        start = min((m.start_time for m in counted), default=2**63 - 1)
        end = max((m.end_time for m in counted), default=0)
        self.metadata = ReaderMetadata(end - start if total else 0, start, end, total, None, None, None, None)
        self.files = [
            {"path": p.name, "message_count": s.metadata.message_count,
             "starting_time": {"nanoseconds_since_epoch": s.metadata.start_time if s.metadata.message_count else 0},
             "duration": {"nanoseconds": s.metadata.duration}}
            for p, s in zip(paths, self.storages)
        ]

    def messages(self, connections, start=None, stop=None):
        wanted = {(c.topic, c.msgtype): c for c in connections}
        for storage in self.storages:
            conns = [c for c in storage.connections if (c.topic, c.msgtype) in wanted]
            if conns:
                for conn, stamp, data in storage.messages(conns, start, stop):
                    yield wanted[(conn.topic, conn.msgtype)], stamp, data


def directory_reader(path: Path) -> DirectoryReader:
    """The reader of a bag directory: from its metadata.yaml, or from its files alone."""
    return BagDirectoryReader(path) if (Path(path) / "metadata.yaml").is_file() else StorageFilesReader(path)


class BagReader(Reader):
    """rosbags' Reader with the storages above."""

    STORAGE_PLUGINS = {"dir": directory_reader, ".mcap": CheckedMcapReader, ".db3": sqlite_storage}


@contextmanager
def open_bag(path: str | os.PathLike) -> Iterator[Reader]:
    """A rosbags Reader on a bag, opened and closed; rosbags and storage failures as UserError."""
    path = Path(path)
    check_bag_path(path)
    try:
        reader = BagReader(path)
        reader.open()
        for storage in sqlite_storages(reader) or ():
            if not isinstance(storage, WalSqlite3Reader):  # SQLite reads a WAL'd file's size itself
                check_sqlite_size(Path(storage.path))
    except UserError:
        raise
    except Exception as exc:  # rosbags, apsw, YAML and struct errors all mean "unreadable"
        raise UserError(f"{path}: cannot open the bag, it may be truncated or corrupt ({_one_line(exc)})") from exc
    try:
        yield reader
    except (UserError, KeyboardInterrupt):
        raise
    except Exception as exc:
        raise UserError(f"{path}: cannot read the bag, it may be truncated or corrupt ({_one_line(exc)})") from exc
    finally:
        try:
            reader.close()
        except Exception:
            pass


def sqlite_storages(reader: Reader) -> list[Sqlite3Reader] | None:
    """The sqlite3 storage files of a bag whose payloads can be read straight from SQL."""
    storage = reader.storage
    if isinstance(storage, Sqlite3Reader):
        return [storage]
    if (
        isinstance(storage, DirectoryReader)
        and not storage.metadata.compression_mode
        and storage.storages
        and all(isinstance(s, Sqlite3Reader) for s in storage.storages)
    ):
        return list(storage.storages)
    return None


PAYLOAD_CHUNK = 65536


def topic_payload_chunks(reader: Reader, topic: str, chunk: int = PAYLOAD_CHUNK) -> Iterator[list[bytes]]:
    """Raw CDR payloads of a topic in timestamp order, ``chunk`` at a time, without
    deserializing any: a large bag is decoded block by block, never held as one list."""
    connections = [c for c in reader.connections if c.topic == topic]
    if not connections:
        return
    sqlite_files = sqlite_storages(reader)
    if sqlite_files is None:  # MCAP or compressed: rosbags yields raw bytes
        sources = [(data for _, _, data in reader.messages(connections))]
    else:
        sources = []
        for storage in sqlite_files:
            ids = [c.id for c in storage.connections if c.topic == topic]
            if ids:
                sources.append(_sqlite_payloads(storage, ids, topic, chunk))
    for source in sources:
        while block := list(itertools.islice(source, chunk)):
            yield block


def _sqlite_payloads(storage: Sqlite3Reader, ids: list[int], topic: str, chunk: int) -> Iterator[bytes]:
    """A topic's payloads from one sqlite3 file, checked against the file's digest when it
    keeps one (files written by this package's recorder do)."""
    marks = ",".join("?" * len(ids))
    expected = stored_digest(storage.dbconn, ids)
    if expected is None:
        query = f"SELECT data FROM messages WHERE topic_id IN ({marks}) ORDER BY timestamp, id"
        yield from (row[0] for row in storage.dbconn.execute(query, ids))
        return
    got = MessageDigest()
    rows = storage.dbconn.execute(f"SELECT timestamp, data FROM messages WHERE topic_id IN ({marks}) ORDER BY timestamp, id", ids)
    while block := list(itertools.islice(rows, chunk)):
        stamps, payloads = zip(*block)
        got.add_many(stamps, payloads)
        yield from payloads
    if got != expected:
        what = f"{got.messages} messages where it recorded {expected.messages}" if got.messages != expected.messages else "their content"
        raise UserError(f"{storage.path}: {topic}: the file is corrupt: {what} do not match the digest stored with them")


def topic_payloads(reader: Reader, topic: str) -> list[bytes]:
    """Raw CDR payloads of a topic in timestamp order, without deserializing any."""
    return [p for block in topic_payload_chunks(reader, topic) for p in block]


def _finite_problem(path: Path, bad_rows: int, total: int, bad_columns: set[int], layout: Layout) -> UserError:
    fields = list(dict.fromkeys(layout.field_of_column(int(c)) for c in sorted(bad_columns)))
    return UserError(
        f"{path}: {bad_rows} of {total} {TRANSITION_TOPIC} rows hold NaN or inf "
        f"(in field{'s' if len(fields) > 1 else ''} {', '.join(fields)})"
    )


def one_topic(reader: Reader, name: str) -> str | None:
    """``name`` in the bag, or the one namespaced copy of it (``/arm2/pusher/transition``,
    recorded under ``__ns:=/arm2``)."""
    names = {c.topic for c in reader.connections}
    if name in names:
        return name
    namespaced = [n for n in names if n.endswith(name)]
    return namespaced[0] if len(namespaced) == 1 else None


def transition_topic(reader: Reader) -> str | None:
    """The bag's transition topic: /pusher/transition, or the one namespaced copy of it."""
    return one_topic(reader, TRANSITION_TOPIC)


def records_transitions(path) -> bool:
    """Whether the bag records transitions (else it holds a robot's raw topics to join)."""
    with open_bag(path) as reader:
        return transition_topic(reader) is not None


def _transition_connections(reader: Reader, path: Path) -> list:
    if reader.message_count == 0:
        raise UserError(f"{path} is an empty bag (no messages); {RECORD_HINT}")
    topic = transition_topic(reader)
    connections = [c for c in reader.connections if c.topic == topic]
    if not connections:
        found = ", ".join(sorted({c.topic for c in reader.connections})) or "none"
        raise UserError(f"{path} has no {TRANSITION_TOPIC} topic (found: {found}); {RECORD_HINT}")
    types = sorted({c.msgtype for c in connections})
    if types != [TRANSITION_MSGTYPE]:
        raise UserError(f"{path}: {topic} has type {', '.join(types)}; expected {TRANSITION_MSGTYPE}")
    return connections


def _decode_into(reader: Reader, path: Path, put) -> int:
    """Decode /pusher/transition block by block, handing each (k, width) block and its
    layout to ``put(start, rows, layout)``; checks that every block has one layout, and
    finiteness; returns the row count."""
    topic = _transition_connections(reader, path)[0].topic
    total, bad_rows, bad_columns = 0, 0, set()
    layout = None
    for payloads in topic_payload_chunks(reader, topic):
        try:
            rows, block_layout = decode_transitions(payloads)
        except TransitionDecodeError as exc:
            raise UserError(f"{path}: {topic}: {exc}") from exc
        if layout is not None and block_layout != layout:
            raise UserError(f"{path}: {topic}: messages of two layouts: [{layout.describe()}] and "
                            f"[{block_layout.describe()}]")
        layout = block_layout
        bad = ~np.isfinite(rows)
        if bad.any():
            bad_rows += int(bad.any(axis=1).sum())
            bad_columns.update(np.flatnonzero(bad.any(axis=0)).tolist())
        put(total, rows, layout)
        total += len(rows)
    if total == 0:
        raise UserError(f"{path}: {topic} has no messages; {RECORD_HINT}")
    if bad_rows:
        raise _finite_problem(path, bad_rows, total, bad_columns, layout)
    return total


def transition_rows_from_reader(reader: Reader, path: Path) -> np.ndarray:
    """The (N, width) float32 transition rows of an open bag, checked; UserError otherwise."""
    return transition_rows_and_layout(reader, path)[0]


def transition_rows_and_layout(reader: Reader, path: Path) -> tuple[np.ndarray, Layout]:
    """The transition rows of an open bag and the layout they carry."""
    blocks: list[np.ndarray] = []
    layouts: list[Layout] = []
    _decode_into(reader, path, lambda start, rows, layout: (blocks.append(rows), layouts.append(layout)))
    return np.concatenate(blocks), layouts[0]


def read_transition_rows(path: str | os.PathLike) -> np.ndarray:
    """The (N, width) float32 rows of ``/pusher/transition`` in a bag, in timestamp order."""
    with open_bag(path) as reader:
        return transition_rows_from_reader(reader, Path(path))


def count_transition_messages(path: str | os.PathLike) -> int:
    """The /pusher/transition messages a bag's index counts; no payload is read."""
    with open_bag(path) as reader:
        return sum(c.msgcount for c in _transition_connections(reader, Path(path)))


def read_transitions(path: str | os.PathLike) -> Transitions:
    """The transitions of a rosbag2 bag (a directory, or a bare .db3/.mcap file).

    Raises UserError, one line naming the file, for a missing path, something that is not a
    bag, a corrupt or empty bag, one without ``/pusher/transition``, an unknown layout, or
    rows holding NaN/inf. Rows are decoded a block at a time straight into the columns,
    so reading needs little more memory than the arrays it returns.
    """
    path = Path(path)
    with open_bag(path) as reader:
        expected = sum(c.msgcount for c in _transition_connections(reader, path))
        out: Transitions | None = None  # allocated once the first block says the layout
        blocks: list[np.ndarray] = []  # only if the index under-counted

        def put(start: int, rows: np.ndarray, layout: Layout) -> None:
            nonlocal out
            if out is None:
                out = Transitions.empty(expected, layout)
            fit = max(0, min(len(rows), expected - start))
            if fit:
                out.fill_rows(start, rows[:fit])
            if fit < len(rows):
                blocks.append(rows[fit:])

        total = _decode_into(reader, path, put)
    if blocks:  # more messages than the metadata said: append the extra rows
        return Transitions.concatenate([out, Transitions.from_rows(np.concatenate(blocks), out.layout)])
    return out if total == expected else out.select(slice(0, total))
