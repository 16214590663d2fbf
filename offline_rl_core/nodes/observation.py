"""A task's observation from its robot's topics, one state at a time (the policy node's, no ROS).

The policy node of any task hands over the fields of what it hears (``offline_rl_core.task.spec``
says which topics and types):

- the state (``sensor_msgs/JointState``): the task's joints picked out by name, in any
  order, other joints ignored; a state that lacks one of them is refused;
- the goal: a ``PointStamped`` / ``PoseStamped`` position (the task's ``goal.axes``) or a
  ``JointState`` goal (the positions of ``goal.joints``, by name);
- tracked points with a topic (``PointStamped`` / ``PoseStamped``, their axes).

:meth:`ObservationBuilder.observe` computes the observation as the task file says
(``task.features.observe``, as the recording's join and the task's env do); a tracked
point not heard for a state comes from forward kinematics (``task.kinematics``). Every
value read is checked (finite, within range) and refused with a
:class:`~offline_rl_core.common.rejections.Rejection`, as ``joint_messages`` does for the
pusher's messages.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..common.errors import UserError
from ..common.rejections import Rejection
from ..task import features
from ..task.kinematics import PointKinematics
from ..task.spec import AXES, JOINT_STATE, TaskSpec
from .joint_messages import checked_vector, joint_index, joints_from_state


def kinematics_model(task: TaskSpec):
    """The MuJoCo model a task's ``site:`` / ``body:`` points need, or None: none needed, or
    no model for the task in this build (``offline_rl_core.task.envs.task_model``)."""
    if not any(p.kinematics not in (None, "planar_two_link") for p in task.points):
        return None
    try:
        from ..task.envs import task_model
    except ImportError:  # the task envs are not part of this build: planar_two_link only
        return None
    return task_model(task)


class ObservationBuilder:
    """Reads a task's messages and builds its observation; ``model``: the task's MuJoCo model
    (``kinematics_model``), for ``site:`` / ``body:`` points."""

    def __init__(self, task: TaskSpec, model=None):
        self.task = task
        computable = tuple(p for p in task.points
                           if p.kinematics == "planar_two_link" or (p.kinematics is not None and model is not None))
        self.kinematics = PointKinematics(replace(task, points=computable), model if computable else None)
        with_kinematics = {p.name for p in computable}
        # points a state must wait for, heard or not: no kinematics stands in for them
        self.topic_only = tuple(p.name for p in task.points if p.name not in with_kinematics)
        lost = [p for p in task.points if p.topic is None and p.name not in with_kinematics]
        if lost:
            raise UserError(f"{task.source_file()}: point {lost[0].name} has no topic and its kinematics "
                            f"({lost[0].kinematics}) need the task's MuJoCo model, which this build does not have "
                            "(offline_rl_core.task.envs); give the point a topic")
        self.point_topics = {p.name: p for p in task.points if p.topic is not None}
        self.needs_velocity = any(f.kind == "velocities" for f in task.observation)

    # ------------------------------------------------------------ reading messages
    def state(self, names, position, velocity) -> tuple[tuple[np.ndarray, np.ndarray] | None, Rejection | None]:
        """(positions, velocities) in the task's joint order, from a JointState's fields."""
        return joints_from_state(names, position, velocity, self.task.state.joints,
                                 velocity_optional=not self.needs_velocity)

    def goal_from_point(self, x: float, y: float, z: float) -> tuple[np.ndarray | None, Rejection | None]:
        """A Cartesian goal (a PointStamped's point or a PoseStamped's position): its axes."""
        return _axes((x, y, z), self.task.goal.axes, self.task.goal.topic)

    def goal_from_joints(self, names, position) -> tuple[np.ndarray | None, Rejection | None]:
        """A joint-space goal (a JointState's positions of ``goal.joints``, by name)."""
        position = np.asarray(position, np.float64)
        index, problem = joint_index(names, len(position), "goal positions", self.task.goal.joints)
        if problem:
            return None, problem
        return checked_vector(position[index], self.task.goal.topic)

    @property
    def joint_goal(self) -> bool:
        return self.task.goal.type == JOINT_STATE

    def point(self, name: str, x: float, y: float, z: float) -> tuple[np.ndarray | None, Rejection | None]:
        """A tracked point heard on its topic: its axes."""
        spec = self.point_topics[name]
        return _axes((x, y, z), spec.axes, spec.topic)

    # ------------------------------------------------------------ the observation
    def vectors(self, positions, goal, points: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The goal and every tracked point of one state (heard, else from kinematics)."""
        out = {"goal": np.asarray(goal, np.float64)}
        for p in self.task.points:
            out[p.name] = np.asarray(points[p.name] if p.name in points else
                                     self.kinematics.point(p, positions), np.float64)
        return out

    def observe(self, positions, velocities, goal, points: dict[str, np.ndarray]) -> np.ndarray:
        """The (obs_dim,) float32 observation of one state."""
        positions = np.asarray(positions, np.float64)
        vectors = {k: v[None] for k, v in self.vectors(positions, goal, points).items()}
        return features.observe(self.task, positions[None], np.asarray(velocities, np.float64)[None], vectors)[0]

    def distance(self, positions, goal, points: dict[str, np.ndarray] | None = None) -> float:
        """The reward's distance (``reward.distance``) of one state, e.g. for the corrector."""
        vectors = {k: v[None] for k, v in self.vectors(np.asarray(positions, np.float64), goal, points or {}).items()}
        a, b = self.task.reward.distance
        positions = np.asarray(positions, np.float64)[None]
        return float(features.distances(features.vector(self.task, a, positions, vectors),
                                        features.vector(self.task, b, positions, vectors))[0])


def _axes(xyz, axes, what: str) -> tuple[np.ndarray | None, Rejection | None]:
    return checked_vector([xyz[AXES.index(a)] for a in axes], what)
