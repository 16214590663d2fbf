"""Bags in every layout their writers can give: MCAP files from Foxglove's own ``mcap``
writer in each combination of its documented options and as rosbag2's MCAP plugin's
storage presets set them, and sqlite3 files as rosbag2's sqlite3 plugin writes them, with
and without its ``resilient`` preset.

The messages are real ones: ``messages_of(bag)`` reads what a bag holds (stamps, payloads,
types) with rosbags, so the same messages can be written again in another layout and the
reader checked against them.
"""

from __future__ import annotations

import itertools
import sqlite3
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

from mcap.writer import CompressionType, IndexType, Writer
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import Reader

from offline_rl_core.data.bag.metadata import (
    FileStats, bag_metadata, make_topic, qos_text, storage_metadata_text, typestore, write_metadata_yaml,
)

REPO = Path(__file__).resolve().parents[1]
MIX = REPO / "bags" / "mix.db3"
_NO_TIME = QosTime(0, 0)
RELIABLE = Qos(QosHistory.KEEP_LAST, 10, QosReliability.RELIABLE, QosDurability.VOLATILE, _NO_TIME, _NO_TIME,
               QosLiveliness.AUTOMATIC, _NO_TIME, False)
QOS = qos_text([RELIABLE])  # offered_qos_profiles as rosbag2 v9 stores it


@dataclass(frozen=True)
class Message:
    topic: str
    msgtype: str
    stamp: int
    data: bytes


def messages_of(bag: Path, limit: int | None = None, topics: set[str] | None = None) -> list[Message]:
    """A bag's messages in timestamp order, as rosbags reads them (the first ``limit``)."""
    out = []
    with Reader(bag) as reader:
        conns = [c for c in reader.connections if topics is None or c.topic in topics]
        for conn, stamp, data in reader.messages(connections=conns):
            out.append(Message(conn.topic, conn.msgtype, stamp, bytes(data)))
            if limit is not None and len(out) == limit:
                break
    return out


# ------------------------------------------------------------------ MCAP, Foxglove's writer
INDEXES = {"all": IndexType.ALL, "chunk": IndexType.CHUNK, "none": IndexType.NONE}
OPTIONS = ("use_chunking", "use_statistics", "use_summary_offsets", "repeat_channels", "repeat_schemas")


def writer_layouts() -> dict[str, dict]:
    """Every combination of the writer's layout options (the full cross product, each valid
    MCAP), by a name listing the options switched off."""
    out = {}
    for flags in itertools.product((True, False), repeat=len(OPTIONS)):
        for index in INDEXES:
            options = dict(zip(OPTIONS, flags), index_types=INDEXES[index])
            off = ["no_" + name.removeprefix("use_") for name, on in zip(OPTIONS, flags) if not on]
            out["-".join(off + ([] if index == "all" else [f"index_{index}"])) or "default"] = options
    return out


def spec_valid(options: dict) -> bool:
    """Whether a layout keeps the specification's two rules on the summary: a Chunk Index's
    channels (its message index offsets) MUST have their Schema and Channel records in the
    summary, and Statistics with per-channel counts MUST come with every Channel record. The
    other layouts are read as well: the data section holds everything."""
    indexed_chunks = options["use_chunking"] and IndexType.MESSAGE in options["index_types"] \
        and IndexType.CHUNK in options["index_types"]
    if indexed_chunks and not (options["repeat_channels"] and options["repeat_schemas"]):
        return False
    return not (options["use_statistics"] and not options["repeat_channels"])


def write_mcap(path: Path, messages: list[Message], *, compression: CompressionType = CompressionType.ZSTD,
               chunk_size: int = 4096, enable_crcs: bool = True, rosbag2_metadata: bool = False,
               extra_records: bool = False, **options) -> Path:
    """``messages`` as an MCAP file (profile ros2) from the ``mcap`` library's Writer; small
    chunks by default, so that a few hundred messages fill several. ``extra_records``: an
    attachment and a metadata record every 100 messages, as a recorder may add."""
    store = typestore()
    with path.open("wb") as f:
        writer = Writer(f, compression=compression, chunk_size=chunk_size, enable_crcs=enable_crcs, **options)
        writer.start(profile="ros2", library="mcap-python (bag_layouts)")
        schemas, channels = {}, {}
        for i, m in enumerate(messages):
            if m.msgtype not in schemas:
                msgdef = store.generate_msgdef(m.msgtype, ros_version=2)[0]
                schemas[m.msgtype] = writer.register_schema(m.msgtype, "ros2msg", msgdef.encode())
            if m.topic not in channels:
                metadata = {"offered_qos_profiles": QOS, "topic_type_hash": store.hash_rihs01(m.msgtype)}
                channels[m.topic] = writer.register_channel(m.topic, "cdr", schemas[m.msgtype], metadata)
            writer.add_message(channels[m.topic], log_time=m.stamp, data=m.data, publish_time=m.stamp)
            if extra_records and i % 100 == 99:
                writer.add_attachment(m.stamp, m.stamp, "calibration.yaml", "application/yaml", b"gain: 1.5\n" * 50)
                writer.add_metadata("session", {"operator": "test", "at": str(m.stamp)})
        if rosbag2_metadata:  # rosbag2's plugin stores the bag's metadata in the file
            writer.add_metadata("rosbag2", {"serialized_metadata": _embedded_metadata(path.name, messages, "mcap")})
        writer.finish()
    return path


def _embedded_metadata(name: str, messages: list[Message], storage_id: str) -> str:
    topics, stats = _topics_and_stats(name, messages)
    return storage_metadata_text(bag_metadata(storage_id, [stats], topics))


def _topics_and_stats(name: str, messages: list[Message]):
    topics = {}
    stats = FileStats(name)
    for m in messages:
        if m.topic not in topics:
            topics[m.topic] = make_topic(len(topics) + 1, m.topic, m.msgtype, qos=[RELIABLE])
        stats.add(topics[m.topic].key, m.stamp)
    return list(topics.values()), stats


def set_summary_crc(path: Path) -> None:
    """Store the footer's summary CRC: rosbag2 turns off the chunks' CRCs but keeps this one,
    where the ``mcap`` writer has one switch for both."""
    data = bytearray(path.read_bytes())
    footer = len(data) - 8 - 29
    summary_start = struct.unpack_from("<Q", data, footer + 9)[0]
    covered = data[summary_start or footer : footer + 25]
    data[footer + 25 : footer + 29] = struct.pack("<I", zlib.crc32(covered))
    path.write_bytes(bytes(data))


def _zstd_level(level: int):
    """The ``mcap`` writer's zstd at another level (it has no option for one)."""
    import zstandard

    class Level:
        def __getattr__(self, name):
            return getattr(zstandard, name)

        @staticmethod
        def compress(data: bytes) -> bytes:
            return zstandard.ZstdCompressor(level=level).compress(data)

    return Level()


# rosbag2_storage_mcap's presets (SetOptionsForPreset in mcap_storage.cpp), over the plugin's
# own defaults (no chunk CRC, no compression); the C++ writer's zstd levels: Fastest -5,
# Slowest 19; its default chunk size 768 KiB. ``noSummary`` is McapWriterOptions' own switch,
# which a storage config file can set.
ROSBAG2_PRESETS = {
    "none": dict(compression=CompressionType.NONE, chunk_size=768 * 1024, crc="summary"),
    "fastwrite": dict(compression=CompressionType.NONE, use_chunking=False, crc="none"),
    "zstd_fast": dict(compression=CompressionType.ZSTD, chunk_size=768 * 1024, zstd_level=-5, crc="summary"),
    "zstd_small": dict(compression=CompressionType.ZSTD, chunk_size=4 * 1024 * 1024, zstd_level=19, crc="summary"),
    "noSummary": dict(compression=CompressionType.NONE, chunk_size=768 * 1024, crc="none", use_statistics=False,
                      repeat_channels=False, repeat_schemas=False, use_summary_offsets=False,
                      index_types=IndexType.MESSAGE),
}


def write_rosbag2_mcap(path: Path, messages: list[Message], preset: str, chunk_size: int | None = None) -> Path:
    """An MCAP file laid out as rosbag2's MCAP plugin writes it with ``preset``."""
    import mcap.writer as mcap_writer

    options = dict(ROSBAG2_PRESETS[preset])
    crc = options.pop("crc")
    level = options.pop("zstd_level", None)
    if chunk_size is not None and "chunk_size" in options:
        options["chunk_size"] = chunk_size
    real = mcap_writer.zstandard
    mcap_writer.zstandard = _zstd_level(level) if level is not None else real
    try:
        write_mcap(path, messages, enable_crcs=False, rosbag2_metadata=True, **options)
    finally:
        mcap_writer.zstandard = real
    if crc == "summary":
        set_summary_crc(path)
    return path


# ------------------------------------------------------------------ sqlite3, rosbag2's schema
ROSBAG2_SQLITE_SCHEMA = """
CREATE TABLE schema(schema_version INTEGER PRIMARY KEY, ros_distro TEXT NOT NULL);
CREATE TABLE metadata(id INTEGER PRIMARY KEY, metadata_version INTEGER NOT NULL, metadata TEXT NOT NULL);
CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT NOT NULL, type TEXT NOT NULL,
  serialization_format TEXT NOT NULL, offered_qos_profiles TEXT NOT NULL, type_description_hash TEXT NOT NULL);
CREATE TABLE message_definitions(id INTEGER PRIMARY KEY, topic_type TEXT NOT NULL, encoding TEXT NOT NULL,
  encoded_message_definition TEXT NOT NULL, type_description_hash TEXT NOT NULL);
CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, timestamp INTEGER NOT NULL, data BLOB NOT NULL);
CREATE INDEX timestamp_idx ON messages (timestamp ASC);
"""
# rosbag2_storage_sqlite3's SqlitePragmas: optimized_writing_pragmas (preset "none") and
# robust_writing_pragmas (preset "resilient").
SQLITE_PRESETS = {
    "none": ("PRAGMA journal_mode=MEMORY", "PRAGMA synchronous=OFF"),
    "resilient": ("PRAGMA journal_mode=WAL", "PRAGMA synchronous=NORMAL"),
}


def write_rosbag2_sqlite(path: Path, messages: list[Message], preset: str = "none") -> Path:
    """A .db3 file as rosbag2's sqlite3 plugin writes it (schema 4, its pragmas, one
    transaction per batch, the metadata row at close)."""
    topics, _ = _topics_and_stats(path.name, messages)
    ids = {t.name: t.id for t in topics}
    db = sqlite3.connect(path, isolation_level=None)
    try:
        for pragma in SQLITE_PRESETS[preset]:
            db.execute(pragma).fetchall()
        db.executescript(ROSBAG2_SQLITE_SCHEMA)
        db.execute("INSERT INTO schema VALUES (4, 'kilted')")
        for t in topics:
            db.execute("INSERT INTO message_definitions (topic_type, encoding, encoded_message_definition, "
                       "type_description_hash) VALUES (?, ?, ?, ?)", (t.msgtype, t.encoding, t.msgdef, t.rihs01))
            db.execute("INSERT INTO topics VALUES (?, ?, ?, 'cdr', ?, ?)", (t.id, t.name, t.msgtype, QOS, t.rihs01))
        for start in range(0, len(messages), 100):  # rosbag2 commits its cache in batches
            db.execute("BEGIN")
            db.executemany("INSERT INTO messages (topic_id, timestamp, data) VALUES (?, ?, ?)",
                           [(ids[m.topic], m.stamp, m.data) for m in messages[start : start + 100]])
            db.execute("COMMIT")
        db.execute("INSERT INTO metadata (metadata_version, metadata) VALUES (9, ?)",
                   (_embedded_metadata(path.name, messages, "sqlite3"),))
    finally:
        db.close()
    return path


def bag_directory(path: Path, files: list[Path], storage_id: str, messages_per_file: list[list[Message]],
                  with_metadata_yaml: bool) -> Path:
    """``files`` (already in ``path``) as a bag directory, with or without metadata.yaml."""
    if with_metadata_yaml:
        stats, topics = [], []
        for file, messages in zip(files, messages_per_file):
            file_topics, file_stats = _topics_and_stats(file.name, messages)
            topics += file_topics
            stats.append(file_stats)
        write_metadata_yaml(path, bag_metadata(storage_id, stats, topics))
    return path
