"""Ray as the engine of sweeps, fleets of bags and the experiment: the one module that imports ray.

What goes where (README, 'Sweeps and fleets'): this process, the driver, reads the spec and
writes every file of the sweep's DIR. Each bag set is decoded once by Ray tasks (on the
driver's machine, where the bags are, unless ``shared_bags`` says every machine sees them at
the same path) into Ray's object store; each run is a task that takes its dataset from
there, trains and evaluates in a temporary folder of whatever machine runs it, and sends
back its result row and its files' bytes. So a cluster needs no shared file system, only
the project installed alike on every machine (the same code trains the same bytes).

Ray is imported lazily, here only: without it everything else runs, and asking for it says
how to install it; a cluster that cannot be reached says how to start one.
"""

from __future__ import annotations

import logging
import os
import socket
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Callable

from ..common.errors import RunFailed, UserError
from ..common.machine import available_cores
from ..data.fleet import decode_bag, count_transitions, read_fleet, writable
from ..learners.stepper import set_default_threads
from .sweep import SweepRun, execute_run_detached, one_line, result_row, store_run_files

INSTALL = "pip install 'torch==2.13.0' -e '.[ray]' in the project (make setup does it where pip can)"
START = "start one with `ray start --head` on the head machine and `ray start --address HEAD:6379` on the others"
CONNECT_TIMEOUT_S = 5.0


def ray_missing() -> str | None:
    """Why the Ray engine cannot run here (None: it can), without importing Ray."""
    import importlib.util

    return None if importlib.util.find_spec("ray") else f"Ray is not installed here; {INSTALL}"


def import_ray():
    """The ray module, or a UserError saying how to install it."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # no report home from a lab's machines
    try:
        import ray
    except ImportError:
        raise UserError(f"--engine ray: Ray is not installed here; {INSTALL}") from None
    return ray


def _check_reachable(address: str) -> None:
    """Ray retries an unreachable HOST:PORT for minutes: say so at once instead."""
    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit():
        raise UserError(f"--address {address}: expected auto or HOST:PORT (the head's `ray start --head` port, 6379)")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=CONNECT_TIMEOUT_S).close()
    except OSError as exc:
        raise UserError(f"--address {address}: no Ray cluster answers there ({exc.strerror or exc}); {START}") from None


@contextmanager
def connected(address: str | None = None, num_cpus: int | None = None) -> Iterator[object]:
    """Ray for the length of the block: the cluster at ``address`` ('auto': the one
    `ray start` runs on this machine; HOST:PORT: its head), or, for None, a private Ray
    on this machine's loopback with ``num_cpus`` (default: this process's cores), shut
    down after. A Ray this process has already initialised (a test's) is used as it is."""
    if address is None and "ray" not in sys.modules:
        # a private cluster: on loopback, out of reach of (and not reaching) the network, with
        # a token all the same (set, so not warned about); Ray reads both when it is imported
        os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
        os.environ.setdefault("RAY_AUTH_MODE", "token")
    ray = import_ray()
    if ray.is_initialized():
        yield ray
        return
    if address not in (None, "auto"):
        _check_reachable(address)
    try:
        if address is None:
            ray.init(num_cpus=num_cpus or available_cores(), include_dashboard=False, logging_level=logging.WARNING)
        else:
            ray.init(address=address, logging_level=logging.WARNING)
    except ConnectionError as exc:
        raise UserError(f"--address {address}: no Ray cluster found ({one_line(exc)[:160]}); {START}") from None
    except RuntimeError as exc:  # Ray's own start failed (its GCS, its raylet)
        where = f"the Ray cluster at {address}" if address else "a private Ray on this machine"
        raise RunFailed(f"--engine ray: could not start or join {where}: {one_line(exc)[:300]}") from None
    try:
        yield ray
    finally:
        ray.shutdown()


def cluster_cpus(ray) -> int:
    return max(1, int(ray.cluster_resources().get("CPU", 1)))


class _RayFuture:
    """A task's result as ``concurrent.futures.Future`` gives it (what ``iter_fleet`` uses)."""

    def __init__(self, ray, ref):
        self.ray, self.ref = ray, ref

    def result(self):
        try:
            return self.ray.get(self.ref)
        except self.ray.exceptions.RayTaskError as exc:
            raise _cause(exc) from None

    def cancel(self) -> bool:
        self.ray.cancel(self.ref)
        return True


class RayExecutor:
    """Submits a fleet's decoding tasks to Ray: pinned to this machine's node (where the
    bags are), or anywhere in the cluster when ``anywhere`` (the bags on shared storage)."""

    def __init__(self, ray, anywhere: bool = False):
        self.ray = ray
        options = {"num_cpus": 1, "max_retries": 1}
        if not anywhere:
            from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

            node = ray.get_runtime_context().get_node_id()
            options["scheduling_strategy"] = NodeAffinitySchedulingStrategy(node_id=node, soft=False)
        self.tasks = {fn: ray.remote(fn).options(**options) for fn in (decode_bag, count_transitions)}

    def submit(self, fn, *args) -> _RayFuture:
        return _RayFuture(self.ray, self.tasks[fn].remote(*args))

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        return None


def read_fleet_on_ray(paths: list[str], shared_bags: bool = False, ahead: int | None = None):
    """``data.fleet.read_fleet`` with each bag decoded by a Ray task (Ray must be connected);
    at most ``ahead`` bags (default: two per CPU of the cluster) decoded and not yet copied."""
    ray = import_ray()
    return read_fleet(paths, executor=RayExecutor(ray, shared_bags), ahead=ahead or 2 * cluster_cpus(ray))


def _cause(exc) -> BaseException:
    """The exception a task raised, from Ray's wrapper of it."""
    cause = getattr(exc, "cause", None)
    return cause if isinstance(cause, BaseException) else RunFailed(one_line(exc))


# ----------------------------------------------------------------------------- sweeps

def _train_run(run: SweepRun, dataset) -> tuple[dict, dict[str, bytes]]:
    """A run's task: its row and files (the dataset arrives as read-only views of the store)."""
    set_default_threads(1)  # one CPU per task, as the local engine's workers
    data, summaries = dataset
    return execute_run_detached(run, (writable(data), summaries))


class RayEngine:
    """A sweep's runs as Ray tasks (Ray connected by ``connected``)."""

    def __init__(self, shared_bags: bool = False, log: Callable[[str], None] = print):
        self.ray = import_ray()
        self.shared_bags = shared_bags
        self.log = log

    def describe(self) -> str:
        nodes = sum(1 for n in self.ray.nodes() if n.get("Alive"))
        return f"Ray ({cluster_cpus(self.ray)} CPUs on {nodes} node(s))"

    def run(self, runs: list[SweepRun], out: Path, on_result: Callable[[SweepRun, dict], None]) -> None:
        ray = self.ray
        task = ray.remote(_train_run).options(num_cpus=1, max_retries=1)
        pending = {}
        try:
            # bag set by bag set: its runs start while the next set is decoded
            for bags in dict.fromkeys(r.bags for r in runs):
                its_runs = [r for r in runs if r.bags == bags]
                try:
                    dataset = ray.put(read_fleet_on_ray(list(bags), self.shared_bags))
                except Exception as exc:  # noqa: BLE001 - a bad bag fails the runs that train on it, no others
                    for run in its_runs:
                        on_result(run, result_row(run, error=one_line(exc)))
                    continue
                pending.update({task.remote(run, dataset): run for run in its_runs})
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1)
                run = pending.pop(ready[0])
                try:
                    row, files = ray.get(ready[0])
                except ray.exceptions.RayError as exc:  # the task's process or node died
                    row, files = result_row(run, error=one_line(_cause(exc))), {}
                if files:
                    store_run_files(out / run.name, files)
                on_result(run, row)
        finally:
            for ref in pending:  # interrupted: the runs still out are cancelled
                ray.cancel(ref, force=True)


# ----------------------------------------------------------------------------- the experiment

def _train_job(job):
    set_default_threads(1)
    job.datasets = [writable(d) for d in job.datasets]
    return job.train()


def run_train_jobs(jobs: list, log: Callable[[str], None] = print) -> list:
    """``parallel.run_jobs`` on Ray (connected): each job a task; results in job order. The
    first job to fail cancels the others and is raised (a UserError as it is)."""
    ray = import_ray()
    task = ray.remote(_train_job).options(num_cpus=1, max_retries=1)
    refs = [task.remote(job) for job in jobs]
    index = {ref: i for i, ref in enumerate(refs)}
    results: list = [None] * len(jobs)
    pending = list(refs)
    try:
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            i = index[ready[0]]
            try:
                results[i] = ray.get(ready[0])
            except ray.exceptions.RayError as exc:
                cause = _cause(exc)
                if isinstance(cause, (UserError, RunFailed)):
                    raise cause from None
                raise RunFailed(f"the Ray task for {jobs[i].label!r} failed: {one_line(cause)}") from None
            log(f"  {jobs[i].label:>8} done on Ray ({len(jobs) - len(pending)}/{len(jobs)})")
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)
    return results
