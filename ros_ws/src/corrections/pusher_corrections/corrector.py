"""``ros2 run corrections corrector``: the human in human-in-the-loop, or a stand-in.

Watches ``/pusher/state`` with its ``/pusher/target`` (paired by stamp, as the policy
node does) and answers every state on ``/teleop/action`` (JointState, stamp = the
state's, frame_id 'human'): either a correction (effort = torques in [-1, 1]) or a
*yield* (empty effort: the policy keeps the arm). A republished state gets the same
answer again; each state is decided once.

``--mode scripted`` (default): takes over with the scripted expert when the fingertip
has not got closer to the target for ``patience`` steps, hands back after
``hold_steps`` steps or on success (see ``pusher_corrections.scripted``). Parameters
(``-p name:=value`` or the flags): ``patience`` (8), ``hold_steps`` (25),
``grace_steps`` (20: states at an episode's start before progress is judged),
``min_progress`` (0.002 m), ``noise`` (0.0, std of torque noise), ``reaction_delay``
(0 steps), ``seed`` (0).

``--mode keyboard``: a person drives from the terminal (raw mode; needs a tty):
  a / d  shoulder torque -1 / +1      j / l  elbow torque -1 / +1
  s      shoulder torque 0            k      elbow torque 0
  space  hand back to the policy      q      quit (Ctrl-C too)
Any torque key takes over; the held torques are sent with every state until space.
"""

from __future__ import annotations

import argparse
import math
import os
import select
import sys
import termios
import threading
import tty

import numpy as np
import rclpy
from geometry_msgs.msg import PointStamped
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.task import Future
from rclpy.utilities import remove_ros_args
from sensor_msgs.msg import JointState

from pusher_common.stamps import stamp_key

from offline_rl_core.errors import caused_by_interrupt
from offline_rl_core.env import ACT_DIM, JOINT_NAMES

from .scripted import CorrectorParams, ScriptedCorrector

KEEP_ANSWERS = 64
KEYS = {
    "a": (0, -1.0), "d": (0, 1.0), "s": (0, 0.0),
    "j": (1, -1.0), "l": (1, 1.0), "k": (1, 0.0),
}


class KeyboardTeleop:
    """Torques set by keys in a raw-mode terminal; read on a background thread."""

    def __init__(self, stream=sys.stdin):
        if not stream.isatty():
            raise ValueError("--mode keyboard needs an interactive terminal (stdin is not a tty)")
        self.stream = stream
        self.torque = np.zeros(ACT_DIM, np.float32)
        self.active = False
        self.quit = threading.Event()
        self.lock = threading.Lock()
        self.saved = termios.tcgetattr(stream.fileno())
        tty.setcbreak(stream.fileno())  # keys arrive one by one, unechoed; Ctrl-C still signals
        self.thread = threading.Thread(target=self.read_keys, daemon=True)
        self.thread.start()
        print("keyboard teleop: a/d shoulder -/+, j/l elbow -/+, s/k zero, space hand back, q quit",
              file=sys.stderr, flush=True)

    def read_keys(self) -> None:
        fd = self.stream.fileno()
        while not self.quit.is_set():
            ready, _, _ = select.select([fd], [], [], 0.1)
            if not ready:
                continue
            key = os.read(fd, 1).decode(errors="ignore").lower()
            with self.lock:
                if key == "q":
                    self.quit.set()
                elif key == " ":
                    self.active = False
                    self.torque[:] = 0.0
                elif key in KEYS:
                    joint, value = KEYS[key]
                    self.torque[joint] = value
                    self.active = True

    def decide(self, qpos, qvel, target_xy) -> np.ndarray | None:
        with self.lock:
            return self.torque.copy() if self.active else None

    def restore(self) -> None:
        self.quit.set()
        termios.tcsetattr(self.stream.fileno(), termios.TCSADRAIN, self.saved)


class Corrector(Node):
    def __init__(self, args: argparse.Namespace, finished: Future):
        super().__init__("corrector")
        p = CorrectorParams()
        values = {
            name: type(getattr(p, name))(self.declare_parameter(
                name, getattr(args, name) if getattr(args, name) is not None else getattr(p, name),
                ParameterDescriptor(dynamic_typing=True)).value)
            for name in ("patience", "hold_steps", "grace_steps", "min_progress", "noise", "reaction_delay", "seed")
        }
        self.mode = args.mode
        self.finished = finished
        if self.mode == "scripted":
            self.params = CorrectorParams(**values)
            self.teleop = ScriptedCorrector(self.params)
        else:
            self.teleop = KeyboardTeleop()
            self.create_timer(0.1, self.check_quit)
        self.target_stamp: int | None = None
        self.target_xy: np.ndarray | None = None
        self.pending: JointState | None = None
        self.answers: dict[int, JointState] = {}
        self.states = 0
        self.corrections = 0
        self.create_subscription(PointStamped, "pusher/target", self.on_target, 10)
        self.create_subscription(JointState, "pusher/state", self.on_state, 10)
        self.pub = self.create_publisher(JointState, "teleop/action", 10)
        desc = f"scripted ({', '.join(f'{k}={v}' for k, v in values.items())})" if self.mode == "scripted" else "keyboard"
        self.get_logger().info(f"corrector {desc}: answering /pusher/state on /teleop/action")

    def check_quit(self) -> None:
        if self.teleop.quit.is_set() and not self.finished.done():
            self.finished.set_result(True)

    def on_target(self, msg: PointStamped) -> None:
        if not (math.isfinite(msg.point.x) and math.isfinite(msg.point.y)):
            return
        self.target_stamp = stamp_key(msg.header.stamp)
        self.target_xy = np.array([msg.point.x, msg.point.y])
        if self.pending is not None and stamp_key(self.pending.header.stamp) == self.target_stamp:
            pending, self.pending = self.pending, None
            self.answer(pending)

    def on_state(self, msg: JointState) -> None:
        if self.target_xy is not None and self.target_stamp == stamp_key(msg.header.stamp):
            self.pending = None
            self.answer(msg)
        else:
            self.pending = msg  # answered when its target arrives

    def answer(self, msg: JointState) -> None:
        stamp = stamp_key(msg.header.stamp)
        out = self.answers.get(stamp)
        if out is None:  # a new state: decide once
            position, velocity = np.asarray(msg.position, np.float64), np.asarray(msg.velocity, np.float64)
            if len(position) < ACT_DIM or len(velocity) < ACT_DIM or not (
                np.all(np.isfinite(position[:ACT_DIM])) and np.all(np.isfinite(velocity[:ACT_DIM]))
            ):
                return
            action = self.teleop.decide(position[:ACT_DIM], velocity[:ACT_DIM], self.target_xy)
            self.states += 1
            out = JointState(name=list(JOINT_NAMES))
            if action is not None:
                out.effort = [float(a) for a in action]
                self.corrections += 1
            out.header.stamp = msg.header.stamp
            out.header.frame_id = "human"
            self.answers[stamp] = out
            if len(self.answers) > KEEP_ANSWERS:
                for key in sorted(self.answers)[:-KEEP_ANSWERS // 2]:
                    del self.answers[key]
        self.pub.publish(out)

    def close(self) -> None:
        if isinstance(self.teleop, KeyboardTeleop):
            self.teleop.restore()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ros2 run corrections corrector",
                                     description="Take over from the policy on /teleop/action: scripted expert or keyboard.")
    parser.add_argument("--mode", choices=("scripted", "keyboard"), default="scripted")
    parser.add_argument("--patience", type=int, help="k: steps without progress before taking over (default 8)")
    parser.add_argument("--grace-steps", type=int, help="states at an episode's start before progress is judged (default 20)")
    parser.add_argument("--hold-steps", type=int, help="m: steps before handing back (default 25)")
    parser.add_argument("--min-progress", type=float, help="metres the distance must shrink to count as progress (0.002)")
    parser.add_argument("--noise", type=float, help="std of Gaussian noise on the corrections (0)")
    parser.add_argument("--reaction-delay", type=int, help="steps between deciding and taking over (0)")
    parser.add_argument("--seed", type=int, help="seed of the noise (0)")
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv if argv is None else argv
    args = build_parser().parse_args(remove_ros_args(argv)[1:])
    rclpy.init(args=argv)
    node = None
    finished = Future()
    try:
        node = Corrector(args, finished)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        executor.spin_until_future_complete(finished)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except ValueError as exc:
        print(f"corrector: error: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:
        if rclpy.ok() and not caused_by_interrupt(exc):
            raise
    finally:
        if node is not None:
            node.close()
            extra = f", {node.teleop.takeovers} takeovers" if node.mode == "scripted" else ""
            print(f"corrector: answered {node.states} states, {node.corrections} with a correction{extra}", file=sys.stderr)
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
