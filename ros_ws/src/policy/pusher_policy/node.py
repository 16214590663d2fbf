"""``ros2 run policy node --checkpoint PATH``: serve a trained policy over topics.

Every ``pusher/state`` (with its ``pusher/target``) is answered on ``policy/action``:
a JointState whose effort is the action in [-1, 1], stamped with the state's stamp; and,
on ``effort_topic`` (default ``effort_controller/commands``), the same action as joint
torques in N·m (std_msgs/Float64MultiArray), what a ros2_control effort controller
takes. A malformed or non-finite state gets no action and a throttled warning. The checkpoint (``--checkpoint`` or ``-p checkpoint:=``)
is polled every ``poll_period`` seconds and hot-swapped when it changes; a file that
fails to load leaves the previous policy serving, with an error logged. A missing or
broken checkpoint at start is one error line and exit status 2.

State, target and fingertip are paired by stamp as ``offline_rl_core.pairing`` says;
an arm that publishes no fingertip gets planar forward kinematics of its joints.
"""

from __future__ import annotations

import math
import os
import sys

# One observation per call: BLAS threads only add hand-off latency (set before numpy loads).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from geometry_msgs.msg import PointStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from offline_rl_core.env import JOINT_NAMES, observation_from_joints
from offline_rl_core.joint_messages import joints_from_state, torques_from_action
from offline_rl_core.pairing import Paired, StatePairing
from offline_rl_core.errors import UserError
from offline_rl_core.policy import load_policy
from pusher_common.node_main import run_node
from pusher_common.params import Param, Settings
from pusher_common.stamps import stamp_key

WARN_THROTTLE_S = 2.0


def file_signature(path: str):
    """What changes when a checkpoint is rewritten (also by an atomic rename)."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_mtime_ns, st.st_size, st.st_ino)


PARAMS = (
    Param("checkpoint", "", "policy checkpoint to serve (policy.pt, or a run directory holding one); "
          "watched and reloaded when replaced; setting it switches to another checkpoint", flag="--checkpoint"),
    Param("poll_period", 0.5, "seconds between checks of the checkpoint file for a new version", low=0.01, high=60.0),
    Param("effort_topic", "effort_controller/commands", "also publish each action as std_msgs/Float64MultiArray joint "
          "torques in N·m (action x motor gear) on this topic, as a ros2_control effort controller takes them "
          "(empty: off)", read_only=True),
)


def checkpoint_file(path: str) -> str:
    """A run directory means the policy.pt in it (the file the trainer replaces)."""
    return os.path.join(path, "policy.pt") if os.path.isdir(path) else path


class PolicyServer(Node):
    def __init__(self, overrides=()):
        super().__init__("policy", parameter_overrides=list(overrides))
        self.settings = Settings(self, PARAMS, on_change=self.on_parameter_change, check=self.check_parameter)
        self.poll_period = self.settings.poll_period
        if not self.settings.checkpoint:
            raise UserError("no checkpoint given: pass --checkpoint PATH or -p checkpoint:=PATH")
        self.path = checkpoint_file(self.settings.checkpoint)
        self.signature = file_signature(self.path)
        self.policy = load_policy(self.path)  # UserError with one clear line if missing/broken
        self.candidate = None  # a checkpoint set at run time, loaded while checking it
        self.pairing = StatePairing()
        self.answered = 0

        # Target subscription first: when both are ready the executor takes it first.
        self.create_subscription(PointStamped, "pusher/target", self.on_target, 10)
        self.create_subscription(PointStamped, "pusher/fingertip", self.on_fingertip, 10)
        self.create_subscription(JointState, "pusher/state", self.on_state, 10)
        self.action_pub = self.create_publisher(JointState, "policy/action", 10)
        effort_topic = self.settings.effort_topic
        self.effort_pub = self.create_publisher(Float64MultiArray, effort_topic, 10) if effort_topic else None
        # Watching a file is wall-clock work, also under use_sim_time.
        self.poll_timer = self.create_timer(self.poll_period, self.check_checkpoint,
                                            clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(f"serving {self.policy.algorithm} policy from {self.path}")

    # -------------------------------------------------------------- parameters
    def check_parameter(self, name: str, value) -> str | None:
        if name != "checkpoint":
            return None
        path = checkpoint_file(value)
        try:
            self.candidate = (path, file_signature(path), load_policy(path))
        except UserError as exc:  # refused with the reason; the old policy serves on
            return str(exc)
        except Exception as exc:  # noqa: BLE001 - whatever is wrong with the file
            return f"cannot load {path}: {exc}"
        return None

    def on_parameter_change(self, name: str, value) -> None:
        if name == "poll_period":
            self.poll_timer.timer_period_ns = int(value * 1e9)
        elif name == "checkpoint" and self.candidate is not None:
            self.path, self.signature, self.policy = self.candidate
            self.candidate = None
            self.get_logger().info(f"serving {self.policy.algorithm} policy from {self.path}")

    # -------------------------------------------------------------- checkpoint
    def check_checkpoint(self) -> None:
        signature = file_signature(self.path)
        if signature == self.signature:
            return
        self.signature = signature
        if signature is None:
            self.get_logger().warning(f"{self.path} disappeared; still serving the loaded policy")
            return
        try:
            policy = load_policy(self.path)
        except Exception as exc:  # noqa: BLE001 - whatever is wrong with the file, keep serving
            self.get_logger().error(f"cannot reload {self.path}, keeping the previous policy: {exc}")
            return
        self.policy = policy  # one reference swap: a callback sees the old or the new policy
        self.get_logger().info(f"reloaded {self.path} ({policy.algorithm})")

    # -------------------------------------------------------------- serving
    def on_target(self, msg: PointStamped) -> None:
        if self.finite_point(msg, "pusher/target"):
            self.answer(self.pairing.on_target(stamp_key(msg.header.stamp), (msg.point.x, msg.point.y)))

    def on_fingertip(self, msg: PointStamped) -> None:
        if self.finite_point(msg, "pusher/fingertip"):
            self.answer(self.pairing.on_fingertip(stamp_key(msg.header.stamp), (msg.point.x, msg.point.y)))

    def on_state(self, msg: JointState) -> None:
        self.answer(self.pairing.on_state(stamp_key(msg.header.stamp), msg))

    def finite_point(self, msg: PointStamped, topic: str) -> bool:
        if math.isfinite(msg.point.x) and math.isfinite(msg.point.y):
            return True
        self.get_logger().warning(f"ignoring {topic}: not finite", throttle_duration_sec=WARN_THROTTLE_S)
        return False

    def answer(self, paired: Paired | None) -> None:
        if paired is None:
            return
        msg = paired.state
        joints, problem = joints_from_state(msg.name, msg.position, msg.velocity)
        if joints is None:
            self.get_logger().warning(f"no action for pusher/state: {problem}", throttle_duration_sec=WARN_THROTTLE_S)
            return
        obs = observation_from_joints(joints[0], joints[1], paired.target_xy, paired.fingertip_xy)
        action = self.policy.act(obs)
        if not np.all(np.isfinite(action)):
            self.get_logger().warning("the policy produced a non-finite action; none sent",
                                      throttle_duration_sec=WARN_THROTTLE_S)
            return
        action = np.clip(action, -1.0, 1.0)
        out = JointState(name=list(JOINT_NAMES), effort=[float(a) for a in action])
        out.header.stamp = msg.header.stamp
        self.action_pub.publish(out)
        if self.effort_pub is not None:
            self.effort_pub.publish(Float64MultiArray(data=[float(t) for t in torques_from_action(action)]))
        self.answered += 1


def main(argv: list[str] | None = None) -> int:
    return run_node(PolicyServer, prog="policy", flags=PARAMS, argv=argv,
                    description="Serve a trained policy on policy/action.")


if __name__ == "__main__":
    sys.exit(main())
