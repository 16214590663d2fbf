"""``ros2 run policy node --checkpoint PATH``: serve a trained policy over topics, on any task's arm.

The task (``-p task:=NAME_OR_FILE``, default: the one the checkpoint records; a checkpoint
that records none is pusher_reach's) says what is heard and what is sent
(``offline_rl_core.task.spec``): every state on its ``robot.state.topic`` (JointState: the
task's joints picked out by name, in any order, other joints ignored), with its goal
(``goal.topic``: PointStamped, PoseStamped or a JointState goal) and the tracked points
that have a topic (forward kinematics of those not heard: ``offline_rl_core.task.kinematics``),
is answered on ``policy/action``: a JointState of the command joints whose effort is the
action in [-1, 1], stamped with the state's stamp; and (``publish_command``) on the
controller's ``robot.command.topic``, as the controller takes it: ``offset + scale *
action`` per joint in the controller's joint order, a std_msgs/Float64MultiArray as a
ros2_control forward_command_controller takes it (or a JointState command where the
task says so). pusher_reach: ``pusher/state`` + ``pusher/target`` + ``pusher/fingertip`` in,
``effort_controller/commands`` in N·m (the action times the motors' 0.5 N·m gear) out.
A task given that is not the checkpoint's is refused at start in one line naming both
layouts (exit 2); so is, at run time, a checkpoint or weights version of another task.

A malformed, non-finite or out-of-order state (``offline_rl_core.nodes.observation``,
``offline_rl_core.nodes.pairing``), goal, point or weights message gets no action: it is
counted by reason on ``~/status`` (``pusher_common.status``) with a throttled warning.
The checkpoint (``--checkpoint`` or ``-p checkpoint:=``)
is polled every ``poll_period`` seconds and hot-swapped when it changes; a file that
fails to load leaves the previous policy serving, with an error logged. A missing or
broken checkpoint at start is one error line and exit status 2.

State, goal and points are paired by stamp as ``offline_rl_core.nodes.pairing`` says.

The actor of the HIL-SERL stage (``offline_rl_core.serving.actor``): with ``weights_topic`` set
(``learner/weights``) it also takes each new weights version the online learner
publishes, signed with the session's key (``weights_key``: the learner's public key; see
``offline_rl_core.serving.weights``: anything else on the topic is refused and counted); it
acts deterministically unless ``explore`` is set, then it samples the
learner's Gaussian from its own ``seed``; with ``paced_every`` (the learner's
``publish_every``) state n waits for weights version n // paced_every, so a lockstep sim
cannot outrun the learner. Every answer is also reported on ``policy/provenance``
(std_msgs/String, JSON: stamp, weights_version, trained_through, weights_age_s: seconds
since the learner cut them, explore), so a bag says which weights acted.

Where no simulator says whether the episode succeeded, ``end_on_success`` (a success
classifier file, ``offline-rl classifier train``) ends it as HIL-SERL's reward classifier
does: each state the classifier judges a success is labelled one on ``episode_label``
(``{"label": "success", "source": "classifier"}``) before the answer, and the sim (or a
robot's reset routine) ends the episode at its next step (``offline_rl_core.data.episode_labels``).

Safety: a forward controller holds its last command for ever, so in ``mode`` realtime (the
default) the node that drives it watches itself (``offline_rl_core.nodes.watchdog``): when
it sent the controller no command within the task's ``safety.command_timeout`` (its states
stopped, or it stalls), it sends the task's safe command once (zero effort or velocity; the
last state's position held) and latches the fault on ``~/status``. In ``mode`` lockstep the
sim waits for each answer, so a silence is no fault. While the e-stop is engaged (``estop``,
released only by ``estop/reset``) it answers no state (counted as ``estop``) and, in
realtime, the controller gets the safe command.

Checkpoint files and weights messages are read, checked and decoded on a worker thread
(``offline_rl_core.nodes.background_loads``), never on the thread that answers states;
a ``checkpoint`` that is not a regular file (a FIFO, a terminal) is refused.
"""

from __future__ import annotations

import json
import os
import sys
import time

# One observation per call: BLAS threads only add hand-off latency (set before numpy loads).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from geometry_msgs.msg import PointStamped, PoseStamped  # noqa: E402
from rclpy.clock import Clock, ClockType  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from rclpy.serialization import deserialize_message  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402
from std_msgs.msg import Float64MultiArray, String, UInt8MultiArray  # noqa: E402

from offline_rl_core.serving.actor import Actor  # noqa: E402
from offline_rl_core.common.errors import UserError  # noqa: E402
from offline_rl_core.nodes.background_loads import BackgroundLoads  # noqa: E402
from offline_rl_core.nodes.command_limits import action_bounds, within_limits  # noqa: E402
from offline_rl_core.nodes.joint_messages import command_from_action  # noqa: E402
from offline_rl_core.nodes.watchdog import CommandWatchdog, safe_action  # noqa: E402
from offline_rl_core.nodes.observation import ObservationBuilder, kinematics_model  # noqa: E402
from offline_rl_core.nodes.pairing import Paired, StatePairing, check_stamp  # noqa: E402
from offline_rl_core.serving.checkpoint import checkpoint_file, checkpoint_task, regular_file_problem  # noqa: E402
from offline_rl_core.serving.policy import LoadedPolicy, load_policy, policy_for_task  # noqa: E402
from offline_rl_core.serving.signing import load_verifier  # noqa: E402
from offline_rl_core.serving.weights import MAX_MESSAGE_BYTES, policy_from_weights_message  # noqa: E402
from offline_rl_core.task.spec import JOINT_STATE, POSE_STAMPED, load_task  # noqa: E402
from offline_rl_core.common.rejections import Rejection  # noqa: E402
from pusher_common.estop import EStopInput  # noqa: E402
from pusher_common.node_main import run_node  # noqa: E402
from pusher_common.params import Param, Settings  # noqa: E402
from pusher_common.scheduling import THREAD_PRIORITY, apply_thread_priority  # noqa: E402
from pusher_common.stamps import stamp_key  # noqa: E402
from pusher_common.status import NodeStatus  # noqa: E402
from offline_rl_core.nodes.diagnostics import StatusDiagnosis, policy_checks  # noqa: E402

WARN_THROTTLE_S = 2.0
PACED_QUEUE_DEPTH = 10_000
# The learner publishes reliable and transient local: a late joiner gets the latest version.
# Several may wait to be read (a burst, or bad messages among good ones): read in order, the
# newest good one acts, and none is overwritten unread.
WEIGHTS_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def file_signature(path: str):
    """Return what changes when a checkpoint is rewritten (also by an atomic rename)."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_mtime_ns, st.st_size, st.st_ino)


PARAMS = (
    Param("checkpoint", "", "policy checkpoint to serve (policy.pt, or a run directory holding one); "
          "watched and reloaded when replaced; setting it switches to another checkpoint", flag="--checkpoint"),
    Param("task", "", "the task served: a built-in task or a task file, which must be the checkpoint's (empty: "
          "the one the checkpoint records; pusher_reach where it records none)", read_only=True, flag="--task"),
    Param("poll_period", 0.5, "seconds between checks of the checkpoint file for a new version", low=0.01, high=60.0),
    Param("publish_command", True, "also publish each action as the task's controller takes it (offset + scale x "
          "action, in the controller's joint order) on its robot.command.topic (pusher_reach: joint torques in N·m "
          "on effort_controller/commands); remap the topic with -r", read_only=True),
    Param("weights_topic", "", "also act on the weights versions the online learner publishes on this topic "
          "(std_msgs/UInt8MultiArray, e.g. learner/weights; empty: off)", read_only=True, flag="--weights-topic"),
    Param("weights_key", "", "the session learner's public key file (weights.pub, from offline-rl weights-key): "
          "weights on weights_topic are taken only when signed with its private key (required with "
          "weights_topic)", read_only=True, flag="--weights-key"),
    Param("explore", False, "sample exploration actions from the policy's Gaussian (the online learner's std) "
          "instead of acting deterministically", flag="--explore"),
    Param("seed", 0, "seed of the exploration noise", low=0, read_only=True, flag="--seed"),
    Param("mode", "realtime", "as the sim's: realtime (a controller driven by this node gets the task's safe command "
          "when this node sent it nothing within the task's command timeout) or lockstep (the sim waits for each "
          "answer: no watchdog)", choices=("realtime", "lockstep"), read_only=True),
    Param("paced_every", 0, "answer state n only with weights version n // paced_every or newer (the learner's "
          "publish_every; 0: never wait)", low=0, read_only=True, flag="--paced-every"),
    Param("end_on_success", "", "a success classifier file (offline-rl classifier train): every state it judges a "
          "success is labelled one on episode_label ({\"label\": \"success\", \"source\": \"classifier\"}), so "
          "the arm's episode ends at its next step where no simulator judges it (HIL-SERL's success classifier); "
          "empty: off", read_only=True, flag="--end-on-success"),
    THREAD_PRIORITY,
)


class PolicyServer(Node):
    def __init__(self, overrides=()):
        super().__init__("policy", parameter_overrides=list(overrides))
        self.settings = Settings(self, PARAMS, on_change=self.on_parameter_change, check=self.check_parameter)
        apply_thread_priority(self.settings.thread_priority, self.get_logger())
        self.poll_period = self.settings.poll_period
        if not self.settings.checkpoint:
            raise UserError("no checkpoint given: pass --checkpoint PATH or -p checkpoint:=PATH")
        self.path = str(checkpoint_file(self.settings.checkpoint))
        self.signature = file_signature(self.path)
        self.verifier = None
        if self.settings.weights_topic:
            if not self.settings.weights_key:
                raise UserError("weights_topic needs weights_key: the session learner's public key file (weights.pub)")
            self.verifier = load_verifier(self.settings.weights_key)
        policy = load_policy(self.path)  # UserError with one clear line if missing/broken
        # the task given must be the checkpoint's (one line naming both layouts otherwise)
        self.task = load_task(self.settings.task) if self.settings.task else checkpoint_task(policy.checkpoint)
        policy = policy_for_task(policy.checkpoint, self.path, self.task)
        self.actor = Actor(policy, explore=self.settings.explore, seed=self.settings.seed,
                           paced_every=self.settings.paced_every)
        self.reverting = None  # the checkpoint parameter being set back after a failed switch
        self.builder = ObservationBuilder(self.task, kinematics_model(self.task))
        self.pairing = StatePairing(points=tuple(self.builder.point_topics), required=self.builder.topic_only)
        self.held: Paired | None = None  # a state waiting for the weights version it needs
        self.answered = 0
        self.labelled = 0  # states the end_on_success classifier labelled a success
        # what the worker loaded is taken on this thread, woken by the guard condition
        self.loads_ready = self.create_guard_condition(self.on_loaded)
        self.loads = BackgroundLoads(self.loads_ready.trigger, max_pending=WEIGHTS_QOS.depth, name="policy-loads")
        self.watchdog = CommandWatchdog(self.task.command_timeout)
        # the task's joint limits as an action range: every answer (exploring too) stays inside
        self.bounds = action_bounds(self.task) if self.task.safety.position_limits or \
            self.task.safety.velocity_limits else None
        self.position = None  # the latest state's joint positions (a safe command that holds them)
        self.status = NodeStatus(self, fields=lambda: {"answered": self.answered, "labelled_success": self.labelled,
                                                       "weights_version": self.policy.weights_version,
                                                       "weights_age_s": self.weights_age_s(),
                                                       "loads_dropped": dict(self.loads.dropped),
                                                       "faults": self.faults(),
                                                       "estop": self.estop.latch.as_dict()},
                                 diagnosis=StatusDiagnosis(checks=(policy_checks,), idle=serving_message),
                                 hardware_id=self.task.name)
        self.estop = EStopInput(self, on_engage=self.on_estop_engaged, on_reset=self.watchdog.reset)

        # Goal subscription first: when both are ready the executor takes it first.
        # Paced, every state counts (it indexes the pacing and the exploration noise), and
        # while a person holds the arm the sim runs ahead of this node: keep them all.
        depth = PACED_QUEUE_DEPTH if self.settings.paced_every else 10
        task = self.task
        goal_type = {JOINT_STATE: JointState, POSE_STAMPED: PoseStamped}.get(task.goal.type, PointStamped)
        self.create_subscription(goal_type, task.goal.topic, self.on_goal, depth)
        for name, point in self.builder.point_topics.items():
            self.create_subscription(PoseStamped if point.type == POSE_STAMPED else PointStamped, point.topic,
                                     lambda msg, name=name: self.on_point(name, msg), depth)
        self.create_subscription(JointState, task.state.topic, self.on_state, depth)
        self.action_pub = self.create_publisher(JointState, "policy/action", 10)
        self.provenance_pub = self.create_publisher(String, "policy/provenance", 10)
        if self.settings.weights_topic:  # raw: its size is checked before anything is decoded
            self.create_subscription(UInt8MultiArray, self.settings.weights_topic, self.on_weights, WEIGHTS_QOS,
                                     raw=True)
        # the classifier that ends episodes: it judges the observation the policy acts on
        self.judge = self.label_pub = None
        if self.settings.end_on_success:  # imported here: a node that only serves stays clear of the training layers
            from offline_rl_core.data.episode_labels import LABEL_TOPIC, label_json
            from offline_rl_core.learners.success_classifier import load_classifier

            self.judge = load_classifier(self.settings.end_on_success, task)
            self.label_pub = self.create_publisher(String, LABEL_TOPIC, 10)
            self.success_label = String(data=label_json(True, source="classifier"))
        self.command_joint_state = task.command.type == JOINT_STATE
        self.command_pub = self.create_publisher(JointState if self.command_joint_state else Float64MultiArray,
                                                 task.command.topic, 10) if self.settings.publish_command else None
        self.commanded_stamp: int | None = None  # the state last answered on the controller's topic
        # Watching a file is wall-clock work, also under use_sim_time.
        self.poll_timer = self.create_timer(self.poll_period, self.check_checkpoint,
                                            clock=Clock(clock_type=ClockType.STEADY_TIME))
        if self.command_pub is not None and self.settings.mode == "realtime":
            self.create_timer(task.control_period, self.check_watchdog, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(f"serving {self.policy.algorithm} policy from {self.path} on task {task.name} "
                               f"({task.source_file()}): {task.state.topic} + {task.goal.topic} -> policy/action"
                               + (f" + {self.command_pub.topic_name}" if self.command_pub is not None else "")
                               + (f"; points {', '.join(self.builder.topic_only)} only from their topics"
                                  if self.builder.topic_only else "")
                               + (f"; {self.settings.end_on_success} ends an episode it judges a success (on "
                                  f"{self.label_pub.topic_name})" if self.judge is not None else ""))

    @property
    def policy(self) -> LoadedPolicy:
        return self.actor.policy

    # -------------------------------------------------------------- parameters
    def check_parameter(self, name: str, value) -> str | None:
        """Refuse a new checkpoint that is not a regular file (the load itself runs on the worker)."""
        if name != "checkpoint":
            return None
        return regular_file_problem(checkpoint_file(value))

    def on_parameter_change(self, name: str, value) -> None:
        if name == "explore":
            self.actor.explore = bool(value)
        elif name == "poll_period":
            self.poll_timer.timer_period_ns = int(value * 1e9)
        elif name == "checkpoint" and value != self.reverting:
            self.load_checkpoint(str(checkpoint_file(value)), switch=True)

    # -------------------------------------------------------------- checkpoint
    def check_checkpoint(self) -> None:
        signature = file_signature(self.path)
        if signature == self.signature:
            return
        self.signature = signature
        if signature is None:
            self.get_logger().warning(f"{self.path} disappeared; still serving the loaded policy")
            return
        self.load_checkpoint(self.path, switch=False)

    def load_checkpoint(self, path: str, switch: bool) -> None:
        """Load ``path`` on the worker; ``on_loaded`` takes it (``switch``: serve from it from now on)."""
        task = self.task

        def job():
            signature = file_signature(path)
            try:
                return "checkpoint", path, signature, switch, load_policy(path, task)  # another task's: refused
            except Exception as exc:  # noqa: BLE001 - whatever is wrong with the file, keep serving
                return "checkpoint", path, signature, switch, exc
        self.loads.submit("checkpoint", job)

    def on_weights(self, raw: bytes) -> None:
        topic = self.settings.weights_topic
        self.status.took(topic)
        if len(raw) > MAX_MESSAGE_BYTES + 1024:  # the CDR framing around the bytes is a few dozen bytes
            self.status.reject(topic, Rejection("bad weights", f"{len(raw)} bytes, more than weights may hold"))
            return
        verifier, task = self.verifier, self.task

        def job():
            msg = deserialize_message(raw, UInt8MultiArray)
            label = msg.layout.dim[0].label if msg.layout.dim else ""
            return ("weights", *policy_from_weights_message(label, msg.data, verifier, topic, task))
        self.loads.submit("weights", job)

    def on_loaded(self) -> None:
        """Take what the worker finished: weights to act on, checkpoints to serve (swapped on this thread)."""
        for result in self.loads.drain():
            if isinstance(result, Exception):  # a bug in a job, not in the input: said, and serving goes on
                self.get_logger().error(f"loading failed: {type(result).__name__}: {result}")
            elif result[0] == "weights":
                self.take_weights(*result[1:])
            else:
                self.take_checkpoint(*result[1:])

    def take_weights(self, policy: LoadedPolicy | None, problem: Rejection | None) -> None:
        topic = self.settings.weights_topic
        if problem is None:
            taken, problem = self.actor.offer_weights(policy)
        if problem:  # whatever is wrong with the message, the held policy serves on
            self.status.reject(topic, problem)
            return
        if taken:
            self.get_logger().info(f"acting on weights version {policy.weights_version}",
                                   throttle_duration_sec=WARN_THROTTLE_S)
            held, self.held = self.held, None
            self.answer(held)

    def take_checkpoint(self, path: str, signature, switch: bool, policy) -> None:
        if not switch and path != self.path:
            return  # a reload of the file served before a switch
        if isinstance(policy, Exception):
            self.status.rejections.add(Rejection("bad checkpoint", str(policy)))
            self.get_logger().error(f"cannot {'load' if switch else 'reload'} {path}, still serving "
                                    f"{self.path}: {policy}")
            if switch:  # the parameter says again what serves
                self.reverting = self.path
                self.set_parameters([Parameter("checkpoint", value=self.path)])
                self.reverting = None
            return
        if switch:
            self.path, self.signature = path, signature
        self.actor.offer(policy)  # one reference swap: a callback sees the old or the new policy
        self.get_logger().info(f"serving {policy.algorithm} policy from {path}" if switch else
                               f"reloaded {path} ({policy.algorithm})")

    def close(self) -> None:
        self.loads.stop()  # before the guard condition it triggers goes with the node

    # -------------------------------------------------------------- serving
    def on_goal(self, msg) -> None:
        topic = self.task.goal.topic
        self.status.took(topic)
        if self.builder.joint_goal:
            value, problem = self.builder.goal_from_joints(msg.name, msg.position)
        else:
            p = msg.pose.position if isinstance(msg, PoseStamped) else msg.point
            value, problem = self.builder.goal_from_point(p.x, p.y, p.z)
        self.pair(msg, topic, problem, lambda stamp: self.pairing.on_goal(stamp, value))

    def on_point(self, name: str, msg) -> None:
        topic = self.builder.point_topics[name].topic
        self.status.took(topic)
        p = msg.pose.position if isinstance(msg, PoseStamped) else msg.point
        value, problem = self.builder.point(name, p.x, p.y, p.z)
        self.pair(msg, topic, problem, lambda stamp: self.pairing.on_point(name, stamp, value))

    def pair(self, msg, topic: str, problem, pair) -> None:
        problem = check_stamp(msg.header.stamp.sec, msg.header.stamp.nanosec) or problem
        if problem:
            self.status.reject(topic, problem)
            return
        self.answer(pair(stamp_key(msg.header.stamp)))

    def on_state(self, msg: JointState) -> None:
        topic = self.task.state.topic
        self.status.took(topic)
        joints, problem = self.builder.state(msg.name, msg.position, msg.velocity)
        problem = check_stamp(msg.header.stamp.sec, msg.header.stamp.nanosec) or problem
        stamp = stamp_key(msg.header.stamp)
        problem = problem or self.pairing.admit(stamp)  # stale and future stamps: only for a sound state
        if problem:
            self.status.reject(topic, problem)
            return
        self.actor.see(stamp)  # every state of the session counts, answered or not
        self.position = joints[0]
        self.answer(self.pairing.on_state(stamp, (msg.header.stamp, joints)))

    def answer(self, paired: Paired | None) -> None:
        if paired is None:
            return
        if self.estop.engaged:  # the controller holds the safe command; nothing is answered
            self.status.reject(self.task.state.topic, Rejection("estop", "a state while the e-stop is engaged: "
                                                                         "not answered"))
            return
        if not self.actor.ready():
            self.held = paired  # answered when the weights version it needs arrives
            return
        header_stamp, (position, velocity) = paired.state
        obs = self.builder.observe(position, velocity, paired.goal, paired.points)
        action, problem = self.actor.answer(obs, paired.stamp)
        if problem:
            self.status.reject(self.task.state.topic, problem)
            return
        if self.judge is not None and bool(self.judge.success(obs[None])[0]):
            # before the answer: the step it lets the arm take is then the episode's last (a
            # label without an episode is of the episode of the arm's last transition)
            self.label_pub.publish(self.success_label)
            self.labelled += 1
        if self.bounds is not None:
            action = within_limits(self.task, action, self.bounds)
        joints = list(self.task.command.joints)
        out = JointState(name=joints, effort=[float(a) for a in action])
        out.header.stamp = header_stamp
        self.action_pub.publish(out)
        if self.provenance_pub.get_subscription_count():  # formatting it costs the answer's latency
            self.publish_provenance(paired.stamp)
        # A command without a header goes once per state: a lockstep arm cannot tell the
        # answer to a republished state from the answer to its next one, and would step twice
        once = self.command_joint_state or paired.stamp != self.commanded_stamp
        if self.command_pub is not None and self.command_pub.get_subscription_count() and once:
            self.publish_command(command_from_action(self.task.command, action), header_stamp)
            self.commanded_stamp = paired.stamp
            self.watchdog.fed(time.monotonic())
        self.answered += 1

    # -------------------------------------------------------------- safety
    def check_watchdog(self) -> None:
        silent_before = self.watchdog.silent
        if self.watchdog.check(time.monotonic()) and not silent_before:
            self.get_logger().error(f"sent the controller nothing for {self.watchdog.timeout_s * 1000:.0f} ms: "
                                    f"sending the safe command ({self.task.safe_command})", throttle_duration_sec=2.0)
            self.send_safe()

    def on_estop_engaged(self) -> None:
        self.watchdog.disarm()
        self.send_safe()

    def send_safe(self) -> None:
        """Send the controller the task's safe command (once: a forward controller holds it).

        Not in lockstep: the sim steps only on an answer, so answering nothing stops the arm.
        """
        action = safe_action(self.task, self.position)
        if self.settings.mode != "realtime" or self.command_pub is None or action is None or \
                not self.command_pub.get_subscription_count():
            return
        self.publish_command(command_from_action(self.task.command, action), self.get_clock().now().to_msg())

    def faults(self) -> dict:
        fault = self.watchdog.fault()
        return {"watchdog": fault} if fault else {}

    def publish_command(self, values, header_stamp) -> None:
        """Publish the action as the controller takes it, in the controller's joint order."""
        data = [float(v) for v in values]
        if not self.command_joint_state:
            self.command_pub.publish(Float64MultiArray(data=data))
            return
        command = JointState(name=list(self.task.command.joints))
        setattr(command, self.task.command.interface, data)  # the interface's field: effort, velocity or position
        command.header.stamp = header_stamp
        self.command_pub.publish(command)

    def weights_age_s(self) -> float | None:
        """Seconds since the learner cut the weights acting (None for a checkpoint file's)."""
        cut = self.policy.checkpoint.get("cut_unix")  # when the learner cut these weights (same machine clock)
        return None if cut is None else round(time.time() - float(cut), 4)

    def publish_provenance(self, stamp: int) -> None:
        self.provenance_pub.publish(String(data=json.dumps({
            "stamp": stamp, "weights_version": self.policy.weights_version,
            "trained_through": int(self.policy.checkpoint.get("trained_through", 0) or 0),
            "weights_age_s": self.weights_age_s(),
            "explore": self.actor.explore})))


def serving_message(status: dict) -> str:
    return f"serving weights version {status['weights_version']}, {status['answered']} states answered"


def main(argv: list[str] | None = None) -> int:
    return run_node(PolicyServer, prog="policy", flags=PARAMS, argv=argv,
                    description="Serve a trained policy on policy/action.")


if __name__ == "__main__":
    sys.exit(main())
