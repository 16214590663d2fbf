"""Several training runs at once, one worker process per CPU core.

One training step is a chain of small matmuls that a second intra-op thread barely
speeds up (and on a shared machine OpenMP's spinning threads stall it), so the cores
are used by whole runs instead: each worker trains with one thread
while runs wait for a worker. Once none waits, a run still training takes the cores
of the finished ones (its step spread over threads by the C++ replay).
A run's result depends only on its seed and data, never on which worker or which
runs beside it trained it (``train_seeds`` guarantees this), so the outcome is the
same with any number of workers.
The parent hands each worker one job at a time down its own pipe and watches the
worker's process, so a worker that dies (the OOM killer, a signal) fails the run at
once with an error naming its job, rather than leaving the run waiting for it.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import multiprocessing.connection
import os
import signal
import threading
import time
from dataclasses import dataclass
from typing import Callable, NamedTuple

from ..common.errors import RunFailed
from ..data.transitions import Transitions
from ..learners.config import TrainConfig
from ..learners.loop import Progress, TrainResult, train_seeds
from ..task.spec import TaskSpec
from ..learners.resume import ResumePoints
from ..common.interrupts import sigterm_as_interrupt
from ..common.machine import available_cores
from ..learners.stepper import set_default_threads


@dataclass
class TrainJob:
    label: str  # shown in progress lines and errors, e.g. "awac s1"
    datasets: list[Transitions]
    cfg: TrainConfig
    seeds: list[int]
    resume: ResumePoints | None = None  # the job's resume points (None: it writes none)
    task: TaskSpec | None = None  # the task of the data, recorded in the checkpoints (None: pusher_reach)

    def train(self, progress: Callable[[Progress], None] | None = None, threads_now=None) -> list[TrainResult]:
        return train_seeds(self.datasets, self.cfg, self.seeds, progress=progress, resume=self.resume,
                           threads_now=threads_now, task=self.task)


class _Worker(NamedTuple):
    process: multiprocessing.process.BaseProcess
    conn: multiprocessing.connection.Connection  # jobs down, progress and results up


_jobs = None  # shared by the workers: [jobs not started yet, jobs running]
_cores = 1


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


def _worker(conn, parent_pid: int, jobs, cores: int) -> None:
    """A worker process: trains the jobs the parent sends down ``conn``, one at a time,
    and sends back ("progress", Progress)... then ("done", results) or ("error", exception)."""
    global _jobs, _cores
    _jobs, _cores = jobs, cores
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole group: the parent stops us
    set_default_threads(1)  # one process per core already
    threading.Thread(target=_exit_with_parent, args=(parent_pid,), daemon=True).start()
    while (job := _next_job(conn)) is not None:
        with _jobs.get_lock():
            _jobs[0] -= 1
            _jobs[1] += 1
        try:
            conn.send(("done", job.train(lambda p: conn.send(("progress", p)), _threads_now)))
        except Exception as exc:  # noqa: BLE001 - the parent re-raises it
            exc.add_note(f"(in the training worker for {job.label!r})")
            conn.send(("error", exc))
        finally:
            with _jobs.get_lock():
                _jobs[1] -= 1


def _next_job(conn) -> TrainJob | None:
    try:
        return conn.recv()
    except EOFError:  # the parent is gone
        return None


def _how_it_ended(exitcode: int | None) -> str:
    if exitcode is not None and exitcode < 0:
        try:
            name = signal.Signals(-exitcode).name
        except ValueError:
            name = "unknown signal"
        return f"killed by signal {-exitcode}, {name}" + ("; out of memory?" if -exitcode == signal.SIGKILL else "")
    return f"exit status {exitcode}"


def _messages(conn):
    """The messages waiting on a worker's pipe, up to the end of a dead worker's."""
    while conn.poll():
        try:
            yield conn.recv()
        except (EOFError, OSError):  # the worker died, perhaps half-way through a message
            return


def run_jobs(jobs: list[TrainJob], workers: int,
             progress_for: Callable[[TrainJob], Callable[[Progress], None]] | None = None,
             on_done: Callable[[int, object], None] | None = None,
             keep_going: bool = False) -> list:
    """Train every job; results in job order. ``workers`` <= 1 trains them one after
    another in this process. Give the heaviest jobs first: they are started first.
    ``on_done(index, result)`` is called here as each job finishes.
    A worker that dies (the OOM killer, a signal) fails the run with RunFailed naming
    its job; a job's exception is raised here; either way the other workers are stopped.
    ``keep_going``: a job that fails stops nothing instead: its result is the exception
    (RunFailed for a worker that died, which a new worker replaces)."""
    reporters = [progress_for(job) if progress_for else None for job in jobs]
    cores = max(1, min(workers, available_cores()))  # what the runs may use between them
    workers = max(1, min(workers, len(jobs)))
    done = on_done or (lambda index, result: None)
    if workers == 1:
        results = []
        for index, (job, reporter) in enumerate(zip(jobs, reporters)):
            try:
                result = job.train(reporter)
            except Exception as exc:  # noqa: BLE001 - the job's result when keep_going
                if not keep_going:
                    raise
                result = exc
            results.append(result)
            done(index, result)
        return results

    # spawn, not fork: the parent has torch (and its OpenMP pool) initialised
    ctx = multiprocessing.get_context("spawn")
    jobs_state = ctx.Array("i", [len(jobs), 0])
    results: list = [None] * len(jobs)
    waiting = list(reversed(range(len(jobs))))  # popped from the end: the heaviest jobs start first
    running: dict[_Worker, int] = {}  # the index of the job each busy worker trains
    pool = []

    def start_worker() -> _Worker:
        conn, child_conn = ctx.Pipe()
        process = ctx.Process(target=_worker, args=(child_conn, os.getpid(), jobs_state, cores), daemon=True)
        process.start()
        child_conn.close()
        pool.append(_Worker(process, conn))
        return pool[-1]

    def hand_out(worker: _Worker) -> None:
        if waiting:
            running[worker] = index = waiting.pop()
            job = jobs[index]
            worker.process.name = f"training worker for {job.label!r}"  # for errors, and to find it
            with contextlib.suppress(OSError):  # a dead worker: found by the loop below
                worker.conn.send(job)

    def finished(worker: _Worker, index: int, result) -> None:
        results[index] = result
        del running[worker]
        done(index, result)

    # SIGTERM stops the workers too, as Ctrl-C does (a SIGKILL leaves it to _exit_with_parent)
    with sigterm_as_interrupt():
        try:
            for _ in range(workers):
                hand_out(start_worker())
            while running:
                # wakes on a message or on a worker's death, whichever comes first
                multiprocessing.connection.wait([w.conn for w in running] + [w.process.sentinel for w in running])
                for worker, index in list(running.items()):
                    for kind, value in _messages(worker.conn):
                        if kind == "progress":
                            if reporters[index] is not None:
                                reporters[index](value)
                        elif kind == "error" and not keep_going:
                            raise value  # now, not after the other runs finish
                        else:
                            finished(worker, index, value)
                            hand_out(worker)
                            break
                    if running.get(worker) == index and not worker.process.is_alive():
                        failure = RunFailed(f"{worker.process.name} died ({_how_it_ended(worker.process.exitcode)})")
                        if not keep_going:
                            raise failure
                        with jobs_state.get_lock():  # the dead worker's count of running jobs
                            jobs_state[1] = max(0, jobs_state[1] - 1)
                        finished(worker, index, failure)
                        if waiting:
                            hand_out(start_worker())
            for worker in pool:
                with contextlib.suppress(OSError):
                    worker.conn.send(None)  # no more jobs: the worker returns
        except BaseException:
            for worker in pool:
                worker.process.terminate()  # stop the other runs now, not when they finish
            raise
        finally:
            for worker in pool:
                worker.process.join()
                worker.conn.close()
    return results
