"""Fleets of bags: many rosbag2 bags (every arm's recordings of a day) read as one dataset.

- ``expand_bags(specs)``: the bags that paths, directories of bags and globs name, in a
  fixed order (so a fleet gives the same dataset, byte for byte, every time it is read).
- ``iter_fleet(paths, executor)``: each bag's transitions and summary, in order, decoded
  by the executor's workers with at most ``ahead`` bags decoded and not yet taken: the
  memory held is that of the bags in flight, whatever the size of the fleet.
- ``read_fleet(paths, workers)``: the bags merged into one Transitions, each bag's episode
  ids offset so they stay unique, filled into one allocation as the bags come in; what
  ``offline-rl train --bag`` and a sweep's runs train on.

Locally the bags are decoded in worker processes (``workers``; one bag per task); the Ray
engine hands ``iter_fleet`` and ``read_fleet`` an executor whose tasks run on a cluster
(``runs/ray_engine.py``). Either way the result is the same bytes as reading the bags one
after another in this process.
"""

from __future__ import annotations

import glob
import multiprocessing
import os
import re
from collections import deque
from collections.abc import Iterable, Iterator
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from dataclasses import fields
from pathlib import Path

import numpy as np

from ..common.errors import UserError
from ..common.machine import available_cores
from .transitions import SOURCE_NAMES, Transitions

BAG_SUFFIXES = (".db3", ".mcap")
# Below this many bytes of bags, worker processes cost more (their start, and each bag
# pickled across) than they save: on a busy 2-core machine a fleet of hundreds of MB still
# decoded faster in one process (bench/RESULTS.md, 'Sweeps and fleets').
PARALLEL_MIN_BYTES = 2**30


def expand_bags(specs: Iterable[str | os.PathLike], what: str = "--bag") -> list[str]:
    """The bags named by ``specs``: a bag (a bag directory, a .db3 or .mcap file) as given;
    a directory holding bags, every bag directly in it; a glob, every path it matches;
    each sorted by name, hidden entries (a writer's staging) left out. A spec that names
    no bag is a UserError naming it (``what``: the flag or field it came from)."""
    out: list[str] = []
    for spec in specs:
        text = os.fspath(spec)
        if glob.has_magic(text):
            matches = sorted(m for m in glob.glob(text, recursive=True) if not Path(m).name.startswith("."))
            if not matches:
                raise UserError(f"{what} {text}: the pattern matches no file or directory")
            out.extend(matches)
            continue
        path = Path(text)
        if path.is_dir() and not (path / "metadata.yaml").is_file() and not _lost_its_metadata(path):
            bags = sorted(str(p) for p in path.iterdir() if _looks_like_bag(p))
            if not bags:
                raise UserError(f"{what} {text}: the directory holds no bags (expected .db3 or .mcap files, "
                                "or bag directories with metadata.yaml)")
            out.extend(bags)
        else:
            out.append(text)  # as given: the summary a run records names it so
    return out


def _lost_its_metadata(path: Path) -> bool:
    """A bag directory without its metadata.yaml (its storage files are named after it, as
    rosbag2 names them): one bag, which the reader refuses with the way to repair it, not
    a fleet of its split files."""
    own = re.compile(re.escape(path.name) + r"(_\d+)?\.(db3|mcap)", re.IGNORECASE)
    return any(own.fullmatch(p.name) for p in path.iterdir())


def _looks_like_bag(path: Path) -> bool:
    if path.name.startswith("."):
        return False
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.suffix.lower() in BAG_SUFFIXES


def check_bags_exist(paths: Iterable[str], what: str = "--bag") -> None:
    """Refuse, in one line naming it, a path that is not a bag (before any is decoded)."""
    from .bag.reader import check_bag_path

    for path in paths:
        try:
            check_bag_path(Path(path))
        except UserError as exc:
            raise UserError(f"{what}: {exc}") from None


def bag_summary(path: str, data: Transitions) -> dict:
    """What a run records of one bag it trained on."""
    counts = {SOURCE_NAMES.get(int(s), str(s)): int(n) for s, n in zip(*np.unique(data.source, return_counts=True))}
    return {"path": str(path), "transitions": len(data), "sources": counts}


def decode_bag(path: str) -> tuple[Transitions, dict]:
    """One bag's transitions and its summary (a worker's task); rows recorded while the
    e-stop was engaged are left out, counted as ``estop_dropped`` (only for a bag that
    records the e-stop, so the summaries of others keep their bytes)."""
    from .bag import read_transitions
    from .bag.estop_spans import drop_engaged

    data, dropped = drop_engaged(path, read_transitions(path))
    summary = bag_summary(path, data)
    if dropped is not None:
        summary["estop_dropped"] = dropped
    return data, summary


def count_transitions(path: str) -> int:
    """The transition messages a bag's index counts (a worker's task; no payload is read)."""
    from .bag.reader import count_transition_messages

    return count_transition_messages(path)


class InProcess(Executor):
    """An executor that runs each task when it is submitted, in this process."""

    def submit(self, fn, /, *args, **kwargs) -> Future:
        future: Future = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as exc:  # noqa: BLE001 - re-raised by result()
            future.set_exception(exc)
        return future


def auto_workers(paths: list[str]) -> int:
    """Worker processes worth starting for these bags: one per core for a fleet large
    enough to pay for their start, none (this process) otherwise, and none inside a
    process that may not have children (a training worker of ``runs/parallel.py``)."""
    if len(paths) < 2 or multiprocessing.current_process().daemon:
        return 1
    size = 0
    for p in paths:
        path = Path(p)
        files = path.rglob("*") if path.is_dir() else [path]
        size += sum(f.stat().st_size for f in files if f.is_file())
    return min(available_cores(), len(paths)) if size >= PARALLEL_MIN_BYTES else 1


def local_executor(workers: int) -> Executor:
    """``workers`` decode processes (spawned: the parent may hold torch's thread pool), or
    this process for one."""
    if workers <= 1:
        return InProcess()
    return ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"))


def iter_fleet(paths: list[str], executor: Executor, ahead: int) -> Iterator[tuple[Transitions, dict]]:
    """(transitions, summary) of each bag in order; at most ``ahead`` bags are submitted
    and not yet taken, so a slow bag never lets the others pile up behind it."""
    pending: deque[Future] = deque()
    todo = iter(paths)
    try:
        for path in todo:
            pending.append(executor.submit(decode_bag, path))
            if len(pending) >= max(1, ahead):
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
    finally:
        for future in pending:
            future.cancel()


def read_fleet(paths: list[str], workers: int | None = None, executor: Executor | None = None,
               ahead: int | None = None) -> tuple[Transitions, list[dict]]:
    """The bags merged into one dataset and a summary per bag. Episode ids are offset per
    bag (each bag's first episode follows the previous bag's last), so they stay unique.
    ``executor`` decodes the bags (default: ``workers`` processes, ``auto_workers`` when
    None); ``ahead``: bags decoded ahead of the one being copied (default: two per worker)."""
    if not paths:
        raise UserError("no bags to read")
    if executor is None:
        workers = auto_workers(paths) if workers is None else max(1, workers)
        with local_executor(workers) as pool:
            return read_fleet(paths, executor=pool, ahead=ahead or 2 * workers)
    ahead = ahead or 2
    if len(paths) == 1:  # nothing to merge: the bag's arrays as they are
        data, summary = executor.submit(decode_bag, paths[0]).result()
        return writable(_rebased(data, 0)), [summary]
    counts = [f.result() for f in [executor.submit(count_transitions, p) for p in paths]]
    out: Transitions | None = None  # in the first bag's layout (its task's sizes)
    extra: list[Transitions] = []  # rows beyond the index's count (a bag still being recorded)
    summaries, cursor, offset = [], 0, 0
    for path, (data, summary) in zip(paths, iter_fleet(paths, executor, ahead)):
        if out is None:
            out = Transitions.empty(sum(counts), data.layout)
        elif data.layout != out.layout:
            raise UserError(f"{path}: its transitions ({data.layout.describe()}) are not those of {paths[0]} "
                            f"({out.layout.describe()}); merge bags of one task")
        data = _rebased(data, offset)
        offset = int(data.episode.max()) + 1
        fit = max(0, min(len(data), len(out) - cursor))
        if fit:
            _copy_into(out, cursor, data if fit == len(data) else data.select(slice(0, fit)))
            cursor += fit
        if fit < len(data):
            extra.append(data.select(slice(fit, None)))
        summaries.append(summary)
    if extra:
        out = Transitions.concatenate([out, *extra])
    elif cursor < len(out):  # fewer rows than the index said
        out = out.select(slice(0, cursor))
    return out, summaries


def _rebased(data: Transitions, offset: int) -> Transitions:
    data.episode = data.episode - data.episode.min() + offset
    return data


def _copy_into(out: Transitions, start: int, data: Transitions) -> None:
    for f in fields(Transitions):
        getattr(out, f.name)[start:start + len(data)] = getattr(data, f.name)


def writable(data: Transitions) -> Transitions:
    """Writable arrays of this process (a cluster's object store hands out read-only views)."""
    if all(getattr(data, f.name).flags.writeable for f in fields(Transitions)):
        return data
    return Transitions(**{f.name: np.array(getattr(data, f.name)) for f in fields(Transitions)})
