"""``ros2 run corrections mux``: the policy drives, a person (or the corrector) can take over.

Forwards ``/policy/action`` to ``/pusher/command`` unless the human acts on
``/teleop/action``; each command's ``header.frame_id`` is its source tag ('policy' or
'human', codes 2 and 3), which the sim writes into ``/pusher/transition`` so the bag
records who acted. ``/corrections/intervening`` (std_msgs/Bool, transient local) is
published on each change.

Parameters:
- ``mode``: ``realtime`` (default) or ``lockstep``, as the sim's.
- ``hold_ms`` (100): realtime: a teleop action holds the arm this long (wall time);
  policy actions inside the hold are dropped. An empty teleop action lets go at once.
- ``require_teleop`` (false): lockstep: always wait for the corrector's word on each
  stamp (an action, or an empty-effort *yield*). When false, the mux waits only while
  a ``/teleop/action`` publisher is matched.

The rule in lockstep: exactly one command per stamp. A teleop action for the stamp
wins; a yield lets the policy's action for the stamp through; a late message for a
decided stamp only repeats the decided command (see ``pusher_corrections.arbiter``).
"""

from __future__ import annotations

import sys
import time

import numpy as np
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool

from offline_rl_core.env import ACT_DIM, JOINT_NAMES
from pusher_common.node_main import run_node
from pusher_common.params import Param, Settings
from pusher_common.stamps import stamp_key

from .arbiter import HUMAN, LockstepArbiter, RealtimeArbiter

WARN_THROTTLE_S = 2.0
LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)


PARAMS = (
    Param("mode", "realtime", "as the sim's: realtime (a teleop action holds the arm for hold_ms) or lockstep "
          "(exactly one command per state stamp)", choices=("realtime", "lockstep"), read_only=True),
    Param("hold_ms", 100.0, "realtime: milliseconds a teleop action holds the arm; policy actions inside the hold "
          "are dropped", low=0.0, high=60_000.0),
    Param("require_teleop", False, "lockstep: always wait for the corrector's word on each stamp (otherwise only "
          "while a teleop/action publisher is matched)"),
)
ONLY_IN = {"hold_ms": "realtime", "require_teleop": "lockstep"}


def hold_check_period(hold_s: float) -> float:
    return min(max(hold_s / 4, 0.005), 0.05)


class Mux(Node):
    def __init__(self, overrides=()):
        super().__init__("mux", parameter_overrides=list(overrides))
        self.settings = Settings(self, PARAMS, on_change=self.on_parameter_change, check=self.check_parameter)
        self.mode = self.settings.mode
        self.hold_s = self.settings.hold_ms / 1000.0
        self.require_teleop = self.settings.require_teleop
        self.arbiter = LockstepArbiter() if self.mode == "lockstep" else RealtimeArbiter(self.hold_s)
        self.intervening: bool | None = None
        self.command_pub = self.create_publisher(JointState, "pusher/command", 10)
        self.intervening_pub = self.create_publisher(Bool, "corrections/intervening", LATCHED)
        self.create_subscription(JointState, "policy/action", self.on_policy, 10)
        self.teleop_sub = self.create_subscription(JointState, "teleop/action", self.on_teleop, 10)
        self.hold_timer = None
        if self.mode == "realtime":
            self.hold_timer = self.create_timer(hold_check_period(self.hold_s), self.check_hold)
        self.set_intervening(False)
        self.get_logger().info(
            f"mux {self.mode}: /policy/action + /teleop/action -> /pusher/command"
            + (f" (hold {self.hold_s * 1000:.0f} ms)" if self.mode == "realtime" else
               f" (one command per stamp{', always waiting for the corrector' if self.require_teleop else ''})")
        )

    def check_parameter(self, name: str, value) -> str | None:
        if ONLY_IN.get(name, self.mode) != self.mode:
            return f"{name} applies in {ONLY_IN[name]} mode only; this mux runs in {self.mode} mode"
        return None

    def on_parameter_change(self, name: str, value) -> None:
        if name == "hold_ms":
            self.hold_s = value / 1000.0
            self.arbiter.hold_s = self.hold_s
            self.hold_timer.timer_period_ns = int(hold_check_period(self.hold_s) * 1e9)
        elif name == "require_teleop":
            self.require_teleop = value

    def parse(self, msg: JointState, topic: str, allow_empty: bool) -> np.ndarray | None | bool:
        """The action; None for an empty effort (a yield) when allowed; False if malformed."""
        effort = msg.effort
        if len(effort) == 0 and allow_empty:
            return None
        action = np.array(effort, dtype=np.float64)
        if len(action) != ACT_DIM or not np.all(np.isfinite(action)):
            self.get_logger().warn(f"ignoring {topic}: effort must be {ACT_DIM} finite values",
                                   throttle_duration_sec=WARN_THROTTLE_S)
            return False
        if len(msg.name) == ACT_DIM and list(msg.name) != list(JOINT_NAMES) and set(msg.name) == set(JOINT_NAMES):
            action = action[[list(msg.name).index(j) for j in JOINT_NAMES]]
        return np.clip(action, -1.0, 1.0).astype(np.float32)

    def corrector_present(self) -> bool:
        return self.require_teleop or self.teleop_sub.get_publisher_count() > 0

    def on_policy(self, msg: JointState) -> None:
        action = self.parse(msg, "policy/action", allow_empty=False)
        if action is False:
            return
        stamp = stamp_key(msg.header.stamp)
        if self.mode == "lockstep":
            self.send(self.arbiter.on_policy(stamp, action, self.corrector_present()), msg)
        else:
            self.send(self.arbiter.on_policy(stamp, action, time.monotonic()), msg)

    def on_teleop(self, msg: JointState) -> None:
        action = self.parse(msg, "teleop/action", allow_empty=True)
        if action is False:
            return
        stamp = stamp_key(msg.header.stamp)
        if self.mode == "lockstep":
            self.send(self.arbiter.on_teleop(stamp, action), msg)
        else:
            self.send(self.arbiter.on_teleop(stamp, action, time.monotonic()), msg)
            self.check_hold()

    def send(self, command, msg: JointState) -> None:
        if command is None:
            return
        out = JointState(name=list(JOINT_NAMES), effort=[float(a) for a in command.action])
        out.header.stamp = msg.header.stamp
        out.header.frame_id = command.source
        self.command_pub.publish(out)
        if self.mode == "lockstep" and not command.resend:
            self.set_intervening(command.source == HUMAN)

    def check_hold(self) -> None:
        if self.mode == "realtime":
            self.set_intervening(self.arbiter.holding(time.monotonic()))

    def set_intervening(self, value: bool) -> None:
        if value != self.intervening:
            self.intervening = value
            self.intervening_pub.publish(Bool(data=value))


    def close(self) -> None:
        counts = self.arbiter.counts
        print(f"mux: forwarded {counts['policy']} policy and {counts['human']} human commands", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    return run_node(Mux, prog="mux", command="ros2 run corrections mux", argv=argv,
                    description="policy/action + teleop/action -> pusher/command, tagged with who acted.")


if __name__ == "__main__":
    sys.exit(main())
