"""Where a bag lives on disk, and publishing a finished bag atomically.

Path rules, for readers and writers alike:
- ``x.db3`` / ``x.mcap``: a single rosbag2 storage file. It is self-describing: the sqlite3
  file carries rosbag2's ``schema`` (version 4) and ``metadata`` tables, the MCAP file its
  ``rosbag2`` metadata record, so rosbag2 (``ros2 bag info x.db3``) and rosbags open it
  without a metadata.yaml.
- any other path: a standard rosbag2 bag directory, ``x/metadata.yaml`` + ``x/x.db3`` (or
  ``x/x.mcap``; the recorder's split files are ``x/x_0.db3``, ``x/x_1.db3``, ...).

``write_transitions`` builds the bag in a hidden temporary directory beside the target and
renames it into place when it is complete (``StagedBag``), so a failed write leaves nothing
half-written and an existing bag is replaced only by a complete one. The recorder's
``BagWriter`` writes in place instead, a bag after every flush (``recording``).
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

from rosbags.rosbag2 import StoragePlugin

from ...common.errors import UserError

STORAGE_SUFFIX = {"sqlite3": ".db3", "mcap": ".mcap"}
SUFFIX_STORAGE = {suffix: storage for storage, suffix in STORAGE_SUFFIX.items()}
STORAGE_PLUGIN = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}


@dataclass(frozen=True)
class BagTarget:
    """A bag to be written: the final path, its storage and whether it is a single file."""

    path: Path
    storage: str  # 'sqlite3' or 'mcap'
    single_file: bool


def resolve_target(path: str | os.PathLike, storage: str | None = None) -> BagTarget:
    """Apply the path rules to a bag about to be written; checks the parent directory."""
    path = Path(path)
    suffix_storage = SUFFIX_STORAGE.get(path.suffix.lower())
    if storage is not None and storage not in STORAGE_SUFFIX:
        raise UserError(f"{path}: unknown storage {storage!r}; expected one of: {', '.join(STORAGE_SUFFIX)}")
    if suffix_storage and storage and storage != suffix_storage:
        raise UserError(f"{path}: storage {storage!r} does not match the {path.suffix} suffix (that is {suffix_storage})")
    parent = path.parent
    if not parent.is_dir():
        if parent.exists():
            raise UserError(f"{path}: {parent} is a file, not a directory")
        raise UserError(f"{path}: the directory {parent} does not exist; create it first")
    return BagTarget(path, suffix_storage or storage or "sqlite3", suffix_storage is not None)


def check_replaceable(target: BagTarget, overwrite: bool) -> None:
    """Refuse an existing ``target`` unless ``overwrite`` and it is a bag: a text file, a
    database or a directory of other files at a bag's path is never replaced."""
    path = target.path
    if not (path.exists() or path.is_symlink()):
        return
    if not overwrite:
        raise UserError(f"{path} exists already; not overwriting a recording")
    if target.single_file and path.is_dir():
        raise UserError(f"{path} is a directory; expected a {path.suffix} file or a new path")
    if not target.single_file and not (path / "metadata.yaml").is_file():
        raise UserError(f"{path} exists and is not a rosbag2 bag directory (no metadata.yaml); not replacing it")
    if target.single_file and not _is_bag_file(path):
        raise UserError(f"{path} exists and is not a rosbag2 {target.storage} bag file; not replacing it")


def _split_order(name: str) -> tuple[int, str]:
    match = re.search(r"_(\d+)\.[^.]+$", name)
    return (int(match.group(1)) if match else -1, name)


def storage_files(bag_dir: Path) -> list[Path]:
    """The .db3 and .mcap files of a bag directory, in split order (x_0, x_1, ..., x_10)."""
    return sorted((p for p in Path(bag_dir).iterdir() if p.suffix.lower() in SUFFIX_STORAGE and p.is_file()),
                  key=lambda p: _split_order(p.name))


def _is_bag_file(path: Path) -> bool:
    """An MCAP file, or an sqlite3 database with rosbag2's topics and messages tables."""
    try:
        with path.open("rb") as f:
            head = f.read(16)
    except OSError:
        return False
    from .storage_mcap import MAGIC
    from .storage_sqlite import SQLITE_MAGIC

    if head.startswith(MAGIC):
        return True
    if not head.startswith(SQLITE_MAGIC):
        return False
    import sqlite3

    try:
        db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
        try:
            tables = {row[0] for row in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        finally:
            db.close()
    except sqlite3.Error:
        return False
    return {"topics", "messages"} <= tables


class StagedBag:
    """A temporary bag directory beside the target, published with ``publish()``."""

    def __init__(self, target: BagTarget, overwrite: bool):
        self.target = target
        path = target.path
        check_replaceable(target, overwrite)
        self.tmpdir = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent))
        # rosbags names the storage file after the bag directory: <dir>/<name>.db3.
        self.bag_dir = self.tmpdir / (path.stem if target.single_file else path.name)

    @property
    def storage_file(self) -> Path:
        return self.bag_dir / f"{self.bag_dir.name}{STORAGE_SUFFIX[self.target.storage]}"

    def publish(self) -> None:
        """Move the finished bag onto the target path (an atomic rename for single files)."""
        path = self.target.path
        if self.target.single_file:
            os.replace(self.storage_file, path)
        else:
            old = None
            if path.exists():
                old = self.tmpdir / "previous"
                os.replace(path, old)
            os.replace(self.bag_dir, path)
        self.discard()

    def discard(self) -> None:
        shutil.rmtree(self.tmpdir, ignore_errors=True)
