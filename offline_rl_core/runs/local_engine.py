"""A sweep's runs in worker processes of this machine, one per core (``parallel.run_jobs``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..common.machine import available_cores
from .parallel import run_jobs
from .sweep import SweepRun, execute_run, one_line, result_row


@dataclass
class SweepJob:
    """One run as a job of ``run_jobs``: its result is its row, a failure included."""

    run: SweepRun
    out_dir: Path

    @property
    def label(self) -> str:
        return self.run.name

    def train(self, progress=None, threads_now=None) -> dict:
        return execute_run(self.run, self.out_dir)


class LocalEngine:
    def __init__(self, workers: int | None = None):
        self.workers = max(1, workers or available_cores())

    def describe(self) -> str:
        return "this machine" if self.workers == 1 else f"{self.workers} worker processes"

    def run(self, runs: list[SweepRun], out: Path, on_result: Callable[[SweepRun, dict], None]) -> None:
        def done(index: int, result) -> None:
            # a worker that died (the OOM killer, a signal) is a failure of its run alone
            row = result if isinstance(result, dict) else result_row(runs[index], error=one_line(result))
            on_result(runs[index], row)

        run_jobs([SweepJob(r, out / r.name) for r in runs], self.workers, on_done=done, keep_going=True)
