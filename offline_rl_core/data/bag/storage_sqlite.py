"""rosbag2's sqlite3 storage (schema 4), written so that a killed writer loses at most
one flush.

Writing: the database is in WAL mode; each flush inserts its messages and refreshes the
``metadata`` row in one transaction, then checkpoints the WAL into the main file and
truncates it. So the main file alone (what readers that open it immutable, like rosbags,
see) holds every flush but the one in progress, and WAL-aware readers (sqlite, rosbag2,
this package) also see a commit whose checkpoint was cut short. Closing checkpoints and
switches the file back to a rollback journal: a closed bag is one plain ``.db3`` file.

Reading: ``WalSqlite3Reader`` is rosbags' reader opened WAL-aware, for a file whose
``-wal`` sidecar holds commits (a live recording, or one killed mid-checkpoint).
``repair_sqlite`` folds the WAL in and rewrites the metadata row (``ros2 bag reindex``).

Integrity: rosbag2's sqlite3 format has no checksums, so a flipped bit in a payload, a
stamp or a topic id would read back as a silently different row. Files written here carry
one more table, ``offline_rl_digest`` (ignored by rosbag2 and rosbags): per topic, the
message count, the sum of the payloads' CRC32s and the sum of the stamps, updated in the
same transaction as the messages. Readers here check it (``MessageDigest``).
"""

from __future__ import annotations

import os
import sqlite3
import zlib
from dataclasses import dataclass
from pathlib import Path

import apsw
from rosbags.interfaces import Connection, ConnectionExtRosbag2, MessageDefinition, MessageDefinitionFormat
from rosbags.rosbag2.errors import ReaderError
from rosbags.rosbag2.metadata import ReaderMetadata, parse_qos
from rosbags.rosbag2.storage_sqlite3 import Sqlite3Reader
from ruamel.yaml import YAML

from ...common.errors import UserError
from .metadata import ROSBAG2_VERSION, FileStats, Topic

SQLITE_MAGIC = b"SQLite format 3\x00"  # the first 16 bytes of every sqlite3 database file
SCHEMA_VERSION = 4
SCHEMA = """
CREATE TABLE schema(schema_version INTEGER PRIMARY KEY, ros_distro TEXT NOT NULL);
CREATE TABLE metadata(id INTEGER PRIMARY KEY, metadata_version INTEGER NOT NULL, metadata TEXT NOT NULL);
CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT NOT NULL, type TEXT NOT NULL,
  serialization_format TEXT NOT NULL, offered_qos_profiles TEXT NOT NULL, type_description_hash TEXT NOT NULL);
CREATE TABLE message_definitions(id INTEGER PRIMARY KEY, topic_type TEXT NOT NULL, encoding TEXT NOT NULL,
  encoded_message_definition TEXT NOT NULL, type_description_hash TEXT NOT NULL);
CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, timestamp INTEGER NOT NULL, data BLOB NOT NULL);
CREATE INDEX timestamp_idx ON messages (timestamp ASC);
CREATE TABLE offline_rl_digest(topic_id INTEGER PRIMARY KEY, messages INTEGER NOT NULL,
  crc_sum INTEGER NOT NULL, stamp_sum INTEGER NOT NULL);
"""
DIGEST_TABLE = "offline_rl_digest"
_MOD = 1 << 63  # sums stay within sqlite's signed 64-bit integers


@dataclass
class MessageDigest:
    """Order-independent digest of a topic's messages: any flipped bit in a payload or a
    stamp, and any message lost or added, changes it."""

    messages: int = 0
    crc_sum: int = 0
    stamp_sum: int = 0

    def add(self, stamp: int, data: bytes) -> None:
        self.messages += 1
        self.crc_sum = (self.crc_sum + zlib.crc32(data)) % _MOD
        self.stamp_sum = (self.stamp_sum + stamp) % _MOD

    def add_many(self, stamps: list[int], payloads: list[bytes]) -> None:
        self.messages += len(payloads)
        self.crc_sum = (self.crc_sum + sum(map(zlib.crc32, payloads))) % _MOD
        self.stamp_sum = (self.stamp_sum + sum(stamps)) % _MOD

    def merged(self, other: "MessageDigest") -> "MessageDigest":
        return MessageDigest(self.messages + other.messages, (self.crc_sum + other.crc_sum) % _MOD,
                             (self.stamp_sum + other.stamp_sum) % _MOD)


def stored_digest(db, topic_ids: list[int]) -> MessageDigest | None:
    """The digest a file stores for these topics together; None if it keeps none."""
    if not _columns(db, DIGEST_TABLE):
        return None
    total = MessageDigest()
    rows = {tid: MessageDigest(n, c, s) for tid, n, c, s in db.execute(f"SELECT * FROM {DIGEST_TABLE}")}
    for tid in topic_ids:
        total = total.merged(rows.get(tid, MessageDigest()))
    return total


def wal_path(path: Path) -> Path:
    return Path(f"{path}-wal")


def has_pending_wal(path: Path) -> bool:
    """Whether ``path``'s WAL holds frames not known to be in the main file."""
    try:
        return wal_path(path).stat().st_size > 0
    except FileNotFoundError:
        return False


class SqliteFileWriter:
    """One ``.db3`` storage file being recorded (see the module docstring)."""

    suffix = ".db3"

    def __init__(self, path: Path, distro: str):
        self.path = path
        os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644))  # never over a file
        # timeout=0: a checkpoint never waits for a reader's snapshot (it copies what it can
        # and the next flush goes on); in WAL mode nothing else here can wait.
        self.conn = sqlite3.connect(path, isolation_level=None, check_same_thread=False, timeout=0)
        self.conn.execute("PRAGMA journal_mode=WAL")
        self.conn.execute("PRAGMA synchronous=NORMAL")  # fsync at each checkpoint
        self.conn.execute("PRAGMA wal_autocheckpoint=0")  # the flush checkpoints
        self.conn.executescript("BEGIN;" + SCHEMA)  # the schema in one transaction
        self.conn.execute("INSERT INTO schema VALUES (?, ?)", (SCHEMA_VERSION, distro))
        self.conn.execute("COMMIT")
        self._types: set[str] = set()
        self._digests: dict[int, MessageDigest] = {}
        self._checkpoint()

    def flush(self, topics: list[Topic], messages: list[tuple[int, int, bytes]], metadata_text: str) -> None:
        """Commit new topics and messages ((topic id, stamp, bytes)) and the metadata."""
        cur = self.conn.cursor()
        cur.execute("BEGIN")
        try:
            for t in topics:
                if t.msgtype not in self._types:
                    cur.execute(
                        "INSERT INTO message_definitions (topic_type, encoding, encoded_message_definition, "
                        "type_description_hash) VALUES (?, ?, ?, ?)",
                        (t.msgtype, t.encoding, t.msgdef, t.rihs01),
                    )
                    self._types.add(t.msgtype)
                cur.execute(
                    "INSERT INTO topics VALUES (?, ?, ?, ?, ?, ?)",
                    (t.id, t.name, t.msgtype, t.serialization_format, t.qos, t.rihs01),
                )
            cur.executemany("INSERT INTO messages (topic_id, timestamp, data) VALUES (?, ?, ?)", messages)
            changed = {}
            for tid, stamp, data in messages:
                digest = changed.get(tid) or changed.setdefault(tid, MessageDigest(**vars(self._digests.get(tid, MessageDigest()))))
                digest.add(stamp, data)
            cur.executemany(f"INSERT OR REPLACE INTO {DIGEST_TABLE} VALUES (?, ?, ?, ?)",
                            [(tid, d.messages, d.crc_sum, d.stamp_sum) for tid, d in changed.items()])
            cur.execute("INSERT OR REPLACE INTO metadata VALUES (1, ?, ?)", (ROSBAG2_VERSION, metadata_text))
            cur.execute("COMMIT")
        except BaseException:
            if self.conn.in_transaction:
                self.conn.rollback()
            raise
        self._digests.update(changed)
        self._checkpoint()

    def _checkpoint(self) -> None:
        # A reader holding a snapshot can keep part of the WAL back; the next flush retries.
        self.conn.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchall()

    def size(self) -> int:
        return os.path.getsize(self.path)

    def close(self) -> None:
        self._checkpoint()
        self.conn.execute("PRAGMA journal_mode=DELETE")  # removes the -wal and -shm files
        self.conn.close()


class WalSqlite3Reader(Sqlite3Reader):
    """rosbags' sqlite3 reader, opened WAL-aware with locking rather than immutable, so it
    sees every commit, also those still in the ``-wal`` file, as one consistent snapshot."""

    def open(self) -> None:
        try:
            self.dbconn = apsw.Connection(f"file:{self.path}?mode=ro", flags=apsw.SQLITE_OPEN_READONLY | apsw.SQLITE_OPEN_URI)
            self.dbconn.execute("BEGIN")  # one snapshot for the index and the messages
            self._read_index()
        except apsw.Error as exc:
            if self.dbconn is not None:
                self.dbconn.close()
                self.dbconn = None
            raise ReaderError(f"Cannot open database {self.path}: {exc}") from exc

    def _read_index(self) -> None:
        db = self.dbconn
        topics, defs, counts, (start, end, total) = read_index(db)
        self.schema = SCHEMA_VERSION if defs is not None else 3
        formats = {"ros2msg": MessageDefinitionFormat.MSG, "ros2idl": MessageDefinitionFormat.IDL}

        def msgdef(msgtype: str) -> MessageDefinition:
            encoding, text = (defs or {}).get(msgtype, ("", ""))
            return MessageDefinition(formats[encoding], text) if encoding in formats else MessageDefinition(MessageDefinitionFormat.NONE, "")

        self.connections = [
            Connection(
                tid,
                name,
                msgtype,
                msgdef(msgtype),
                digest,
                counts.get(tid, 0),
                ConnectionExtRosbag2(serialization, parse_qos(qos)),
                self,
            )
            for tid, name, msgtype, serialization, qos, digest in topics
        ]
        self.metadata = ReaderMetadata(
            end + 1 - start if total else 0, start if total else 2**63 - 1, end + 1 if total else 0, total,
            None, None, None, None,
        )


def _columns(db, table: str) -> list[str]:
    return [row[1] for row in db.execute(f"PRAGMA table_info({table})")]


def read_index(db):
    """(topics, definitions or None, counts per topic id, (first stamp, last stamp, count))
    of an open rosbag2 sqlite3 database; topics as (id, name, type, serialization, qos, hash)."""
    columns = _columns(db, "topics")
    if not columns or not _columns(db, "messages"):
        raise ReaderError("the database has no rosbag2 topics/messages tables")
    qos = "offered_qos_profiles" if "offered_qos_profiles" in columns else "''"
    digest = "type_description_hash" if "type_description_hash" in columns else "''"
    topics = list(db.execute(f"SELECT id, name, type, serialization_format, {qos}, {digest} FROM topics ORDER BY id"))
    defs = None
    if _columns(db, "message_definitions"):
        defs = {name: (enc, text) for name, enc, text in db.execute(
            "SELECT topic_type, encoding, encoded_message_definition FROM message_definitions ORDER BY id")}
    counts = dict(db.execute("SELECT topic_id, COUNT(*) FROM messages GROUP BY topic_id"))
    start, end, total = next(iter(db.execute("SELECT MIN(timestamp), MAX(timestamp), COUNT(*) FROM messages")))
    return topics, defs, counts, (start, end, total)


def scan_sqlite(path: Path) -> tuple[list[Topic], FileStats]:
    """The topics and statistics of a (closed) sqlite3 storage file, from its tables."""
    db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        topics_rows, defs, counts, _ = read_index(db)
        stats = FileStats(path.name)
        topics = []
        for tid, name, msgtype, serialization, qos, digest in topics_rows:
            text = defs.get(msgtype, ("", ""))[1] if defs else ""
            topic = Topic(tid, name, msgtype, text, digest, qos or "", serialization)
            topics.append(topic)
            if counts.get(tid):
                first, last = db.execute("SELECT MIN(timestamp), MAX(timestamp) FROM messages WHERE topic_id = ?", (tid,)).fetchone()
                stats.add(topic.key, first, counts[tid])
                stats.add(topic.key, last, 0)
        return topics, stats
    except ReaderError as exc:
        raise UserError(f"{path}: not a rosbag2 sqlite3 file ({exc})") from exc
    except sqlite3.Error as exc:
        raise UserError(f"{path}: cannot read the sqlite3 file, it may be truncated or corrupt ({exc})") from exc
    finally:
        db.close()


def _stored_count(text: str) -> int | None:
    """The message count a metadata row states, or None if it states none."""
    try:
        return int(YAML(typ="safe").load(text)["message_count"])
    except Exception:  # noqa: BLE001 - whatever the row holds, it is not a usable count
        return None


def repair_sqlite(path: Path, metadata_text) -> list[str]:
    """Fold a WAL left by a killed writer into ``path`` and rewrite its metadata row.

    ``metadata_text(topics, stats)`` renders the metadata to store. Each step is an
    sqlite transaction, so a repair that is itself interrupted can be run again.
    Returns what was done, one line per step.
    """
    done = []
    if has_pending_wal(path):
        done.append(f"folded {wal_path(path).stat().st_size} bytes of write-ahead log into {path.name}")
    # A WAL left beside the file is a killed writer's: fold it in and leave WAL mode, so the
    # file stands alone. A WAL-mode file closed by its writer (rosbag2's resilient preset)
    # has none, and is left in its mode.
    left_wal = wal_path(path).exists()
    try:
        db = sqlite3.connect(path, isolation_level=None)
        try:
            if left_wal:
                db.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchall()
                if db.execute("PRAGMA journal_mode=DELETE").fetchone()[0] != "delete":
                    raise UserError(f"{path}: cannot leave WAL mode (another process has it open?)")
            check = db.execute("PRAGMA quick_check").fetchone()[0]
            if check != "ok":
                raise UserError(f"{path}: the sqlite3 file is corrupt ({check}); it cannot be repaired in place")
        finally:
            db.close()
        topics, stats = scan_sqlite(path)
        text = metadata_text(topics, stats)
        db = sqlite3.connect(path, isolation_level=None)
        try:
            db.execute("BEGIN")
            db.execute("CREATE TABLE IF NOT EXISTS metadata(id INTEGER PRIMARY KEY, metadata_version INTEGER NOT NULL, metadata TEXT NOT NULL)")
            old = db.execute("SELECT metadata FROM metadata ORDER BY id DESC LIMIT 1").fetchone()
            if old is None or done or _stored_count(old[0]) != stats.message_count:
                db.execute("DELETE FROM metadata")
                db.execute("INSERT INTO metadata VALUES (1, ?, ?)", (ROSBAG2_VERSION, text))
                done.append(f"{'rewrote' if old else 'wrote'} the metadata of {path.name} ({stats.message_count} messages)")
            db.execute("COMMIT")
        finally:
            db.close()
    except sqlite3.Error as exc:
        raise UserError(f"{path}: cannot repair the sqlite3 file ({exc})") from exc
    return done
