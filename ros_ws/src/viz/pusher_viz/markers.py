"""``ros2 run viz markers -p task:=FILE``: any arm in RViz or Foxglove, from its joint states alone.

For a real arm (the sim publishes its own): reads the task's state topic (``robot.state.topic``,
``joint_states`` by default: sensor_msgs/JointState, the task's joints picked out by name;
velocities optional) and its goal topic, and publishes ``markers``
(visualization_msgs/MarkerArray, frame ``world``, stamped with the state's stamp): the links
(from the task's MuJoCo model when it has one, else its ``planar_two_link`` point), the
tracked points with forward kinematics, and the goal (``offline_rl_core.nodes.arm_markers``),
at most every ``marker_period`` seconds of wall time. A malformed state or goal draws
nothing; it is counted by reason on ``/diagnostics``.
"""

from __future__ import annotations

import sys
import time

from geometry_msgs.msg import PointStamped, PoseStamped
from rclpy.node import Node
from sensor_msgs.msg import JointState
from visualization_msgs.msg import MarkerArray

from offline_rl_core.common.rejections import RejectionCounter
from offline_rl_core.nodes.arm_markers import ArmMarkers
from offline_rl_core.nodes.diagnostics import StatusDiagnosis
from offline_rl_core.nodes.joint_messages import joints_from_state
from offline_rl_core.nodes.observation import ObservationBuilder
from offline_rl_core.task.envs import task_model
from offline_rl_core.task.spec import DEFAULT_TASK, JOINT_STATE, POSE_STAMPED, load_task
from pusher_common.diagnostics import NodeDiagnostics
from pusher_common.markers import MARKERS_TOPIC, marker_array
from pusher_common.node_main import run_node
from pusher_common.params import Param, Settings

PARAMS = (
    Param("task", DEFAULT_TASK, "the task: a built-in task or a task file (its state and goal topics, joints, "
          "points and model)", read_only=True, flag="--task"),
    Param("marker_period", 0.04, "seconds of wall time between markers (a state in between draws nothing)",
          low=0.0, high=60.0, flag="--marker-period"),
)


class Markers(Node):
    def __init__(self, overrides=()):
        super().__init__("markers", parameter_overrides=list(overrides))
        # marker_period is read on every state: a new value holds from the next one
        self.settings = Settings(self, PARAMS, on_change=lambda name, value: None)
        self.task = task = load_task(self.settings.task or None)  # UserError: one line naming the task
        model = task_model(task) if task.sim else None
        self.arm = ArmMarkers(task, model)
        self.builder = ObservationBuilder(task, model)
        self.goal = None
        self.states = self.published = 0
        self.last = -float("inf")
        self.rejected = RejectionCounter()
        self.pub = self.create_publisher(MarkerArray, MARKERS_TOPIC, 10)
        goal_type = {JOINT_STATE: JointState, POSE_STAMPED: PoseStamped}.get(task.goal.type, PointStamped)
        self.create_subscription(goal_type, task.goal.topic, self.on_goal, 10)
        state_sub = self.create_subscription(JointState, task.state.topic, self.on_state, 10)
        self.diagnostics = NodeDiagnostics(self, lambda: {"states": self.states, "published": self.published,
                                                          "rejected": dict(self.rejected.counts)},
                                           StatusDiagnosis(idle=lambda st: f"{st['published']} markers published"),
                                           hardware_id=task.name)
        self.get_logger().info(f"markers of task {task.name}: {state_sub.topic_name} -> {self.pub.topic_name}")

    def on_goal(self, msg) -> None:
        if self.builder.joint_goal:
            goal, problem = self.builder.goal_from_joints(msg.name, msg.position)
        else:
            p = msg.pose.position if isinstance(msg, PoseStamped) else msg.point
            goal, problem = self.builder.goal_from_point(p.x, p.y, p.z)
        if problem:
            self.rejected.add(problem)
            return
        self.goal = goal

    def on_state(self, msg: JointState) -> None:
        self.states += 1
        now = time.monotonic()
        if now - self.last < self.settings.marker_period:
            return
        joints, problem = joints_from_state(msg.name, msg.position, msg.velocity, self.task.state.joints,
                                            velocity_optional=True)
        if problem:
            self.rejected.add(problem)
            return
        self.last = now
        self.pub.publish(marker_array(self.arm.markers(joints[0], self.goal), msg.header.stamp))
        self.published += 1


def main(argv: list[str] | None = None) -> int:
    return run_node(Markers, prog="markers", command="ros2 run viz markers", flags=PARAMS, argv=argv,
                    description="The arm's markers (visualization_msgs/MarkerArray) from its joint states.")


if __name__ == "__main__":
    sys.exit(main())
