"""``ros2 run sim node``: the MuJoCo pusher-reach arm behind ROS 2 topics.

Publishes ``pusher/state`` (JointState; also on ``joint_states`` for robot_state_publisher),
``pusher/target`` and ``pusher/fingertip`` (PointStamped, frame ``world``),
``pusher/transition`` (Float32MultiArray, the 25-float layout of
offline_rl_core.data.transitions) and ``/clock`` (its sim time); obeys JointState commands
(effort = action in [-1, 1]) and, where ``effort_topic`` is set, Float64MultiArray torques
in N·m as an effort controller takes them; serves ``pusher/reset`` (std_srvs/Trigger).

Who acted (the transition's ``source``) is the command topic a command came on:
``pusher/command/expert``, ``.../random``, ``.../policy``, ``.../human``; plain
``pusher/command`` counts as policy (or, for older publishers, the source named in
``header.frame_id``, which is deprecated: frame_id names a TF frame).

The protocol (realtime / lockstep, sim time, episodes) is ``offline_rl_core.nodes.sim_loop``;
this node moves messages to it and publishes what it returns. A command it cannot take
(malformed, non-finite, a bad stamp; in lockstep, a stamp other than the current
state's) is counted by reason on ``~/status`` (``pusher_common.status``) with a
throttled warning.
"""

from __future__ import annotations

import array
import json
import sys
import time

import rclpy
from geometry_msgs.msg import PointStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import JointState
from std_msgs.msg import Float32MultiArray, Float64MultiArray
from std_srvs.srv import Trigger

from offline_rl_core.common.atomic import atomic_path
from offline_rl_core.data.bag.cdr import encode_transition_rows
from offline_rl_core.task.pusher_reach import CONTROL_HZ, JOINT_NAMES
from offline_rl_core.nodes.joint_messages import action_from_effort, action_from_torques
from offline_rl_core.nodes.pairing import check_answer_stamp, check_stamp
from offline_rl_core.common.output_paths import check_output_file
from offline_rl_core.nodes.sim_loop import MAX_START_TIME_S, MODES, ArmState, SimLoop, Step, TickTiming
from offline_rl_core.data.transitions import SOURCE_NAMES, SOURCE_POLICY, source_from_tag
from pusher_common.node_main import run_node
from pusher_common.params import Param, Settings
from pusher_common.scheduling import THREAD_PRIORITY, apply_thread_priority
from pusher_common.spin import spin_node_fast
from pusher_common.stamps import NS_PER_S, stamp_from_ns, stamp_key
from pusher_common.status import NodeStatus

# Transitions must not be dropped by a slow reader: a deep reliable history.
TRANSITION_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)

PARAMS = (
    Param("mode", "realtime", "realtime: a 50 Hz timer steps the arm with the latest command held; "
          "lockstep: the arm steps once per command stamped with the current state's stamp",
          choices=MODES, read_only=True),
    Param("seed", 0, "episode e resets with reset seed seed + e", low=0, read_only=True),
    Param("episodes", 0, "episodes to run before exiting (0: run until stopped)", low=0),
    Param("summary", "", "JSON file written on exit: episodes, success_rate, mean_final_dist, mean_return, "
          "abandoned (episodes cut short by pusher/reset, failures in the success rate; absent when none) "
          "(empty: none); checked at start, missing directories made on writing; fixed at start, so no one "
          "on the domain can point it at another file", read_only=True),
    Param("terminate_on_success", False, "end an episode as soon as the fingertip reaches the target"),
    Param("republish_period", 0.1, "lockstep: seconds before a state whose command has not come is published again",
          low=0.001, high=60.0),
    # a passive recorder started beside the sim then gets every transition from the first on
    Param("wait_for_subscribers", 0, "hold the first state (lockstep) or the first tick (realtime) until this "
          "many pusher/transition readers are matched", low=0, read_only=True),
    Param("start_time", 0.0, "sim time of the first state, in seconds since the epoch (0: the wall clock at start, "
          "whole seconds); every stamp and /clock count 20 ms per tick from it (stamps are int32 seconds: "
          "at most a year before 2038)", low=0.0, high=float(MAX_START_TIME_S), read_only=True),
    Param("effort_topic", "", "also take commands as std_msgs/Float64MultiArray joint torques in N·m on this "
          "topic, as an effort controller does (realtime; e.g. effort_controller/commands; empty: off)",
          read_only=True),
    THREAD_PRIORITY,
)


class PusherSim(Node):
    def __init__(self, overrides=()):
        super().__init__("sim", parameter_overrides=list(overrides))
        self.settings = s = Settings(self, PARAMS, on_change=self.on_parameter_change)
        if s.summary:  # checked now, not after the whole run
            check_output_file(s.summary, "parameter summary:")
        apply_thread_priority(self.settings.thread_priority, self.get_logger())
        start_ns = int(s.start_time * NS_PER_S) if s.start_time > 0 else time.time_ns() // NS_PER_S * NS_PER_S
        self.loop = SimLoop(s.mode, s.seed, s.episodes, s.terminate_on_success, start_ns)
        self.mode = s.mode
        self.wait_for_subscribers = s.wait_for_subscribers
        self.finished = Future()  # done when `episodes` episodes have run
        self.last_publish = 0.0
        self.timing = TickTiming()
        self.status = NodeStatus(self, fields=lambda: {"episode": self.loop.episode,
                                                       "episodes_done": len(self.loop.results)})

        self.clock_pub = self.create_publisher(ClockMsg, "/clock", 10)
        self.state_pub = self.create_publisher(JointState, "pusher/state", 10)
        self.joint_states_pub = self.create_publisher(JointState, "joint_states", 10)
        self.target_pub = self.create_publisher(PointStamped, "pusher/target", 10)
        # The fingertip the env's observation uses (MuJoCo's site, see env.apply_action):
        # lets a ROS policy rebuild the training observation exactly.
        self.fingertip_pub = self.create_publisher(PointStamped, "pusher/fingertip", 10)
        self.transition_pub = self.create_publisher(Float32MultiArray, "pusher/transition", TRANSITION_QOS)
        self.create_subscription(JointState, "pusher/command", lambda m: self.on_command(m, None, "pusher/command"), 10)
        for code, name in SOURCE_NAMES.items():
            topic = f"pusher/command/{name}"
            self.create_subscription(JointState, topic, lambda m, c=code, t=topic: self.on_command(m, c, t), 10)
        if s.effort_topic:
            self.create_subscription(Float64MultiArray, s.effort_topic, self.on_effort, 10)
        self.create_service(Trigger, "pusher/reset", self.on_reset)
        self.state_msg = JointState(name=list(JOINT_NAMES))
        self.target_msg = PointStamped()
        self.target_msg.header.frame_id = "world"
        self.fingertip_msg = PointStamped()
        self.fingertip_msg.header.frame_id = "world"

        self.publish_state(self.loop.start_episode())
        # Wall-clock timers: the sim is the clock, so they must not wait for /clock.
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.republish_timer = None
        if self.mode == "realtime":
            self.create_timer(1.0 / CONTROL_HZ, self.on_tick, clock=steady)
        else:
            self.republish_timer = self.create_timer(s.republish_period, self.on_republish_timer, clock=steady)
        self.get_logger().info(
            f"{self.mode} pusher-reach, seed {s.seed}, "
            f"{'endless' if not s.episodes else f'{s.episodes} episodes'}"
        )

    def on_parameter_change(self, name: str, value) -> None:
        if name == "episodes":
            self.loop.max_episodes = value
            if self.loop.finished:
                self.finish()
        elif name == "terminate_on_success":
            self.loop.env.terminate_on_success = value  # from the next step on
        elif name == "republish_period" and self.republish_timer is not None:
            self.republish_timer.timer_period_ns = int(value * 1e9)

    # -------------------------------------------------------------- publishing
    def publish_state(self, state: ArmState | None = None, new: bool = True) -> None:
        state = state or self.loop.current
        if self.mode == "lockstep" and not self.readers_matched():
            return  # the republish timer tries again
        stamp = stamp_from_ns(state.stamp_ns)
        # /clock and joint_states only when someone listens: each publish costs the
        # lockstep loop as much as a physics step
        if new and self.clock_pub.get_subscription_count():
            self.clock_pub.publish(ClockMsg(clock=stamp))
        for msg, point in ((self.target_msg, state.target), (self.fingertip_msg, state.fingertip)):
            msg.header.stamp = stamp
            msg.point.x, msg.point.y, msg.point.z = (float(v) for v in point)
        msg = self.state_msg
        msg.header.stamp = stamp
        msg.position = array.array("d", state.position.tobytes())
        msg.velocity = array.array("d", state.velocity.tobytes())
        msg.effort = array.array("d", state.torque.tobytes())
        # Target and fingertip first: a subscriber pairing by stamp then usually has them
        # when the state lands.
        self.target_pub.publish(self.target_msg)
        self.fingertip_pub.publish(self.fingertip_msg)
        self.state_pub.publish(msg)
        if self.joint_states_pub.get_subscription_count():
            self.joint_states_pub.publish(msg)
        self.last_publish = time.monotonic()

    def publish_step(self, step: Step | None) -> None:
        if step is None:
            return
        self.transition_pub.publish(encode_transition_rows(step.transition[None, :])[0])
        if step.next_state is not None:
            self.publish_state(step.next_state)
        elif step.new_episode is not None:
            self.publish_state(step.new_episode)
        if self.loop.finished:
            self.finish()

    def finish(self) -> None:
        if not self.finished.done():
            self.get_logger().info(f"{len(self.loop.results)} episodes done: {json.dumps(self.loop.summary())}")
            # Let reliable readers (a recorder) acknowledge the last transition before exit.
            self.transition_pub.wait_for_all_acked(rclpy.duration.Duration(seconds=2.0))
            self.finished.set_result(True)

    # -------------------------------------------------------------- callbacks
    def on_command(self, msg: JointState, source: int | None, topic: str) -> None:
        self.status.took(topic)
        if self.finished.done():
            return
        stamp = msg.header.stamp
        problem = check_stamp(stamp.sec, stamp.nanosec)
        if problem is None and self.mode == "lockstep":
            # checked before parsing: a late duplicate costs no more than a count
            problem = check_answer_stamp(stamp_key(stamp), self.loop.current.stamp_ns)
        if problem is None:
            action, problem = action_from_effort(msg.name, msg.effort)
        if problem:
            self.status.reject(topic, problem)
            return
        if source is None:
            source = source_from_tag(msg.header.frame_id)
            if source is None:
                source = SOURCE_POLICY
            else:
                self.warn_tag_deprecated()
        self.publish_step(self.loop.command(stamp_key(msg.header.stamp), action, source))

    def warn_tag_deprecated(self) -> None:
        # a method of its own: rclpy ties a log call's filters (once, throttle) to its caller
        self.get_logger().warning("a source tag in header.frame_id is deprecated; publish on "
                                  "pusher/command/<expert|random|policy|human> instead", once=True)

    def on_effort(self, msg: Float64MultiArray) -> None:
        self.status.took(self.settings.effort_topic)
        if self.mode != "realtime":
            self.warn_effort_in_lockstep()
            return
        action, problem = action_from_torques(msg.data)
        if action is None:
            self.status.reject(self.settings.effort_topic, problem)
            return
        self.loop.command(None, action, SOURCE_POLICY)

    def warn_effort_in_lockstep(self) -> None:
        self.get_logger().warning(f"ignoring {self.settings.effort_topic}: torques carry no stamp, and lockstep "
                                  "steps on the command for a state's stamp (use pusher/command)", once=True)

    def readers_matched(self) -> bool:
        """Whether the transition readers asked for are there (matched once: never hold again)."""
        if self.wait_for_subscribers > 0:
            if self.transition_pub.get_subscription_count() < self.wait_for_subscribers:
                return False
            self.wait_for_subscribers = 0
        return True

    def on_tick(self) -> None:
        if self.finished.done():
            return
        if not self.readers_matched():
            return  # the arm waits at its first state: a recorder or learner started beside it gets every step
        self.timing.tick(time.monotonic())
        self.publish_step(self.loop.tick())

    def on_republish_timer(self) -> None:
        period_s = self.republish_timer.timer_period_ns / 1e9
        if not self.finished.done() and time.monotonic() - self.last_publish >= period_s:
            self.publish_state(new=False)

    def on_reset(self, request, response):
        if self.finished.done():
            response.success, response.message = False, "the sim has finished its episodes"
            return response
        self.publish_state(self.loop.reset())
        response.success = True
        response.message = f"episode {self.loop.episode} (reset seed {self.loop.seed + self.loop.episode})"
        return response

    # -------------------------------------------------------------- on exit
    def close(self) -> None:
        if self.settings.summary:
            with atomic_path(self.settings.summary) as tmp:
                tmp.write_text(json.dumps(self.loop.summary(), indent=2) + "\n")
        report = self.timing.report()
        if report:  # printed: after Ctrl-C the context is shut down and the logger's rosout publisher with it
            print(f"sim: realtime timing: {report}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    return run_node(PusherSim, prog="sim", argv=argv, spin=spin_node_fast,
                    description="The MuJoCo pusher-reach arm behind ROS 2 topics.")


if __name__ == "__main__":
    sys.exit(main())
