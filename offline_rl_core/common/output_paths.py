"""Checks of an output path before the work that fills it, so that a path that cannot be
written fails in one line at the start, not with a traceback after minutes of training,
rolling out or benchmarking (and before anything else of the run is written)."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from .errors import UserError


def check_output_file(path: str | os.PathLike, flag: str) -> Path:
    """``path`` (given as ``flag``) can be written as a file: not a directory, and its nearest
    existing ancestor is a writable directory (missing directories are created on writing)."""
    path = Path(path)
    if path.is_dir():
        raise UserError(f"{flag} {path}: is a directory; expected a file path")
    _check_parent(path, flag)
    return path


def check_output_dir(path: str | os.PathLike, flag: str) -> Path:
    """``path`` (given as ``flag``) is, or can be created as, a writable directory."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise UserError(f"{flag} {path}: exists and is not a directory; expected a directory")
    if path.is_dir():
        _probe(path, path, flag)
    else:
        _check_parent(path, flag)
    return path


def _check_parent(path: Path, flag: str) -> None:
    ancestor = path.absolute().parent
    while not ancestor.exists() and not ancestor.is_symlink() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise UserError(f"{flag} {path}: cannot write: {ancestor} is a file, not a directory")
    _probe(ancestor, path, flag)


def _probe(directory: Path, path: Path, flag: str) -> None:
    """Create and remove a file in ``directory``: the one test that permission bits, read-only
    mounts and pseudo file systems (/proc) all answer truly."""
    try:
        fd, probe = tempfile.mkstemp(prefix=".offline-rl-probe.", dir=directory)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise UserError(f"{flag} {path}: cannot write in {directory} ({exc.strerror})") from None


def remove_if_empty(path: Path, created: bool) -> None:
    """Remove ``path`` if this run ``created`` it and a failure left it empty."""
    if created and path.is_dir() and not any(path.iterdir()):
        path.rmdir()
