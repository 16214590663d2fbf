"""rosbag2's MCAP storage, written so that the file is a complete MCAP after every flush.

Layout (the MCAP spec's, as rosbag2 writes it): magic, Header (profile ``ros2``), then the
data section: Schema and Channel records, one Chunk per flush (CRC-checked messages)
followed by its MessageIndex records; then, rewritten at every flush, the tail: the
``rosbag2`` Metadata record, DataEnd, the summary (schemas, channels, chunk indexes,
metadata index, statistics), summary offsets and the Footer.

A flush cuts the file back to the end of the data section and writes the new chunk and a
new tail in one write, so a reader sees a complete file with everything flushed. A writer
killed inside that write (a window of a few writes per flush) leaves a file that ends
without its footer: readers refuse it with one line, and ``repair_mcap`` (like
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
from rosbags.rosbag2.storage_mcap import decompress

from ...common.errors import UserError
from .metadata import FileStats, Topic

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK, OP_MESSAGE_INDEX, OP_CHUNK_INDEX = range(1, 9)
OP_ATTACHMENT, OP_ATTACHMENT_INDEX, OP_STATISTICS, OP_METADATA, OP_METADATA_INDEX, OP_SUMMARY_OFFSET, OP_DATA_END = range(9, 16)
FOOTER_SIZE = 1 + 8 + 20 + len(MAGIC)
LIBRARY = "offline_rl_core rosbag2 writer"

u16, u32, u64 = (struct.Struct(f"<{c}").pack for c in "HIQ")
_CHUNK_HEAD = struct.Struct("<QQQI")  # start, end, uncompressed size, crc
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel, sequence, log time, publish time


def _str(text: str | bytes) -> bytes:
    data = text.encode() if isinstance(text, str) else text
    return u32(len(data)) + data


def _map(items: dict[str, str]) -> bytes:
    body = b"".join(_str(k) + _str(v) for k, v in items.items())
    return u32(len(body)) + body


def record(op: int, body: bytes) -> bytes:
    return bytes((op,)) + u64(len(body)) + body


class _Cursor:
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
        sub = _Cursor(self.bytes())
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

    def index_record(self) -> bytes:
        offsets = b"".join(u16(cid) + u64(off) for cid, off in sorted(self.index_offsets.items()))
        return record(
            OP_CHUNK_INDEX,
            u64(self.start) + u64(self.end) + u64(self.offset) + u64(self.length) + u32(len(offsets)) + offsets
            + u64(self.index_length) + _str(self.compression) + u64(self.compressed_size) + u64(self.uncompressed_size),
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

    def schema_record(self, sid: int) -> bytes:
        name, encoding, data = self.schemas[sid]
        return record(OP_SCHEMA, u16(sid) + _str(name) + _str(encoding) + _str(data))

    def channel_record(self, cid: int) -> bytes:
        sid, topic, encoding, metadata = self.channels[cid]
        return record(OP_CHANNEL, u16(cid) + u16(sid) + _str(topic) + _str(encoding) + _map(metadata))

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
        metadata = record(OP_METADATA, _str("rosbag2") + _map({"serialized_metadata": metadata_text}))
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
            (OP_METADATA_INDEX, [record(OP_METADATA_INDEX, u64(data_end) + u64(len(metadata)) + _str("rosbag2"))]),
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
        body += record(OP_MESSAGE, _MESSAGE_HEAD.pack(cid, 0, stamp, stamp) + data)
        index.count(cid, stamp)
    stamps = [stamp for _, stamp, _ in messages]
    start, end = min(stamps), max(stamps)
    chunk = record(OP_CHUNK, _CHUNK_HEAD.pack(start, end, len(body), crc32(body)) + _str("") + u64(len(body)) + body)
    info = ChunkInfo(offset, len(chunk), start, end, len(body), len(body))
    out = bytearray(chunk)
    for cid in sorted(entries):
        info.index_offsets[cid] = offset + len(out)
        pairs = b"".join(u64(stamp) + u64(at) for stamp, at in sorted(entries[cid]))
        out += record(OP_MESSAGE_INDEX, u16(cid) + u32(len(pairs)) + pairs)
    info.index_length = len(out) - len(chunk)
    index.chunks.append(info)
    return bytes(out)


def _pwrite_all(fd: int, data: bytes, offset: int) -> None:
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
        head = MAGIC + record(OP_HEADER, _str("ros2") + _str(LIBRARY))
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
        _pwrite_all(self.fd, data, self.data_end)
        os.fdatasync(self.fd)
        self.data_end += len(body)

    def size(self) -> int:
        return os.fstat(self.fd).st_size

    def close(self) -> None:
        os.close(self.fd)


# ------------------------------------------------------------------ checking and repair
def has_footer(path: Path) -> bool:
    """Whether an MCAP file ends with a Footer record and the closing magic."""
    size = path.stat().st_size
    if size < len(MAGIC) + FOOTER_SIZE:
        return False
    with path.open("rb") as f:
        f.seek(size - FOOTER_SIZE)
        tail = f.read(FOOTER_SIZE)
    return tail.endswith(MAGIC) and tail[0] == OP_FOOTER and tail[1:9] == u64(20)


def summary_problem(path: Path) -> str | None:
    """Why the summary of an MCAP file with a footer cannot be trusted (its CRC, when the
    writer stored one, does not match), else None."""
    size = path.stat().st_size
    with path.open("rb") as f:
        f.seek(size - FOOTER_SIZE)
        footer = f.read(FOOTER_SIZE)
        summary_start, _, crc = struct.unpack_from("<QQI", footer, 9)
        if not crc:
            return None
        if not len(MAGIC) <= summary_start <= size - FOOTER_SIZE:
            return f"the footer points its summary at byte {summary_start}, outside the file"
        f.seek(summary_start)
        covered = f.read(size - FOOTER_SIZE - summary_start) + footer[:25]
    return None if crc32(covered) == crc else "the summary does not match its checksum"


@dataclass
class McapScan:
    """What a record-by-record scan of an MCAP file found."""

    index: McapIndex
    keep_end: int  # end of the last data record worth keeping
    size: int
    complete: bool  # the scan reached DataEnd and the file has its footer
    problem: str = ""  # why the scan stopped before DataEnd
    has_header: bool = True  # the Header record is whole
    reindex_last_chunk: list[tuple[int, int, bytes]] | None = None  # its MessageIndex was cut off


def _chunk_messages(body: bytes, path: Path, offset: int) -> tuple[ChunkInfo, list[tuple[int, int, int]]]:
    cur = _Cursor(body)
    start, end, size, crc = _CHUNK_HEAD.unpack(cur.take(_CHUNK_HEAD.size))
    compression = cur.str()
    compressed = cur.take(cur.int("<Q"))
    try:
        data = decompress(compressed, compression, size, crc)
    except ReaderError as exc:
        raise UserError(f"{path}: the chunk at byte {offset} is corrupt ({exc})") from exc
    except Exception as exc:  # lz4 / zstd errors
        raise UserError(f"{path}: the chunk at byte {offset} does not decompress ({exc})") from exc
    messages = []
    inner = 0
    while inner < len(data):
        if inner + 9 > len(data):
            raise UserError(f"{path}: the chunk at byte {offset} holds a cut record")
        op, length = data[inner], struct.unpack_from("<Q", data, inner + 1)[0]
        if inner + 9 + length > len(data):
            raise UserError(f"{path}: the chunk at byte {offset} holds a record running past it")
        if op == OP_MESSAGE:
            if length < _MESSAGE_HEAD.size:
                raise UserError(f"{path}: the chunk at byte {offset} holds a message record of {length} bytes")
            cid, _, stamp, _ = _MESSAGE_HEAD.unpack_from(data, inner + 9)
            messages.append((cid, stamp, inner))
        inner += 9 + length
    info = ChunkInfo(offset, 9 + len(body), start, end, size, len(compressed), compression)
    return info, messages


def scan_mcap(path: Path) -> McapScan:
    """Read an MCAP file record by record up to DataEnd, rebuilding its index; stops at a
    record cut off by the end of the file (a killed writer). Corruption raises UserError."""
    size = path.stat().st_size
    index = McapIndex()
    with path.open("rb") as f:
        if f.read(len(MAGIC)) != MAGIC:
            raise UserError(f"{path}: not an MCAP file (bad magic)")
        pos, keep_end, problem, reached_end = len(MAGIC), len(MAGIC), "", False
        last_chunk: tuple[ChunkInfo, list] | None = None
        indexed: set[int] = set()
        while True:
            head = f.read(9)
            if len(head) < 9:
                problem = f"the file ends inside a record header at byte {pos}" if head else "the file ends without its summary"
                break
            op, length = head[0], struct.unpack_from("<Q", head, 1)[0]
            if not OP_HEADER <= op <= OP_DATA_END:
                problem = f"unknown record 0x{op:02x} at byte {pos}"
                break
            if pos + 9 + length > size:
                problem = f"the record at byte {pos} is cut off by the end of the file"
                break
            if op == OP_DATA_END:
                reached_end = True
                break
            body = f.read(length)
            cur = _Cursor(body)
            try:
                if op == OP_HEADER:
                    if cur.str() != "ros2":
                        raise UserError(f"{path}: the MCAP profile is not ros2")
                elif op == OP_SCHEMA:
                    sid = cur.int("<H")
                    index.schemas[sid] = (cur.str(), cur.str(), cur.bytes())
                elif op == OP_CHANNEL:
                    cid, sid = cur.int("<H"), cur.int("<H")
                    index.channels[cid] = (sid, cur.str(), cur.str(), cur.map())
                elif op == OP_MESSAGE:
                    cid, _, stamp, _ = _MESSAGE_HEAD.unpack_from(body)
                    index.count(cid, stamp)
                elif op == OP_CHUNK:
                    info, messages = _chunk_messages(body, path, pos)
                    for cid, stamp, _ in messages:
                        index.count(cid, stamp)
                    index.chunks.append(info)
                    last_chunk, indexed = (info, messages), set()
                elif op == OP_MESSAGE_INDEX and last_chunk is not None:
                    cid = cur.int("<H")
                    last_chunk[0].index_offsets[cid] = pos
                    last_chunk[0].index_length += 9 + length
                    indexed.add(cid)
            except (ReaderError, struct.error) as exc:
                raise UserError(f"{path}: the record at byte {pos} is corrupt ({exc})") from exc
            pos += 9 + length
            if not (op == OP_METADATA and cur.str() == "rosbag2"):  # the tail's, rewritten by repair
                keep_end = pos
        scan = McapScan(index, keep_end, size, reached_end and has_footer(path), problem, keep_end > len(MAGIC))
        if last_chunk is not None:
            info, messages = last_chunk
            if {cid for cid, _, _ in messages} - indexed:  # its MessageIndex records were cut off
                keep_end = info.offset + info.length
                info.index_offsets, info.index_length = {}, 0
                scan.keep_end = keep_end
                scan.reindex_last_chunk = messages
    return scan


def repair_mcap(path: Path, metadata_text) -> list[str]:
    """Make a truncated MCAP file whole again, in place: keep every whole record, drop the
    cut one, write the message indexes of the last chunk if they were cut, then the tail.

    Only bytes after the last whole record are replaced, so a repair that is itself
    interrupted leaves a file this repairs again. ``metadata_text(topics, stats)``
    renders the rosbag2 metadata. Returns what was done, one line per step.
    """
    scan = scan_mcap(path)
    if scan.complete and scan.reindex_last_chunk is None:
        return []
    index = scan.index
    done = [f"{scan.problem or 'no summary'}; kept {scan.keep_end} of {scan.size} bytes of {path.name}"]
    body = b"" if scan.has_header else record(OP_HEADER, _str("ros2") + _str(LIBRARY))
    if scan.reindex_last_chunk is not None:
        info = index.chunks[-1]
        entries: dict[int, list[tuple[int, int]]] = defaultdict(list)
        for cid, stamp, at in scan.reindex_last_chunk:
            entries[cid].append((stamp, at))
        for cid in sorted(entries):
            info.index_offsets[cid] = scan.keep_end + len(body)
            pairs = b"".join(u64(stamp) + u64(at) for stamp, at in sorted(entries[cid]))
            body += record(OP_MESSAGE_INDEX, u16(cid) + u32(len(pairs)) + pairs)
        info.index_length = sum(len(record(OP_MESSAGE_INDEX, b"")) + 6 + 16 * len(e) for e in entries.values())
        done.append(f"rebuilt the message index of the last chunk ({len(scan.reindex_last_chunk)} messages)")
    text = metadata_text(index.topics(), index.stats(path.name))
    with path.open("r+b") as f:
        fd = f.fileno()
        os.ftruncate(fd, scan.keep_end)
        _pwrite_all(fd, body + index.tail(scan.keep_end + len(body), text), scan.keep_end)
        os.fsync(fd)
    done.append(f"wrote the summary of {path.name} ({sum(index.counts.values())} messages in {len(index.chunks)} chunks)")
    return done
