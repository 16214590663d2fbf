"""``ros2 run corrections corrector``: the human in human-in-the-loop, or a stand-in.

Watches the task's state (``-p task:=NAME_OR_FILE``, default pusher_reach: ``pusher/state``)
with its goal (``pusher/target``) and the tracked points that have a topic (a puck from its
tracker), paired by stamp as the policy node does (``offline_rl_core.nodes.pairing``), and
answers every state on ``teleop/action`` (JointState of the command joints, stamp = the
state's): either a correction (effort =
the action in [-1, 1]) or a *yield* (empty effort: the policy keeps the arm). A
republished state gets the same answer again; each state is decided once. The scripted
rule is the in-process stage's (``ScriptedCorrector.for_task``): it judges the task's reward
distances (points heard on their topics, else from forward kinematics) and takes over with
the task's scripted expert; a task without one in this build is refused at start in one line.
With ``--action-labels`` it also publishes, before its yield, the action it would take on
every state it leaves to the policy (``corrections/action_label``, stamp = the state's): labels
a learner with ``action_labels`` imitates (DAgger's); no node that moves the arm reads them.

``--mode scripted`` (default): takes over with the scripted expert when the fingertip
has not got closer to the target for ``patience`` steps, hands back after
``hold_steps`` steps or on success (see ``pusher_corrections.scripted``). Parameters
(``-p name:=value`` or the flags): ``patience`` (8), ``hold_steps`` (25),
``grace_steps`` (20: states at an episode's start before progress is judged),
``min_progress`` (0.002 m), ``noise`` (0.0, std of torque noise), ``reaction_delay``
(0 steps), ``seed`` (0), ``steer`` (expert: the scripted expert's joint-space swing; stick:
the fingertip steered straight at the goal, as a person with a Cartesian stick would; a
reach task's only).

``--mode keyboard``: a person drives from the terminal (raw mode; needs a tty):
  a / d  shoulder torque -1 / +1      j / l  elbow torque -1 / +1
  s      shoulder torque 0            k      elbow torque 0
  space  hand back to the policy      q      quit (Ctrl-C too)
  y      label the episode a success  n      label the episode a failure
Any torque key takes over; the held torques are sent with every state until space. A label
(``y`` / ``n``) is published on ``episode_label`` as the gamepad's buttons publish it
(std_msgs/String, ``{"label": "success"}``): the sim ends the episode at its next step and
a recorder keeps the label in the bag (``offline_rl_core.data.episode_labels``).

``--mode gamepad``: a person with a gamepad, read from ``joy`` (sensor_msgs/Joy, as the
standard ``joy`` node publishes it): while the dead-man button is held the sticks' action
answers every state (scaled into [-1, 1], in the command joints' order); released, the
policy keeps the arm. With ``mode: cartesian`` in the mapping the sticks move the task's
tracked point (the fingertip) instead, turned into joint actions by damped least squares on
the task's Jacobian. Two buttons label the episode a success or a failure on
``episode_label`` (std_msgs/String, ``{"label": "success"}``). The mapping is ``gamepad``
(a YAML file; empty: an Xbox pad, as ``config/gamepad_xbox.yaml`` documents; a PlayStation
pad under ``joy_linux``: ``config/gamepad_ps.yaml``; Cartesian: ``config/gamepad_xbox_cartesian.yaml``;
``offline_rl_core.nodes.gamepad``). A Joy message the mapping cannot read is refused and
counted on ``/diagnostics``.
"""

from __future__ import annotations

import os
import select
import sys
import termios
import threading
import tty
from dataclasses import replace

import numpy as np
from geometry_msgs.msg import PointStamped, PoseStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.task import Future
from sensor_msgs.msg import JointState, Joy
from std_msgs.msg import String

from offline_rl_core.common.errors import UserError
from offline_rl_core.nodes.observation import ObservationBuilder, kinematics_model
from offline_rl_core.nodes.pairing import Paired, StatePairing
from offline_rl_core.task.spec import DEFAULT_TASK, JOINT_STATE, POSE_STAMPED, load_task
from pusher_common.node_main import run_node
from pusher_common.params import Param, Settings
from pusher_common.readers import ReadersGate
from pusher_common.stamps import stamp_key
from pusher_common.diagnostics import NodeDiagnostics
from offline_rl_core.nodes.diagnostics import StatusDiagnosis
from offline_rl_core.nodes.gamepad import LABEL_TOPIC, GamepadTeleop, label_json, load_mapping
from offline_rl_core.common.rejections import RejectionCounter

from offline_rl_core.data.raw_topics.spec import ACTION_LABEL_TOPIC
from offline_rl_core.task.corrector import STEERS, CorrectorParams, ScriptedCorrector

READERS_CHECK_PERIOD_S = 0.01  # while the first answer is held for the labels' readers
KEEP_ANSWERS = 64
KEYS = {
    "a": (0, -1.0), "d": (0, 1.0), "s": (0, 0.0),
    "j": (1, -1.0), "l": (1, 1.0), "k": (1, 0.0),
}
LABEL_KEYS = {"y": "success", "n": "failure"}


class KeyboardTeleop:
    """Torques set by keys in a raw-mode terminal; read on a background thread."""

    def __init__(self, act_dim: int, stream=sys.stdin):
        if not stream.isatty():
            raise UserError("--mode keyboard needs an interactive terminal (stdin is not a tty)")
        self.stream = stream
        self.torque = np.zeros(act_dim, np.float32)
        self.active = False
        self.labels: list[str] = []  # pressed, not yet published (the node's thread publishes them)
        self.labels_sent = {label: 0 for label in LABEL_KEYS.values()}
        self.quit = threading.Event()
        self.lock = threading.Lock()
        self.saved = termios.tcgetattr(stream.fileno())
        tty.setcbreak(stream.fileno())  # keys arrive one by one, unechoed; Ctrl-C still signals
        self.thread = threading.Thread(target=self.read_keys, daemon=True)
        self.thread.start()
        print("keyboard teleop: a/d shoulder -/+, j/l elbow -/+, s/k zero, space hand back, "
              "y/n label the episode success/failure, q quit", file=sys.stderr, flush=True)

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
                elif key in LABEL_KEYS:
                    self.labels.append(LABEL_KEYS[key])
                    self.labels_sent[LABEL_KEYS[key]] += 1

    def take_labels(self) -> list[str]:
        """Return the labels pressed since the last call, in order."""
        with self.lock:
            labels, self.labels = self.labels, []
        return labels

    def decide(self, qpos, qvel, target_xy) -> np.ndarray | None:
        with self.lock:
            return self.torque.copy() if self.active else None

    def restore(self) -> None:
        self.quit.set()
        termios.tcsetattr(self.stream.fileno(), termios.TCSADRAIN, self.saved)


PARAMS = (
    Param("task", DEFAULT_TASK, "the task: a built-in task or a task file (its state, goal, reward distance and "
          "scripted expert)", read_only=True, flag="--task"),
    Param("mode", "scripted", "scripted: the scripted expert takes over when progress stalls; keyboard: a person "
          "at this terminal; gamepad: a person with a gamepad on joy (sensor_msgs/Joy)",
          choices=("scripted", "keyboard", "gamepad"), read_only=True, flag="--mode"),
    Param("gamepad", "", "gamepad mode: the mapping file (YAML: deadman, mode, point, axes, deadzone, success, "
          "failure; empty: an Xbox pad, as config/gamepad_xbox.yaml)", read_only=True, flag="--gamepad"),
    Param("patience", 8, "k: states without progress before taking over", low=1, flag="--patience"),
    Param("grace_steps", 20, "states at an episode's start before progress is judged", low=0, flag="--grace-steps"),
    Param("hold_steps", 25, "m: steps of a takeover before handing back", low=1, flag="--hold-steps"),
    Param("min_progress", 0.002, "metres the distance must shrink to count as progress", low=0.0,
          flag="--min-progress"),
    Param("noise", 0.0, "std of Gaussian noise on the corrections' torques (a shaky hand)", low=0.0, flag="--noise"),
    Param("reaction_delay", 0, "states between deciding to take over and acting", low=0, flag="--reaction-delay"),
    Param("seed", 0, "seed of the correction noise", low=0, read_only=True, flag="--seed"),
    Param("action_labels", False, "scripted: also publish, on every state it leaves to the policy, the action it "
          f"would take on {ACTION_LABEL_TOPIC} (DAgger's labels, for a learner with action_labels); the arm "
          "never reads them", read_only=True, flag="--action-labels"),
    Param("wait_for_readers", [], "with action_labels: hold the first answer until these nodes (names, e.g. "
          f"[learner, recorder]) read {ACTION_LABEL_TOPIC} (a label sent before a reader is matched never reaches "
          "it; a lockstep arm waits for the answer)", read_only=True),
    Param("steer", "expert", "how a takeover moves the arm: expert (the task's scripted expert) or stick (the "
          "fingertip steered straight at the goal, as with a Cartesian stick; reach tasks)", choices=STEERS,
          read_only=True, flag="--steer"),
)
RULE_PARAMS = tuple(p.name for p in PARAMS
                    if p.name not in ("mode", "task", "gamepad", "action_labels", "wait_for_readers"))


class Corrector(Node):
    def __init__(self, overrides=()):
        super().__init__("corrector", parameter_overrides=list(overrides))
        self.settings = Settings(self, PARAMS, on_change=self.on_parameter_change, check=self.check_parameter)
        self.mode = self.settings.mode
        self.finished = Future()  # done when the person quits (keyboard mode)
        values = {name: getattr(self.settings, name) for name in RULE_PARAMS}
        task = self.task = load_task(self.settings.task or None)  # UserError: one line naming the task
        self.builder = ObservationBuilder(task, kinematics_model(task))
        if self.mode == "scripted":
            # the in-process stage's corrector (ScriptedCorrector.for_task), fed with the tracked
            # points this node hears (a puck from its tracker) and computes (the fingertip)
            try:  # UserError: no expert for the task, or a stick for a task that is no reach
                self.teleop = ScriptedCorrector.for_task(task, CorrectorParams(**values))
            except ValueError as exc:
                raise UserError(str(exc)) from None
        elif self.mode == "gamepad":
            self.teleop = GamepadTeleop.for_task(load_mapping(self.settings.gamepad), task)
        else:
            if task.act_dim != 2:
                raise UserError(f"--mode keyboard drives a two-joint arm; task {task.name} has {task.act_dim} "
                                "command joints")
            self.teleop = KeyboardTeleop(task.act_dim)
            self.create_timer(0.1, self.check_keys, clock=Clock(clock_type=ClockType.STEADY_TIME))
        # points with a topic are paired with their state (those without kinematics waited for)
        self.pairing = StatePairing(points=tuple(self.builder.point_topics), required=self.builder.topic_only)
        self.answers: dict[int, JointState] = {}
        self.states = 0
        self.corrections = 0
        self.correcting = False  # the last state decided was answered with a correction
        goal_type = {JOINT_STATE: JointState, POSE_STAMPED: PoseStamped}.get(task.goal.type, PointStamped)
        self.create_subscription(goal_type, task.goal.topic, self.on_goal, 10)
        for name, point in self.builder.point_topics.items():
            self.create_subscription(PoseStamped if point.type == POSE_STAMPED else PointStamped, point.topic,
                                     lambda msg, name=name: self.on_point(name, msg), 10)
        state_sub = self.create_subscription(JointState, task.state.topic, self.on_state, 10)
        self.pub = self.create_publisher(JointState, "teleop/action", 10)
        # DAgger's labels: the action it would take on each state it leaves to the policy
        self.action_labels = self.mode == "scripted" and self.settings.action_labels
        self.action_label_pub = self.create_publisher(JointState, ACTION_LABEL_TOPIC, 10) \
            if self.action_labels else None
        self.labelled = 0
        # the first answer waits until the labels' readers can hear them (pusher_common.readers)
        self.labels_gate = ReadersGate(self, self.settings.wait_for_readers if self.action_labels else ())
        self.held: Paired | None = None  # the state whose answer waits for the gate
        self.gate_timer = self.create_timer(READERS_CHECK_PERIOD_S, self.answer_held, clock=Clock(
            clock_type=ClockType.STEADY_TIME)) if self.labels_gate.waiting else None
        self.rejected = RejectionCounter()
        if self.mode == "gamepad":
            self.create_subscription(Joy, "joy", self.on_joy, 10)
        if self.mode in ("gamepad", "keyboard"):  # a person labels episodes
            self.label_pub = self.create_publisher(String, LABEL_TOPIC, 10)
        self.diagnostics = NodeDiagnostics(self, self.status, StatusDiagnosis(idle=lambda st: (
            f"{st['mode']}: {'taking over' if st['correcting'] else 'watching'}")), hardware_id=task.name)
        rule = ", ".join(f"{k}={v}" for k, v in values.items())
        desc = {"scripted": f"scripted ({rule})", "keyboard": "keyboard",
                "gamepad": f"gamepad ({self.teleop.mapping.source if self.mode == 'gamepad' else ''})"}[self.mode]
        self.get_logger().info(f"corrector {desc} of task {task.name}: answering {state_sub.topic_name} on "
                               f"{self.pub.topic_name}")

    def status(self) -> dict:
        out = {"mode": self.mode, "states": self.states, "corrections": self.corrections,
               "correcting": self.correcting}
        if self.mode == "scripted":
            out["takeovers"] = self.teleop.takeovers
        if self.action_labels:
            out["action_labels"] = self.labelled
        if self.mode == "gamepad":
            out["deadman_held"] = self.teleop.active
            out["rejected"] = dict(self.rejected.counts)
        if self.mode in ("gamepad", "keyboard"):
            out["labels"] = dict(self.teleop.labels_sent)
            out["label_readers"] = self.label_pub.get_subscription_count()  # the sim and a recorder, when heard
        return out

    def on_joy(self, msg: Joy) -> None:
        events, problem = self.teleop.on_joy(msg.axes, msg.buttons)
        if problem:
            self.rejected.add(problem)
            line = self.rejected.warning("joy", problem)
            if line is not None:
                self.get_logger().warning(line)
            return
        for label in events.labels:
            self.publish_label(label)

    def publish_label(self, label: str) -> None:
        self.label_pub.publish(String(data=label_json(label)))
        self.get_logger().info(f"episode labelled {label}")

    def check_parameter(self, name: str, value) -> str | None:
        if self.mode != "scripted":
            return f"{name} belongs to the scripted corrector; this one is a {self.mode}"
        try:
            replace(self.teleop.p, **{name: value})  # the rule's own validation
        except ValueError as exc:
            return str(exc)
        return None

    def on_parameter_change(self, name: str, value) -> None:
        self.teleop.p = replace(self.teleop.p, **{name: value})  # from the next state on

    def check_keys(self) -> None:
        for label in self.teleop.take_labels():  # pressed on the key thread, published on this one
            self.publish_label(label)
        if self.teleop.quit.is_set() and not self.finished.done():
            self.finished.set_result(True)

    def on_goal(self, msg) -> None:
        if self.builder.joint_goal:
            goal, problem = self.builder.goal_from_joints(msg.name, msg.position)
        else:
            p = msg.pose.position if isinstance(msg, PoseStamped) else msg.point
            goal, problem = self.builder.goal_from_point(p.x, p.y, p.z)
        if problem is None:
            self.answer(self.pairing.on_goal(stamp_key(msg.header.stamp), goal))

    def on_point(self, name: str, msg) -> None:
        p = msg.pose.position if isinstance(msg, PoseStamped) else msg.point
        value, problem = self.builder.point(name, p.x, p.y, p.z)
        if problem is None:
            self.answer(self.pairing.on_point(name, stamp_key(msg.header.stamp), value))

    def on_state(self, msg: JointState) -> None:
        self.answer(self.pairing.on_state(stamp_key(msg.header.stamp), msg))

    def answer_held(self) -> None:
        """Answer the state held for the labels' readers, once they read the labels (its timer)."""
        if not self.labels_gate.open([self.action_label_pub]):
            return
        self.gate_timer.cancel()
        self.get_logger().info(f"the readers of {self.action_label_pub.topic_name} are matched: answering")
        held, self.held = self.held, None
        self.answer(held)

    def answer(self, paired: Paired | None) -> None:
        if paired is None:
            return
        if self.labels_gate.waiting:
            self.held = paired  # the newest state: the arm waits for its answer
            return
        msg, stamp = paired.state, paired.stamp
        out = self.answers.get(stamp)
        if out is None:  # a new state: decide once
            joints, _ = self.builder.state(msg.name, msg.position, msg.velocity)
            if joints is None:
                return
            if self.mode == "scripted":  # every tracked point, heard or from kinematics
                points = {k: v for k, v in self.builder.vectors(joints[0], paired.goal, paired.points).items()
                          if k != "goal"}
                action = self.teleop.decide(joints[0], joints[1], paired.goal, points)
                if action is None and self.action_labels:  # sent before the answer that lets the arm move
                    label = JointState(name=list(self.task.command.joints))
                    label.header.stamp = msg.header.stamp
                    label.effort = [float(a) for a in self.teleop.label(joints[0], joints[1], points)]
                    self.action_label_pub.publish(label)
                    self.labelled += 1
            else:
                action = self.teleop.decide(joints[0], joints[1], paired.goal)
            self.states += 1
            self.correcting = action is not None
            out = JointState(name=list(self.task.command.joints))
            if action is not None:
                out.effort = [float(a) for a in action]
                self.corrections += 1
            out.header.stamp = msg.header.stamp
            self.answers[stamp] = out
            if len(self.answers) > KEEP_ANSWERS:
                for key in sorted(self.answers)[:-KEEP_ANSWERS // 2]:
                    del self.answers[key]
        self.pub.publish(out)  # a republished state gets the same answer again

    def close(self) -> None:
        if isinstance(self.teleop, KeyboardTeleop):
            self.teleop.restore()
        extra = f", {self.teleop.takeovers} takeovers" if self.mode == "scripted" else ""
        print(f"corrector: answered {self.states} states, {self.corrections} with a correction{extra}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    return run_node(Corrector, prog="corrector", command="ros2 run corrections corrector", flags=PARAMS, argv=argv,
                    description="Take over from the policy on teleop/action: scripted expert or keyboard.")


if __name__ == "__main__":
    sys.exit(main())
