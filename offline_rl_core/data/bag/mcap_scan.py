"""What an MCAP file holds, whatever its writer put in its summary; and repair.

The MCAP specification makes every part of the summary optional: a writer may leave out the
statistics, the repeated schemas and channels, the chunk or message indexes, or the whole
summary (summary start 0 in the footer). Readers that trust the summary alone then see no
topics, no messages or types without schemas. Here:

- ``has_footer`` / ``summary_problem``: whether the file ends whole, and whether its footer
  and summary agree with the footer's CRC.
- ``read_summary`` / ``summary_gaps``: what the summary holds, and what it lacks for reading
  the file from it alone.
- ``scan_mcap``: the data section read record by record, chunks decompressed and their CRCs
  checked: the schemas and channels (also those inside chunks), every chunk's message counts
  and where the messages outside chunks are, i.e. the index a complete summary would give.
- ``repair_mcap``: a file cut off by a kill made whole again, like ``mcap recover``.
"""

from __future__ import annotations

import os
import struct
from array import array
from binascii import crc32
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path

from rosbags.rosbag2.errors import ReaderError
from rosbags.rosbag2.storage_mcap import decompress

from ...common.errors import UserError
from .storage_mcap import (
    CHUNK_HEAD, FOOTER_SIZE, LIBRARY, MAGIC, MESSAGE_HEAD, OP_CHANNEL, OP_CHUNK, OP_CHUNK_INDEX, OP_DATA_END,
    OP_FOOTER, OP_HEADER, OP_MESSAGE, OP_MESSAGE_INDEX, OP_METADATA, OP_SCHEMA, OP_STATISTICS, ChunkInfo, Cursor,
    McapIndex, pwrite_all, record, str_field, u16, u32, u64,
)

_RECORD_HEAD = struct.Struct("<BQ")
_MESSAGE_INDEX_HEAD = 9 + 2 + 4  # record head, channel id, array length; then 16 bytes per message


# ------------------------------------------------------------------ the footer
def has_footer(path: Path) -> bool:
    """Whether an MCAP file ends with a Footer record and the closing magic."""
    size = path.stat().st_size
    if size < len(MAGIC) + FOOTER_SIZE:
        return False
    with path.open("rb") as f:
        f.seek(size - FOOTER_SIZE)
        tail = f.read(FOOTER_SIZE)
    return tail.endswith(MAGIC) and tail[0] == OP_FOOTER and tail[1:9] == u64(20)


def footer_fields(path: Path) -> tuple[int, int, int]:
    """(summary start, summary offset start, summary CRC) of a file with a footer."""
    with path.open("rb") as f:
        f.seek(path.stat().st_size - FOOTER_SIZE)
        return struct.unpack_from("<QQI", f.read(FOOTER_SIZE), 9)


def summary_problem(path: Path) -> str | None:
    """Why the footer or summary of an MCAP file with a footer cannot be trusted, else None.

    Summary start 0 means the file has no summary (the spec allows it); the CRC, when the
    writer stored one, covers the summary and the footer's fields before it, so with no
    summary it covers those fields alone."""
    size = path.stat().st_size
    footer_start = size - FOOTER_SIZE
    summary_start, _, crc = footer_fields(path)
    if summary_start and not len(MAGIC) <= summary_start <= footer_start:
        return f"the footer points its summary at byte {summary_start}, outside the file"
    if not crc:
        return None
    with path.open("rb") as f:
        f.seek(summary_start or footer_start)
        covered = f.read(footer_start + 25 - (summary_start or footer_start))
    return None if crc32(covered) == crc else "the summary does not match its checksum"


# ------------------------------------------------------------------ the summary
@dataclass
class McapStatistics:
    message_count: int
    schema_count: int
    channel_count: int
    chunk_count: int
    channel_message_counts: dict[int, int]


@dataclass
class McapSummary:
    """The summary records that say what the data section holds."""

    schemas: set[int] = field(default_factory=set)
    channels: dict[int, int] = field(default_factory=dict)  # channel id -> schema id
    chunk_messages: list[int | None] = field(default_factory=list)  # per Chunk Index; None: no message index
    statistics: McapStatistics | None = None


def _id_map(cur: Cursor) -> dict[int, int]:
    """A Map<uint16, uint64> field."""
    body = cur.bytes()
    if len(body) % 10:
        raise ReaderError(f"a map of {len(body)} bytes is not whole (uint16, uint64) pairs")
    return dict(struct.iter_unpack("<HQ", body))


def _indexed_messages(chunk_end: int, offsets: dict[int, int], index_length: int) -> int | None:
    """Messages a chunk's Message Index records list, from their offsets and lengths (each
    record is its head and 16 bytes per message); None where the chunk has no message index."""
    if not offsets:
        return None
    starts = sorted(offsets.values())
    ends = starts[1:] + [chunk_end + index_length]
    return sum(max(0, (end - start - _MESSAGE_INDEX_HEAD) // 16) for start, end in zip(starts, ends))


def read_summary(path: Path, summary_start: int) -> McapSummary:
    """The summary section of a file whose footer was checked (``summary_problem``)."""
    footer_start = path.stat().st_size - FOOTER_SIZE
    with path.open("rb") as f:
        f.seek(summary_start)
        data = f.read(footer_start - summary_start)
    summary = McapSummary()
    pos = 0
    try:
        while pos < len(data):
            op, length = _RECORD_HEAD.unpack_from(data, pos)
            body = data[pos + 9 : pos + 9 + length]
            if len(body) < length:
                raise ReaderError(f"the record at byte {summary_start + pos} runs past the summary")
            cur = Cursor(body)
            if op == OP_SCHEMA:
                summary.schemas.add(cur.int("<H"))
            elif op == OP_CHANNEL:
                cid, sid = cur.int("<H"), cur.int("<H")
                summary.channels[cid] = sid
            elif op == OP_CHUNK_INDEX:
                _, _, offset, chunk_length = struct.unpack("<QQQQ", cur.take(32))
                offsets = _id_map(cur)
                summary.chunk_messages.append(_indexed_messages(offset + chunk_length, offsets, cur.int("<Q")))
            elif op == OP_STATISTICS:
                count, schemas, channels, _, _, chunks, _, _ = struct.unpack("<QHIIIIQQ", cur.take(42))
                summary.statistics = McapStatistics(count, schemas, channels, chunks, _id_map(cur))
            pos += 9 + length
    except (ReaderError, struct.error) as exc:
        raise UserError(f"{path}: the MCAP file is corrupt: its summary does not parse ({exc})") from exc
    return summary


def summary_gaps(summary: McapSummary | None) -> list[str]:
    """What a summary lacks for reading the file from it alone (empty: nothing). Only the
    Statistics record says how much the data section holds, so without it the rest of the
    summary cannot be checked against the data."""
    if summary is None:
        return ["no summary"]
    stats = summary.statistics
    if stats is None:
        return ["no statistics"]
    gaps = []
    if stats.message_count and sum(stats.channel_message_counts.values()) != stats.message_count:
        gaps.append("no message counts per channel")
    if len(summary.channels) < stats.channel_count or not set(stats.channel_message_counts) <= set(summary.channels):
        gaps.append("channels not repeated")
    if any(sid and sid not in summary.schemas for sid in summary.channels.values()):
        gaps.append("schemas not repeated")
    if stats.chunk_count:
        if len(summary.chunk_messages) != stats.chunk_count:
            gaps.append("no chunk index")
        elif None in summary.chunk_messages:
            gaps.append("no message index")
        elif sum(summary.chunk_messages) != stats.message_count:
            gaps.append("messages outside the indexed chunks")
    return gaps


# ------------------------------------------------------------------ the data section
@dataclass
class LooseMessages:
    """Message records outside chunks, in file order: channel, stamp and where the payload is."""

    channel: array = field(default_factory=lambda: array("H"))
    stamp: array = field(default_factory=lambda: array("Q"))
    offset: array = field(default_factory=lambda: array("Q"))
    size: array = field(default_factory=lambda: array("Q"))

    def __len__(self) -> int:
        return len(self.channel)


@dataclass
class McapScan:
    """What a record-by-record scan of an MCAP file found."""

    index: McapIndex
    keep_end: int  # end of the last data record worth keeping
    size: int
    complete: bool  # the scan reached the end of the data section and the file has its footer
    problem: str = ""  # why the scan stopped before the end of the data section
    has_header: bool = True  # the Header record is whole
    data_start: int = 0  # the first byte after the Header record
    loose: LooseMessages = field(default_factory=LooseMessages)
    last_chunk_indexed: set[int] = field(default_factory=set)  # channels of the Message Index after the last chunk


def _decompressed_chunk(body: bytes, path: Path, offset: int) -> tuple[ChunkInfo, bytes]:
    cur = Cursor(body)
    start, end, size, crc = CHUNK_HEAD.unpack(cur.take(CHUNK_HEAD.size))
    compression = cur.str()
    compressed = cur.take(cur.int("<Q"))
    try:
        data = decompress(compressed, compression, size, crc)
    except ReaderError as exc:
        raise UserError(f"{path}: the chunk at byte {offset} is corrupt ({exc})") from exc
    except Exception as exc:  # lz4 / zstd errors
        raise UserError(f"{path}: the chunk at byte {offset} is corrupt: it does not decompress ({exc})") from exc
    return ChunkInfo(offset, 9 + len(body), start, end, size, len(compressed), compression), data


def _add_schema(index: McapIndex, cur: Cursor) -> None:
    sid = cur.int("<H")
    if sid:  # schema id 0 is invalid and ignored (the spec)
        index.schemas[sid] = (cur.str(), cur.str(), cur.bytes())


def _add_channel(index: McapIndex, cur: Cursor) -> None:
    cid, sid = cur.int("<H"), cur.int("<H")
    index.channels[cid] = (sid, cur.str(), cur.str(), cur.map())


def _scan_chunk(body: bytes, path: Path, offset: int, index: McapIndex) -> ChunkInfo:
    """A chunk's schemas and channels into ``index``, and its messages counted. The walk is
    the per-message cost of a scan: one unpack and two appends; counting and the stamp range
    come after, at C speed."""
    info, data = _decompressed_chunk(body, path, offset)
    channels, stamps = array("H"), array("Q")
    unpack_head, unpack_message = _RECORD_HEAD.unpack_from, MESSAGE_HEAD.unpack_from
    pos, size = 0, len(data)
    while pos < size:
        if pos + 9 > size:
            raise UserError(f"{path}: the chunk at byte {offset} holds a cut record")
        op, length = unpack_head(data, pos)
        start, pos = pos + 9, pos + 9 + length
        if pos > size:
            raise UserError(f"{path}: the chunk at byte {offset} holds a record running past it")
        if op == OP_MESSAGE:
            if length < MESSAGE_HEAD.size:
                raise UserError(f"{path}: the chunk at byte {offset} holds a message record of {length} bytes")
            cid, _, stamp, _ = unpack_message(data, start)
            channels.append(cid)
            stamps.append(stamp)
        elif op == OP_SCHEMA:
            _add_schema(index, Cursor(data[start:pos]))
        elif op == OP_CHANNEL:
            _add_channel(index, Cursor(data[start:pos]))
    if stamps:  # the messages' own stamps: the chunk header's copies are outside its CRC
        info.message_counts = dict(Counter(channels))
        info.start, info.end = min(stamps), max(stamps)
        index.add_counts(info.message_counts, info.start, info.end)
    return info


class _CheckedFile:
    """A file read forward, keeping the CRC32 of every byte read: the DataEnd record's
    checksum covers the data section from the file's first byte."""

    def __init__(self, f):
        self.f, self.crc = f, 0

    def read(self, n: int) -> bytes:
        data = self.f.read(n)
        self.crc = crc32(data, self.crc)
        return data

    def skip(self, n: int) -> None:
        while n > 0:  # in blocks: an attachment may be large
            n -= len(self.read(min(n, 1 << 20)))


def chunk_message_positions(path: Path, info: ChunkInfo) -> list[tuple[int, int, int]]:
    """(channel, stamp, offset in the chunk) of each message of a chunk: its Message Index."""
    with path.open("rb") as f:
        f.seek(info.offset + 9)
        body = f.read(info.length - 9)
    _, data = _decompressed_chunk(body, path, info.offset)
    out, pos = [], 0
    while pos + 9 <= len(data):  # the chunk was walked whole by the scan
        op, length = _RECORD_HEAD.unpack_from(data, pos)
        if op == OP_MESSAGE:
            cid, _, stamp, _ = MESSAGE_HEAD.unpack_from(data, pos + 9)
            out.append((cid, stamp, pos))  # offsets are to the record, opcode included
        pos += 9 + length
    return out


_END_NAMES = {OP_DATA_END: "DataEnd", OP_FOOTER: "Footer"}


def _closes_the_data(op: int, record_end: int, end: int | None, size: int) -> bool:
    """Whether a DataEnd or Footer record ending at ``record_end`` can be where the data
    section ends: a Footer only before the closing magic; with the data section's end known
    (``end``, from a checked footer), a DataEnd only right before it."""
    if op == OP_FOOTER:
        return record_end + len(MAGIC) == size
    return end is None or record_end == end


def scan_mcap(path: Path, end: int | None = None) -> McapScan:
    """Read an MCAP file record by record through its data section, rebuilding its index.

    The data section ends at DataEnd, at a Footer (files with neither summary nor DataEnd)
    or at ``end`` (the summary's start, from a checked footer). A record cut off by the end
    of the file (a killed writer) stops the scan; records this reader does not know are
    skipped, as the spec asks. Chunk CRCs and the data section's CRC (in DataEnd), where
    the writer stored them, are checked. Corruption raises UserError.
    """
    size = path.stat().st_size
    limit = size if end is None else end
    index, loose = McapIndex(), LooseMessages()
    with path.open("rb") as raw:
        f = _CheckedFile(raw)
        if f.read(len(MAGIC)) != MAGIC:
            raise UserError(f"{path}: not an MCAP file (bad magic)")
        pos = keep_end = data_start = len(MAGIC)
        problem, reached_end = "", False
        last_chunk: ChunkInfo | None = None
        indexed: set[int] = set()
        while True:
            if end is not None and pos == end:
                reached_end = True
                break
            data_crc = f.crc  # of every byte before this record
            head = f.read(9)
            if len(head) < 9:
                problem = f"the file ends inside a record header at byte {pos}" if head else "the file ends without its summary"
                break
            op, length = _RECORD_HEAD.unpack(head)
            if op == 0:
                problem = f"unknown record 0x00 at byte {pos}"
                break
            if pos + 9 + length > limit:
                problem = f"the record at byte {pos} " + ("is cut off by the end of the file" if limit == size
                                                          else "runs past the data section")
                break
            if op in (OP_DATA_END, OP_FOOTER):
                if not _closes_the_data(op, pos + 9 + length, end, size):
                    # a flipped opcode reads as an early end: the rest of the file would go unread
                    raise UserError(f"{path}: the MCAP file is corrupt: a {_END_NAMES[op]} record at byte {pos} "
                                    "before the end of its data section")
                stored = struct.unpack("<I", f.read(4))[0] if op == OP_DATA_END and length >= 4 else 0
                if stored and stored != data_crc:
                    raise UserError(f"{path}: the MCAP file is corrupt: its data section does not match "
                                    "the checksum in its DataEnd record")
                reached_end = True
                break
            if pos == len(MAGIC) and op != OP_HEADER:
                raise UserError(f"{path}: the MCAP file is corrupt: it does not start with a Header record")
            name = ""
            try:
                if op == OP_MESSAGE:
                    if length < MESSAGE_HEAD.size:
                        raise UserError(f"{path}: the MCAP file is corrupt: a message record of {length} bytes at byte {pos}")
                    cid, _, stamp, _ = MESSAGE_HEAD.unpack_from(f.read(length))
                    loose.channel.append(cid)
                    loose.stamp.append(stamp)
                    loose.offset.append(pos + 9 + MESSAGE_HEAD.size)
                    loose.size.append(length - MESSAGE_HEAD.size)
                elif op in (OP_HEADER, OP_SCHEMA, OP_CHANNEL, OP_CHUNK, OP_MESSAGE_INDEX, OP_METADATA):
                    body = f.read(length)
                    cur = Cursor(body)
                    if op == OP_HEADER:
                        profile = cur.str()
                        if profile != "ros2":
                            raise UserError(f"{path}: the MCAP profile is {profile!r}, not ros2")
                        data_start = pos + 9 + length
                    elif op == OP_SCHEMA:
                        _add_schema(index, cur)
                    elif op == OP_CHANNEL:
                        _add_channel(index, cur)
                    elif op == OP_CHUNK:
                        last_chunk, indexed = _scan_chunk(body, path, pos, index), set()
                        index.chunks.append(last_chunk)
                    elif op == OP_MESSAGE_INDEX and last_chunk is not None:
                        cid = cur.int("<H")
                        last_chunk.index_offsets[cid] = pos
                        last_chunk.index_length += 9 + length
                        indexed.add(cid)
                    elif op == OP_METADATA:
                        name = cur.str()
                else:  # attachments, and records of later versions or applications
                    f.skip(length)
            except (ReaderError, struct.error) as exc:
                raise UserError(f"{path}: the record at byte {pos} is corrupt ({exc})") from exc
            pos += 9 + length
            if name != "rosbag2":  # the tail's, rewritten by repair
                keep_end = pos
    if loose:
        index.add_counts(Counter(loose.channel), min(loose.stamp), max(loose.stamp))
    complete = reached_end and has_footer(path)
    return McapScan(index, keep_end, size, complete, problem, keep_end > len(MAGIC), data_start, loose, indexed)


# ------------------------------------------------------------------ repair
def repair_mcap(path: Path, metadata_text) -> list[str]:
    """Make a truncated MCAP file whole again, in place: keep every whole record, drop the
    cut one, write the message indexes of the last chunk if they were cut, then the tail.

    A whole file (its data section ends and its footer is there) is left as it is, whatever
    its summary holds: readers scan what the summary lacks. Only bytes after the last whole
    record are replaced, so a repair that is itself interrupted leaves a file this repairs
    again. ``metadata_text(topics, stats)`` renders the rosbag2 metadata. Returns what was
    done, one line per step.
    """
    scan = scan_mcap(path)
    if scan.complete:
        return []
    index = scan.index
    reindex = None
    if index.chunks and set(index.chunks[-1].message_counts) - scan.last_chunk_indexed:
        last = index.chunks[-1]  # its Message Index records were cut off: drop what is left of them
        reindex = chunk_message_positions(path, last)
        scan.keep_end = last.offset + last.length
        last.index_offsets, last.index_length = {}, 0
    done = [f"{scan.problem or 'no summary'}; kept {scan.keep_end} of {scan.size} bytes of {path.name}"]
    body = b"" if scan.has_header else record(OP_HEADER, str_field("ros2") + str_field(LIBRARY))
    if reindex is not None:
        info = index.chunks[-1]
        entries: dict[int, list[tuple[int, int]]] = defaultdict(list)
        for cid, stamp, at in reindex:
            entries[cid].append((stamp, at))
        start = len(body)
        for cid in sorted(entries):
            info.index_offsets[cid] = scan.keep_end + len(body)
            pairs = b"".join(u64(stamp) + u64(at) for stamp, at in sorted(entries[cid]))
            body += record(OP_MESSAGE_INDEX, u16(cid) + u32(len(pairs)) + pairs)
        info.index_length = len(body) - start
        done.append(f"rebuilt the message index of the last chunk ({len(reindex)} messages)")
    text = metadata_text(index.topics(), index.stats(path.name))
    with path.open("r+b") as f:
        fd = f.fileno()
        os.ftruncate(fd, scan.keep_end)
        pwrite_all(fd, body + index.tail(scan.keep_end + len(body), text), scan.keep_end)
        os.fsync(fd)
    done.append(f"wrote the summary of {path.name} ({sum(index.counts.values())} messages in {len(index.chunks)} chunks)")
    return done
