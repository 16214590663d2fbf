"""``ros2 run sim node``: the MuJoCo pusher-reach arm behind ROS 2 topics.

Publishes ``/pusher/state`` (JointState), ``/pusher/target`` and ``/pusher/fingertip``
(PointStamped) and
``/pusher/transition`` (Float32MultiArray, the 25-float layout of
offline_rl_core.transitions), obeys ``/pusher/command`` (JointState, effort = action),
and serves ``/pusher/reset`` (std_srvs/Trigger: abandon the episode, start the next).

Modes (parameter ``mode``):
- ``realtime``: a 50 Hz timer steps the arm with the latest command held (zero-order
  hold, as a motor driver does); stamps are the node's clock.
- ``lockstep``: the arm steps only when the command stamped with the current state's
  stamp arrives, so data collection and evaluation run as fast as the loop allows and
  are reproducible. Stamps are synthetic sim time: state ``step`` of episode ``e`` is
  tick ``e * 100 + step`` of 20 ms. The current state is republished every
  ``republish_period`` seconds until its command arrives, which also covers messages
  lost before DDS discovery matched a subscriber.

Every state published is one a command applies to: the state after an episode's last
step is not published (it is the ``next_obs`` of the final transition); the first state
of the next episode follows the final transition.

The source tag of a transition comes from the command's ``header.frame_id``:
'expert', 'random', 'policy', 'human' or the digit 0-3; anything else counts as policy.
"""

from __future__ import annotations

import array
import json
import sys
import time

import numpy as np
import rclpy
from geometry_msgs.msg import PointStamped
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from sensor_msgs.msg import JointState
from std_msgs.msg import Float32MultiArray
from std_srvs.srv import Trigger

from offline_rl_core.atomic import atomic_path
from offline_rl_core.bag import encode_transition_rows
from offline_rl_core.env import ACT_DIM, CONTROL_HZ, JOINT_NAMES, MAX_STEPS, PusherReachEnv
from offline_rl_core.transitions import LAYOUT_SLICES, SOURCE_NAMES, SOURCE_POLICY, TRANSITION_WIDTH

from pusher_common.node_main import run_node
from pusher_common.params import Param, Settings
from pusher_common.spin import spin_node_fast
from pusher_common.stamps import stamp_from_ns, stamp_key

TICK_NS = 1_000_000_000 // CONTROL_HZ  # 20 ms
TICKS_PER_EPISODE = MAX_STEPS  # lockstep: one tick per published state
SOURCE_BY_NAME = {name: code for code, name in SOURCE_NAMES.items()}
WARN_THROTTLE_S = 2.0
# Transitions must not be dropped by a slow reader: a deep reliable history.
TRANSITION_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


def source_from_tag(frame_id: str) -> int:
    """The transition's source code from a command's ``header.frame_id``."""
    tag = frame_id.strip().lower()
    if tag in SOURCE_BY_NAME:
        return SOURCE_BY_NAME[tag]
    if tag.isdigit() and int(tag) in SOURCE_NAMES:
        return int(tag)
    return SOURCE_POLICY


PARAMS = (
    Param("mode", "realtime", "realtime: a 50 Hz timer steps the arm with the latest command held; "
          "lockstep: the arm steps once per command stamped with the current state's stamp",
          choices=("realtime", "lockstep"), read_only=True),
    Param("seed", 0, "episode e resets with reset seed seed + e", low=0, read_only=True),
    Param("episodes", 0, "episodes to run before exiting (0: run until stopped)", low=0),
    Param("summary", "", "JSON file written on exit: episodes, success_rate, mean_final_dist, mean_return "
          "(empty: none)"),
    Param("terminate_on_success", False, "end an episode as soon as the fingertip reaches the target"),
    Param("republish_period", 0.1, "lockstep: seconds before a state whose command has not come is published again",
          low=0.001, high=60.0),
    # a passive recorder started beside the sim then gets every transition from the first on
    Param("wait_for_subscribers", 0, "lockstep: hold the first state until this many pusher/transition readers "
          "are matched", low=0, read_only=True),
)


class PusherSim(Node):
    def __init__(self, overrides=()):
        super().__init__("sim", parameter_overrides=list(overrides))
        self.settings = Settings(self, PARAMS, on_change=self.on_parameter_change)
        s = self.settings
        self.mode = s.mode
        self.seed = s.seed
        self.max_episodes = s.episodes
        self.summary_path = s.summary
        self.wait_for_subscribers = s.wait_for_subscribers
        self.republish_period = s.republish_period

        self.env = PusherReachEnv(terminate_on_success=s.terminate_on_success)
        self.finished = Future()  # done when `episodes` episodes have run
        self.episode = 0  # index of the current episode; it resets with seed + episode
        self.results: list[tuple[bool, float, float]] = []  # (success, final dist, return) per episode
        self.ep_return = 0.0
        self.obs = None
        self.stamp_ns = 0
        self.last_publish = 0.0
        self.held_action = np.zeros(ACT_DIM, np.float32)
        self.held_source = SOURCE_POLICY
        self.tick_times: list[float] = []

        self.state_pub = self.create_publisher(JointState, "pusher/state", 10)
        self.target_pub = self.create_publisher(PointStamped, "pusher/target", 10)
        # The fingertip the env's observation uses (MuJoCo's site, see env.apply_action):
        # lets a ROS policy rebuild the training observation exactly.
        self.fingertip_pub = self.create_publisher(PointStamped, "pusher/fingertip", 10)
        self.transition_pub = self.create_publisher(Float32MultiArray, "pusher/transition", TRANSITION_QOS)
        self.create_subscription(JointState, "pusher/command", self.on_command, 10)
        self.create_service(Trigger, "pusher/reset", self.on_reset)
        self.state_msg = JointState(name=list(JOINT_NAMES))
        self.target_msg = PointStamped()
        self.target_msg.header.frame_id = "world"
        self.fingertip_msg = PointStamped()
        self.fingertip_msg.header.frame_id = "world"

        self.start_episode()
        self.republish_timer = None
        if self.mode == "realtime":
            self.create_timer(1.0 / CONTROL_HZ, self.on_tick)
        else:
            self.republish_timer = self.create_timer(self.republish_period, self.on_republish_timer)
        self.get_logger().info(
            f"{self.mode} pusher-reach, seed {self.seed}, "
            f"{'endless' if self.max_episodes == 0 else f'{self.max_episodes} episodes'}"
        )

    def on_parameter_change(self, name: str, value) -> None:
        if name == "episodes":
            self.max_episodes = value
            if value and len(self.results) >= value:
                self.finish()
        elif name == "summary":
            self.summary_path = value
        elif name == "terminate_on_success":
            self.env.terminate_on_success = value  # from the next step on
        elif name == "republish_period":
            self.republish_period = value
            if self.republish_timer is not None:
                self.republish_timer.timer_period_ns = int(value * 1e9)

    # -------------------------------------------------------------- episodes
    def start_episode(self) -> None:
        self.obs = self.env.reset(seed=self.seed + self.episode)
        self.ep_return = 0.0
        self.update_stamp()
        self.publish_state()

    def update_stamp(self) -> None:
        if self.mode == "lockstep":
            self.stamp_ns = (self.episode * TICKS_PER_EPISODE + self.env.steps) * TICK_NS
        else:
            self.stamp_ns = self.get_clock().now().nanoseconds

    def publish_state(self) -> None:
        if self.wait_for_subscribers > 0 and self.mode == "lockstep":
            if self.transition_pub.get_subscription_count() < self.wait_for_subscribers:
                return  # the republish timer tries again
            self.wait_for_subscribers = 0  # matched once: never hold again
        stamp = stamp_from_ns(self.stamp_ns)
        target = self.env.target
        self.target_msg.header.stamp = stamp
        self.target_msg.point.x, self.target_msg.point.y, self.target_msg.point.z = (float(v) for v in target)
        self.fingertip_msg.header.stamp = stamp
        self.fingertip_msg.point.x, self.fingertip_msg.point.y, self.fingertip_msg.point.z = (float(v) for v in self.env.fingertip)
        msg = self.state_msg
        msg.header.stamp = stamp
        msg.position = array.array("d", self.env.qpos.tobytes())
        msg.velocity = array.array("d", self.env.qvel.tobytes())
        msg.effort = array.array("d", np.ascontiguousarray(self.env.data.actuator_force[:ACT_DIM]).tobytes())
        # Target and fingertip first: a subscriber pairing by stamp then usually has them
        # when the state lands.
        self.target_pub.publish(self.target_msg)
        self.fingertip_pub.publish(self.fingertip_msg)
        self.state_pub.publish(msg)
        self.last_publish = time.monotonic()

    def step(self, action: np.ndarray, source: int) -> None:
        obs = self.obs
        step_index = self.env.steps
        next_obs, reward, done, info = self.env.step(action)
        row = np.empty(TRANSITION_WIDTH, np.float32)
        row[LAYOUT_SLICES["obs"]] = obs
        row[LAYOUT_SLICES["action"]] = action
        row[LAYOUT_SLICES["reward"]] = reward
        row[LAYOUT_SLICES["next_obs"]] = next_obs
        row[LAYOUT_SLICES["terminated"]] = info["terminated"]
        row[LAYOUT_SLICES["truncated"]] = info["truncated"]
        row[LAYOUT_SLICES["success"]] = info["success"]
        row[LAYOUT_SLICES["episode"]] = self.episode
        row[LAYOUT_SLICES["step"]] = step_index
        row[LAYOUT_SLICES["source"]] = source
        self.transition_pub.publish(encode_transition_rows(row[None, :])[0])
        self.ep_return += reward
        self.obs = next_obs
        if not done:
            self.update_stamp()
            self.publish_state()
            return
        self.results.append((bool(info["success"]), float(info["dist"]), self.ep_return))
        self.episode += 1
        if self.max_episodes and len(self.results) >= self.max_episodes:
            self.finish()
        else:
            self.start_episode()

    def finish(self) -> None:
        if not self.finished.done():
            self.get_logger().info(f"{len(self.results)} episodes done: {json.dumps(self.summary())}")
            # Let reliable readers (a recorder) acknowledge the last transition before exit.
            self.transition_pub.wait_for_all_acked(rclpy.duration.Duration(seconds=2.0))
            self.finished.set_result(True)

    def summary(self) -> dict:
        n = len(self.results)
        if n == 0:
            return {"episodes": 0, "success_rate": 0.0, "mean_final_dist": None, "mean_return": None}
        success, dist, ret = (np.array(col, np.float64) for col in zip(*self.results))
        return {
            "episodes": n,
            "success_rate": float(success.mean()),
            "mean_final_dist": float(dist.mean()),
            "mean_return": float(ret.mean()),
        }

    def write_summary(self) -> None:
        if not self.summary_path:
            return
        with atomic_path(self.summary_path) as tmp:
            tmp.write_text(json.dumps(self.summary(), indent=2) + "\n")

    # -------------------------------------------------------------- callbacks
    def parse_command(self, msg: JointState) -> np.ndarray | None:
        effort = msg.effort
        if len(effort) != ACT_DIM:
            self.get_logger().warn(
                f"ignoring /pusher/command: effort has {len(effort)} values, expected {ACT_DIM} "
                f"({', '.join(JOINT_NAMES)})",
                throttle_duration_sec=WARN_THROTTLE_S,
            )
            return None
        action = np.array(effort, dtype=np.float64)
        if len(msg.name) == ACT_DIM and list(msg.name) != list(JOINT_NAMES) and set(msg.name) == set(JOINT_NAMES):
            action = action[[list(msg.name).index(j) for j in JOINT_NAMES]]
        if not np.all(np.isfinite(action)):
            self.get_logger().warn(
                "ignoring /pusher/command: effort is not finite", throttle_duration_sec=WARN_THROTTLE_S
            )
            return None
        return np.clip(action, -1.0, 1.0).astype(np.float32)

    def on_command(self, msg: JointState) -> None:
        if self.finished.done():
            return
        if self.mode == "lockstep" and stamp_key(msg.header.stamp) != self.stamp_ns:
            return  # answers an older state (or a republished one, answered twice): stale
        action = self.parse_command(msg)
        if action is None:
            return
        source = source_from_tag(msg.header.frame_id)
        if self.mode == "lockstep":
            self.step(action, source)
        else:
            self.held_action, self.held_source = action, source

    def on_tick(self) -> None:
        if self.finished.done():
            return
        self.tick_times.append(time.monotonic())
        self.step(self.held_action, self.held_source)

    def on_republish_timer(self) -> None:
        if not self.finished.done() and time.monotonic() - self.last_publish >= self.republish_period:
            self.publish_state()

    def on_reset(self, request, response):
        if self.finished.done():
            response.success, response.message = False, "the sim has finished its episodes"
            return response
        self.episode += 1
        self.start_episode()
        response.success = True
        response.message = f"episode {self.episode} (reset seed {self.seed + self.episode})"
        return response

    def timing_report(self) -> str | None:
        """Tick period statistics of realtime mode (a missed step is a gap over 1.5 periods)."""
        if len(self.tick_times) < 3:
            return None
        gaps = np.diff(np.array(self.tick_times)) * 1000.0
        period = 1000.0 / CONTROL_HZ
        missed = int(np.clip(np.floor(gaps / period + 0.5) - 1, 0, None).sum())
        return (
            f"{len(self.tick_times)} ticks, period mean {gaps.mean():.3f} ms, std {gaps.std():.3f} ms, "
            f"min {gaps.min():.3f} ms, max {gaps.max():.3f} ms, missed steps {missed}"
        )


    def close(self) -> None:
        self.write_summary()
        report = self.timing_report()
        if report:
            self.get_logger().info(f"realtime timing: {report}")


def main(argv: list[str] | None = None) -> int:
    return run_node(PusherSim, prog="sim", argv=argv, spin=spin_node_fast,
                    description="The MuJoCo pusher-reach arm behind ROS 2 topics.")


if __name__ == "__main__":
    sys.exit(main())
