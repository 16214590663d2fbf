"""The recorder's side of the lockstep loop with the sim, as a plain class (no ROS).

The recorder node drives a lockstep sim to record a dataset: it answers each state with a
command and counts the transitions that come back. This class holds that bookkeeping;
the node only moves messages (``offline_rl_core.nodes.sim_loop`` is the sim's side).

Protocol: a command answers the latest state whose target (same stamp) has arrived, and
only once the transition caused by the previous command is in, so episode boundaries are
known before the next action is chosen. Stamps are integer nanoseconds. A state carrying
the stamp of the last command is the sim republishing the state we answered: while its
transition is awaited our command was lost (e.g. before discovery matched), so the same
command goes again, never a new draw; otherwise it is a stale copy and ignored.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..data.collect import EpisodePlan

# Targets kept by stamp: only the current state's matters, so trim to the newest few.
MAX_TARGETS = 64
TARGETS_KEPT = 8


@dataclass(frozen=True)
class Command:
    """An action answering the state stamped ``stamp`` (ns), and who chose it."""

    stamp: int
    action: np.ndarray  # float32[ACT_DIM]
    source: int  # SOURCE_EXPERT or SOURCE_RANDOM


class CollectDriver:
    """Episode counting and the command/transition handshake of one recording.

    ``episodes``: episodes to record (None: until stopped). ``plan``: who acts (None when
    only recording what flows: no command is ever ready).
    """

    def __init__(self, episodes: int | None, plan: EpisodePlan | None = None):
        self.episodes = episodes
        self.plan = plan
        self.episodes_done = 0
        self.transitions = 0
        self.awaiting_transition = False
        self.last_command: Command | None = None
        self._state: tuple[int, object, object] | None = None  # (stamp, position, velocity) to answer
        self._targets: dict[int, np.ndarray] = {}

    @property
    def finished(self) -> bool:
        return self.episodes is not None and self.episodes_done >= self.episodes

    def on_state(self, stamp: int, position, velocity) -> Command | None:
        """Take a state; returns the command to send again when it is a republished one."""
        if self.last_command is not None and stamp == self.last_command.stamp:
            return self.last_command if self.awaiting_transition else None
        self._state = (stamp, position, velocity)
        return None

    def on_target(self, stamp: int, target_xy) -> None:
        self._targets[stamp] = np.array(target_xy)
        if len(self._targets) > MAX_TARGETS:
            for key in sorted(self._targets)[:-TARGETS_KEPT]:
                del self._targets[key]

    def on_transition(self, ended: bool) -> bool:
        """Count a transition (``ended``: its episode's last); returns ``ended``."""
        self.transitions += 1
        self.awaiting_transition = False
        if ended:
            self.episodes_done += 1
        return ended

    def ready(self) -> bool:
        """A state with its target waits, and the previous command's transition is in."""
        return (
            self.plan is not None
            and not self.awaiting_transition
            and self._state is not None
            and self._state[0] in self._targets
        )

    def next_command(self) -> Command:
        """The command answering the waiting state (call when ``ready()``)."""
        if not self.ready():
            raise RuntimeError("no state ready to answer")
        stamp, position, velocity = self._state
        episode = self.episodes_done
        action = self.plan.action(episode, position, velocity, self._targets[stamp])
        command = Command(stamp, action, self.plan.source(episode))
        self._state = None
        self.awaiting_transition = True
        self.last_command = command
        return command
