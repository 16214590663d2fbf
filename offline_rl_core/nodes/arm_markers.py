"""The arm as markers, from its joint positions alone (no ROS): links, joints, tracked points, goal.

RViz and Foxglove draw a ``visualization_msgs/MarkerArray``; this computes what goes in one,
in the task's world frame, as plain :class:`Marker` records (``pusher_common.markers``
makes the message). Where the links come from:

- a task with a MuJoCo model (``sim:``; ``offline_rl_core.task.envs.task_model``):
  ``mj_kinematics`` at the state's joint positions (other joints at their reference
  position); a link is each moving body's segment from its parent, and from a body to each
  of its sites (pusher_reach's fingertip), so the drawn arm ends where the task's points do;
- otherwise, a ``planar_two_link`` point (a real arm's task file with no model): base,
  elbow and tip of the planar chain.

The tracked points with kinematics are drawn where forward kinematics puts them
(``task.kinematics``); the goal where its message says (a point goal; a joint-space goal
is drawn as the arm's links at the goal's joint positions).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..task.kinematics import PointKinematics
from ..task.spec import JOINT_STATE, TaskSpec

FRAME = "world"
# visualization_msgs/Marker types and actions
SPHERE, LINE_STRIP, LINE_LIST, SPHERE_LIST = 2, 4, 5, 7
ADD = 0
LINK_COLOR = (0.3, 0.5, 0.8, 1.0)
JOINT_COLOR = (0.15, 0.2, 0.3, 1.0)
POINT_COLOR = (0.9, 0.3, 0.2, 1.0)
GOAL_COLOR = (0.2, 0.8, 0.3, 0.8)
GHOST_COLOR = (0.2, 0.8, 0.3, 0.4)
LINK_WIDTH = 0.012  # m: line width of the links
JOINT_SIZE = 0.02
POINT_SIZE = 0.016
GOAL_SIZE = 0.024

Vec = tuple[float, float, float]


@dataclass
class Marker:
    ns: str
    id: int
    type: int
    points: list[Vec]
    scale: Vec
    color: tuple[float, float, float, float]

    @property
    def position(self) -> Vec:
        """A single-point marker's position (its pose), else the origin."""
        return self.points[0] if self.type == SPHERE else (0.0, 0.0, 0.0)


def _vec(v) -> Vec:
    x = [float(a) for a in v] + [0.0] * (3 - len(v))
    return (x[0], x[1], x[2])


class ArmMarkers:
    """``markers(positions, goal)``: the markers of one state, in ``task.state.joints`` order.

    ``model``: the task's MuJoCo model (None: links from a planar_two_link point, if any).
    """

    def __init__(self, task: TaskSpec, model=None):
        self.task = task
        self.model = model
        # points whose kinematics can be computed here (site:/body: ones need the model)
        computable = tuple(p for p in task.points
                           if p.kinematics == "planar_two_link" or (p.kinematics is not None and model is not None))
        self.kinematics = PointKinematics(replace(task, points=computable), model) if computable else None
        self.planar = next((p for p in task.points if p.kinematics == "planar_two_link"), None)
        self._links: list[tuple[int, str, int]] = []  # (from body, "body"/"site", to id)
        if model is not None:
            import mujoco

            self._data = mujoco.MjData(model)
            self._qpos_adr = [int(model.jnt_qposadr[model.joint(j).id]) for j in task.state.joints]
            moving = self._moving_bodies(model)
            for body in sorted(moving):
                self._links.append((int(model.body_parentid[body]), "body", body))
            for site in range(model.nsite):
                if int(model.site_bodyid[site]) in moving:
                    self._links.append((int(model.site_bodyid[site]), "site", site))
            self._moving = sorted(moving)

    @staticmethod
    def _moving_bodies(model) -> set[int]:
        """Bodies a joint moves: those with a joint, and every body below one."""
        moving: set[int] = set()
        for body in range(1, model.nbody):  # parents come before their children
            if model.body_jntnum[body] > 0 or int(model.body_parentid[body]) in moving:
                moving.add(body)
        return moving

    # ------------------------------------------------------------------ geometry
    def link_segments(self, positions) -> tuple[list[Vec], list[Vec]]:
        """(segment end points in pairs, joint positions) of the arm at ``positions``."""
        if self.model is not None:
            import mujoco

            for adr, q in zip(self._qpos_adr, positions):
                self._data.qpos[adr] = float(q)
            mujoco.mj_kinematics(self.model, self._data)
            segments: list[Vec] = []
            for parent, kind, child in self._links:
                a = self._data.xpos[parent]
                b = self._data.xpos[child] if kind == "body" else self._data.site_xpos[child]
                if float(np.linalg.norm(b - a)) > 1e-9:  # a body at its parent's origin draws nothing
                    segments += [_vec(a), _vec(b)]
            return segments, [_vec(self._data.xpos[b]) for b in self._moving]
        if self.planar is not None:
            q0, q1 = float(positions[0]), float(positions[1])
            l1, l2 = self.planar.link_lengths
            elbow = (l1 * math.cos(q0), l1 * math.sin(q0), 0.0)
            tip = (elbow[0] + l2 * math.cos(q0 + q1), elbow[1] + l2 * math.sin(q0 + q1), 0.0)
            return [(0.0, 0.0, 0.0), elbow, elbow, tip], [(0.0, 0.0, 0.0), elbow]
        return [], []

    def goal_point(self, goal) -> Vec | None:
        """Where a point goal is, in 3-D (axes the task does not use at 0)."""
        if goal is None or self.task.goal.type == JOINT_STATE:
            return None
        where = dict(zip(self.task.goal.axes, (float(v) for v in goal)))
        return (where.get("x", 0.0), where.get("y", 0.0), where.get("z", 0.0))

    # ------------------------------------------------------------------ markers
    def markers(self, positions, goal=None, points: dict | None = None) -> list[Marker]:
        """Every marker of one state.

        ``goal``: the goal's values as the task has them (its axes, or a joint-space goal's
        positions), or None; ``points``: tracked points already known in 3-D (the sim's own),
        name -> (x, y, z); the others with kinematics are computed.
        """
        segments, joints = self.link_segments(positions)
        out = [Marker("links", 0, LINE_LIST, segments, (LINK_WIDTH, 0.0, 0.0), LINK_COLOR),
               Marker("joints", 0, SPHERE_LIST, joints, (JOINT_SIZE,) * 3, JOINT_COLOR)]
        where = {name: _vec(v) for name, v in (points or {}).items()}
        if self.kinematics:
            for name, value in self.kinematics.all(positions).items():
                if name not in where:
                    axes = dict(zip(self.task.point(name).axes, (float(v) for v in value)))
                    where[name] = (axes.get("x", 0.0), axes.get("y", 0.0), axes.get("z", 0.0))
        for i, name in enumerate(p.name for p in self.task.points if p.name in where):
            out.append(Marker(f"points/{name}", i, SPHERE, [where[name]], (POINT_SIZE,) * 3, POINT_COLOR))
        point = self.goal_point(goal)
        if point is not None:
            out.append(Marker("goal", 0, SPHERE, [point], (GOAL_SIZE,) * 3, GOAL_COLOR))
        elif goal is not None and self.task.goal.type == JOINT_STATE:
            at_goal = self._goal_positions(goal, positions)
            out.append(Marker("goal", 0, LINE_LIST, self.link_segments(at_goal)[0], (LINK_WIDTH, 0.0, 0.0),
                              GHOST_COLOR))
        return out

    def _goal_positions(self, goal, positions) -> list[float]:
        """The state's joints with the goal's joints set to the goal's values."""
        out = [float(q) for q in positions]
        for name, value in zip(self.task.goal.joints, goal):
            if name in self.task.state.joints:
                out[self.task.state.joints.index(name)] = float(value)
        return out
