"""Message classes by type name ('pkg/msg/Name').

For nodes that subscribe to what a task or the graph names.
"""

from __future__ import annotations

import importlib
import re

MESSAGE_TYPE = re.compile(r"[A-Za-z][A-Za-z0-9_]*/msg/[A-Za-z][A-Za-z0-9_]*")


def message_class(msgtype: str):
    """Return the class of 'pkg/msg/Name', or None (not a type name, or not installed)."""
    if not MESSAGE_TYPE.fullmatch(msgtype):
        return None
    package, _, name = msgtype.split("/")
    try:
        return getattr(importlib.import_module(f"{package}.msg"), name)
    except Exception:  # noqa: BLE001 - whatever importing a package named by discovery raises
        return None
