"""Message classes by type name ('pkg/msg/Name'), for nodes that subscribe to what a task or
the graph names."""

from __future__ import annotations

import importlib


def message_class(msgtype: str):
    """The Python class of 'pkg/msg/Name', or None when its package is not installed."""
    package, _, name = msgtype.split("/")
    try:
        return getattr(importlib.import_module(f"{package}.msg"), name)
    except (ImportError, AttributeError):
        return None
