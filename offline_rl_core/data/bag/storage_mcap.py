"""rosbag2's MCAP storage, written so that the file is a complete MCAP after every flush.

Layout (the MCAP spec's, as rosbag2 writes it): magic, Header (profile ``ros2``), then the
data section: Schema and Channel records, one Chunk per flush (CRC-checked messages)
followed by its MessageIndex records; then, rewritten at every flush, the tail: the
``rosbag2`` Metadata record, DataEnd, the summary (schemas, channels, chunk indexes,
metadata index, statistics), summary offsets and the Footer.

A flush cuts the file back to the end of the data section and writes the new chunk and a
new tail in one write, so a reader sees a complete file with everything flushed. A writer
killed inside that write (a window of a few writes per flush) leaves a file that ends
without its footer: readers refuse it with one line, and ``mcap_scan.repair_mcap`` (like
``mcap recover``) keeps every whole record and writes the tail again.
"""

from __future__ import annotations

import os
import struct
from binascii import crc32
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

from rosbags.rosbag2.errors import ReaderError

from .metadata import FileStats, Topic

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK, OP_MESSAGE_INDEX, OP_CHUNK_INDEX = range(1, 9)
OP_ATTACHMENT, OP_ATTACHMENT_INDEX, OP_STATISTICS, OP_METADATA, OP_METADATA_INDEX, OP_SUMMARY_OFFSET, OP_DATA_END = range(9, 16)
FOOTER_SIZE = 1 + 8 + 20 + len(MAGIC)
LIBRARY = "offline_rl_core rosbag2 writer"

u16, u32, u64 = (struct.Struct(f"<{c}").pack for c in "HIQ")
CHUNK_HEAD = struct.Struct("<QQQI")  # start, end, uncompressed size, crc
MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel, sequence, log time, publish time


def str_field(text: str | bytes) -> bytes:
    data = text.encode() if isinstance(text, str) else text
    return u32(len(data)) + data


def map_field(items: dict[str, str]) -> bytes:
    body = b"".join(str_field(k) + str_field(v) for k, v in items.items())
    return u32(len(body)) + body


def record(op: int, body: bytes) -> bytes:
    return bytes((op,)) + u64(len(body)) + body


class Cursor:
    """Reads the fields of one record body; a short body raises ReaderError."""

    def __init__(self, body: bytes, pos: int = 0):
        self.body, self.pos = body, pos

    def take(self, n: int) -> bytes:
        if self.pos + n > len(self.body):
            raise ReaderError(f"record field runs past its record ({self.pos + n} > {len(self.body)} bytes)")
        out = self.body[self.pos : self.pos + n]
        self.pos += n
        return out

    def int(self, fmt: str) -> int:
        return struct.unpack(fmt, self.take(struct.calcsize(fmt)))[0]

    def bytes(self) -> bytes:
        return self.take(self.int("<I"))

    def str(self) -> str:
        return self.bytes().decode("utf-8", "replace")

    def map(self) -> dict[str, str]:
        sub = Cursor(self.bytes())
        out = {}
        while sub.pos < len(sub.body):
            key = sub.str()
            out[key] = sub.str()
        return out


@dataclass
class ChunkInfo:
    offset: int
    length: int
    start: int
    end: int
    uncompressed_size: int
    compressed_size: int
    compression: str = ""
    index_offsets: dict[int, int] = field(default_factory=dict)  # channel -> MessageIndex offset
    index_length: int = 0
    message_counts: dict[int, int] = field(default_factory=dict)  # channel -> messages in the chunk

    def index_record(self) -> bytes:
        offsets = b"".join(u16(cid) + u64(off) for cid, off in sorted(self.index_offsets.items()))
        return record(
            OP_CHUNK_INDEX,
            u64(self.start) + u64(self.end) + u64(self.offset) + u64(self.length) + u32(len(offsets)) + offsets
            + u64(self.index_length) + str_field(self.compression) + u64(self.compressed_size) + u64(self.uncompressed_size),
        )


@dataclass
class McapIndex:
    """Everything the tail of an MCAP file summarizes."""

    schemas: dict[int, tuple[str, str, bytes]] = field(default_factory=dict)  # id -> name, encoding, data
    channels: dict[int, tuple[int, str, str, dict[str, str]]] = field(default_factory=dict)  # id -> schema, topic, encoding, metadata
    chunks: list[ChunkInfo] = field(default_factory=list)
    counts: dict[int, int] = field(default_factory=dict)
    start: int | None = None
    end: int | None = None

    def count(self, channel: int, stamp: int) -> None:
        self.counts[channel] = self.counts.get(channel, 0) + 1
        self.start = stamp if self.start is None else min(self.start, stamp)
        self.end = stamp if self.end is None else max(self.end, stamp)

    def add_counts(self, counts: dict[int, int], start: int, end: int) -> None:
        """Messages per channel, stamped from ``start`` to ``end``."""
        for channel, n in counts.items():
            self.counts[channel] = self.counts.get(channel, 0) + n
        self.start = start if self.start is None else min(self.start, start)
        self.end = end if self.end is None else max(self.end, end)

    def schema_record(self, sid: int) -> bytes:
        name, encoding, data = self.schemas[sid]
        return record(OP_SCHEMA, u16(sid) + str_field(name) + str_field(encoding) + str_field(data))

    def channel_record(self, cid: int) -> bytes:
        sid, topic, encoding, metadata = self.channels[cid]
        return record(OP_CHANNEL, u16(cid) + u16(sid) + str_field(topic) + str_field(encoding) + map_field(metadata))

    def add_topic(self, topic: Topic) -> bytes:
        """Register a topic; returns the Schema (if its type is new) and Channel records."""
        out = b""
        sid = next((s for s, (name, _, _) in self.schemas.items() if name == topic.msgtype), None)
        if sid is None:
            sid = len(self.schemas) + 1
            self.schemas[sid] = (topic.msgtype, topic.encoding, topic.msgdef.encode())
            out += self.schema_record(sid)
        metadata = {"offered_qos_profiles": topic.qos, "topic_type_hash": topic.rihs01}
        self.channels[topic.id] = (sid, topic.name, topic.serialization_format, metadata)
        return out + self.channel_record(topic.id)

    def topics(self) -> list[Topic]:
        out = []
        for cid, (sid, name, encoding, metadata) in sorted(self.channels.items()):
            msgtype, _, data = self.schemas.get(sid, ("", "", b""))
            out.append(Topic(cid, name, msgtype, data.decode("utf-8", "replace"), metadata.get("topic_type_hash", ""),
                             metadata.get("offered_qos_profiles", ""), encoding))
        return out

    def stats(self, name: str) -> FileStats:
        stats = FileStats(name)
        keys = {t.id: t.key for t in self.topics()}
        for cid, n in self.counts.items():
            if cid in keys:
                stats.counts[keys[cid]] = stats.counts.get(keys[cid], 0) + n
        stats.start_ns, stats.end_ns = self.start, self.end
        return stats

    def tail(self, data_end: int, metadata_text: str) -> bytes:
        """The rosbag2 Metadata record, DataEnd, summary, summary offsets and Footer, for a
        data section ending at ``data_end``."""
        metadata = record(OP_METADATA, str_field("rosbag2") + map_field({"serialized_metadata": metadata_text}))
        out = bytearray(metadata + record(OP_DATA_END, u32(0)))
        summary_start = data_end + len(out)
        counts = b"".join(u16(cid) + u64(n) for cid, n in sorted(self.counts.items()))
        statistics = record(
            OP_STATISTICS,
            u64(sum(self.counts.values())) + u16(len(self.schemas)) + u32(len(self.channels)) + u32(0) + u32(1)
            + u32(len(self.chunks)) + u64(self.start or 0) + u64(self.end or 0) + u32(len(counts)) + counts,
        )
        groups = [
            (OP_SCHEMA, [self.schema_record(s) for s in sorted(self.schemas)]),
            (OP_CHANNEL, [self.channel_record(c) for c in sorted(self.channels)]),
            (OP_CHUNK_INDEX, [c.index_record() for c in self.chunks]),
            (OP_METADATA_INDEX, [record(OP_METADATA_INDEX, u64(data_end) + u64(len(metadata)) + str_field("rosbag2"))]),
            (OP_STATISTICS, [statistics]),
        ]
        offsets = []
        for op, records in groups:
            if records:
                body = b"".join(records)
                offsets.append(record(OP_SUMMARY_OFFSET, bytes((op,)) + u64(data_end + len(out)) + u64(len(body))))
                out += body
        summary_offset_start = data_end + len(out)
        out += b"".join(offsets)
        # The footer's CRC covers the summary: a flipped bit there is caught, not misread.
        footer_head = bytes((OP_FOOTER,)) + u64(20) + u64(summary_start) + u64(summary_offset_start)
        crc = crc32(footer_head, crc32(out[summary_start - data_end :]))
        out += footer_head + u32(crc) + MAGIC
        return bytes(out)


def chunk_records(index: McapIndex, offset: int, messages: list[tuple[int, int, bytes]]) -> bytes:
    """A Chunk of ``messages`` ((channel, stamp, bytes)) at file ``offset`` and its
    MessageIndex records; adds the chunk to ``index``."""
    body = bytearray()
    entries: dict[int, list[tuple[int, int]]] = defaultdict(list)
    for cid, stamp, data in messages:
        entries[cid].append((stamp, len(body)))
        body += record(OP_MESSAGE, MESSAGE_HEAD.pack(cid, 0, stamp, stamp) + data)
        index.count(cid, stamp)
    stamps = [stamp for _, stamp, _ in messages]
    start, end = min(stamps), max(stamps)
    chunk = record(OP_CHUNK, CHUNK_HEAD.pack(start, end, len(body), crc32(body)) + str_field("") + u64(len(body)) + body)
    info = ChunkInfo(offset, len(chunk), start, end, len(body), len(body))
    for cid in entries:
        info.message_counts[cid] = len(entries[cid])
    out = bytearray(chunk)
    for cid in sorted(entries):
        info.index_offsets[cid] = offset + len(out)
        pairs = b"".join(u64(stamp) + u64(at) for stamp, at in sorted(entries[cid]))
        out += record(OP_MESSAGE_INDEX, u16(cid) + u32(len(pairs)) + pairs)
    info.index_length = len(out) - len(chunk)
    index.chunks.append(info)
    return bytes(out)


def pwrite_all(fd: int, data: bytes, offset: int) -> None:
    view = memoryview(data)
    while view:
        n = os.pwrite(fd, view, offset)
        view, offset = view[n:], offset + n


class McapFileWriter:
    """One ``.mcap`` storage file being recorded (see the module docstring)."""

    suffix = ".mcap"

    def __init__(self, path: Path, distro: str):
        self.path = path
        self.fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)  # never over a file
        self.index = McapIndex()
        head = MAGIC + record(OP_HEADER, str_field("ros2") + str_field(LIBRARY))
        self.data_end = 0
        self._append(head, "")

    def flush(self, topics: list[Topic], messages: list[tuple[int, int, bytes]], metadata_text: str) -> None:
        body = b"".join(self.index.add_topic(t) for t in topics)
        if messages:
            body += chunk_records(self.index, self.data_end + len(body), messages)
        self._append(body, metadata_text)

    def _append(self, body: bytes, metadata_text: str) -> None:
        data = body + self.index.tail(self.data_end + len(body), metadata_text)
        # Cut the old tail, then write: a write cut short leaves a file without a footer
        # (refused, repairable), never an old footer pointing into new bytes. Only these
        # two system calls are the window.
        os.ftruncate(self.fd, self.data_end)
        pwrite_all(self.fd, data, self.data_end)
        os.fdatasync(self.fd)
        self.data_end += len(body)

    def size(self) -> int:
        return os.fstat(self.fd).st_size

    def close(self) -> None:
        os.close(self.fd)
