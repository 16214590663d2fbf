"""A node's ``/diagnostics`` entry from its status: OK, WARN or ERROR, a message, key-values (no ROS).

``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``) is where ROS engineers look at a
robot's health (rqt_robot_monitor, Foxglove's diagnostics panels). Each node already
reports on ``~/status`` what it took and refused; :class:`StatusDiagnosis` turns that same
dict into one ``DiagnosticStatus``'s contents, a :class:`Diagnosis`:

- ``values``: every counter of the status, flattened (``rejected/bad stamp``,
  ``messages/pusher/state``), as strings;
- ``level``: WARN while messages were refused since the previous report (a count that
  only grows says nothing about now), or while a node's own check says so; ERROR for a
  fault the node cannot work through (a full disk, a failed flush); otherwise OK;
- ``message``: the problems, worst first, or what the node is doing when all is well.

A node's own checks (``checks``) take the status dict and return ``(level, text)`` pairs:
``policy_checks`` (weights age, dropped loads), ``recorder_checks`` (flush lag, disk),
``learner_checks`` (updates owed). ``pusher_common.diagnostics`` publishes the result once a
second.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Callable, Iterable

# diagnostic_msgs/DiagnosticStatus levels
OK, WARN, ERROR, STALE = 0, 1, 2, 3
LEVEL_NAMES = {OK: "OK", WARN: "WARN", ERROR: "ERROR", STALE: "STALE"}

# A policy acting on the online learner's weights: older than this, the learner has stalled.
STALE_WEIGHTS_S = 30.0
# Updates the online learner owes the data it has received, beyond which it is falling behind.
LEARNER_BEHIND_UPDATES = 1000

Check = Callable[[dict], Iterable[tuple[int, str]]]


@dataclass
class Diagnosis:
    level: int
    message: str
    values: list[tuple[str, str]] = field(default_factory=list)


def flatten(status: dict, prefix: str = "") -> list[tuple[str, str]]:
    """``{"rejected": {"bad stamp": 2}, "answered": 5}`` -> ``[("rejected/bad stamp", "2"), ("answered", "5")]``."""
    out: list[tuple[str, str]] = []
    for key, value in status.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out += flatten(value, name + "/")
        else:
            out.append((name, value_text(value)))
    return out


def value_text(value) -> str:
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(round(value, 6)) if math.isfinite(value) else str(value)
    if isinstance(value, (list, tuple)):
        return json.dumps(list(value))
    return str(value)


class StatusDiagnosis:
    """Status dicts, one per report, in; a :class:`Diagnosis` of each out.

    ``idle``: the message when nothing is wrong (a string or a function of the status).
    """

    def __init__(self, checks: Iterable[Check] = (), idle: str | Callable[[dict], str] = "running"):
        self.checks = tuple(checks)
        self.idle = idle
        self._last_rejected: dict[str, int] = {}

    def report(self, status: dict) -> Diagnosis:
        problems: list[tuple[int, str]] = []
        rejected = {k: int(v) for k, v in (status.get("rejected") or {}).items()}
        new = {k: n - self._last_rejected.get(k, 0) for k, n in rejected.items() if n > self._last_rejected.get(k, 0)}
        self._last_rejected = rejected
        if new:
            reasons = ", ".join(f"{k}: {n}" for k, n in sorted(new.items()))
            problems.append((WARN, f"{sum(new.values())} messages refused since the last report ({reasons})"))
        for check in (safety_checks,) + self.checks:
            problems += list(check(status))
        if problems:
            problems.sort(key=lambda p: -p[0])
            level, message = problems[0][0], "; ".join(text for _, text in problems)
        else:
            level = OK
            message = self.idle(status) if callable(self.idle) else self.idle
        return Diagnosis(level, message, flatten(status))


# ------------------------------------------------------------------ each node's checks
def safety_checks(status: dict) -> list[tuple[int, str]]:
    """Every node that consumes commands: an engaged e-stop is an ERROR (the arm is stopped
    until ``estop/reset``); a latched fault (a watchdog that tripped) a WARN until the reset."""
    out = []
    estop = status.get("estop")
    if isinstance(estop, dict) and estop.get("engaged"):
        out.append((ERROR, "e-stop engaged: the safe command applies until estop/reset"))
    faults = status.get("faults")
    if isinstance(faults, dict) and faults.get("watchdog"):
        trips = faults["watchdog"].get("trips") if isinstance(faults["watchdog"], dict) else None
        out.append((WARN, f"watchdog tripped {trips} time(s): commands went silent (latched until estop/reset)"))
    return out


def policy_checks(status: dict) -> list[tuple[int, str]]:
    out = []
    age = status.get("weights_age_s")
    if age is not None and age > STALE_WEIGHTS_S:
        out.append((WARN, f"acting on weights {age:.0f} s old (version {status.get('weights_version')}): "
                          "is the learner publishing?"))
    dropped = sum((status.get("loads_dropped") or {}).values())
    if dropped:
        out.append((WARN, f"{dropped} checkpoint/weights loads dropped (newer ones came first)"))
    return out


def recorder_checks(status: dict) -> list[tuple[int, str]]:
    out = []
    if status.get("error"):
        out.append((ERROR, f"the bag cannot be written: {status['error']}"))
    if status.get("low_space_bytes") is not None:
        out.append((ERROR, f"recording stopped: {status['low_space_bytes'] >> 20} MiB free, below min_free_space"))
    lag, interval = status.get("flush_lag_s"), status.get("flush_interval_s")
    if lag is not None and interval and lag > 3 * interval:
        out.append((WARN, f"messages waiting {lag:.1f} s for the disk (flush_interval {interval} s)"))
    if status.get("dropped_before_clock"):
        out.append((WARN, f"{status['dropped_before_clock']} messages dropped waiting for /clock"))
    return out


def learner_checks(status: dict) -> list[tuple[int, str]]:
    owed = status.get("owed") or 0
    if owed > LEARNER_BEHIND_UPDATES:
        return [(WARN, f"{owed} updates behind the data received")]
    return []


def level_name(level: int) -> str:
    return LEVEL_NAMES.get(level, str(level))
