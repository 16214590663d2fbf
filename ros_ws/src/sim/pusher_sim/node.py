"""``ros2 run sim node``: a task's MuJoCo arm behind ROS 2 topics (``-p task:=NAME_OR_FILE``).

The arm is any task with a ``sim`` section (``offline_rl_core.task.envs``): the default,
``pusher_reach`` (the chapter's planar arm), or e.g. ``pusher7_reach`` (Gymnasium's 7-joint
Pusher model), exposed as a ros2_control arm is. For the task it publishes

- the state on the task's state topic (sensor_msgs/JointState: the state joints' names,
  positions, velocities, and as effort what the actuators applied, N·m), pusher_reach's
  on ``pusher/state`` and, for robot_state_publisher, also on ``joint_states``;
- the goal on the task's goal topic (PointStamped, PoseStamped or JointState, as the task
  says) and each tracked point that has a topic (PointStamped, frame ``world``);
- ``pusher/transition`` (Float32MultiArray, the task's layout of
  offline_rl_core.data.transitions), ``/clock`` (its sim time), and the task itself on
  ``task_description`` (std_msgs/String, the task's JSON, reliable and transient local as
  robot_description is: a late subscriber, a recorder, gets it);
- ``markers`` (visualization_msgs/MarkerArray, frame ``world``: the links, joints, tracked
  points and goal, ``offline_rl_core.nodes.arm_markers``) for RViz and Foxglove, only while
  someone subscribes, with a new state at most every ``marker_period`` seconds of wall time;
- ``/diagnostics`` (with every node: ``pusher_common.diagnostics``);

and takes commands on

- the task's command topic, as its controller would (std_msgs/Float64MultiArray in the
  controller's joint order, or JointState): action = (command - offset) / scale; a command
  outside the controller's limits (or the task's joint limits), or of another length, is
  refused and counted, never clipped. pusher_reach
  takes these only where ``effort_topic`` is set (its closed loops send the action on
  pusher/command too, and a state must not be answered twice);
- ``pusher/command``, ``pusher/command/expert``, ``.../random``, ``.../policy``, ``.../human``
  (JointState, effort = the action in [-1, 1], as the mux sends): who acted (the
  transition's ``source``) is the topic; plain ``pusher/command`` counts as policy (or, for
  older publishers, the source named in ``header.frame_id``, deprecated: frame_id names a
  TF frame).

It serves ``pusher/reset`` (std_srvs/Trigger), and ends an episode on a person's label:
``episode_label`` (std_msgs/String, ``{"label": "success"}``, optionally with ``"episode"``,
as the corrector's keys and gamepad buttons send it: ``offline_rl_core.data.episode_labels``)
of the current episode makes its next step its last, marked as the label says (see
``offline_rl_core.nodes.sim_loop``); a label of a past episode ends nothing (the bag records
it); one that is no label, or of an episode not yet begun, is refused and counted
(``bad label``).

Safety (``offline_rl_core.nodes.watchdog``, ``.estop``): in realtime, when no valid command
came within the task's ``safety.command_timeout`` (three control periods unless the task
says), or while the e-stop is engaged (``estop``, released only by ``estop/reset``), each
tick applies the task's safe command (zero effort or velocity; the position held), and
``~/status`` carries the latched fault (``faults``) and the e-stop (``estop``). In lockstep
the arm steps only on a command; while the e-stop is engaged every command is refused
(counted as ``estop``). For an effort interface with ``safety.position_limits`` /
``velocity_limits`` (``offline_rl_core.nodes.state_limits``), a command whose effort pushes a
joint further beyond them, where the arm is measured now, is refused (counted as ``beyond
limits``) and one back inside is taken; a held command that has come to push outward applies
the safe command on those ticks (``limit_steps`` on ``~/status``).

Lockstep: a stamped command steps the arm when its stamp is the current state's. A
Float64MultiArray has no header, so it cannot name the state it answers: the first one that
arrives after a state was published is taken as that state's answer (one that answers a
republished state late can be taken for the next state's: a controller that falls behind
the republish period should send stamped JointState commands). Once stamped commands have
come, headerless ones are refused (counted as ``unpaired``): stamps pair exactly.

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

import numpy as np

import rclpy
from geometry_msgs.msg import PointStamped, PoseStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import JointState
from std_msgs.msg import Float32MultiArray, Float64MultiArray, String
from visualization_msgs.msg import MarkerArray
from std_srvs.srv import Trigger

from offline_rl_core.common.atomic import atomic_path
from offline_rl_core.data.bag.cdr import encode_transition_rows
from offline_rl_core.data.episode_labels import LABEL_TOPIC, parse_label
from offline_rl_core.data.task_record import task_json
from offline_rl_core.nodes.joint_messages import action_from_command, action_from_effort
from offline_rl_core.nodes.pairing import check_answer_stamp, check_stamp
from offline_rl_core.common.errors import UserError
from offline_rl_core.common.output_paths import check_output_file
from offline_rl_core.nodes.sim_loop import MAX_START_TIME_S, MODES, ArmState, SimLoop, Step, TickTiming
from offline_rl_core.data.transitions import SOURCE_NAMES, SOURCE_POLICY, source_from_tag
from offline_rl_core.task.spec import (
    DEFAULT_TASK, FLOAT64_MULTI_ARRAY, JOINT_STATE, POSE_STAMPED, load_task,
)
from offline_rl_core.common.rejections import Rejection
from pusher_common.estop import EStopInput
from pusher_common.node_main import run_node
from pusher_common.params import Param, Settings
from pusher_common.readers import ReadersGate
from pusher_common.scheduling import THREAD_PRIORITY, apply_thread_priority
from pusher_common.spin import spin_node_fast
from pusher_common.stamps import NS_PER_S, stamp_from_ns, stamp_key
from pusher_common.status import NodeStatus
from pusher_common.markers import MARKERS_TOPIC, marker_array
from offline_rl_core.nodes.arm_markers import ArmMarkers
from offline_rl_core.task.envs import task_model
from offline_rl_core.nodes.diagnostics import StatusDiagnosis

# Transitions must not be dropped by a slow reader: a deep reliable history.
TRANSITION_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
# the arm's state, goal, points and /clock: a KEEP_LAST writer replaces samples a reader has
# not yet acknowledged, so at depth 10 a learner busy with an update for a few ticks lost states
STREAM_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
# The task, as robot_description is published: kept for subscribers that come later.
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
FIELD_OF_INTERFACE = {"effort": "effort", "velocity": "velocity", "position": "position"}

PARAMS = (
    Param("task", DEFAULT_TASK, "the task the sim hosts: a built-in task's name (pusher_reach, pusher7_reach) or "
          "the path of a task file with a sim section", read_only=True),
    Param("mode", "realtime", "realtime: a timer steps the arm every control period with the latest command held; "
          "lockstep: the arm steps once per command answering the current state",
          choices=MODES, read_only=True),
    Param("seed", 0, "episode e resets with reset seed seed + e", low=0, read_only=True),
    Param("episodes", 0, "episodes to run before exiting (0: run until stopped)", low=0),
    Param("steps", 0, "environment steps to run before exiting, however the episodes end (0: no cap; the step "
          "that reaches it ends its episode, truncated): a budget of steps where episodes end early", low=0,
          read_only=True),
    Param("summary", "", "JSON file written on exit: episodes, success_rate, mean_final_dist, mean_return, "
          "abandoned (episodes cut short by pusher/reset, failures in the success rate; absent when none), "
          "labelled and labels_against_simulator (episodes a person's label ended, and of them those the "
          "simulator judged otherwise; absent when none) (empty: none); checked at start, missing directories "
          "made on writing; fixed at start, so no one on the domain can point it at another file", read_only=True),
    Param("terminate_on_success", False, "end an episode as soon as it succeeds (also where the task's "
          "reward.terminate_on_success says so)"),
    Param("republish_period", 0.1, "lockstep: seconds before a state whose command has not come is published again",
          low=0.001, high=60.0),
    # a passive recorder started beside the sim then gets every transition from the first on
    Param("wait_for_subscribers", 0, "hold the first state (lockstep) or the first tick (realtime) until this "
          "many pusher/transition readers are matched", low=0, read_only=True),
    # raw topics (no pusher/transition): the readers of the state that must not miss a step,
    # by node name, since other nodes (a policy, a mux) read it too
    Param("wait_for_readers", [], "hold the first state (lockstep) or the first tick (realtime) until these nodes "
          "(names, e.g. [learner, recorder]) read the task's state, goal and point topics", read_only=True),
    Param("start_time", 0.0, "sim time of the first state, in seconds since the epoch (0: the wall clock at start, "
          "whole seconds); every stamp and /clock count one control period per tick from it (stamps are int32 seconds: "
          "at most a year before 2038)", low=0.0, high=float(MAX_START_TIME_S), read_only=True),
    Param("effort_topic", "", "also take commands as std_msgs/Float64MultiArray in the task's units (torques in "
          "N·m for an effort interface) on this topic, as its controller does (besides the task's command topic, "
          "which pusher_reach takes only through this; empty: off)", read_only=True),
    Param("marker_period", 0.04, "seconds of wall time between the arm's markers (while someone subscribes)",
          low=0.0, high=60.0),
    THREAD_PRIORITY,
)


class PusherSim(Node):
    def __init__(self, overrides=()):
        super().__init__("sim", parameter_overrides=list(overrides))
        self.settings = s = Settings(self, PARAMS, on_change=self.on_parameter_change)
        if s.summary:  # checked now, not after the whole run
            check_output_file(s.summary, "parameter summary:")
        self.task = task = load_task(s.task)
        apply_thread_priority(self.settings.thread_priority, self.get_logger())
        start_ns = int(s.start_time * NS_PER_S) if s.start_time > 0 else time.time_ns() // NS_PER_S * NS_PER_S
        self.mode = s.mode
        self.wait_for_subscribers = s.wait_for_subscribers
        self.readers_gate = ReadersGate(self, s.wait_for_readers or ())
        self.finished = Future()  # done when `episodes` episodes have run
        self.last_publish = 0.0
        self.timing = TickTiming(task.control_period)
        self.status = NodeStatus(self, fields=lambda: {"episode": self.loop.episode,
                                                       "episodes_done": len(self.loop.results),
                                                       "faults": self.loop.faults(),
                                                       "estop": self.loop.estop.as_dict(),
                                                       "safe_steps": self.loop.safe_steps,
                                                       "limit_steps": self.loop.limit_steps,
                                                       "labelled": self.loop.labelled},
                                 diagnosis=StatusDiagnosis(idle=lambda st: f"{s.mode}, episode {st['episode']}, "
                                                                           f"{st['episodes_done']} done"),
                                 hardware_id=task.name)
        # every endpoint before the env is built (below): what the node announces on
        # ros_discovery_info is whole from the start, so `ros2 topic list` never sees half of it
        self.estop = EStopInput(self, on_engage=lambda: self.loop.estop_engaged(),
                                on_reset=lambda: self.loop.reset_faults())
        self.tripped = 0  # watchdog trips logged so far

        self.clock_pub = self.create_publisher(ClockMsg, "/clock", STREAM_QOS)
        self.clock_ns: int | None = None  # the sim time last published on /clock
        self.state_pub = self.create_publisher(JointState, task.state.topic, STREAM_QOS)
        # robot_state_publisher reads joint_states: the state goes there too (when someone listens)
        self.joint_states_pub = None if self.resolve(task.state.topic) == self.resolve("joint_states") else \
            self.create_publisher(JointState, "joint_states", STREAM_QOS)
        goal_type = {JOINT_STATE: JointState, POSE_STAMPED: PoseStamped}.get(task.goal.type, PointStamped)
        self.goal_pub = self.create_publisher(goal_type, task.goal.topic, STREAM_QOS)
        self.goal_msg = goal_type()
        # Tracked points with a topic (pusher_reach's fingertip: MuJoCo's site, see env.apply_action,
        # so a ROS policy rebuilds the training observation exactly).
        self.point_pubs = [(p.name, self.create_publisher(PoseStamped if p.type == POSE_STAMPED else PointStamped,
                                                          p.topic, STREAM_QOS),
                            PoseStamped() if p.type == POSE_STAMPED else PointStamped())
                           for p in task.points if p.topic]
        for msg in [self.goal_msg] + [m for _, _, m in self.point_pubs]:
            msg.header.frame_id = "world"
        if task.goal.type == JOINT_STATE:
            self.goal_msg.name = list(task.goal.joints)
        self.transition_pub = self.create_publisher(Float32MultiArray, "pusher/transition", TRANSITION_QOS)
        self.marker_pub = self.create_publisher(MarkerArray, MARKERS_TOPIC, 10)
        self.last_markers = -float("inf")
        self.task_pub = self.create_publisher(String, "task_description", LATCHED_QOS)
        self.create_subscription(JointState, "pusher/command", lambda m: self.on_command(m, None, "pusher/command"), 10)
        for code, name in SOURCE_NAMES.items():
            topic = f"pusher/command/{name}"
            self.create_subscription(JointState, topic, lambda m, c=code, t=topic: self.on_command(m, c, t), 10)
        # the controller's topics: the task's (pusher_reach's only through effort_topic), and effort_topic
        self.controller_topics = [] if task.name == DEFAULT_TASK else [(task.command.topic, task.command.type)]
        if s.effort_topic and self.resolve(s.effort_topic) not in {self.resolve(t) for t, _ in self.controller_topics}:
            self.controller_topics.append((s.effort_topic, FLOAT64_MULTI_ARRAY))
        for topic, kind in self.controller_topics:
            if kind == JOINT_STATE:
                self.create_subscription(JointState, topic, lambda m, t=topic: self.on_controller_state(m, t), 10)
            else:
                self.create_subscription(Float64MultiArray, topic, lambda m, t=topic: self.on_controller(m, t), 10)
        self.create_subscription(String, LABEL_TOPIC, self.on_label, 10)
        self.create_service(Trigger, "pusher/reset", self.on_reset)
        self.state_msg = JointState(name=list(task.state.joints))

        self.loop = SimLoop(s.mode, s.seed, s.episodes, s.terminate_on_success, start_ns, task=task,
                            estop=self.estop.latch, steps=s.steps)
        self.arm_markers = ArmMarkers(task, task_model(task))
        self.task_pub.publish(String(data=task_json(task)))

        self.publish_state(self.loop.start_episode())
        # Wall-clock timers: the sim is the clock, so they must not wait for /clock.
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.republish_timer = None
        if self.mode == "realtime":
            self.create_timer(task.control_period, self.on_tick, clock=steady)
        else:
            self.republish_timer = self.create_timer(s.republish_period, self.on_republish_timer, clock=steady)
        commands = ", ".join(t for t, _ in self.controller_topics) or "pusher/command"
        self.get_logger().info(
            f"{self.mode} {task.name}, seed {s.seed}, "
            f"{'endless' if not s.episodes else f'{s.episodes} episodes'}"
            + (f" (at most {s.steps} steps)" if s.steps else "")
            + ("" if task.name == DEFAULT_TASK else f"; state on {task.state.topic}, commands on {commands}")
        )

    def resolve(self, topic: str) -> str:
        return self.resolve_topic_name(topic)

    def check_parameter(self, name: str, value) -> str | None:
        if name == "summary" and value:
            try:
                check_output_file(value, "")
            except UserError as exc:
                return str(exc).strip()
        return None

    def on_parameter_change(self, name: str, value) -> None:
        if name == "episodes":
            self.loop.max_episodes = value
            if self.loop.finished:
                self.finish()
        elif name == "terminate_on_success":
            # from the next step on
            self.loop.env.terminate_on_success = value or self.task.reward.terminate_on_success
        elif name == "republish_period" and self.republish_timer is not None:
            self.republish_timer.timer_period_ns = int(value * 1e9)

    # -------------------------------------------------------------- publishing
    def publish_state(self, state: ArmState | None = None, new: bool = True) -> None:
        state = state or self.loop.current
        if self.mode == "lockstep" and not self.readers_matched():
            return  # the republish timer tries again
        stamp = stamp_from_ns(state.stamp_ns)
        # /clock and joint_states only when someone listens: each publish costs the
        # lockstep loop as much as a physics step. A republished state brings the clock
        # to a reader that came after it was first published (a recorder on sim time
        # stamps what it hears by it).
        if (new or self.clock_ns != state.stamp_ns) and self.clock_pub.get_subscription_count():
            self.clock_pub.publish(ClockMsg(clock=stamp))
            self.clock_ns = state.stamp_ns
        self.fill_goal(state, stamp)
        for name, _, msg in self.point_pubs:
            msg.header.stamp = stamp
            fill_point(msg, state.points[name])
        msg = self.state_msg
        msg.header.stamp = stamp
        msg.position = array.array("d", state.position.tobytes())
        msg.velocity = array.array("d", state.velocity.tobytes())
        msg.effort = array.array("d", state.torque.tobytes())
        # Goal and points first: a subscriber pairing by stamp then usually has them
        # when the state lands.
        self.goal_pub.publish(self.goal_msg)
        for _, pub, point in self.point_pubs:
            pub.publish(point)
        self.state_pub.publish(msg)
        if self.joint_states_pub is not None and self.joint_states_pub.get_subscription_count():
            self.joint_states_pub.publish(msg)
        self.publish_markers(state, stamp)
        self.last_publish = time.monotonic()
        self.loop.published()

    def publish_markers(self, state: ArmState, stamp) -> None:
        now = time.monotonic()
        if now - self.last_markers < self.settings.marker_period or not self.marker_pub.get_subscription_count():
            return
        self.last_markers = now
        markers = self.arm_markers.markers(state.position, state.goal, state.points)
        self.marker_pub.publish(marker_array(markers, stamp))

    def fill_goal(self, state: ArmState, stamp) -> None:
        msg = self.goal_msg
        msg.header.stamp = stamp
        if self.task.goal.type == JOINT_STATE:
            msg.position = array.array("d", np.asarray(state.goal, np.float64).tobytes())
        else:
            fill_point(msg, state.target)

    def publish_step(self, step: Step | None) -> None:
        if step is None:
            return
        self.transition_pub.publish(encode_transition_rows(step.transition[None, :], self.loop.layout)[0])
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
    def stamp_problem(self, stamp):
        """Check a stamped command's stamp; in lockstep, that it answers the current state.

        Checked before parsing: a late duplicate costs no more than a count.
        """
        problem = check_stamp(stamp.sec, stamp.nanosec)
        if problem is None and self.mode == "lockstep":
            problem = check_answer_stamp(stamp_key(stamp), self.loop.current.stamp_ns)
        return problem

    def on_command(self, msg: JointState, source: int | None, topic: str) -> None:
        self.status.took(topic)
        if self.finished.done():
            return
        stamp = msg.header.stamp
        problem = self.stamp_problem(stamp)
        if problem is None:
            action, problem = action_from_effort(msg.name, msg.effort, joints=self.task.command.joints)
        if problem:
            if self.mode == "lockstep":
                self.loop.stamped_commands = True  # a stamped command came, even if refused
            self.status.reject(topic, problem)
            return
        if self.refused_for_estop(topic) or self.refused_for_state_limits(topic, action):
            return
        if source is None:
            source = source_from_tag(msg.header.frame_id)
            if source is None:
                source = SOURCE_POLICY
            else:
                self.warn_tag_deprecated()
        self.publish_step(self.loop.command(stamp_key(msg.header.stamp), action, source, time.monotonic()))

    def refused_for_estop(self, topic: str) -> bool:
        """While the e-stop is engaged no command is taken (the safe command applies)."""
        if not self.loop.estop.engaged:
            return False
        self.status.reject(topic, Rejection("estop", "a command while the e-stop is engaged (estop/reset "
                                                     "releases it)"))
        return True

    def refused_for_state_limits(self, topic: str, action, stamped: bool = True) -> bool:
        """Refuse an effort that pushes a joint further beyond the task's limits.

        Counted as ``beyond limits``; an effort that brings the joint back is taken.
        """
        problem = self.loop.beyond_state_limits(action)
        if problem is None:
            return False
        if self.mode == "lockstep" and stamped:
            self.loop.stamped_commands = True  # a stamped command came, even if refused
        self.status.reject(topic, problem)
        return True

    def warn_tag_deprecated(self) -> None:
        # a method of its own: rclpy ties a log call's filters (once, throttle) to its caller
        self.get_logger().warning("a source tag in header.frame_id is deprecated; publish on "
                                  "pusher/command/<expert|random|policy|human> instead", once=True)

    def on_controller(self, msg: Float64MultiArray, topic: str) -> None:
        """Take the task's controller command (Float64MultiArray: no header, no names)."""
        self.status.took(topic)
        if self.finished.done():
            return
        action, problem = action_from_command(self.task, msg.data)
        if problem is None and (self.refused_for_estop(topic)
                                or self.refused_for_state_limits(topic, action, stamped=False)):
            return
        if problem is None:
            step, problem = self.loop.command_unstamped(action, SOURCE_POLICY, time.monotonic())
        if problem:
            self.status.reject(topic, problem)
            return
        self.publish_step(step)

    def on_controller_state(self, msg: JointState, topic: str) -> None:
        """Take a JointState command: the interface's field, named; stamped, so lockstep pairs it by stamp."""
        self.status.took(topic)
        if self.finished.done():
            return
        stamp = msg.header.stamp
        problem = self.stamp_problem(stamp)
        if problem is None:
            values = getattr(msg, FIELD_OF_INTERFACE[self.task.command.interface])
            action, problem = action_from_command(self.task, values, msg.name)
        if problem:
            self.status.reject(topic, problem)
            return
        if self.refused_for_estop(topic) or self.refused_for_state_limits(topic, action):
            return
        self.publish_step(self.loop.command(stamp_key(stamp), action, SOURCE_POLICY, time.monotonic()))

    def readers_matched(self) -> bool:
        """Whether the readers asked for are there (matched once: never hold again)."""
        if self.wait_for_subscribers > 0:
            if self.transition_pub.get_subscription_count() < self.wait_for_subscribers:
                return False
            self.wait_for_subscribers = 0
        # every topic a join needs from the sim: a reader of the state whose goal reader was
        # not matched yet lost the first goal
        return self.readers_gate.open([self.state_pub, self.goal_pub, *(p for _, p, _ in self.point_pubs)])

    def on_tick(self) -> None:
        if self.finished.done():
            return
        if not self.readers_matched():
            return  # the arm waits at its first state: a recorder or learner started beside it gets every step
        now = time.monotonic()
        self.timing.tick(now)
        self.publish_step(self.loop.tick(now))
        if self.loop.watchdog.trips > self.tripped:
            self.warn_watchdog()
        self.tripped = self.loop.watchdog.trips

    def warn_watchdog(self) -> None:
        self.get_logger().error(f"no valid command for {self.loop.watchdog.timeout_s * 1000:.0f} ms: "
                                f"applying the safe command ({self.task.safe_command}) until one comes",
                                throttle_duration_sec=2.0)

    def on_republish_timer(self) -> None:
        period_s = self.republish_timer.timer_period_ns / 1e9
        if not self.finished.done() and time.monotonic() - self.last_publish >= period_s:
            self.publish_state(new=False)

    def on_label(self, msg: String) -> None:
        """Take a person's label: one of the current episode makes its next step its last."""
        self.status.took(LABEL_TOPIC)
        try:
            success, episode = parse_label(msg.data, self.resolve(LABEL_TOPIC))
        except UserError as exc:
            self.status.reject(LABEL_TOPIC, Rejection("bad label", str(exc)))
            return
        current = self.loop.episode
        labelled, problem = self.loop.label(success, episode)
        if problem:
            self.status.reject(LABEL_TOPIC, problem)
        elif labelled is not None:
            verdict = "success" if success else "failure"
            self.get_logger().info(f"episode {labelled} labelled {verdict}"
                                   + (": it ends at its next step" if labelled == current else " (already over)"))

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


def fill_point(msg, xyz) -> None:
    """Set a PointStamped's point, or a PoseStamped's position (orientation: identity)."""
    where = msg.pose.position if isinstance(msg, PoseStamped) else msg.point
    where.x, where.y, where.z = (float(v) for v in xyz)
    if isinstance(msg, PoseStamped):
        msg.pose.orientation.w = 1.0


def main(argv: list[str] | None = None) -> int:
    return run_node(PusherSim, prog="sim", argv=argv, spin=spin_node_fast,
                    description="A task's MuJoCo arm behind ROS 2 topics (pusher-reach by default).")


if __name__ == "__main__":
    sys.exit(main())
