"""``ros2 run recorder node``: record a pusher-reach dataset as a rosbag2 bag.

Active (default): drives the sim with the scripted expert for the first
``round(expert_frac * episodes)`` episodes and uniform random actions after, exactly as
``offline-rl collect`` does in process, and records ``/pusher/transition`` plus
``/pusher/state``, ``/pusher/target`` and the ``/pusher/command`` messages it sends.
Against a lockstep sim started with the same seed the bag's transitions equal
``offline-rl collect``'s bit for bit.

  ros2 run recorder node --out bags/mix.db3 --episodes 200 --expert-frac 0.3 --seed 0

``--passive`` records whatever flows (e.g. a policy or a human driving) until Ctrl-C,
or until ``--episodes`` episodes have ended when given. Ctrl-C or SIGTERM at any time
closes the bag with every message received so far; a SIGKILL loses at most the last
``--flush-interval`` (1 s) of messages (``offline_rl_core.bag.recording``).

Protocol of the active loop: a command answers the latest state whose target (same stamp)
has arrived, and only once the transition caused by the previous command is in, so
episode boundaries are known before the next action is chosen.
"""

from __future__ import annotations

import argparse
import struct
import sys
import time

import numpy as np
import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from rclpy.task import Future
from rclpy.utilities import remove_ros_args
from geometry_msgs.msg import PointStamped
from sensor_msgs.msg import JointState
from std_msgs.msg import Float32MultiArray

from offline_rl_core.bag import TRANSITION_CDR_HEADER, BagWriter, decode_transition_payloads
from offline_rl_core.collect import expert_episode_count
from offline_rl_core.env import ACT_DIM, JOINT_NAMES
from offline_rl_core.errors import UserError, caused_by_interrupt
from offline_rl_core.expert import expert_action
from offline_rl_core.transitions import LAYOUT_SLICES, SOURCE_NAMES, SOURCE_EXPERT, SOURCE_RANDOM
from pusher_common.spin import spin_until_future_complete

TOPICS = {
    "/pusher/transition": ("std_msgs/msg/Float32MultiArray", Float32MultiArray),
    "/pusher/state": ("sensor_msgs/msg/JointState", JointState),
    "/pusher/target": ("geometry_msgs/msg/PointStamped", PointStamped),
    "/pusher/command": ("sensor_msgs/msg/JointState", JointState),
}
TRANSITION_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
DONE = (LAYOUT_SLICES["terminated"].start, LAYOUT_SLICES["truncated"].start)
# Byte offsets of those two float32 flags in a transition carrying the sim's header.
DONE_AT = tuple(len(TRANSITION_CDR_HEADER) + 4 * column for column in DONE)


def stamp_key(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ends_episode(raw: bytes) -> bool:
    """Whether a raw /pusher/transition is its episode's last (terminated or truncated)."""
    if raw.startswith(TRANSITION_CDR_HEADER):  # the sim's own bytes: read the flags in place
        return any(struct.unpack_from("<f", raw, at)[0] for at in DONE_AT)
    row = decode_transition_payloads([raw])[0]  # another writer's header
    return bool(row[DONE[0]] or row[DONE[1]])


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ros2 run recorder node",
        description="Drive the pusher sim with the scripted expert / random actions (or listen) and record a rosbag2 bag.",
    )
    parser.add_argument("--out", required=True, help="bag to write: x.db3 / x.mcap (one file) or a directory")
    parser.add_argument("--episodes", type=int, default=None, help="episodes to record (required unless --passive)")
    parser.add_argument("--expert-frac", type=float, default=0.3, help="fraction of expert episodes, first (default 0.3)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random-action generator (default 0)")
    parser.add_argument("--storage", choices=("sqlite3", "mcap"), default=None, help="storage (default: from --out, else sqlite3)")
    parser.add_argument("--passive", action="store_true", help="only record what flows, until Ctrl-C (or --episodes)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing bag at --out (deleted at start)")
    parser.add_argument("--flush-interval", type=float, default=1.0,
                        help="seconds between writes to disk: a kill loses at most this much (default 1.0)")
    parser.add_argument("--max-bag-size", type=int, default=0,
                        help="start a new file of the bag directory past this many bytes (0: never)")
    parser.add_argument("--max-bag-duration", type=float, default=0.0,
                        help="start a new file of the bag directory after this many seconds (0: never)")
    return parser


class Recorder(Node):
    def __init__(self, bag: BagWriter, args: argparse.Namespace):
        super().__init__("recorder")
        self.bag = bag
        self.active = not args.passive
        self.episodes = args.episodes
        self.n_expert = expert_episode_count(args.episodes, args.expert_frac) if self.active else 0
        self.rng = np.random.default_rng(args.seed)
        self.finished = Future()
        self.episodes_done = 0
        self.transitions = 0
        self.last_stamp_ns = 0
        self.start_time = time.monotonic()
        self.progress_tty = sys.stderr.isatty()
        self.last_progress_decile = -1

        # Active-loop state.
        self.state: JointState | None = None
        self.targets: dict[int, np.ndarray] = {}
        self.awaiting_transition = False
        self.last_command: JointState | None = None
        self.matched = False

        for topic, (type_name, msg_type) in TOPICS.items():
            bag.add_topic(topic, type_name)
            if self.active and topic == "/pusher/command":
                continue  # written as sent (see send): no loop back over DDS
            qos = TRANSITION_QOS if topic == "/pusher/transition" else 10
            self.create_subscription(msg_type, topic, self.make_callback(topic), qos, raw=True)
        self.subs = {s.topic_name: s for s in self.subscriptions}
        if self.active:
            self.command_pub = self.create_publisher(JointState, "/pusher/command", 10)
            self.create_timer(0.1, self.try_act)
        what = f"{self.episodes} episodes ({self.n_expert} expert)" if self.active else "passively"
        self.get_logger().info(f"recording {what} to {bag.path}")

    # -------------------------------------------------------------- recording
    def make_callback(self, topic: str):
        def on_raw(raw: bytes) -> None:
            self.write(topic, raw)
            if topic == "/pusher/transition":
                self.on_transition(raw)
            elif self.active and topic == "/pusher/state":
                self.on_state(deserialize_message(raw, JointState))
            elif self.active and topic == "/pusher/target":
                self.on_target(deserialize_message(raw, PointStamped))

        return on_raw

    def write(self, topic: str, raw: bytes) -> None:
        if self.finished.done():
            return
        # Receive time, kept strictly increasing so the bag's order is the arrival order.
        stamp = max(time.time_ns(), self.last_stamp_ns + 1)
        self.last_stamp_ns = stamp
        self.bag.write(topic, stamp, raw)

    def on_transition(self, raw: bytes) -> None:
        if self.finished.done():
            return
        ended = ends_episode(raw)
        self.transitions += 1
        self.awaiting_transition = False
        if ended:
            self.episodes_done += 1
            self.show_progress()
            if self.episodes and self.episodes_done >= self.episodes:
                self.finished.set_result(True)
                return
        self.try_act()

    def show_progress(self) -> None:
        if not self.episodes:
            return
        elapsed = max(time.monotonic() - self.start_time, 1e-9)
        line = (
            f"recorder: {self.episodes_done}/{self.episodes} episodes, {self.transitions} transitions, "
            f"{self.transitions / elapsed:.0f} transitions/s"
        )
        if self.progress_tty:
            end = "\n" if self.episodes_done >= self.episodes else ""
            print("\r" + line, end=end, file=sys.stderr, flush=True)
            return
        decile = 10 * self.episodes_done // self.episodes
        if decile != self.last_progress_decile:
            self.last_progress_decile = decile
            print(line, file=sys.stderr, flush=True)

    # -------------------------------------------------------------- driving
    def on_state(self, msg: JointState) -> None:
        stamp = stamp_key(msg.header.stamp)
        if self.last_command is not None and stamp == stamp_key(self.last_command.header.stamp):
            if self.awaiting_transition:
                # The sim republished the state we answered: our command was lost (e.g.
                # before discovery matched). Send the same one again; never redraw.
                self.send(self.last_command)
            return
        self.state = msg
        self.try_act()

    def on_target(self, msg: PointStamped) -> None:
        self.targets[stamp_key(msg.header.stamp)] = np.array([msg.point.x, msg.point.y])
        if len(self.targets) > 64:  # only the current state's target matters
            for key in sorted(self.targets)[:-8]:
                del self.targets[key]
        self.try_act()

    def connected(self) -> bool:
        """Sim and recorder have matched on every topic of the loop (checked until true)."""
        if not self.matched:
            self.matched = (
                self.subs["/pusher/transition"].get_publisher_count() > 0
                and self.subs["/pusher/state"].get_publisher_count() > 0
                and self.subs["/pusher/target"].get_publisher_count() > 0
                and self.command_pub.get_subscription_count() > 0
            )
        return self.matched

    def try_act(self) -> None:
        if not self.active or self.finished.done() or self.awaiting_transition or self.state is None:
            return
        state = self.state
        stamp = stamp_key(state.header.stamp)
        target = self.targets.get(stamp)
        if target is None or not self.connected():
            return
        if self.episodes_done < self.n_expert:
            action, source = expert_action(state.position, state.velocity, target), SOURCE_EXPERT
        else:
            action, source = self.rng.uniform(-1, 1, size=ACT_DIM).astype(np.float32), SOURCE_RANDOM
        command = JointState(name=list(JOINT_NAMES), effort=[float(a) for a in action])
        command.header.stamp = state.header.stamp
        command.header.frame_id = SOURCE_NAMES[source]
        self.state = None
        self.awaiting_transition = True
        self.last_command = command
        self.send(command)

    def send(self, command: JointState) -> None:
        self.command_pub.publish(command)
        self.write("/pusher/command", serialize_message(command))


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv if argv is None else argv
    args = build_parser().parse_args(remove_ros_args(argv)[1:])
    if not args.passive and args.episodes is None:
        build_parser().error("--episodes is required (or --passive)")
    if args.episodes is not None and args.episodes < 1:
        build_parser().error(f"--episodes must be >= 1, got {args.episodes}")
    if not 0.0 <= args.expert_frac <= 1.0:
        build_parser().error(f"--expert-frac must be in [0, 1], got {args.expert_frac}")
    try:
        bag = BagWriter(args.out, storage=args.storage, overwrite=args.overwrite, flush_interval=args.flush_interval,
                        max_bag_size=args.max_bag_size, max_bag_duration=args.max_bag_duration)
    except UserError as exc:
        print(f"recorder: error: {exc}", file=sys.stderr)
        return 2
    rclpy.init(args=argv)
    node = None
    interrupted = False
    rc = 0
    try:
        node = Recorder(bag, args)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        spin_until_future_complete(executor, node.finished)
    except (KeyboardInterrupt, ExternalShutdownException):
        interrupted = True
    except UserError as exc:  # the disk failed under the bag: what was flushed stays
        print(f"recorder: error: {exc}", file=sys.stderr)
        rc = 2
    except Exception as exc:
        if rclpy.ok() and not caused_by_interrupt(exc):
            raise
        interrupted = True  # a signal shut the context down mid-wait (rclpy may raise RCLError)
    finally:
        try:
            bag.close()  # every message received is in the bag, however we got here
        except UserError as exc:
            print(f"recorder: error: {exc}", file=sys.stderr)
            rc = 2
        if node is not None:
            interrupted = interrupted or not node.finished.done()  # SIGTERM: spin just returns
            elapsed = time.monotonic() - node.start_time
            print(
                f"recorder: {'interrupted; ' if interrupted else ''}wrote {node.transitions} transitions "
                f"({node.episodes_done} episodes, {bag.message_count} messages) to {bag.path} in {elapsed:.1f} s",
                file=sys.stderr,
            )
            node.destroy_node()
        rclpy.try_shutdown()
    return rc


if __name__ == "__main__":
    sys.exit(main())
