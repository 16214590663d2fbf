"""`ros2 bag info` for any rosbag2 bag, plus a dataset summary when it holds transitions.

Topics are listed from the bag's own index (names, types, counts), so bags with message
types this project does not know, or service events, open without their definitions.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rosbags.rosbag2.storage_mcap import McapReader

from ...common.errors import UserError
from ..transitions import SOURCE_NAMES, Transitions
from .cdr import TRANSITION_TOPIC
from .reader import sqlite_storages, open_bag, transition_rows_and_layout, transition_topic
from .storage_sqlite import WalSqlite3Reader

_SERVICE_EVENT_SUFFIX = "/_service_event"
_INDENT = " " * 19  # aligns continuation lines under the values, as ros2 bag info does


@dataclass
class TopicSummary:
    name: str
    msgtype: str
    count: int
    serialization_format: str = "cdr"


@dataclass
class SourceSummary:
    source: str  # expert, random, policy, human
    transitions: int
    episodes: int
    mean_return: float


@dataclass
class BagInfo:
    path: Path
    files: list[str]
    size_bytes: int
    storage_id: str
    ros_distro: str | None
    start_ns: int | None  # first message stamp
    end_ns: int | None  # last message stamp
    message_count: int
    topics: list[TopicSummary] = field(default_factory=list)
    services: list[TopicSummary] = field(default_factory=list)  # service event topics
    transitions: int | None = None  # set when /pusher/transition decodes
    episodes: int | None = None
    sources: list[SourceSummary] = field(default_factory=list)
    transition_problem: str | None = None  # why /pusher/transition did not decode
    notes: list[str] = field(default_factory=list)  # the state of a bag being (or cut off while) recorded

    @property
    def duration_ns(self) -> int:
        return 0 if self.start_ns is None else self.end_ns - self.start_ns

    def format(self) -> str:
        lines = [
            "Files:             " + ("\n" + _INDENT).join(self.files),
            f"Bag size:          {_format_size(self.size_bytes)}",
            f"Storage id:        {self.storage_id}",
            f"ROS Distro:        {self.ros_distro or 'unknown'}",
            f"Duration:          {self.duration_ns // 10**9}.{self.duration_ns % 10**9:09d}s",
            f"Start:             {_format_stamp(self.start_ns)}",
            f"End:               {_format_stamp(self.end_ns)}",
            f"Messages:          {self.message_count}",
            "Topic information: " + _format_topics(self.topics, "Topic", "Count"),
            f"Service:           {len(self.services)}",
            "Service information: " + _format_topics(self.services, "Service", "Event Count"),
        ]
        if self.transitions is not None:
            lines.append(f"Transitions:       {self.transitions} in {self.episodes} episodes ({TRANSITION_TOPIC})")
            for s in self.sources:
                lines.append(
                    f"{_INDENT}{s.source + ':':8s}{s.episodes:6d} episodes, {s.transitions:8d} transitions, "
                    f"mean return {s.mean_return:.3f}"
                )
        elif self.transition_problem:
            lines.append(f"Transitions:       not usable: {self.transition_problem}")
        lines += [f"Note:              {note}" for note in self.notes]
        return "\n".join(lines)


def _format_size(size: int) -> str:
    units = ["B", "KiB", "MiB", "GiB", "TiB"]
    value, index = float(size), 0
    while value >= 1024 and index < len(units) - 1:
        value /= 1024
        index += 1
    return f"{value:.{0 if index == 0 else 1}f} {units[index]}"


def _format_stamp(ns: int | None) -> str:
    if ns is None:
        return "none"
    sec, nsec = divmod(ns, 10**9)
    tm = time.localtime(sec)
    return f"{time.strftime('%b %e %Y %H:%M:%S', tm)}.{nsec:09d} ({sec}.{nsec:09d})"


def _format_topics(topics: list[TopicSummary], kind: str, count_name: str) -> str:
    return ("\n" + " " * (len(kind) + 14)).join(
        f"{kind}: {t.name} | Type: {t.msgtype} | {count_name}: {t.count} | Serialization Format: {t.serialization_format}"
        for t in topics
    )


def summarize_sources(transitions: Transitions) -> list[SourceSummary]:
    """Transitions, episodes and mean undiscounted episode return per source, by source code."""
    _, returns, episode_source = transitions.episode_returns()
    out = []
    for code in np.unique(transitions.source):
        mask = episode_source == code
        out.append(
            SourceSummary(
                SOURCE_NAMES.get(int(code), f"source {int(code)}"),
                int((transitions.source == code).sum()),
                int(mask.sum()),
                float(returns[mask].mean()),
            )
        )
    return out


def _bag_files(path: Path, reader) -> tuple[list[str], int]:
    if path.is_file():
        return [path.name], path.stat().st_size
    files = [Path(f["path"]).name for f in getattr(reader.storage, "files", [])] or sorted(
        p.name for p in path.iterdir() if p.suffix in (".db3", ".mcap", ".zstd")
    )
    size = sum(p.stat().st_size for p in path.iterdir() if p.is_file())
    return files, size


def bag_info(path: str | os.PathLike) -> BagInfo:
    """Inspect any rosbag2 bag; decodes /pusher/transition when present to summarize it."""
    path = Path(path)
    with open_bag(path) as reader:
        files, size = _bag_files(path, reader)
        storage_id = "mcap" if path.suffix.lower() == ".mcap" else "sqlite3"
        if path.is_dir():
            storages = getattr(reader.storage, "storages", [])
            storage_id = "mcap" if storages and isinstance(storages[0], McapReader) else "sqlite3"
        distro = reader.ros_distro
        for storage in sqlite_storages(reader) or ():  # sqlite3 files name it in their schema table
            distro = distro or _sqlite_distro(storage)
        count = reader.message_count
        info = BagInfo(
            path=path,
            files=files,
            size_bytes=size,
            storage_id=storage_id,
            ros_distro=distro,
            start_ns=reader.start_time if count else None,
            end_ns=reader.end_time - 1 if count else None,
            message_count=count,
        )
        for name, topic in sorted(reader.topics.items()):
            fmt = topic.connections[0].ext.serialization_format if topic.connections else "cdr"
            msgtype = topic.msgtype or "/".join(sorted({c.msgtype for c in topic.connections}))
            if name.endswith(_SERVICE_EVENT_SUFFIX) and "/srv/" in msgtype and msgtype.endswith("_Event"):
                info.services.append(TopicSummary(name[: -len(_SERVICE_EVENT_SUFFIX)], msgtype[: -len("_Event")], topic.msgcount, fmt))
            else:
                info.topics.append(TopicSummary(name, msgtype, topic.msgcount, fmt))
        if path.is_dir() and not (path / "metadata.yaml").is_file():
            info.notes.append(f"no metadata.yaml: read from the storage files; `offline-rl bag repair {path}` writes it")
        for storage in sqlite_storages(reader) or ():
            if isinstance(storage, WalSqlite3Reader):
                name = Path(storage.path).name
                info.notes.append(
                    f"{name}-wal holds commits not yet in {name} (a live recording, or one killed inside a flush); "
                    f"read here, and by rosbags after `offline-rl bag repair {path}`"
                )
        if transition_topic(reader) is not None:
            try:
                transitions = Transitions.from_rows(*transition_rows_and_layout(reader, path))
            except UserError as exc:
                info.transition_problem = str(exc).removeprefix(f"{path}: ")
            else:
                info.transitions = len(transitions)
                info.episodes = int(np.unique(transitions.episode).size)
                info.sources = summarize_sources(transitions)
    return info


def _sqlite_distro(storage) -> str | None:
    """The distro a rosbag2 sqlite3 file names in its schema table."""
    try:
        row = storage.dbconn.execute("SELECT ros_distro FROM schema").fetchone()
    except Exception:
        return None
    return row[0] if row else None
