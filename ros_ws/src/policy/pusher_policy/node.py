"""``ros2 run policy node --checkpoint PATH``: serve a trained policy over topics.

Every ``/pusher/state`` (with its ``/pusher/target``) is answered on ``/policy/action``:
a JointState whose effort is the action in [-1, 1], stamped with the state's stamp,
``frame_id`` 'policy' (the sim's source tag). A malformed or non-finite state gets no
action and a throttled warning. The checkpoint (``--checkpoint`` or ``-p checkpoint:=``)
is polled every ``poll_period`` seconds and hot-swapped when it changes; a file that
fails to load leaves the previous policy serving, with an error logged. A missing or
broken checkpoint at start is one error line and exit status 2.

Target pairing: when the source stamps each target with the state it belongs to (the
sim does), a state waits for the target with its stamp, so the first state of an
episode is never answered with the previous episode's target. Otherwise the latest
target is used. Fingertip: once ``/pusher/fingertip`` has been heard (the sim publishes
the fingertip its observation uses), a state also waits for the fingertip with its
stamp; an arm that publishes none gets planar forward kinematics of its joints.
"""

from __future__ import annotations

import math
import os
import sys

# One observation per call: BLAS threads only add hand-off latency (set before numpy loads).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from geometry_msgs.msg import PointStamped
from rclpy.node import Node
from sensor_msgs.msg import JointState

from offline_rl_core.env import ACT_DIM, JOINT_NAMES, observation_from_joints
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
        self.target_stamp: int | None = None
        self.target_xy: np.ndarray | None = None
        self.co_stamped = False  # the source stamps targets with their state's stamp
        self.fingertip_stamp: int | None = None
        self.fingertip_xy: np.ndarray | None = None
        self.pending: JointState | None = None
        self.answered = 0

        # Target subscription first: when both are ready the executor takes it first.
        self.create_subscription(PointStamped, "pusher/target", self.on_target, 10)
        self.create_subscription(PointStamped, "pusher/fingertip", self.on_fingertip, 10)
        self.create_subscription(JointState, "pusher/state", self.on_state, 10)
        self.action_pub = self.create_publisher(JointState, "policy/action", 10)
        self.poll_timer = self.create_timer(self.poll_period, self.check_checkpoint)
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
            self.get_logger().warn(f"{self.path} disappeared; still serving the loaded policy")
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
        x, y = msg.point.x, msg.point.y
        if not (math.isfinite(x) and math.isfinite(y)):
            self.get_logger().warn("ignoring /pusher/target: not finite", throttle_duration_sec=WARN_THROTTLE_S)
            return
        self.target_stamp = stamp_key(msg.header.stamp)
        self.target_xy = np.array([x, y])
        if self.pending is not None and stamp_key(self.pending.header.stamp) == self.target_stamp:
            self.co_stamped = True
        self.answer_pending()

    def on_fingertip(self, msg: PointStamped) -> None:
        x, y = msg.point.x, msg.point.y
        if not (math.isfinite(x) and math.isfinite(y)):
            self.get_logger().warn("ignoring /pusher/fingertip: not finite", throttle_duration_sec=WARN_THROTTLE_S)
            return
        self.fingertip_stamp = stamp_key(msg.header.stamp)
        self.fingertip_xy = np.array([x, y])
        self.answer_pending()

    def on_state(self, msg: JointState) -> None:
        if self.target_xy is not None and self.target_stamp == stamp_key(msg.header.stamp):
            self.co_stamped = True
        self.pending = msg
        self.answer_pending()

    def answer_pending(self) -> None:
        """Answer the waiting state once what it pairs with has arrived."""
        msg = self.pending
        if msg is None or self.target_xy is None:
            return
        stamp = stamp_key(msg.header.stamp)
        if self.co_stamped and self.target_stamp != stamp:
            return  # its target is still on the way
        if self.fingertip_xy is not None and self.fingertip_stamp != stamp:
            return  # the source publishes fingertips: wait for this state's
        self.pending = None
        self.answer(msg)

    def joints(self, msg: JointState):
        """(position, velocity) of shoulder, elbow, or None (with a warning) if malformed."""
        position, velocity = np.asarray(msg.position, np.float64), np.asarray(msg.velocity, np.float64)
        problem = None
        if len(position) < ACT_DIM or len(velocity) < ACT_DIM:
            problem = f"needs {ACT_DIM} positions and velocities, got {len(position)} and {len(velocity)}"
        elif len(msg.name) >= ACT_DIM and set(JOINT_NAMES) <= set(msg.name):
            names = list(msg.name)
            index = [names.index(j) for j in JOINT_NAMES]
            if max(index) >= min(len(position), len(velocity)):
                problem = "names and values differ in length"
            else:
                position, velocity = position[index], velocity[index]
        if problem is None and not (np.all(np.isfinite(position[:ACT_DIM])) and np.all(np.isfinite(velocity[:ACT_DIM]))):
            problem = "position or velocity is not finite"
        if problem:
            self.get_logger().warn(f"no action for /pusher/state: {problem}", throttle_duration_sec=WARN_THROTTLE_S)
            return None
        return position[:ACT_DIM], velocity[:ACT_DIM]

    def answer(self, msg: JointState) -> None:
        joints = self.joints(msg)
        if joints is None:
            return
        fingertip = self.fingertip_xy if self.fingertip_stamp == stamp_key(msg.header.stamp) else None
        obs = observation_from_joints(joints[0], joints[1], self.target_xy, fingertip)
        action = self.policy.act(obs)
        if not np.all(np.isfinite(action)):
            self.get_logger().warn("the policy produced a non-finite action; none sent", throttle_duration_sec=WARN_THROTTLE_S)
            return
        out = JointState(name=list(JOINT_NAMES), effort=[float(a) for a in np.clip(action, -1.0, 1.0)])
        out.header.stamp = msg.header.stamp
        out.header.frame_id = "policy"
        self.action_pub.publish(out)
        self.answered += 1


def main(argv: list[str] | None = None) -> int:
    return run_node(PolicyServer, prog="policy", flags=PARAMS, argv=argv,
                    description="Serve a trained policy on policy/action.")


if __name__ == "__main__":
    sys.exit(main())
