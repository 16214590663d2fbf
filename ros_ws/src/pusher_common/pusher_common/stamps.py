"""Message stamps as integer nanoseconds: the key nodes pair messages by."""

from __future__ import annotations

from builtin_interfaces.msg import Time

NS_PER_S = 1_000_000_000


def stamp_key(stamp) -> int:
    """Return a ``builtin_interfaces/Time`` (a header's stamp) as integer nanoseconds."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def stamp_from_ns(ns: int) -> Time:
    """Invert :func:`stamp_key`."""
    return Time(sec=int(ns) // NS_PER_S, nanosec=int(ns) % NS_PER_S)
