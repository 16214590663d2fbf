"""The C++ replayer of recorded training steps (``csrc/graph_runner.cpp``).

Built with torch's extension loader on first use and cached under
``TORCH_EXTENSIONS_DIR`` (default ``~/.cache/torch_extensions``), one directory per
source version and environment; ``make setup`` builds it ahead so no run waits for it.
Needs g++, ninja and the Python headers; where any is missing ``unavailable_reason``
says which, and recorded steps replay in Python instead (``learners/traced.py``).
``python -m offline_rl_core.fast.graph_runner`` builds it and reports.
"""

from __future__ import annotations

import functools
import hashlib
import os
import sys
import time
from pathlib import Path

import torch

SOURCE = Path(__file__).resolve().parent / "csrc" / "graph_runner.cpp"
COMPILE_FLAGS = ["-O2"]


def _build_dir(source: bytes) -> Path:
    """One build directory per (source, torch install, Python): checkouts that share an
    environment share one build, and a changed source or another environment never
    overwrites a build that some process may have loaded."""
    # torch's location too: the build's include paths point into this environment's torch
    where = f"{torch.__version__} {Path(torch.__file__).parent} {sys.version} {COMPILE_FLAGS}"
    digest = hashlib.sha256(source + where.encode()).hexdigest()
    root = Path(os.environ.get("TORCH_EXTENSIONS_DIR") or Path.home() / ".cache" / "torch_extensions")
    return root / f"pusher_rl_graph_runner_{digest[:16]}"


def _cached(build_dir: Path) -> bool:
    return any(build_dir.glob("*.so"))


def _clear_stale_lock(build_dir: Path, max_age_s: float = 300.0) -> None:
    """torch's loader waits forever on the lock file of a build that was interrupted
    (Ctrl-C during the first compile); a compile takes well under a minute, so an old
    lock is stale."""
    try:
        if time.time() - (build_dir / "lock").stat().st_mtime > max_age_s:
            (build_dir / "lock").unlink()
    except OSError:
        pass


@functools.lru_cache(maxsize=1)
def _load():
    """(module, None) or (None, reason)."""
    try:
        from torch.utils.cpp_extension import load, verify_ninja_availability

        verify_ninja_availability()
    except Exception as exc:  # noqa: BLE001
        return None, f"no ninja ({exc})"
    try:
        source = SOURCE.read_bytes()
    except OSError as exc:
        return None, f"cannot read {SOURCE}: {exc.strerror}"
    build_dir = _build_dir(source)
    name = build_dir.name
    try:
        build_dir.mkdir(parents=True, exist_ok=True)
        # compiled from a copy inside the build directory: ninja's commands then name
        # the same path from every checkout, so a second checkout does not rebuild
        copy = build_dir / SOURCE.name
        if not copy.exists() or copy.read_bytes() != source:
            tmp = build_dir / f".{SOURCE.name}.{os.getpid()}"
            tmp.write_bytes(source)
            tmp.replace(copy)
    except OSError as exc:
        return None, f"cannot write {build_dir}: {exc.strerror}"
    _clear_stale_lock(build_dir)
    if not _cached(build_dir):
        print("pusher-rl: compiling the C++ step replayer (once; about 30 s, then cached)", file=sys.stderr, flush=True)
    try:
        module = load(name=name, sources=[str(copy)], extra_cflags=COMPILE_FLAGS, build_directory=str(build_dir),
                      verbose=False)
        return module, None
    except Exception as exc:  # noqa: BLE001 - a compiler error is a reason to fall back, not to stop
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        return None, f"build failed: {first}"


def unavailable_reason() -> str | None:
    """None when the extension is built (building it now if needed), else why not."""
    return _load()[1]


def extension():
    """The built module (``Program``); call ``unavailable_reason`` first."""
    return _load()[0]


def main() -> int:
    t0 = time.perf_counter()
    reason = unavailable_reason()
    if reason is not None:
        print(f"C++ step replayer not built: {reason}; recorded steps replay in Python", file=sys.stderr)
        return 1
    print(f"C++ step replayer ready ({time.perf_counter() - t0:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
