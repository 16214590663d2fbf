"""Work a serving node must not do on the thread that answers the arm (no ROS).

The policy node answers every state within its control period on one executor thread.
Reading a checkpoint file (which may be large, on a slow disk, or something that is no
file at all) and checking and decoding a weights message are done here instead, on one
worker thread, in the order submitted; the serving thread collects what came of them with
:meth:`BackgroundLoads.drain` when ``notify`` (e.g. a guard condition's trigger) says
something is ready, and swaps policies itself, so a state always sees one whole policy.

What waits is bounded: at most ``max_pending`` jobs of a kind; a new one beyond that
replaces the oldest waiting (counted in ``dropped``): a flood of messages costs the worker
time, never the node's memory.
"""

from __future__ import annotations

import threading
from collections import deque
from typing import Any, Callable


class BackgroundLoads:
    def __init__(self, notify: Callable[[], None], max_pending: int = 10, name: str = "loads"):
        self.notify = notify
        self.max_pending = int(max_pending)
        self.dropped: dict[str, int] = {}
        self._jobs: deque[tuple[str, Callable[[], Any]]] = deque()
        self._results: deque[Any] = deque()
        self._wake = threading.Condition()
        self._stopping = False
        self._busy = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, kind: str, job: Callable[[], Any]) -> None:
        """Run ``job()`` on the worker; its return value is what :meth:`drain` yields."""
        with self._wake:
            waiting = [i for i, (k, _) in enumerate(self._jobs) if k == kind]
            if len(waiting) >= self.max_pending:
                del self._jobs[waiting[0]]
                self.dropped[kind] = self.dropped.get(kind, 0) + 1
            self._jobs.append((kind, job))
            self._wake.notify()

    def drain(self) -> list:
        """What finished since the last call, oldest first (call on the serving thread)."""
        out = []
        while self._results:
            out.append(self._results.popleft())
        return out

    def idle(self) -> bool:
        with self._wake:
            return not self._jobs and not self._busy

    def stop(self, timeout: float = 5.0) -> None:
        """Stop after the job running now (those waiting are dropped); before the node goes."""
        with self._wake:
            self._stopping = True
            self._jobs.clear()
            self._wake.notify()
        self._thread.join(timeout)

    def _run(self) -> None:
        while True:
            with self._wake:
                while not self._jobs and not self._stopping:
                    self._wake.wait()
                if self._stopping:
                    return
                _, job = self._jobs.popleft()
                self._busy = True
            try:
                result = job()
            except Exception as exc:  # noqa: BLE001 - a job's own failure is its result; the worker goes on
                result = exc
            with self._wake:  # notified under the lock: after stop() returns, never again
                self._busy = False
                if self._stopping:
                    return
                self._results.append(result)
                self.notify()
