"""The mux's arbitration rule, free of ROS (the node and the tests use it).

Inputs are the policy's actions and the teleop messages, each with its stamp; the
output is the commands to send, each tagged with who acted. A teleop message with an
empty action is a *yield*: "no correction for this state" (lockstep), or "let go"
(realtime: ends the hold at once).

Realtime (zero-order hold sim): a teleop action is forwarded at once and holds the
arm for ``hold_s`` seconds of wall time; policy actions that arrive inside the hold
are dropped. After the hold (or a yield) the policy's actions flow again.

Lockstep (the sim steps once per stamp): exactly one command per stamp.
- teleop action for stamp s            -> forward it (human) - the decision for s.
- teleop yield for s, policy action    -> forward the policy's action for s.
- policy action for s, no teleop word  -> wait, when a corrector is present (a teleop
  publisher is matched, or ``require_teleop``); otherwise forward it at once.
- a late message for a decided stamp   -> resend the same decided command (the sim
  republishes a state whose command was lost; it ignores commands of other stamps), so
  a policy action can never replace the human's for a stamp, nor the reverse.
"intervening" is true while the latest decided stamp went to the human.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

POLICY = "policy"
HUMAN = "human"
KEEP_STAMPS = 256  # decided / pending stamps remembered (the sim only ever waits on the latest)


@dataclass
class Command:
    stamp: int
    action: np.ndarray
    source: str  # POLICY or HUMAN
    resend: bool = False


class LockstepArbiter:
    def __init__(self):
        self.policy: OrderedDict[int, np.ndarray] = OrderedDict()
        self.teleop: OrderedDict[int, np.ndarray | None] = OrderedDict()  # None: a yield
        self.decided: OrderedDict[int, Command] = OrderedDict()
        self.intervening = False
        self.counts = {POLICY: 0, HUMAN: 0}

    @staticmethod
    def _remember(store: OrderedDict, stamp: int, value) -> None:
        store[stamp] = value
        store.move_to_end(stamp)
        while len(store) > KEEP_STAMPS:
            store.popitem(last=False)

    def on_policy(self, stamp: int, action: np.ndarray, corrector_present: bool) -> Command | None:
        if stamp in self.decided:
            return self._resend(stamp)
        self._remember(self.policy, stamp, action)
        if stamp in self.teleop:
            return self._decide(stamp)
        if not corrector_present:
            return self._decide(stamp, POLICY)
        return None  # wait for the corrector's word on this stamp

    def on_teleop(self, stamp: int, action: np.ndarray | None) -> Command | None:
        if stamp in self.decided:
            return self._resend(stamp)
        self._remember(self.teleop, stamp, action)
        if action is not None:
            return self._decide(stamp)
        if stamp in self.policy:
            return self._decide(stamp)
        return None  # a yield: the policy's action for this stamp goes when it comes

    def _decide(self, stamp: int, source: str | None = None) -> Command:
        correction = self.teleop.get(stamp)
        if source is None:
            source = HUMAN if correction is not None else POLICY
        action = correction if source == HUMAN else self.policy[stamp]
        command = Command(stamp, np.asarray(action, np.float32), source)
        self._remember(self.decided, stamp, command)
        self.policy.pop(stamp, None)
        self.teleop.pop(stamp, None)
        self.counts[source] += 1
        self.intervening = source == HUMAN
        return command

    def _resend(self, stamp: int) -> Command:
        c = self.decided[stamp]
        return Command(c.stamp, c.action, c.source, resend=True)


class RealtimeArbiter:
    def __init__(self, hold_s: float = 0.1):
        self.hold_s = float(hold_s)
        self.last_teleop: float | None = None  # wall time of the latest teleop action
        self.counts = {POLICY: 0, HUMAN: 0}

    def holding(self, now: float) -> bool:
        return self.last_teleop is not None and now - self.last_teleop < self.hold_s

    def on_policy(self, stamp: int, action: np.ndarray, now: float) -> Command | None:
        if self.holding(now):
            return None  # the human has the arm
        self.counts[POLICY] += 1
        return Command(stamp, np.asarray(action, np.float32), POLICY)

    def on_teleop(self, stamp: int, action: np.ndarray | None, now: float) -> Command | None:
        if action is None:  # let go: the policy's next action goes through
            self.last_teleop = None
            return None
        self.last_teleop = now
        self.counts[HUMAN] += 1
        return Command(stamp, np.asarray(action, np.float32), HUMAN)
