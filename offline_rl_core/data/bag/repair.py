"""``offline-rl bag repair PATH``: make a bag whose writer was killed whole again, in place
(``ros2 bag reindex`` and ``mcap recover`` in one).

- ``x.db3``: folds a write-ahead log left behind into the file, leaves WAL mode, and
  (re)writes the rosbag2 metadata row (also for files that lack the metadata table).
- ``x.mcap``: keeps every whole record, drops the one cut off, rebuilds the last chunk's
  message index if it was cut, and writes the summary and footer.
- a bag directory: repairs each storage file (also files metadata.yaml does not list, in
  split order) and rewrites metadata.yaml from what the files hold; a missing
  metadata.yaml is rebuilt.

Every step either completes or can be run again: sqlite changes are transactions, MCAP
repair only replaces bytes after the last whole record, metadata.yaml is replaced
atomically. A bag still being recorded (its lock is held) is refused.
"""

from __future__ import annotations

import os
from pathlib import Path

from rosbags.rosbag2.errors import ReaderError
from ruamel.yaml import YAML
from ruamel.yaml.error import YAMLError

from ...common.errors import UserError
from .metadata import FileStats, Topic, bag_metadata, dump_yaml, ros_distro, storage_metadata_text, write_metadata_yaml
from .mcap_scan import repair_mcap, scan_mcap
from .paths import SUFFIX_STORAGE, storage_files
from .recording import lock_bag
from .storage_sqlite import repair_sqlite, scan_sqlite


def _embedded_text(storage_id: str):
    return lambda topics, stats: storage_metadata_text(bag_metadata(storage_id, [stats], topics))


def repair_storage_file(path: Path) -> tuple[list[str], list[Topic], FileStats]:
    """Repair one storage file; returns (what was done, its topics, its statistics)."""
    storage_id = SUFFIX_STORAGE[path.suffix.lower()]
    text = _embedded_text(storage_id)
    if storage_id == "sqlite3":
        done = repair_sqlite(path, text)
        topics, stats = scan_sqlite(path)
    else:
        done = repair_mcap(path, text)
        scan = scan_mcap(path)
        topics, stats = scan.index.topics(), scan.index.stats(path.name)
    return done, topics, stats


def _old_metadata(bag_dir: Path) -> dict:
    try:
        data = YAML(typ="safe").load((bag_dir / "metadata.yaml").read_text())
        info = data["rosbag2_bagfile_information"]
        return info if isinstance(info, dict) else {}
    except (OSError, YAMLError, KeyError, TypeError):
        return {}


def _facts(info: dict) -> tuple | None:
    """What a metadata.yaml says about the bag's files and messages; a healthy bag's file is
    left alone even where its writer spelled the rest differently (version, empty QoS)."""
    try:
        files = tuple((f["path"], f["message_count"], f["duration"]["nanoseconds"],
                       f["starting_time"]["nanoseconds_since_epoch"]) for f in info["files"])
        topics = sorted((t["topic_metadata"]["name"], t["topic_metadata"]["type"],
                         t["topic_metadata"]["serialization_format"], t["message_count"])
                        for t in info["topics_with_message_count"])
        return (info["storage_identifier"], tuple(info["relative_file_paths"]), info["message_count"],
                info["duration"]["nanoseconds"], info["starting_time"]["nanoseconds_since_epoch"], files, topics)
    except (KeyError, TypeError):
        return None  # missing or malformed: rebuilt


def _repair_directory(bag_dir: Path) -> list[str]:
    old = _old_metadata(bag_dir)
    listed = [Path(str(p)).name for p in old.get("relative_file_paths") or []]
    present = [p.name for p in storage_files(bag_dir)]
    names = [n for n in listed if (bag_dir / n).is_file()] + [n for n in present if n not in listed]
    if not names:
        raise UserError(f"{bag_dir}: no .db3 or .mcap storage files to rebuild the bag from")
    storages = {SUFFIX_STORAGE[Path(n).suffix.lower()] for n in names}
    if len(storages) > 1:
        raise UserError(f"{bag_dir}: holds both sqlite3 and MCAP files; expected one storage per bag")
    storage_id = storages.pop()
    done, topics, files = [], [], []
    for name in names:
        file_done, file_topics, stats = repair_storage_file(bag_dir / name)
        done += file_done
        topics += file_topics
        files.append(stats)
    info = bag_metadata(storage_id, files, topics, old.get("custom_data"), old.get("ros_distro") or ros_distro())
    if _facts(YAML(typ="safe").load(dump_yaml(info))) != _facts(old):
        write_metadata_yaml(bag_dir, info)
        what = "rebuilt" if not old else "rewrote"
        done.append(f"{what} metadata.yaml: {len(files)} file(s), {info['message_count']} messages")
    return done


def repair_bag(path: str | os.PathLike) -> list[str]:
    """Repair a bag in place (see the module docstring); returns what was done, one line
    per step (empty: the bag was whole). UserError for what cannot be repaired."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such file or directory")
    if not path.is_dir() and path.suffix.lower() not in SUFFIX_STORAGE:
        raise UserError(f"{path} is not a rosbag2 bag: expected a bag directory, or a .db3 or .mcap file")
    lock = lock_bag(path)  # refuses a bag that is being recorded
    try:
        if path.is_dir():
            return _repair_directory(path)
        return repair_storage_file(path)[0]
    except ReaderError as exc:
        raise UserError(f"{path}: cannot repair the bag ({exc})") from exc
    except OSError as exc:
        raise UserError(f"{path}: cannot repair the bag: {exc}") from exc
    finally:
        os.close(lock)
