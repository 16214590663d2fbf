"""A robot this project never modelled: an N-joint velocity-controlled arm, in numpy.

Each joint follows the velocity it is commanded (q' = v, held until the next command, as
ros2_control's forward_command_controller holds it), within its velocity and position
limits. Its driver publishes ``joint_states`` at 100 Hz (sensor_msgs/JointState, names in
the broadcaster's own order, a gripper joint besides) and takes
``velocity_controller/commands`` (std_msgs/Float64MultiArray, no header, in the
controller's ``joints`` order); each episode's goal (a joint-space goal) comes once, on
``goal_joints`` (JointState). The controller runs at 50 Hz and its command reaches the arm
a couple of milliseconds after the state it answers.

``record_bag`` writes what ``ros2 bag record`` leaves of such a session (stamps are the
recorder's receive times: the command has no header), with the arm's own steps for
checking the join; ``task_yaml`` is the task file a user would write for it; ``rollouts``
runs a policy in closed loop on held-out resets; ``ArmNode`` is the same arm as an rclpy
node, for driving it over ROS.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PHYSICS_NS = 10_000_000  # the driver's 100 Hz
CONTROL_NS = 20_000_000  # the controller's 50 Hz
COMMAND_LATENCY_NS = 2_000_000  # a command acts this long after the state it answers
START_NS = 1_767_225_600 * 10**9  # 2026-01-01
V_MAX = 2.0  # rad/s: the action's scale
Q_LIMIT = 2.5  # rad, each joint
MAX_STEPS = 60
SUCCESS_WITHIN = 0.15
EXPERT_GAIN = 4.0  # 1/s: the expert's P-controller
EXPERT_NOISE = 0.1
HELD_OUT_SEED = 1_000_000


def joint_names(n: int) -> list[str]:
    return [f"joint_{i + 1}" for i in range(n)]


def task_yaml(n: int, name: str | None = None) -> str:
    """The task file for an n-joint arm: only what a user knows of the robot."""
    joints = ", ".join(joint_names(n))
    controller = ", ".join(reversed(joint_names(n)))  # the controller's own order
    return f"""\
name: {name or f"velocity_arm_{n}"}
description: a {n}-joint velocity-controlled arm reaching joint-space goals
control_period: 0.02
robot:
  state: {{topic: joint_states, joints: [{joints}]}}
  command:
    interface: velocity
    controller: velocity_controller
    joints: [{controller}]
    limits: [{", ".join([f"[-{V_MAX}, {V_MAX}]"] * n)}]
goal: {{topic: goal_joints, type: sensor_msgs/JointState}}
observation:
  - positions: [{joints}]
  - velocities: [{joints}]
  - difference: [goal, joints]
reward: {{distance: [goal, joints], success_within: {SUCCESS_WITHIN}, success_bonus: 1.0}}
episodes: {{max_steps: {MAX_STEPS}}}
join: {{stamps: receive}}
"""


class Arm:
    """B arms of n joints at once: positions and velocities (in ``joint_names`` order)."""

    def __init__(self, n: int, batch: int = 1):
        self.n = n
        self.q = np.zeros((batch, n))
        self.v = np.zeros((batch, n))  # the velocity held

    def reset(self, q0: np.ndarray) -> None:
        self.q = np.array(q0, dtype=np.float64).reshape(self.q.shape)
        self.v = np.zeros_like(self.q)

    def command(self, action: np.ndarray) -> None:
        """An action in [-1, 1] per joint (``joint_names`` order): velocity = V_MAX * action."""
        self.v = V_MAX * np.clip(np.asarray(action, np.float64).reshape(self.q.shape), -1.0, 1.0)

    def advance(self, ns: int) -> None:
        self.q = np.clip(self.q + self.v * (ns * 1e-9), -Q_LIMIT, Q_LIMIT)

    @property
    def velocity(self) -> np.ndarray:
        """What the driver reports: the held velocity, zero where a limit stops the joint."""
        stopped = ((self.q >= Q_LIMIT) & (self.v > 0)) | ((self.q <= -Q_LIMIT) & (self.v < 0))
        return np.where(stopped, 0.0, self.v)


def sample_reset(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng([seed, n])
    return rng.uniform(-1.0, 1.0, n), rng.uniform(-1.0, 1.0, n)


def expert_action(q, goal, rng) -> np.ndarray:
    action = np.clip(EXPERT_GAIN * (goal - q) / V_MAX, -1.0, 1.0)
    return np.clip(action + rng.normal(0.0, EXPERT_NOISE, np.shape(q)), -1.0, 1.0)


def observe(task, q, qdot, goal) -> np.ndarray:
    from offline_rl_core.task import features

    return features.observe(task, q, qdot, {"goal": goal})


# ------------------------------------------------------------------------ closed loop

def rollouts(task, act, n: int, episodes: int, seed: int = HELD_OUT_SEED) -> np.ndarray:
    """Success (latched, as the task's reward says) of ``act(obs) -> actions`` on
    ``episodes`` held-out resets, the arm driven with the recording's timing."""
    from offline_rl_core.task import features

    resets = [sample_reset(n, seed + e) for e in range(episodes)]
    arm = Arm(n, episodes)
    arm.reset(np.array([q for q, _ in resets]))
    goal = np.array([g for _, g in resets])
    success = np.zeros(episodes, bool)
    for step in range(MAX_STEPS):
        action = np.asarray(act(observe(task, arm.q, arm.velocity, goal)), np.float64)
        arm.advance(COMMAND_LATENCY_NS)
        arm.command(_to_joint_order(task, action))
        arm.advance(CONTROL_NS - COMMAND_LATENCY_NS)
        success = features.score(task, arm.q, {"goal": goal}, np.full(episodes, step + 1), success).success
    return success


def _to_joint_order(task, action: np.ndarray) -> np.ndarray:
    """An action in the controller's order (the task's command joints) as ``joint_names`` order."""
    cols = [task.command.joints.index(j) for j in task.state.joints]
    return action[:, cols]


# ------------------------------------------------------------------------ a recording

@dataclass
class Recorded:
    """The arm's own steps of a recording: per control step the state (positions,
    velocities), the goal, the action (controller order) and the next state."""

    q: np.ndarray
    qdot: np.ndarray
    goal: np.ndarray
    action: np.ndarray
    next_q: np.ndarray
    next_qdot: np.ndarray
    episode: np.ndarray
    step: np.ndarray
    expert: np.ndarray  # bool: the expert acted


class _Messages:
    def __init__(self):
        from offline_rl_core.data.bag import typestore

        ts = self.ts = typestore()
        self.JS, self.H, self.T = (ts.types[t] for t in ("sensor_msgs/msg/JointState", "std_msgs/msg/Header",
                                                          "builtin_interfaces/msg/Time"))
        self.F64, self.L = ts.types["std_msgs/msg/Float64MultiArray"], ts.types["std_msgs/msg/MultiArrayLayout"]

    def joint_state(self, ns: int, names, position, velocity=(), effort=()) -> bytes:
        msg = self.JS(header=self.H(stamp=self.T(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=""), name=list(names),
                      position=np.asarray(position, np.float64), velocity=np.asarray(velocity, np.float64),
                      effort=np.asarray(effort, np.float64))
        return bytes(self.ts.serialize_cdr(msg, "sensor_msgs/msg/JointState"))

    def command(self, values) -> bytes:
        msg = self.F64(layout=self.L(dim=[], data_offset=0), data=np.asarray(values, np.float64))
        return bytes(self.ts.serialize_cdr(msg, "std_msgs/msg/Float64MultiArray"))


def record_bag(path, task, n: int, episodes: int, expert_frac: float, seed: int) -> Recorded:
    """Run ``episodes`` (the first ``round(expert_frac * episodes)`` by the expert, the rest
    uniform random, reset seeds ``seed + e``) and write the session's bag; returns its steps."""
    from offline_rl_core.data.bag import BagWriter

    msgs = _Messages()
    rng = np.random.default_rng([seed, 7])
    names = joint_names(n)
    published = [*names, "gripper_joint"]
    rng.shuffle(published)  # the broadcaster's own order
    columns = [names.index(j) for j in published if j != "gripper_joint"]
    gripper = published.index("gripper_joint")
    n_expert = int(round(expert_frac * episodes))
    arm = Arm(n)
    log: dict[str, list] = {k: [] for k in Recorded.__dataclass_fields__}
    clock = [START_NS]

    def at(ns: int) -> int:  # the recorder's receive time: strictly increasing, as it writes them
        clock[0] = max(clock[0] + 1000, ns)
        return clock[0]

    with BagWriter(path) as bag:
        bag.add_topic("/joint_states", "sensor_msgs/msg/JointState")
        bag.add_topic("/velocity_controller/commands", "std_msgs/msg/Float64MultiArray")
        bag.add_topic("/goal_joints", "sensor_msgs/msg/JointState")

        def publish_state(t: int) -> None:
            position = np.insert(arm.q[0][columns], gripper, 0.04)
            velocity = np.insert(arm.velocity[0][columns], gripper, 0.0)
            latency = int(rng.integers(200_000, 500_000))
            bag.write("/joint_states", at(t + latency), msgs.joint_state(t, published, position, velocity))

        t = START_NS
        for ep in range(episodes):
            q0, goal = sample_reset(n, seed + ep)
            order = list(rng.permutation(n))
            bag.write("/goal_joints", at(t + 7_000_000),
                      msgs.joint_state(t + 7_000_000, [names[i] for i in order], goal[order]))
            arm.reset(q0)
            t += PHYSICS_NS
            expert = ep < n_expert
            for step in range(MAX_STEPS):
                q, qdot = arm.q[0].copy(), arm.velocity[0].copy()
                publish_state(t)
                action = expert_action(q, goal, rng) if expert else rng.uniform(-1.0, 1.0, n)
                controller = action[[names.index(j) for j in task.command.joints]]
                sent = t + COMMAND_LATENCY_NS + int(rng.integers(-400_000, 400_000))
                bag.write("/velocity_controller/commands", at(sent),
                          msgs.command(np.asarray(task.command.offset) + np.asarray(task.command.scale) * controller))
                arm.advance(COMMAND_LATENCY_NS)
                arm.command(action)
                arm.advance(PHYSICS_NS - COMMAND_LATENCY_NS)
                publish_state(t + PHYSICS_NS)
                arm.advance(PHYSICS_NS)
                t += CONTROL_NS
                for key, value in (("q", q), ("qdot", qdot), ("goal", goal), ("action", controller),
                                   ("next_q", arm.q[0].copy()), ("next_qdot", arm.velocity[0].copy()),
                                   ("episode", ep), ("step", step), ("expert", expert)):
                    log[key].append(value)
            for _ in range(5):  # the arm goes on (the last command held) until the next reset
                publish_state(t)
                arm.advance(PHYSICS_NS)
                t += PHYSICS_NS
    return Recorded(**{k: np.array(v) for k, v in log.items()})


def expected_transitions(task, rec: Recorded):
    """The transitions of the arm's own steps (what the join must build from the bag): the
    controller's command mapped back to the action, who acted unknown (policy), the
    task's reward and success latch."""
    from offline_rl_core.data.transitions import SOURCE_POLICY, Transitions
    from offline_rl_core.task import features

    n = len(rec.q)
    reward, success = np.zeros(n), np.zeros(n, bool)
    for i in range(n):
        before = bool(success[i - 1]) if rec.step[i] > 0 else False
        s = features.score(task, rec.next_q[i:i + 1], {"goal": rec.goal[i:i + 1]}, [rec.step[i] + 1], [before])
        reward[i], success[i] = s.reward[0], s.success[0]
    command = np.asarray(task.command.offset) + np.asarray(task.command.scale) * rec.action
    return Transitions(
        obs=observe(task, rec.q, rec.qdot, rec.goal),
        action=np.clip((command - np.asarray(task.command.offset)) / np.asarray(task.command.scale),
                       -1.0, 1.0).astype(np.float32),
        reward=reward.astype(np.float32),
        next_obs=observe(task, rec.next_q, rec.next_qdot, rec.goal),
        terminated=np.zeros(n, bool),
        truncated=rec.step + 1 >= task.episodes.max_steps,
        success=success,
        episode=rec.episode.astype(np.int64),
        step=rec.step.astype(np.int64),
        source=np.full(n, SOURCE_POLICY, np.int64),
    )


# ------------------------------------------------------------------------ over ROS

class ArmOverRos:
    """The same arm behind ROS 2 topics, on an rclpy ``node`` (a test's): ``joint_states``
    at 100 Hz of the wall clock (names in the broadcaster's order, a gripper besides),
    ``velocity_controller/commands`` taken as a forward_command_controller takes them (the
    latest held; one of another length ignored), and each episode's goal on ``goal_joints``
    (transient local: a node that starts later still gets it). Episodes run on the held-out
    resets, ``MAX_STEPS`` control periods each; ``success`` holds each one's outcome."""

    def __init__(self, node, task, n: int, episodes: int, seed: int = HELD_OUT_SEED):
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import JointState
        from std_msgs.msg import Float64MultiArray

        self.node, self.task, self.n, self.episodes, self.seed = node, task, n, episodes, seed
        self.JointState = JointState
        self.names = joint_names(n)
        self.published = [*reversed(self.names[1:]), "gripper_joint", self.names[0]]
        self.arm = Arm(n)
        self.success: list[bool] = []
        self.ignored = 0
        self.commands = 0
        self.goal_heard = False  # the first goal published with a reader matched
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.state_pub = node.create_publisher(JointState, "joint_states", 10)
        self.goal_pub = node.create_publisher(JointState, "goal_joints", latched)
        node.create_subscription(Float64MultiArray, "velocity_controller/commands", self.on_command, 10)
        self._start_episode()
        self.timer = node.create_timer(PHYSICS_NS / 1e9, self.tick)

    @property
    def done(self) -> bool:
        return len(self.success) >= self.episodes

    def _start_episode(self) -> None:
        q0, self.goal = sample_reset(self.n, self.seed + len(self.success))
        self.arm.reset(q0)
        self.ticks, self.reached = 0, False
        self._publish_goal()

    def _publish_goal(self) -> None:
        msg = self.JointState(name=list(self.names), position=[float(v) for v in self.goal])
        msg.header.stamp = self.node.get_clock().now().to_msg()
        self.goal_pub.publish(msg)

    def on_command(self, msg) -> None:
        values = np.asarray(msg.data, np.float64)
        if values.size != self.n:
            self.ignored += 1
            return
        self.commands += 1
        action = (values - np.asarray(self.task.command.offset)) / np.asarray(self.task.command.scale)
        self.arm.command(_to_joint_order(self.task, action[None]))

    def tick(self) -> None:
        if self.done:
            return
        if self.commands == 0:
            # until the controller's first command the arm holds still at the first reset,
            # publishing its state: an episode's clock starts once the loop is closed
            # (discovery of the policy node's topics takes a while), as a real arm waits
            # for its controller to come up. The first goal went out before anyone
            # listened: it goes again once a reader is matched.
            if not self.goal_heard and self.goal_pub.get_subscription_count() > 0:
                self.goal_heard = True
                self._publish_goal()
            self._publish_state()
            return
        self.arm.advance(PHYSICS_NS)
        self.ticks += 1
        if self.ticks % 2 == 0:  # a control period: judged as the task's reward judges a step
            from offline_rl_core.task import features

            self.reached = bool(features.score(self.task, self.arm.q, {"goal": self.goal[None]}, [self.ticks // 2],
                                               [self.reached]).success[0])
            if self.ticks // 2 >= MAX_STEPS:
                self.success.append(self.reached)
                if not self.done:
                    self._start_episode()
                return
        self._publish_state()

    def _publish_state(self) -> None:
        cols = [self.names.index(j) for j in self.published if j != "gripper_joint"]
        gripper = self.published.index("gripper_joint")
        msg = self.JointState(name=list(self.published),
                              position=[float(v) for v in np.insert(self.arm.q[0][cols], gripper, 0.04)],
                              velocity=[float(v) for v in np.insert(self.arm.velocity[0][cols], gripper, 0.0)])
        msg.header.stamp = self.node.get_clock().now().to_msg()
        self.state_pub.publish(msg)
