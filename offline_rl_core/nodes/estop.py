"""The e-stop latch, as a plain class (no ROS; ``pusher_common.estop`` wires it to DDS).

``estop`` (std_msgs/Bool, reliable, transient local) true engages it in every node that
listens (sim, mux, policy, learner); false only says the button is released. Nothing on
the topic releases it: only a reset (the ``estop/reset`` service, std_srvs/Trigger) does,
and a reset is refused while the latest word is still true (release the button first, as
an e-stop circuit wants). While engaged, a node applies the task's safe command and
forwards, answers and trains on nothing.
"""

from __future__ import annotations


class EStopLatch:
    def __init__(self):
        self.engaged = False
        self.held = False  # the latest estop word was true
        self.engagements = 0
        self.resets_refused = 0  # resets asked for while held (status shows the node heard them)

    def on_estop(self, value: bool) -> bool:
        """Take an ``estop`` word; True where it engaged the latch just now."""
        self.held = bool(value)
        if self.held and not self.engaged:
            self.engaged = True
            self.engagements += 1
            return True
        return False

    def reset(self) -> tuple[bool, str]:
        """Release (the reset service): (success, message)."""
        if self.held:
            self.resets_refused += 1
            return False, "the e-stop is still held (the latest estop message is true): publish false, then reset"
        if not self.engaged:
            return True, "not engaged"
        self.engaged = False
        return True, "released"

    def as_dict(self) -> dict:
        return {"engaged": self.engaged, "held": self.held, "engagements": self.engagements,
                "resets_refused": self.resets_refused}
