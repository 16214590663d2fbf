"""The scripted expert of a MuJoCo task: inverse kinematics on MuJoCo's Jacobian, then a PD law.

From the joint state and the goal alone (what a ROS node has), so collection, evaluation
and a corrector all call the same function:

1. the joint goal ``q*``: for a Cartesian goal, inverse kinematics of the goal's point by
   damped least squares (``dq = Jᵀ (J Jᵀ + λ² I)⁻¹ (goal - point)``, with MuJoCo's
   ``mj_jacSite`` / ``mj_jacBody`` over the command joints, each iterate clipped into the
   joints' ranges) from the current pose, or where that does not converge from a few fixed
   poses; for a joint-space goal, the goal itself;
2. the command toward it, in the task's interface: effort ``M (kp (q* - q) - kd q̇) + bias +
   damping q̇`` over the actuators' gear (the arm's own mass matrix, so one pair of gains suits
   every joint), velocity
   ``(kp / kd) (q* - q)``, position ``q*``; as an action, ``(command - offset) / scale``
   clipped to [-1, 1] (the controller's limits).

Moving in joint space toward a solution inside the joints' ranges never runs into a joint
limit, which a Cartesian velocity law on the Jacobian does where the goal lies behind one.
"""

from __future__ import annotations

import numpy as np
import mujoco

from .kinematics import damped_least_squares
from .mujoco_task import ArmIndex, SimSettings
from .spec import AXES, JOINT_STATE, TaskSpec

IK_ITERATIONS = 60
IK_TOLERANCE = 1e-4  # m: a pose whose point is this close to the goal solves it
LIMIT_MARGIN = 0.01  # IK solutions stay this far inside the joints' ranges (rad or m)


class ReachExpert:
    """``expert(positions, velocities, goal, points=None) -> action`` (float32, in [-1, 1]);
    a reach needs no tracked point beyond the arm's own (``points`` is not read)."""

    def __init__(self, task: TaskSpec, model: mujoco.MjModel, settings: SimSettings | None = None):
        self.task, self.model = task, model
        self.settings = settings or SimSettings.of(task)
        self.gains = self.settings.expert
        self.index = ArmIndex(task, model, self.settings)
        self.data = mujoco.MjData(model)
        self.scale = np.array(task.command.scale, np.float64)
        self.offset = np.array(task.command.offset, np.float64)
        # the command joints among the state joints
        self.command_in_state = np.array([task.state.joints.index(j) if j in task.state.joints else -1
                                          for j in task.command.joints])
        ranges = np.array([model.jnt_range[model.joint(j).id] if model.jnt_limited[model.joint(j).id]
                           else self.settings.joint_range for j in task.command.joints], np.float64)
        self.low, self.high = ranges[:, 0] + LIMIT_MARGIN, ranges[:, 1] - LIMIT_MARGIN
        self.cartesian = task.goal.type != JOINT_STATE
        if self.cartesian:
            name = self.settings.goal_point or next(v for v in task.reward.distance if v != "goal")
            self.point = self.index.points[name]
            self.rows = [AXES.index(a) for a in task.point(name).axes]
            rng = np.random.Generator(np.random.PCG64(0))  # fixed: the same restarts everywhere
            middle = (self.low + self.high) / 2.0
            self.restarts = [middle] + [rng.uniform(self.low, self.high) for _ in range(self.gains.restarts)]
        else:
            self.goal_in_command = [task.command.joints.index(j) if j in task.command.joints else -1
                                    for j in task.goal.joints]
        self._jacp = np.zeros((3, model.nv))
        self._mass = np.zeros((model.nv, model.nv))

    def __call__(self, positions, velocities, goal, points=None) -> np.ndarray:
        positions, velocities, q, qdot = self.command_joints(positions, velocities)
        target = self.joint_goal(positions, q, np.asarray(goal, np.float64))
        return self.action_toward(positions, velocities, q, qdot, target)

    def command_joints(self, positions, velocities):
        """The state as float64 arrays, with the command joints' positions and velocities."""
        positions = np.asarray(positions, np.float64)
        velocities = np.asarray(velocities, np.float64)
        q = np.where(self.command_in_state >= 0, positions[self.command_in_state], 0.0)
        qdot = np.where(self.command_in_state >= 0, velocities[self.command_in_state], 0.0)
        return positions, velocities, q, qdot

    def action_toward(self, positions, velocities, q, qdot, target) -> np.ndarray:
        """The action (float32, in [-1, 1]) that moves the command joints toward ``target``."""
        command = self.command(positions, velocities, q, qdot, target)
        return np.clip((command - self.offset) / self.scale, -1.0, 1.0).astype(np.float32)

    # ------------------------------------------------------------ 1. where to go
    def joint_goal(self, positions: np.ndarray, q: np.ndarray, goal: np.ndarray) -> np.ndarray:
        if not self.cartesian:
            target = q.copy()
            for k, c in enumerate(self.goal_in_command):
                if c >= 0:
                    target[c] = goal[k]
            return np.clip(target, self.low, self.high)
        best, best_err = None, np.inf
        for start in [q] + self.restarts:
            solution, err = self.solve(positions, start, goal)
            if err < IK_TOLERANCE:
                return solution
            if err < best_err:
                best, best_err = solution, err
        return best  # unreachable (a box sampler's goal): the nearest pose found

    def solve(self, positions: np.ndarray, start: np.ndarray, goal: np.ndarray) -> tuple[np.ndarray, float]:
        """Damped least squares from ``start``: (pose, its point's distance to the goal)."""
        d, idx = self.data, self.index
        d.qpos[idx.qpos] = positions  # the model's other joints stay at their reference pose
        q = np.clip(start, self.low, self.high)
        err = np.inf
        for _ in range(IK_ITERATIONS):
            delta = goal - self.point_at(q, self.point, self.rows)
            err = float(np.sqrt(delta @ delta))
            if err < IK_TOLERANCE:
                break
            jac = self.jacobian(self.point, self.rows)
            q = np.clip(q + damped_least_squares(jac, delta, self.gains.damping), self.low, self.high)
        return q, err

    def point_at(self, q: np.ndarray, point: tuple[str, int], rows: list[int]) -> np.ndarray:
        """Pose the model's command joints at ``q`` (the others as ``self.data`` has them) and
        return where ``point`` (``("site" | "body", id)``) is, its ``rows`` of x, y, z."""
        d = self.data
        d.qpos[self.index.command_qpos] = q
        mujoco.mj_kinematics(self.model, d)
        mujoco.mj_comPos(self.model, d)
        kind, pid = point
        return (d.site_xpos[pid] if kind == "site" else d.xpos[pid])[rows]

    def jacobian(self, point: tuple[str, int], rows: list[int]) -> np.ndarray:
        """MuJoCo's Jacobian of ``point`` at the pose :meth:`point_at` set: its ``rows`` by the command joints."""
        kind, pid = point
        if kind == "site":
            mujoco.mj_jacSite(self.model, self.data, self._jacp, None, pid)
        else:
            mujoco.mj_jacBody(self.model, self.data, self._jacp, None, pid)
        return self._jacp[rows][:, self.index.command_dof]

    # ------------------------------------------------------------ 2. how to get there
    def command(self, positions, velocities, q, qdot, target) -> np.ndarray:
        interface, g = self.task.command.interface, self.gains
        if interface == "position":
            return target
        if interface == "velocity":
            return (g.kp / g.kd) * (target - q) if g.kd > 0 else np.zeros_like(q)
        d, idx = self.data, self.index
        d.qpos[idx.qpos] = positions
        d.qvel[idx.dof] = velocities
        mujoco.mj_forward(self.model, d)
        mujoco.mj_fullM(self.model, d, self._mass)
        dof = idx.command_dof
        mass = self._mass[np.ix_(dof, dof)]
        force = mass @ (g.kp * (target - q) - g.kd * qdot) + d.qfrc_bias[dof] + self.model.dof_damping[dof] * qdot
        return force / self.model.actuator_gear[idx.actuators, 0]  # in the actuators' units


class CartesianJog:
    """``jog(positions, velocities, delta) -> action``: the action that moves the tracked point
    ``point`` by ``delta`` (its axes, in m): one damped-least-squares step on MuJoCo's Jacobian
    (the expert's damping), kept inside the joints' ranges, then the expert's law toward that
    pose in the task's interface. A person's stick, not a goal: no restarts, no convergence."""

    def __init__(self, expert: ReachExpert, point: str):
        self.expert = expert
        self.point = expert.index.points[point]
        self.rows = [AXES.index(a) for a in expert.task.point(point).axes]

    def __call__(self, positions, velocities, delta) -> np.ndarray:
        return self._jog(positions, velocities, lambda here: np.asarray(delta, np.float64))

    def toward(self, positions, velocities, goal, points=None) -> np.ndarray:
        """The jog that moves the point by all of what separates it from ``goal`` (its axes):
        a stick held toward the goal, pushed the further the further the point is."""
        return self._jog(positions, velocities, lambda here: np.asarray(goal, np.float64) - here)

    def _jog(self, positions, velocities, delta_at) -> np.ndarray:
        e = self.expert
        positions, velocities, q, qdot = e.command_joints(positions, velocities)
        e.data.qpos[e.index.qpos] = positions
        delta = delta_at(e.point_at(q, self.point, self.rows))
        step = damped_least_squares(e.jacobian(self.point, self.rows), delta, e.gains.damping)
        return e.action_toward(positions, velocities, q, qdot, np.clip(q + step, e.low, e.high))
