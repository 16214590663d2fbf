"""Several training runs at once, one worker process per CPU core.

One training step is a chain of small matmuls that a second intra-op thread barely
speeds up (and on a shared machine OpenMP's spinning threads slow it down many-fold),
so the cores are used by whole runs instead: each worker trains with one thread.
A run's result depends only on its seed and data, never on which worker or which
runs beside it trained it (``train_seeds`` guarantees this), so the outcome is the
same with any number of workers.
"""

from __future__ import annotations

import multiprocessing
import os
import queue as queue_module
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass
from typing import Callable

from ..transitions import Transitions
from .config import TrainConfig
from .loop import Progress, TrainResult, train_seeds


@dataclass
class TrainJob:
    label: str  # shown in progress lines, e.g. "awac s1"
    datasets: list[Transitions]
    cfg: TrainConfig
    seeds: list[int]


def available_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


_progress_queue = None  # set in each worker process


def _init_worker(progress_queue) -> None:
    global _progress_queue
    _progress_queue = progress_queue


def _run_job(index: int, job: TrainJob) -> list[TrainResult]:
    def report(p: Progress) -> None:
        _progress_queue.put((index, p))

    return train_seeds(job.datasets, job.cfg, job.seeds, progress=report)


def run_jobs(jobs: list[TrainJob], workers: int,
             progress_for: Callable[[TrainJob], Callable[[Progress], None]] | None = None) -> list[list[TrainResult]]:
    """Train every job; results in job order. ``workers`` <= 1 trains them one after
    another in this process. Give the heaviest jobs first: they are started first."""
    reporters = [progress_for(job) if progress_for else None for job in jobs]
    workers = max(1, min(workers, len(jobs)))
    if workers == 1:
        return [train_seeds(job.datasets, job.cfg, job.seeds, progress=rep) for job, rep in zip(jobs, reporters)]

    # spawn, not fork: the parent has torch (and its OpenMP pool) initialised
    ctx = multiprocessing.get_context("spawn")
    progress_queue = ctx.Queue()
    results: list[list[TrainResult] | None] = [None] * len(jobs)

    def drain(timeout: float) -> None:
        try:
            while True:
                index, p = progress_queue.get(timeout=timeout)
                timeout = 0.0
                if reporters[index] is not None:
                    reporters[index](p)
        except queue_module.Empty:
            pass

    with ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker, initargs=(progress_queue,)) as pool:
        pending = {pool.submit(_run_job, i, job): i for i, job in enumerate(jobs)}
        try:
            while pending:
                drain(0.2)
                done, _ = wait(pending, timeout=0, return_when=FIRST_COMPLETED)
                for future in done:
                    results[pending.pop(future)] = future.result()
        except BaseException:
            pool.shutdown(wait=False, cancel_futures=True)
            raise
        drain(0.1)  # the last progress lines may trail the results
    return results  # type: ignore[return-value]
