"""Start and stop ROS 2 node processes by pid, on an isolated DDS domain.

No ROS import: the nodes are separate processes (``ros2 run PKG EXE ...`` or the
``lib/<pkg>/<exe>`` scripts of the virtualenv), so ``offline_rl_core`` stays free of rclpy.

    env = isolated_ros_env()                      # a free random ROS_DOMAIN_ID, localhost only
    with RosProcess(ros2_run("sim", "node", "--ros-args", "-p", "mode:=lockstep"), env, "sim.log") as sim:
        ...
    # leaving the block stops it: SIGINT, then SIGTERM, then SIGKILL, each by its pid

Every process is started in its own process group (so a terminal's Ctrl-C reaches only
the parent, which then stops its children in order), and is only ever signalled by its
own pid. On Linux a node also gets SIGTERM when the process that started it dies without
stopping it (killed, or a timeout's SIGKILL), so no node outlives its pipeline to drive
an arm, or load the machine, on its own.
"""

from __future__ import annotations

import ctypes
import fcntl
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ..common.errors import UserError

# Environment of an isolated node: DDS discovery on localhost only, on one domain.
_ISOLATION = {
    "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
    "PYTHONUNBUFFERED": "1",
    "RCUTILS_COLORIZED_OUTPUT": "0",
    "RCUTILS_LOGGING_BUFFERED_STREAM": "0",  # node logs reach the log file as they happen
    "OPENBLAS_NUM_THREADS": "1",
    "OMP_NUM_THREADS": "1",
}


# Domains this process holds (id -> the open lock file): kept open for the process's life.
_CLAIMED: dict[int, object] = {}


def domain_lock_dir() -> Path:
    return Path(tempfile.gettempdir()) / f"pusher-rl-ros-domains-{os.getuid()}"


def claim_free_domain(low: int = 1, high: int = 100) -> int:
    """A random DDS domain in low..high that no other pusher-rl process on this machine holds,
    held (an flock on a file per id) until this process exits. Two sessions on one machine (a
    HIL session and the test suite, two benchmarks) drawing the same id would hear each
    other's nodes; the lock is released by the kernel however the holder ends. With every id
    taken, one at random (as before the locks)."""
    lock_dir = domain_lock_dir()
    lock_dir.mkdir(parents=True, exist_ok=True)
    ids = list(range(low, high + 1))
    random.SystemRandom().shuffle(ids)
    for domain_id in ids:
        if domain_id in _CLAIMED:
            continue
        handle = open(lock_dir / f"{domain_id}.lock", "a")
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        _CLAIMED[domain_id] = handle
        return domain_id
    return ids[0]


def isolated_ros_env(domain_id: int | None = None, base: dict | None = None) -> dict:
    """A copy of ``base`` (default ``os.environ``) on a private DDS domain.

    ``domain_id`` None claims a free one at random from 1..100 (``claim_free_domain``; 0 is
    everybody's default; localhost-only discovery keeps other machines out whatever the id).
    """
    env = dict(os.environ if base is None else base)
    if domain_id is None:
        domain_id = claim_free_domain()
    if not 0 <= int(domain_id) <= 232:
        raise ValueError(f"ROS_DOMAIN_ID must be in 0..232, got {domain_id}")
    env.update(_ISOLATION)
    env["ROS_DOMAIN_ID"] = str(int(domain_id))
    env.pop("ROS_LOCALHOST_ONLY", None)  # deprecated twin of the range; must not contradict it
    return env


PR_SET_PDEATHSIG = 1  # linux/prctl.h
# loaded here, not in the child: between fork and exec only async-signal-safe calls are safe
_LIBC = ctypes.CDLL(None, use_errno=True) if sys.platform.startswith("linux") else None


def _child_setup(parent_pid: int) -> None:
    """In the child, before exec: SIGINT back to its default, so a graceful stop works even
    when the parent was started with SIGINT ignored (a background job of a non-interactive
    shell); SIGTERM when the parent dies (a parent already gone: at once)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    if _LIBC is not None:
        _LIBC.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
        if os.getppid() != parent_pid:
            os.kill(os.getpid(), signal.SIGTERM)


class RosProcess:
    """One node process, its stdout+stderr in ``log_path``, stopped by pid."""

    def __init__(self, cmd: list[str], env: dict, log_path: str | os.PathLike, cwd: str | os.PathLike | None = None,
                 name: str | None = None):
        self.cmd = [str(c) for c in cmd]
        self.env = env
        self.log_path = Path(log_path)
        self.cwd = cwd
        self.name = name or Path(self.cmd[0]).name
        self.proc: subprocess.Popen | None = None
        self._log = None

    @property
    def pid(self) -> int | None:
        return None if self.proc is None else self.proc.pid

    def start(self) -> "RosProcess":
        if self.proc is not None:
            raise RuntimeError(f"{self.name} already started (pid {self.pid})")
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self._log = open(self.log_path, "wb")
        self.proc = subprocess.Popen(
            self.cmd, env=self.env, cwd=self.cwd, stdout=self._log, stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL, start_new_session=True,
            preexec_fn=lambda parent=os.getpid(): _child_setup(parent),
        )
        return self

    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def poll(self) -> int | None:
        return None if self.proc is None else self.proc.poll()

    def wait(self, timeout: float | None = None) -> int | None:
        """Exit status, or None while it still runs after ``timeout`` s (so that
        ``assert p.wait(60) == 0, p.output()`` shows what the process printed)."""
        if self.proc is None:
            raise RuntimeError(f"{self.name} was never started")
        try:
            return self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return None

    def output(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""

    def wait_for_output(self, text: str, timeout: float = 30.0) -> bool:
        """True once ``text`` is in the log; False on timeout or when the process exits without it."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if text in self.output():
                return True
            if not self.running():
                return text in self.output()
            time.sleep(0.05)
        return False

    def stop(self, sig: int = signal.SIGINT, timeout: float = 5.0) -> int | None:
        """``sig`` (SIGINT), then SIGTERM after ``timeout`` s, then SIGKILL: always by this pid.
        Returns the exit status (None if never started)."""
        if self.proc is None:
            return None
        signals = [sig] + [s for s in (signal.SIGTERM, signal.SIGKILL) if s != sig]
        try:
            for sig in signals:
                if self.proc.poll() is not None:
                    break
                try:
                    self.proc.send_signal(sig)
                except ProcessLookupError:
                    break
                try:
                    self.proc.wait(timeout=timeout if sig != signal.SIGKILL else 10.0)
                except subprocess.TimeoutExpired:
                    continue
            return self.proc.poll()
        finally:
            if self._log is not None:
                self._log.close()
                self._log = None

    def __enter__(self) -> "RosProcess":
        if self.proc is None:
            self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def __repr__(self) -> str:
        return f"RosProcess({self.name!r}, pid={self.pid})"


class LaunchedProcesses:
    """The processes of a launch file's nodes (``ros2_shim.launch_files.LaunchNode``), each
    logged to ``log_dir/<name>.log``, stopped by pid.

        with LaunchedProcesses.of("pusher_bringup", "serve.launch.yaml", args, env, log_dir) as launched:
            launched.start(ready={"mux": "mux lockstep"})   # in file order, waiting where asked
            launched.wait(timeout=300)                      # until the on_exit: shutdown node ends
    Leaving the block stops every process still running, last started first.
    """

    def __init__(self, nodes: list, env: dict, log_dir: str | Path, cwd: str | Path | None = None):
        self.nodes = nodes
        self.processes: dict[str, RosProcess] = {}
        self.labels = [node.label for node in nodes]  # each node's key in processes
        self.end_with_all = False  # together: the launch ends when every part's on_exit node has
        for node in nodes:
            label = node.label
            if label in self.processes:
                raise UserError(f"two nodes named {label!r} in one launch")
            self.processes[label] = RosProcess(node.command(), env, Path(log_dir) / f"{label}.log", cwd=cwd, name=label)

    @classmethod
    def together(cls, parts: dict[str, "LaunchedProcesses"]) -> "LaunchedProcesses":
        """Several launches as one (not started yet), their nodes labelled ``PART/label`` (a
        part named "" keeps its labels), started part by part; it ends when every
        ``on_exit: shutdown`` node of them has ended (each part is one robot of several)."""
        merged = cls([], {}, ".")
        merged.end_with_all = True
        for part, launched in parts.items():
            for node, label in zip(launched.nodes, launched.labels):
                key = f"{part}/{label}" if part else label
                if key in merged.processes:
                    raise UserError(f"two nodes named {key!r} in one launch")
                merged.nodes.append(node)
                merged.labels.append(key)
                merged.processes[key] = launched.processes[label]
        return merged

    @classmethod
    def of(cls, package: str, file_name: str, arguments: dict, env: dict, log_dir: str | Path) -> "LaunchedProcesses":
        """The nodes of ``package``'s launch file ``file_name`` with ``arguments`` (values
        given as text, as on a ``ros2 launch`` command line)."""
        from ros2_shim.launch_files import find_launch_file, load_launch

        nodes = load_launch(find_launch_file(package, file_name), {k: str(v) for k, v in arguments.items()})
        return cls(nodes, env, log_dir)

    def __getitem__(self, label: str) -> RosProcess:
        return self.processes[label]

    def start(self, ready: dict[str, str] | None = None, timeout: float = 60.0) -> "LaunchedProcesses":
        """Start every node in order; where ``ready`` names it, wait for that text in its log."""
        for label, proc in self.processes.items():
            proc.start()
            text = (ready or {}).get(label)
            if text and not proc.wait_for_output(text, timeout):
                tail = "\n".join(proc.output().rstrip().splitlines()[-15:])
                raise UserError(f"{label} did not start (no {text!r} within {timeout:.0f} s); see {proc.log_path}:\n{tail}")
        return self

    def finished(self) -> RosProcess | None:
        """The process that ended the launch: the first ``on_exit: shutdown`` node to exit
        (together: once all have, the first that failed, else the last), or, where no node
        is marked, the last one once all have exited."""
        marked = [self.processes[label] for n, label in zip(self.nodes, self.labels) if n.shutdown_on_exit]
        if marked and self.end_with_all:
            if any(p.running() for p in marked):
                return None
            return next((p for p in marked if p.poll() != 0), marked[-1])
        if marked:
            return next((p for p in marked if not p.running()), None)
        procs = list(self.processes.values())
        return None if any(p.running() for p in procs) else procs[-1]

    def wait(self, timeout: float | None = None, poll_s: float = 0.1) -> int:
        """Exit status of the process that ended the launch; UserError after ``timeout`` s."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while (done := self.finished()) is None:
            if deadline is not None and time.monotonic() > deadline:
                running = [p for p in self.processes.values() if p.running()]
                raise UserError(f"{', '.join(p.name for p in running)} did not finish within {timeout:.0f} s; "
                                f"see {running[0].log_path}")
            time.sleep(poll_s)
        return done.poll()

    def stop(self) -> None:
        for proc in reversed(list(self.processes.values())):
            proc.stop()

    def __enter__(self) -> "LaunchedProcesses":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
