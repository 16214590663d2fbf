"""Atomic file writes: write beside the target, then rename over it.

A reader (the policy node watching a checkpoint, a user opening metrics.json) sees
the old file or the new one, never half of one; a failed write leaves nothing behind,
and a write killed half-way leaves a temp file that ``remove_partial_writes`` clears.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


def _create_beside(path: Path, suffix: str) -> Path:
    """A new empty file in ``path``'s directory, with the mode a plain ``open()`` gives
    (0o666 less the umask; mkstemp's 0o600 would hide a policy.pt from the policy node
    running as another user)."""
    for _ in range(100):
        tmp = path.parent / f".{path.name}.{secrets.token_hex(4)}{suffix}"
        try:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            return tmp
        except FileExistsError:
            continue
    raise FileExistsError(f"{path.parent}: no free temporary name for {path.name}")


@contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = ".tmp") -> Iterator[Path]:
    """Yield a temporary path in ``path``'s directory; on success it replaces ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _create_beside(path, suffix)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def remove_partial_writes(path: str | os.PathLike, suffix: str = ".tmp") -> None:
    """Delete the temp files that writes of ``path`` killed half-way left beside it (a
    resume point's is as big as the resume point). Call it when nothing else writes ``path``."""
    path = Path(path)
    for tmp in path.parent.glob(f".{path.name}.*{suffix}"):
        tmp.unlink(missing_ok=True)


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; returns the path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def write_json_atomic(path: str | os.PathLike, payload) -> Path:
    """``json.dumps(indent=2, sort_keys=True)`` + newline, atomically: a reader never
    sees half a file, and equal payloads give equal bytes."""
    import json

    return write_text_atomic(path, json.dumps(payload, indent=2, sort_keys=True) + "\n")
