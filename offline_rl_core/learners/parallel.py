"""Several training runs at once, one worker process per CPU core.

One training step is a chain of small matmuls that a second intra-op thread barely
speeds up (and on a shared machine OpenMP's spinning threads slow it down many-fold),
so the cores are used by whole runs instead: each worker trains with one thread
while runs wait for a worker. Once none waits, a run still training takes the cores
of the finished ones (its step spread over threads by the C++ replay).
A run's result depends only on its seed and data, never on which worker or which
runs beside it trained it (``train_seeds`` guarantees this), so the outcome is the
same with any number of workers.
"""

from __future__ import annotations

import multiprocessing
import os
import queue as queue_module
import signal
import threading
import time
from dataclasses import dataclass
from typing import Callable

from ..transitions import Transitions
from .config import TrainConfig
from .loop import Progress, TrainResult, train_seeds
from .stepper import available_cores, set_default_threads


@dataclass
class TrainJob:
    label: str  # shown in progress lines, e.g. "awac s1"
    datasets: list[Transitions]
    cfg: TrainConfig
    seeds: list[int]


_progress_queue = None  # set in each worker process
_jobs = None  # shared by the workers: [jobs not started yet, jobs running]
_cores = 1


def _init_worker(progress_queue, parent_pid: int, jobs, cores: int) -> None:
    global _progress_queue, _jobs, _cores
    _progress_queue, _jobs, _cores = progress_queue, jobs, cores
    set_default_threads(1)  # one process per core already
    threading.Thread(target=_exit_with_parent, args=(parent_pid,), daemon=True).start()


def _threads_now() -> int:
    """One thread while runs wait for a worker; once none waits, the cores of finished
    runs go to the ones still training (the last AWAC run no longer trains on one core
    while the other idles)."""
    with _jobs.get_lock():
        waiting, running = _jobs[0], _jobs[1]
    return 1 if waiting > 0 else max(1, _cores // max(1, running))


def _exit_with_parent(parent_pid: int) -> None:
    """A worker outlives a killed parent (SIGTERM, SIGKILL) and would train on for
    minutes with nobody to report to: leave as soon as the parent is gone."""
    while os.getppid() == parent_pid:
        time.sleep(0.5)
    os._exit(1)


def _run_job(index: int, job: TrainJob) -> list[TrainResult]:
    def report(p: Progress) -> None:
        _progress_queue.put((index, p))

    with _jobs.get_lock():
        _jobs[0] -= 1
        _jobs[1] += 1
    try:
        return train_seeds(job.datasets, job.cfg, job.seeds, progress=report, threads_now=_threads_now)
    finally:
        with _jobs.get_lock():
            _jobs[1] -= 1


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt


def run_jobs(jobs: list[TrainJob], workers: int,
             progress_for: Callable[[TrainJob], Callable[[Progress], None]] | None = None) -> list[list[TrainResult]]:
    """Train every job; results in job order. ``workers`` <= 1 trains them one after
    another in this process. Give the heaviest jobs first: they are started first."""
    reporters = [progress_for(job) if progress_for else None for job in jobs]
    cores = max(1, min(workers, available_cores()))  # what the runs may use between them
    workers = max(1, min(workers, len(jobs)))
    if workers == 1:
        return [train_seeds(job.datasets, job.cfg, job.seeds, progress=rep) for job, rep in zip(jobs, reporters)]

    # spawn, not fork: the parent has torch (and its OpenMP pool) initialised
    ctx = multiprocessing.get_context("spawn")
    progress_queue = ctx.Queue()

    def drain(timeout: float) -> None:
        try:
            while True:
                index, p = progress_queue.get(timeout=timeout)
                timeout = 0.0
                if reporters[index] is not None:
                    reporters[index](p)
        except queue_module.Empty:
            pass

    jobs_state = ctx.Array("i", [len(jobs), 0])
    pool = ctx.Pool(workers, initializer=_init_worker, initargs=(progress_queue, os.getpid(), jobs_state, cores))
    # SIGTERM stops the workers too, as Ctrl-C does (a SIGKILL leaves it to _exit_with_parent)
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _raise_interrupt) if main_thread else None
    try:
        # handed out in this order, so the heaviest jobs start first
        pending = [pool.apply_async(_run_job, (i, job)) for i, job in enumerate(jobs)]
        while not all(p.ready() for p in pending):
            drain(0.2)
            for p in pending:
                if p.ready() and not p.successful():
                    p.get()  # re-raises the worker's exception now, not after the others finish
        results = [p.get() for p in pending]
        pool.close()
    except BaseException:
        pool.terminate()  # stop the other runs now, not when they finish
        raise
    finally:
        pool.join()
        if main_thread:
            signal.signal(signal.SIGTERM, previous)
    drain(0.1)  # the last progress lines may trail the results
    return results
