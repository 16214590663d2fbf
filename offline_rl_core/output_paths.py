"""Where a long-running process will write, checked when it starts, not when it ends.

A node that writes its file on exit (the sim's summary) or a directory of its own (the
learner's ``out``) would otherwise find out after the whole run that it cannot. The rules
follow the command line's: an output *file* needs an existing directory (as ``offline-rl
collect --out`` does) unless the caller asks for it to be made (``make_parents``: a launch
file naming a new session directory); a run *directory* is made with its parents (as
``offline-rl train --out`` does).
"""

from __future__ import annotations

import os
from pathlib import Path

from .errors import UserError


def ensure_parent(path: str | os.PathLike, what: str, make_parents: bool = False) -> Path:
    """``path``'s directory: existing and writable, or made when ``make_parents``; else a UserError."""
    path = Path(path)
    if not path.parent.is_dir() and not make_parents:
        raise UserError(f"{what} {path}: the directory {path.parent} does not exist; create it first")
    return _writable_dir(path.parent, f"{what} {path}: ", f"the directory {path.parent} ")


def checked_output_file(path: str | os.PathLike, what: str, make_parents: bool = False) -> Path:
    """A file to be written later: not a directory, in a writable directory."""
    path = Path(path)
    if path.is_dir():
        raise UserError(f"{what} {path}: is a directory; expected a file to write")
    ensure_parent(path, what, make_parents)
    return path


def checked_output_dir(path: str | os.PathLike, what: str) -> Path:
    """A run directory: made with its parents, writable."""
    path = Path(path)
    return _writable_dir(path, f"{what} {path}: ", "the directory ")


def _writable_dir(directory: Path, prefix: str, name: str) -> Path:
    """``directory``, made with its parents if missing; a UserError ``prefix`` + why when it cannot be written."""
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"{prefix}cannot create {name}({exc.strerror or exc})") from None
    if not os.access(directory, os.W_OK | os.X_OK):
        raise UserError(f"{prefix}{name}is not writable")
    return directory
