"""rosbags' MCAP reader for every valid MCAP file, whatever its writer left out of the summary.

A file whose summary holds what reading needs (statistics, every channel and schema, a chunk
index with message indexes: what rosbag2, rosbags and this package's recorder write) is read
from the summary by rosbags, as before. Any other file is scanned once at open
(``mcap_scan.scan_mcap``, chunks decompressed and CRC-checked) and the reader is handed the
index the summary would have held; rosbags then reads the chunks as usual. Messages outside
chunks are read in stamp order from the positions the scan found.
"""

from __future__ import annotations

import heapq
import os
from operator import itemgetter
from pathlib import Path

import numpy as np
from rosbags.interfaces import (
    Connection, ConnectionExtRosbag2, MessageDefinition, MessageDefinitionFormat,
)
from rosbags.rosbag2.metadata import parse_qos
from rosbags.rosbag2.storage_mcap import MAXSIZE, Channel, ChunkInfo, McapReader, Schema, Statistics

from ...common.errors import UserError
from .mcap_scan import LooseMessages, footer_fields, has_footer, read_summary, scan_mcap, summary_gaps, summary_problem
from .storage_mcap import FOOTER_SIZE

SCHEMALESS = "__schemaless__"  # rosbags' type name for a channel without a schema
_DEFINITION_FORMATS = {"ros2msg": MessageDefinitionFormat.MSG, "ros2idl": MessageDefinitionFormat.IDL,
                       "omgidl": MessageDefinitionFormat.IDL}


def _qos(text: str) -> list:
    try:
        return parse_qos(text)
    except Exception:  # noqa: BLE001 - QoS is informative; a profile rosbags cannot parse is none
        return []


class CheckedMcapReader(McapReader):
    """rosbags' MCAP reader: a file without its footer (its writer was killed mid-flush) is
    refused with the way out; a footer or summary that fails its CRC is refused as corrupt;
    a summary that lacks what reading needs is made up for by a scan of the data section."""

    loose: LooseMessages | None = None  # messages outside chunks, once known
    scanned_because: tuple[str, ...] = ()  # what the summary lacked (empty: read from the summary)

    def open(self) -> None:
        path = Path(self.path)
        self.loose, self.scanned_because = None, ()
        if not has_footer(path):
            if path.stat().st_size > 8:
                raise UserError(
                    f"{path}: the MCAP file ends without its summary (its recording was cut off); "
                    f"`offline-rl bag repair {path}` makes it whole"
                )
            super().open()  # rosbags words what is wrong with an empty file
            return
        if problem := summary_problem(path):
            raise UserError(f"{path}: the MCAP file is corrupt: {problem}")
        summary_start = footer_fields(path)[0]
        gaps = summary_gaps(read_summary(path, summary_start) if summary_start else None)
        if not gaps:
            super().open()
            return
        self.scanned_because = tuple(gaps)
        try:
            self._open_scanned(path, summary_start or path.stat().st_size - FOOTER_SIZE)
        except BaseException:
            if self.bio is not None:
                self.close()
            raise

    def _open_scanned(self, path: Path, data_end: int) -> None:
        scan = scan_mcap(path, end=data_end)
        if not scan.complete:
            raise UserError(f"{path}: the MCAP file is corrupt: {scan.problem}")
        index = scan.index
        self.bio = path.open("rb")
        self.data_start, self.data_end = scan.data_start, data_end
        for sid, (name, encoding, data) in index.schemas.items():
            self.schemas[sid] = Schema(sid, name, encoding, data.decode("utf-8", "replace"))
        for cid, (sid, topic, encoding, metadata) in sorted(index.channels.items()):
            schema = self.schemas.get(sid)
            msgtype = schema.name if schema else SCHEMALESS
            self.channels[cid] = Channel(cid, msgtype, topic, encoding, b"")
            fmt = _DEFINITION_FORMATS.get(schema.encoding) if schema else None
            msgdef = MessageDefinition(fmt, schema.data) if fmt else MessageDefinition(MessageDefinitionFormat.NONE, "")
            ext = ConnectionExtRosbag2(encoding, _qos(metadata.get("offered_qos_profiles", "")))
            self.connections.append(Connection(cid, topic, msgtype, msgdef, "", index.counts.get(cid, 0), ext, self))
        self.chunks = [
            ChunkInfo(c.start, c.end, c.offset, c.length, {}, 0, c.compression, c.compressed_size,
                      c.uncompressed_size, dict(c.message_counts))
            for c in index.chunks if c.message_counts
        ]
        count = sum(index.counts.values())
        start, end = (index.start, index.end) if count else (MAXSIZE, 0)
        self.statistics = Statistics(count, len(self.schemas), len(self.channels), 0, 0, len(index.chunks), start, end,
                                     dict(index.counts))
        self.metadata = self.metadata._replace(
            duration=end - start + 1 if count else 0, start_time=start, end_time=end + 1 if count else 0,
            message_count=count,
        )
        self.loose = scan.loose

    def messages(self, connections, start=None, stop=None):
        """Messages of ``connections`` in stamp order: rosbags reads the chunks; messages
        outside chunks come from their positions (rosbags would refuse them out of order)."""
        if self.loose is None and not self.chunks and self.metadata.message_count:
            self.loose = scan_mcap(Path(self.path), end=self.data_end).loose  # a summary without chunks
        if not self.loose:
            yield from super().messages(connections, start, stop)
            return
        streams = [self._loose_messages(connections, start, stop)]
        if self.chunks:
            streams.append(super().messages(connections, start, stop))
        yield from heapq.merge(*streams, key=itemgetter(1))

    def _loose_messages(self, connections, start, stop):
        loose, wanted = self.loose, {c.id: c for c in connections}
        channel = np.frombuffer(loose.channel, np.uint16)
        stamp = np.frombuffer(loose.stamp, np.uint64)
        keep = np.isin(channel, np.fromiter(wanted, np.uint16, len(wanted)))
        if start is not None:
            keep &= stamp >= start
        if stop is not None:
            keep &= stamp < stop
        picked = np.flatnonzero(keep)
        order = picked[np.argsort(stamp[picked], kind="stable")].tolist()
        fd = self.bio.fileno()
        offsets, sizes, channels, stamps = loose.offset, loose.size, loose.channel, loose.stamp
        for i in order:
            yield wanted[channels[i]], stamps[i], os.pread(fd, sizes[i], offsets[i])
