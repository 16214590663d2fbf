"""rosbag2 metadata (format version 9): topics, per-file statistics and metadata.yaml.

The streaming writer, repair and reindexing all describe a bag through the same two
records, ``Topic`` and ``FileStats``, and render them with ``bag_metadata``: the dict that
rosbag2 stores as ``metadata.yaml`` (under ``rosbag2_bagfile_information``), in the
sqlite3 ``metadata`` table and in the MCAP ``rosbag2`` metadata record.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from io import StringIO
from pathlib import Path

from rosbags.interfaces import Qos
from rosbags.rosbag2.metadata import dump_qos_v9, parse_qos
from rosbags.typesys import Stores, get_typestore
from ruamel.yaml import YAML

from ...common.atomic import atomic_path
from ...common.errors import UserError

ROSBAG2_VERSION = 9
IDL_PREFIX = "=" * 80 + "\nIDL: "


@lru_cache(maxsize=1)
def typestore():
    """The message definitions bags are written with (ROS 2 Kilted, else Jazzy)."""
    store = getattr(Stores, "ROS2_KILTED", None) or Stores.ROS2_JAZZY
    return get_typestore(store)


def ros_distro() -> str:
    """The distro recorded in new bags: $ROS_DISTRO, else the typestore's."""
    return os.environ.get("ROS_DISTRO") or ("kilted" if hasattr(Stores, "ROS2_KILTED") else "jazzy")


def dump_yaml(data) -> str:
    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    out = StringIO()
    yaml.dump(data, out)
    return out.getvalue()


def qos_text(profiles: Sequence[Qos]) -> str:
    """Offered QoS profiles as rosbag2 v9 stores them (a YAML list; '' for none)."""
    return dump_yaml(dump_qos_v9(list(profiles))).strip() if profiles else ""


@dataclass(frozen=True)
class Topic:
    """One recorded topic: its id in the storage file, type, definition and QoS."""

    id: int
    name: str
    msgtype: str
    msgdef: str
    rihs01: str
    qos: str = ""  # offered_qos_profiles, as qos_text writes it
    serialization_format: str = "cdr"

    @property
    def key(self) -> tuple[str, str]:
        """Topics of split files match by name and type (their ids may differ)."""
        return (self.name, self.msgtype)

    @property
    def encoding(self) -> str:
        """The message definition's encoding, as rosbag2 names it."""
        return "ros2idl" if self.msgdef.startswith(IDL_PREFIX) else "ros2msg"

    @property
    def qos_profiles(self) -> list[Qos]:
        return parse_qos(self.qos)


def make_topic(
    topic_id: int,
    name: str,
    msgtype: str,
    *,
    msgdef: str | None = None,
    rihs01: str | None = None,
    qos: Sequence[Qos] = (),
    where: str = "",
) -> Topic:
    """A Topic; the definition and hash come from the typestore unless given."""
    if msgdef is None or rihs01 is None:
        store = typestore()
        if msgtype not in store.fielddefs:
            raise UserError(f"{where}message type {msgtype} of {name} is not a known ROS 2 type; pass msgdef and rihs01")
        msgdef = store.generate_msgdef(msgtype, ros_version=2)[0] if msgdef is None else msgdef
        rihs01 = store.hash_rihs01(msgtype) if rihs01 is None else rihs01
    return Topic(topic_id, name, msgtype, msgdef, rihs01, qos_text(qos))


@dataclass
class FileStats:
    """What one storage file holds: message counts per topic id and the stamp range."""

    name: str  # the file's name, relative to the bag directory
    counts: dict[tuple[str, str], int] = field(default_factory=dict)  # by Topic.key
    start_ns: int | None = None
    end_ns: int | None = None

    @property
    def message_count(self) -> int:
        return sum(self.counts.values())

    def add(self, key: tuple[str, str], stamp_ns: int, n: int = 1) -> None:
        self.counts[key] = self.counts.get(key, 0) + n
        self.start_ns = stamp_ns if self.start_ns is None else min(self.start_ns, stamp_ns)
        self.end_ns = stamp_ns if self.end_ns is None else max(self.end_ns, stamp_ns)


def _time(start: int | None, end: int | None) -> tuple[dict, dict]:
    start = 0 if start is None else start
    end = start if end is None else end
    return {"nanoseconds_since_epoch": start}, {"nanoseconds": end - start}


def bag_metadata(
    storage_id: str,
    files: Sequence[FileStats],
    topics: Sequence[Topic],
    custom_data: dict[str, str] | None = None,
    distro: str | None = None,
) -> dict:
    """rosbag2's ``rosbag2_bagfile_information`` for files sharing one topic list.

    A topic is matched across files by name and type; its count is the sum over files.
    """
    topics = list({t.key: t for t in topics}.values())
    starts = [f.start_ns for f in files if f.start_ns is not None]
    ends = [f.end_ns for f in files if f.end_ns is not None]
    starting, duration = _time(min(starts, default=None), max(ends, default=None))
    totals = {t.key: sum(f.counts.get(t.key, 0) for f in files) for t in topics}
    file_entries = []
    for f in files:
        f_start, f_duration = _time(f.start_ns, f.end_ns)
        file_entries.append({"path": f.name, "starting_time": f_start, "duration": f_duration, "message_count": f.message_count})
    return {
        "version": ROSBAG2_VERSION,
        "storage_identifier": storage_id,
        "relative_file_paths": [f.name for f in files],
        "duration": duration,
        "starting_time": starting,
        "message_count": sum(totals.values()),
        "topics_with_message_count": [
            {
                "topic_metadata": {
                    "name": t.name,
                    "type": t.msgtype,
                    "serialization_format": t.serialization_format,
                    "offered_qos_profiles": dump_qos_v9(t.qos_profiles),
                    "type_description_hash": t.rihs01,
                },
                "message_count": totals[t.key],
            }
            for t in topics
        ],
        "compression_format": "",
        "compression_mode": "",
        "files": file_entries,
        "custom_data": dict(custom_data) if custom_data else None,
        "ros_distro": distro or ros_distro(),
    }


def storage_metadata_text(info: dict) -> str:
    """The metadata as rosbag2 embeds it in a storage file (no top-level key)."""
    return dump_yaml(info).strip()


def write_metadata_yaml(bag_dir: Path, info: dict) -> None:
    """``bag_dir/metadata.yaml``, replaced atomically."""
    text = dump_yaml({"rosbag2_bagfile_information": info})
    with atomic_path(bag_dir / "metadata.yaml") as tmp:
        tmp.write_text(text, encoding="utf-8")
