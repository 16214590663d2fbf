"""The ament resource index, read the way ros2cli and launch read it (no ROS import).

A package is installed in a prefix when ``<prefix>/share/ament_index/resource_index/
packages/<name>`` exists; its shared files are under ``<prefix>/share/<name>/`` and its
executables are the executable files directly in ``<prefix>/lib/<name>/``. Prefixes come
from ``AMENT_PREFIX_PATH`` plus this interpreter's environment (the project's .venv is an
ament prefix, and nobody has to source a setup script for it).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

PACKAGES_MARKER_DIR = Path("share", "ament_index", "resource_index", "packages")


def prefixes() -> list[Path]:
    """Ament prefixes in lookup order, without duplicates."""
    found = [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    found.append(Path(sys.prefix))
    unique: list[Path] = []
    seen: set[str] = set()
    for prefix in found:
        key = os.path.realpath(prefix)
        if key not in seen:
            seen.add(key)
            unique.append(prefix)
    return unique


def packages() -> dict[str, Path]:
    """Every package name with the first prefix that holds it."""
    result: dict[str, Path] = {}
    for prefix in prefixes():
        marker_dir = prefix / PACKAGES_MARKER_DIR
        if not marker_dir.is_dir():
            continue
        for marker in marker_dir.iterdir():
            if not marker.name.startswith(".") and marker.name not in result:
                result[marker.name] = prefix
    return result


def package_prefix(name: str) -> Path | None:
    for prefix in prefixes():
        if (prefix / PACKAGES_MARKER_DIR / name).exists():
            return prefix
    return None


def package_share(name: str) -> Path | None:
    """``<prefix>/share/<name>`` of an installed package (launch's ``$(find-pkg-share name)``)."""
    prefix = package_prefix(name)
    return None if prefix is None else prefix / "share" / name


def executables(name: str) -> dict[str, Path] | None:
    """``{executable name: path}`` of package ``name``; None when it is not installed."""
    prefix = package_prefix(name)
    if prefix is None:
        return None
    lib_dir = prefix / "lib" / name
    found: dict[str, Path] = {}
    if lib_dir.is_dir():
        for path in sorted(lib_dir.iterdir()):
            if path.is_file() and os.access(path, os.X_OK):
                found[path.name] = path
    return found


def venv_bin(name: str) -> Path:
    """``<prefix>/bin/<name>`` of the running interpreter's environment."""
    return Path(sys.prefix) / "bin" / name


def ros2_run(package: str, executable: str, *args) -> list[str]:
    """The command line of ``ros2 run PACKAGE EXECUTABLE ARGS...``.

    Uses the installed ``lib/<pkg>/<exe>`` script directly when it exists (what
    ``ros2 run`` would exec: one process, one pid), else the ``ros2`` command.
    """
    script = Path(sys.prefix) / "lib" / package / executable
    if script.is_file() and os.access(script, os.X_OK):
        return [str(script), *map(str, args)]
    return [str(venv_bin("ros2")), "run", package, executable, *map(str, args)]
