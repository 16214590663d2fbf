"""``ros2 run corrections mux``: the policy drives, a person (or the corrector) can take over.

Forwards ``policy/action`` to the sim unless the human acts on ``teleop/action``: each
command goes to ``pusher/command/policy`` or ``pusher/command/human``, the sim's inputs
that say who acted (codes 2 and 3 in ``pusher/transition``, so the bag records it).
``corrections/intervening`` (std_msgs/Bool, transient local) is published on each change.

Its parameters:
- ``task`` (pusher_reach): a built-in task or a task file: the actions are JointStates of
  its command joints (``robot.command.joints``, named in any order, or unnamed in that
  order); one of another length, or lacking one of them, is refused and counted.
- ``mode``: ``realtime`` (default) or ``lockstep``, as the sim's.
- ``hold_ms`` (100): realtime: a teleop action holds the arm this long (on the node's
  clock: sim time under ``use_sim_time``);
  policy actions inside the hold are dropped. An empty teleop action lets go at once.
- ``require_teleop`` (false): lockstep: always wait for the corrector's word on each
  stamp (an action, or an empty-effort *yield*). When false, the mux waits only while
  a ``/teleop/action`` publisher is matched.
- ``wait_for_readers`` ([]): lockstep: hold the first command until these nodes (by name:
  a raw-topic learner and recorder) read ``pusher/command/policy`` and ``.../human``. The
  lockstep arm waits for it, so neither misses the session's first steps however slowly
  discovery matches them (as the sim's parameter of that name holds its first state).

The rule in lockstep: exactly one command per stamp. A teleop action for the stamp
wins; a yield lets the policy's action for the stamp through; a late message for a
decided stamp only repeats the decided command (see ``offline_rl_core.nodes.arbiter``).
A malformed or non-finite action, one outside [-1, 1] (refused, never clipped), or one with
a bad stamp, is not forwarded: it is counted by reason on ``~/status``
(``pusher_common.status``) with a throttled warning.

Safety: with the task's ``safety.slew`` each forwarded action moves at most that far from
the one before (``offline_rl_core.nodes.command_limits``). Realtime: when neither the policy
nor the human sent a valid action within the task's ``safety.command_timeout`` (a person's
hold counts as a command for its ``hold_ms``), the mux sends
the task's safe command once on ``pusher/command/policy`` (``offline_rl_core.nodes.watchdog``)
and latches the fault on ``~/status``; while the e-stop is engaged (``estop``, released only
by ``estop/reset``) it sends the safe command and forwards nothing (counted as ``estop``), in
lockstep too. For an effort interface with ``safety.position_limits`` / ``velocity_limits`` it
reads the arm's state and refuses an action whose effort pushes a joint further beyond them
(counted as ``beyond limits``; ``offline_rl_core.nodes.state_limits``); one back inside passes.
"""

from __future__ import annotations

import sys
import time

import numpy as np
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile
from rclpy.clock import Clock, ClockType
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool

from offline_rl_core.common.rejections import Rejection
from offline_rl_core.nodes.command_limits import SlewLimiter
from offline_rl_core.nodes.state_limits import StateLimits
from offline_rl_core.nodes.joint_messages import action_from_effort, joints_from_state
from offline_rl_core.nodes.watchdog import CommandWatchdog, safe_action
from pusher_common.estop import EStopInput
from offline_rl_core.task.spec import DEFAULT_TASK, load_task
from offline_rl_core.nodes.pairing import check_stamp
from pusher_common.node_main import run_node
from pusher_common.params import Param, Settings
from pusher_common.readers import ReadersGate
from pusher_common.scheduling import THREAD_PRIORITY, apply_thread_priority
from pusher_common.stamps import stamp_key
from pusher_common.status import NodeStatus
from offline_rl_core.nodes.diagnostics import StatusDiagnosis

from offline_rl_core.nodes.arbiter import HUMAN, POLICY, LockstepArbiter, RealtimeArbiter

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)


PARAMS = (
    Param("task", DEFAULT_TASK, "the task: a built-in task or a task file; actions are JointStates of its command "
          "joints", read_only=True),
    Param("mode", "realtime", "as the sim's: realtime (a teleop action holds the arm for hold_ms) or lockstep "
          "(exactly one command per state stamp)", choices=("realtime", "lockstep"), read_only=True),
    Param("hold_ms", 100.0, "realtime: milliseconds a teleop action holds the arm; policy actions inside the hold "
          "are dropped", low=0.0, high=60_000.0),
    Param("require_teleop", False, "lockstep: always wait for the corrector's word on each stamp (otherwise only "
          "while a teleop/action publisher is matched)"),
    # the sim holds its first state for the readers of its topics; the commands are the mux's
    Param("wait_for_readers", [], "lockstep: hold the first command until these nodes (names, e.g. [learner, "
          "recorder]) read pusher/command/policy and pusher/command/human", read_only=True),
    THREAD_PRIORITY,
)
ONLY_IN = {"hold_ms": "realtime", "require_teleop": "lockstep"}
READERS_CHECK_PERIOD_S = 0.01  # while the first command is held for its readers


def hold_check_period(hold_s: float) -> float:
    return min(max(hold_s / 4, 0.005), 0.05)


class Mux(Node):
    def __init__(self, overrides=()):
        super().__init__("mux", parameter_overrides=list(overrides))
        self.settings = Settings(self, PARAMS, on_change=self.on_parameter_change, check=self.check_parameter)
        apply_thread_priority(self.settings.thread_priority, self.get_logger())
        self.mode = self.settings.mode
        self.hold_s = self.settings.hold_ms / 1000.0
        self.require_teleop = self.settings.require_teleop
        self.task = task = load_task(self.settings.task or None)  # UserError: one line naming the task
        self.joints = task.command.joints
        self.arbiter = LockstepArbiter() if self.mode == "lockstep" else RealtimeArbiter(self.hold_s)
        self.intervening: bool | None = None
        self.slew = SlewLimiter(task.safety.slew)
        self.watchdog = CommandWatchdog(task.command_timeout)
        self.state_limits = StateLimits(task)  # effort interface: soft limits on the measured state
        self.position = None  # the state joints' latest positions, where the safe command holds them
        self.velocity = None  # and their speeds, for the soft limits
        self.last_sent = (None, None)  # (stamp, action) of the latest command sent
        # lockstep: nodes that must read the commands before the first goes (then never again)
        self.readers_gate = ReadersGate(self, (self.settings.wait_for_readers or ()) if self.mode == "lockstep" else ())
        self.held: tuple | None = None  # (command, msg) decided while the readers were not there
        self.status = NodeStatus(self, fields=lambda: {"forwarded": dict(self.arbiter.counts),
                                                       "intervening": self.intervening,
                                                       "slew_limited": self.slew.limited,
                                                       "faults": self.faults(),
                                                       "estop": self.estop.latch.as_dict()},
                                 diagnosis=StatusDiagnosis(idle=lambda st: "a person drives" if st["intervening"]
                                                           else "the policy drives"))
        self.estop = EStopInput(self, on_engage=self.on_estop_engaged, on_reset=self.watchdog.reset)
        if task.safe_command == "hold" or self.state_limits.active:
            self.create_subscription(JointState, task.state.topic, self.on_state, 10)
        # who acted is the topic: pusher/command/policy or pusher/command/human (the sim logs it)
        self.command_pubs = {source: self.create_publisher(JointState, f"pusher/command/{source}", 10)
                             for source in (POLICY, HUMAN)}
        self.intervening_pub = self.create_publisher(Bool, "corrections/intervening", LATCHED)
        self.policy_sub = self.create_subscription(JointState, "policy/action", self.on_policy, 10)
        self.teleop_sub = self.create_subscription(JointState, "teleop/action", self.on_teleop, 10)
        self.hold_timer = None
        self.readers_timer = None
        if self.readers_gate.waiting:
            self.readers_timer = self.create_timer(READERS_CHECK_PERIOD_S, self.send_held,
                                                   clock=Clock(clock_type=ClockType.STEADY_TIME))
        if self.mode == "realtime":
            self.hold_timer = self.create_timer(hold_check_period(self.hold_s), self.check_hold)
            # wall time: a controller gone silent is a fault whatever the sim clock does
            self.create_timer(task.control_period, self.check_watchdog, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.set_intervening(False)
        self.get_logger().info(
            f"mux {self.mode}: {self.policy_sub.topic_name} + {self.teleop_sub.topic_name} -> "
            f"{self.command_pubs[POLICY].topic_name} | {self.command_pubs[HUMAN].topic_name}"
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
        """Read the action: None for an empty effort (a yield) when allowed; False if refused."""
        self.status.took(topic)
        action, problem = action_from_effort(msg.name, msg.effort, allow_empty, self.joints)
        problem = check_stamp(msg.header.stamp.sec, msg.header.stamp.nanosec) or problem
        if problem is None and self.estop.engaged:
            problem = Rejection("estop", "an action while the e-stop is engaged (estop/reset releases it)")
        if problem is None and action is not None and self.position is not None:
            problem = self.state_limits.check(action, self.position, self.velocity)  # outward beyond: refused
        if problem:
            self.status.reject(topic, problem)
            return False
        self.watchdog.fed(time.monotonic())
        return action

    def now(self) -> float:
        """Seconds on the node's clock: the hold is in sim time under use_sim_time."""
        return self.get_clock().now().nanoseconds / 1e9

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
            self.send(self.arbiter.on_policy(stamp, action, self.now()), msg)

    def on_teleop(self, msg: JointState) -> None:
        action = self.parse(msg, "teleop/action", allow_empty=True)
        if action is False:
            return
        stamp = stamp_key(msg.header.stamp)
        if self.mode == "lockstep":
            self.send(self.arbiter.on_teleop(stamp, action), msg)
        else:
            self.send(self.arbiter.on_teleop(stamp, action, self.now()), msg)
            self.check_hold()

    def readers_matched(self) -> bool:
        """Tell whether the nodes of ``wait_for_readers`` read both command topics.

        And whether the writers have matched those readers (``pusher_common.readers``).
        """
        if not self.readers_gate.waiting:
            return True
        if not self.readers_gate.open(self.command_pubs.values()):
            return False
        self.get_logger().info("the command topics' readers are matched: forwarding")
        return True

    def send_held(self) -> None:
        """Send what was held, once, when the readers read the commands (their timer)."""
        if not self.readers_matched():
            return
        self.readers_timer.cancel()
        if self.held is not None:
            held, self.held = self.held, None
            self.send(*held)

    def send(self, command, msg: JointState) -> None:
        if command is None:
            return
        if not self.readers_matched():
            # the lockstep arm waits for its command; re-sends of a held stamp are the held command
            if not command.resend or self.held is None:
                self.held = (command, msg)
            return
        if not command.resend:
            self.last_sent = (command.stamp, self.slew.limit(command.action))
        # a resend repeats what was sent for the stamp (ramped), not what was decided
        action = self.last_sent[1] if self.last_sent[0] == command.stamp else command.action
        out = JointState(name=list(self.joints), effort=[float(a) for a in action])
        out.header.stamp = msg.header.stamp
        self.command_pubs[command.source].publish(out)
        if self.mode == "lockstep" and not command.resend:
            self.set_intervening(command.source == HUMAN)

    # -------------------------------------------------------------- safety
    def on_state(self, msg: JointState) -> None:
        """Keep the arm's positions (a safe command holds them) and speeds (the soft limits)."""
        joints, problem = joints_from_state(msg.name, msg.position, msg.velocity, self.task.state.joints,
                                            velocity_optional=True)
        if problem is None:
            self.position, self.velocity = joints

    def check_watchdog(self) -> None:
        now = time.monotonic()
        if self.arbiter.holding(self.now()):
            self.watchdog.fed(now)  # a person's hold is a command for its whole length (hold_ms)
        silent_before = self.watchdog.silent
        if self.watchdog.check(now) and not silent_before:
            self.get_logger().error(f"no valid action for {self.watchdog.timeout_s * 1000:.0f} ms: sending the "
                                    f"safe command ({self.task.safe_command})", throttle_duration_sec=2.0)
            self.send_safe()

    def on_estop_engaged(self) -> None:
        self.watchdog.disarm()
        self.send_safe()

    def send_safe(self) -> None:
        """Realtime: send the task's safe command (once: the sim and a controller hold it).

        In lockstep the sim steps only on a command: forwarding nothing stops the arm.
        """
        if self.mode != "realtime":
            return
        action = safe_action(self.task, self.position)
        if action is None:  # a position to hold that no state has told: the sim's own watchdog holds it
            return
        self.slew.restart(action)
        out = JointState(name=list(self.joints), effort=[float(a) for a in action])
        out.header.stamp = self.get_clock().now().to_msg()
        self.command_pubs[POLICY].publish(out)

    def faults(self) -> dict:
        fault = self.watchdog.fault()
        return {"watchdog": fault} if fault else {}

    def check_hold(self) -> None:
        if self.mode == "realtime":
            self.set_intervening(self.arbiter.holding(self.now()))

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
