"""``BagWriter``: a streaming rosbag2 writer that loses at most one flush interval when its
process is killed, and splits a long recording into several files like
``ros2 bag record --max-bag-size/--max-bag-duration``.

The bag is written in place at the path given, never staged elsewhere:
- ``x.db3`` / ``x.mcap``: one self-describing storage file (its embedded rosbag2 metadata
  is rewritten at every flush);
- any other path: a bag directory ``x/`` with ``x_0.db3`` (or ``.mcap``), ``x_1.db3``, ...
  and ``metadata.yaml``, replaced atomically after every flush and when a file is added.

Messages are buffered and handed to the storage every ``flush_interval`` seconds (by a
background thread, so a quiet topic is flushed too) and whenever ``FLUSH_BYTES`` are
pending. What a flush leaves on disk is a complete bag (see ``storage_sqlite`` and
``storage_mcap`` for the exceptions a kill inside a flush can leave, and ``repair``).
``close()`` flushes everything, so SIGINT/SIGTERM lose nothing received.

With ``min_free_space``, a flush that leaves less than that free on the bag's file system
sets ``low_space``: the bag holds everything written so far, ``close()`` still fits (the
margin is for it), and further writes are refused (``OutOfSpace``), so a full disk ends a
recording cleanly instead of in the middle of a transaction.
"""

from __future__ import annotations

import fcntl
import os
import shutil
import threading
from contextlib import suppress
from pathlib import Path

from rosbags.interfaces import Qos

from ...common.errors import UserError
from ...common.interrupts import signals_deferred
from .metadata import FileStats, Topic, bag_metadata, make_topic, ros_distro, storage_metadata_text, write_metadata_yaml
from .paths import STORAGE_SUFFIX, resolve_target
from .storage_mcap import McapFileWriter
from .storage_sqlite import SqliteFileWriter, wal_path

FILE_WRITERS = {"sqlite3": SqliteFileWriter, "mcap": McapFileWriter}
DEFAULT_FLUSH_INTERVAL = 1.0
FLUSH_BYTES = 8 << 20  # flush early past this much pending data: bounded memory
MIN_SQLITE_SPLIT_SIZE = 86016  # rosbag2's minimum: an empty rosbag2 sqlite3 file is about this big


class OutOfSpace(UserError):
    """The bag stopped taking messages: its file system is below ``min_free_space``."""


def free_space(directory: Path) -> int:
    """Bytes an unprivileged writer may still use on ``directory``'s file system."""
    st = os.statvfs(directory)
    return st.f_bavail * st.f_frsize


def split_file_name(bag_dir: Path, index: int, storage: str) -> str:
    """rosbag2's name for the index-th file of a bag directory: ``<dir>_<index>.<ext>``."""
    return f"{bag_dir.name}_{index}{STORAGE_SUFFIX[storage]}"


def lock_bag(path: Path) -> int:
    """Take the bag's recording lock (held until the fd closes); UserError if held."""
    fd = os.open(path, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise UserError(f"{path} is being recorded by another process") from None
    return fd


def _remove_bag(path: Path, single_file: bool) -> None:
    if single_file:
        if path.is_dir():
            raise UserError(f"{path} is a directory; expected a {path.suffix} file or a new path")
        for p in (path, wal_path(path), Path(f"{path}-shm")):
            p.unlink(missing_ok=True)
    else:
        if not (path / "metadata.yaml").is_file():
            raise UserError(f"{path} exists and is not a rosbag2 bag directory (no metadata.yaml); not replacing it")
        shutil.rmtree(path)


class BagWriter:
    """A streaming rosbag2 writer of already-serialized CDR messages (the recorder node).

    ``with BagWriter("bags/run.db3") as bag: bag.add_topic("/pusher/state",
    "sensor_msgs/msg/JointState"); bag.write("/pusher/state", stamp_ns, cdr_bytes)``.
    ``close()`` (idempotent; also on leaving the ``with`` block, even by an exception
    such as KeyboardInterrupt) writes everything. An existing ``path`` is refused unless
    ``overwrite=True`` (then it is deleted at once), as ``ros2 bag record`` refuses one.
    ``max_bag_size`` (bytes) / ``max_bag_duration`` (seconds of message stamps) start a
    new file of the bag directory when the current one reaches them (0: never).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        storage: str | None = None,
        *,
        overwrite: bool = False,
        flush_interval: float = DEFAULT_FLUSH_INTERVAL,
        max_bag_size: int = 0,
        max_bag_duration: float = 0.0,
        custom_data: dict[str, str] | None = None,
        min_free_space: int = 0,
    ):
        self.target = resolve_target(path, storage)
        self.path = path = self.target.path
        self.storage_id = self.target.storage
        if not flush_interval > 0:
            raise UserError(f"{path}: the flush interval must be > 0 s, got {flush_interval}")
        if max_bag_size < 0 or max_bag_duration < 0:
            raise UserError(f"{path}: max bag size and duration must be >= 0 (0: no splitting)")
        if (max_bag_size or max_bag_duration) and self.target.single_file:
            raise UserError(f"{path}: splitting needs a bag directory as output, not a single {path.suffix} file")
        if self.storage_id == "sqlite3" and 0 < max_bag_size < MIN_SQLITE_SPLIT_SIZE:
            raise UserError(f"{path}: max bag size {max_bag_size} B is below the sqlite3 minimum of {MIN_SQLITE_SPLIT_SIZE} B")
        self.min_free_space = int(min_free_space)
        self.low_space: int | None = None  # free bytes when the bag stopped for lack of space
        where = path.parent if path.parent.is_dir() else None
        if self.min_free_space and where is not None and free_space(where) < self.min_free_space:
            raise UserError(f"{path}: only {free_space(where) >> 20} MiB free on {where}, below the minimum of "
                            f"{self.min_free_space >> 20} MiB; not starting a recording")
        if path.exists() or path.is_symlink():
            if not overwrite:
                raise UserError(f"{path} exists already; not overwriting a recording")
            _remove_bag(path, self.target.single_file)
        if self.target.single_file and wal_path(path).exists():  # sqlite would apply it to the new file
            if not overwrite:
                raise UserError(f"{wal_path(path)} is left from an earlier recording without {path.name}; move it away first")
            _remove_bag(path, True)
        self.flush_interval = float(flush_interval)
        self.max_bag_size = int(max_bag_size)
        self.max_bag_duration_ns = int(max_bag_duration * 1e9)
        self.custom_data = dict(custom_data or {})
        self.distro = ros_distro()
        self.message_count = 0
        self.closed = False
        self._lock = threading.RLock()
        self._topics: dict[str, Topic] = {}
        self._unwritten_topics: list[Topic] = []  # not yet in the current file
        self._pending: list[tuple[int, int, bytes]] = []
        self._pending_bytes = 0
        self._pending_stats: list[tuple[tuple[str, str], int]] = []
        self._file_first_stamp: int | None = None
        self._error: BaseException | None = None
        self._files: list[FileStats] = []
        self._storage = None
        self._lock_fd = None
        try:
            if self.target.single_file:
                self._bag_dir = path.parent
            else:
                self._bag_dir = path
                path.mkdir()
                self._lock_fd = lock_bag(path)
            self._open_file()
            if self._lock_fd is None:
                self._lock_fd = lock_bag(path)
        except OSError as exc:
            self._release()
            raise UserError(f"{path}: cannot create the bag: {exc}") from exc
        self._stop = threading.Event()
        self._flusher = threading.Thread(target=self._flush_loop, name=f"bag-flush {path.name}", daemon=True)
        self._flusher.start()

    # ------------------------------------------------------------------ API
    def add_topic(
        self,
        topic: str,
        msgtype: str,
        *,
        msgdef: str | None = None,
        rihs01: str | None = None,
        offered_qos_profiles: list[Qos] | tuple[Qos, ...] = (),
    ) -> None:
        """Declare a topic; ``msgtype`` like 'sensor_msgs/msg/JointState'. Idempotent per
        topic. ``msgdef``/``rihs01`` default to the ROS 2 typestore's definition."""
        with self._lock:
            self._check_open()
            old = self._topics.get(topic)
            if old is not None:
                if old.msgtype != msgtype:
                    raise UserError(f"{self.path}: topic {topic} was added as {old.msgtype}, not {msgtype}")
                return
            entry = make_topic(len(self._topics) + 1, topic, msgtype, msgdef=msgdef, rihs01=rihs01,
                               qos=offered_qos_profiles, where=f"{self.path}: ")
            self._topics[topic] = entry
            self._unwritten_topics.append(entry)

    def write(self, topic: str, timestamp_ns: int, data: bytes | bytearray | memoryview) -> None:
        """Append one serialized (CDR) message of a topic added with ``add_topic``."""
        with self._lock:
            self._check_open()
            entry = self._topics.get(topic)
            if entry is None:
                raise UserError(f"{self.path}: topic {topic} was not added; call add_topic first")
            stamp = int(timestamp_ns)
            if self._split_due(stamp, len(data)):
                self._flush()
                self._next_file()
            if self._file_first_stamp is None:
                self._file_first_stamp = stamp
            self._pending.append((entry.id, stamp, bytes(data)))
            self._pending_stats.append((entry.key, stamp))
            self._pending_bytes += len(data)
            self.message_count += 1
            if self._pending_bytes >= FLUSH_BYTES:
                self._flush()

    def flush(self) -> None:
        """Write everything pending now (a flush also runs every ``flush_interval``)."""
        with self._lock:
            self._check_open()
            self._flush()

    def close(self) -> None:
        """Write everything pending and finalize the bag. Safe to call more than once. A
        Ctrl-C (or SIGTERM) that comes meanwhile waits until the bag is whole, then acts."""
        with signals_deferred(), self._lock:
            if self.closed:
                return
            self.closed = True
            self._stop.set()
            try:
                if self._error is None:
                    self._flush()
                self._storage.close()
            except UserError:
                raise
            except Exception as exc:  # OSError, sqlite3.Error
                raise UserError(f"{self.path}: cannot finalize the bag: {exc}") from exc
            finally:
                self._release()
            if self._error is not None:
                raise UserError(f"{self.path}: writing the bag failed: {self._error}") from self._error

    # ------------------------------------------------------------------ internals
    def _check_open(self) -> None:
        if self.closed:
            raise UserError(f"{self.path}: the bag is closed")
        if self.low_space is not None:
            raise OutOfSpace(f"{self.path}: stopped: {self.low_space >> 20} MiB free, below the minimum of "
                             f"{self.min_free_space >> 20} MiB")
        if self._error is not None:
            raise UserError(f"{self.path}: writing the bag failed: {self._error}") from self._error

    def _release(self) -> None:
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    def _open_file(self) -> None:
        if self.target.single_file:
            file_path = self.path
        else:
            file_path = self._bag_dir / split_file_name(self._bag_dir, len(self._files), self.storage_id)
        self._storage = FILE_WRITERS[self.storage_id](file_path, self.distro)
        self._files.append(FileStats(file_path.name))
        self._file_first_stamp = None
        self._flush(force=True)  # the new file is listed in metadata.yaml at once

    def _next_file(self) -> None:
        self._storage.close()
        self._storage = None
        self._unwritten_topics = list(self._topics.values())  # every file declares every topic
        self._open_file()

    def _split_due(self, stamp: int, size: int) -> bool:
        if self.max_bag_size and self._files[-1].message_count + len(self._pending) > 0:
            if self._storage.size() + self._pending_bytes + size > self.max_bag_size:
                return True
        if self.max_bag_duration_ns and self._file_first_stamp is not None:
            return stamp - self._file_first_stamp >= self.max_bag_duration_ns
        return False

    def metadata(self) -> dict:
        """The rosbag2 metadata of what has been flushed."""
        return bag_metadata(self.storage_id, self._files, list(self._topics.values()), self.custom_data, self.distro)

    def _flush(self, force: bool = False) -> None:
        if not (force or self._pending or self._unwritten_topics):
            return
        stats = self._files[-1]
        for key, stamp in self._pending_stats:
            stats.add(key, stamp)
        topics, messages = self._unwritten_topics, self._pending
        self._unwritten_topics, self._pending, self._pending_stats, self._pending_bytes = [], [], [], 0
        info = self.metadata()
        try:
            self._storage.flush(topics, messages, storage_metadata_text(info))
            if not self.target.single_file:
                write_metadata_yaml(self._bag_dir, info)
        except Exception as exc:  # OSError (disk full), sqlite3.Error: the bag keeps what it had
            self._error = exc
            raise UserError(f"{self.path}: writing the bag failed: {exc}") from exc
        if self.min_free_space and self.low_space is None and not self.closed:
            free = free_space(self._bag_dir)
            if free < self.min_free_space:
                self.low_space = free

    def _flush_loop(self) -> None:
        while not self._stop.wait(self.flush_interval):
            with self._lock:
                if self.closed or self._error is not None:
                    return
                try:
                    self._flush()
                except BaseException as exc:  # reported by the next write() or close()
                    self._error = exc
                    return

    def __enter__(self) -> "BagWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        self.close()
        return False

    def __del__(self):
        # A writer dropped without close() keeps what it recorded.
        if not getattr(self, "closed", True):
            with suppress(Exception):
                self.close()
