"""The env, model and scripted expert of any task that a sim can host (a ``sim`` section).

- ``make_env(task)``: ``sim: {env: pusher_reach}`` is the chapter's ``PusherReachEnv``
  (its bytes); ``sim: {model: ...}`` is a ``MujocoTaskEnv`` of that model; ``sim: {env:
  pusher_push, model: ...}`` a ``PushEnv`` (the model's puck placed at every reset too).
- ``task_model(task)``: the MuJoCo model the task's kinematics need (``site:`` / ``body:``
  points), or None for a task without a model.
- ``task_expert(task)``: the task's scripted expert as one function of what a robot
  publishes, ``expert(positions, velocities, goal, points) -> action`` (float32, in [-1, 1];
  ``points``: the tracked points' vectors, in their axes, e.g. the puck a tracker sees), so
  ``collect``, ``eval --expert`` and a corrector that only hears topics act alike;
  ``expert_action(env)`` asks it about an env's current state.
- ``task_jog(task, point)``: the action that moves a tracked point by a small Cartesian step
  (a gamepad's Cartesian mode), by damped least squares on the task's Jacobian.
- ``task_stick(task)``: an expert-shaped function that jogs the reward's point straight at
  the goal (a person steering the fingertip with a Cartesian stick, as HIL-SERL's operators
  do with a SpaceMouse): a reach task's other way for the scripted corrector to take over.

Every env has the same face: ``reset(seed) -> obs``; ``step(action) -> (obs, reward, done,
info)``; ``observation()``; ``steps``, ``success``, ``terminate_on_success``, ``obs_dim``,
``act_dim``, ``max_steps``, ``task``, ``model``, ``data``; the state as a robot publishes it:
``joint_positions``, ``joint_velocities``, ``joint_efforts`` (state-joint order), ``goal``
(the task's goal vector), ``goal_position`` (x, y, z of a Cartesian goal) and
``point_positions()`` (each tracked point's x, y, z).
"""

from __future__ import annotations

import os
from typing import Callable

import numpy as np

from ..common.errors import UserError
from .spec import JOINT_STATE, TaskSpec, load_task

Expert = Callable[..., np.ndarray]  # (positions, velocities, goal, points=None) -> action
SIM_ENVS = ("pusher_reach", "pusher_push")

_models: dict = {}
_experts: dict = {}


def _kind(task: TaskSpec) -> str:
    """'pusher_reach', 'pusher_push', 'model', or a UserError saying why no sim can host the task."""
    sim = task.sim or {}
    if not sim:
        raise UserError(f"{task.source_file()}: task {task.name} has no sim section: no simulator hosts it "
                        "(give sim: {model: FILE} to host it in MuJoCo)")
    env = sim.get("env")
    if env == "pusher_reach" and len(sim) != 1:
        raise UserError(f"{task.source_file()}: field sim.env: pusher_reach is the chapter's env and takes no other "
                        f"sim field, got {sim!r}")
    if env is not None and env not in SIM_ENVS:
        raise UserError(f"{task.source_file()}: field sim.env: expected one of {', '.join(SIM_ENVS)}, got {env!r}")
    if "push" in sim and env != "pusher_push":
        raise UserError(f"{task.source_file()}: field sim.push: only with sim.env: pusher_push")
    return env or "model"


def _key(task: TaskSpec) -> tuple:
    return task.digest, str(task.path)


def task_model(task: TaskSpec | str | os.PathLike | None) -> "mujoco.MjModel | None":  # noqa: F821
    """The task's compiled MuJoCo model (shared: read it, do not change it), or None for a
    task without a sim section."""
    task = load_task(task)
    if not task.sim:
        return None
    key = _key(task)
    if key not in _models:
        if _kind(task) == "pusher_reach":
            from .pusher_reach import build_model

            _models[key] = build_model()
        else:
            from .mujoco_task import load_model

            _models[key] = load_model(task)
    return _models[key]


def make_env(task: TaskSpec | str | os.PathLike | None, terminate_on_success: bool | None = None):
    """A fresh env of the task (None: the task's ``reward.terminate_on_success``)."""
    task = load_task(task)
    terminate = task.reward.terminate_on_success if terminate_on_success is None else bool(terminate_on_success)
    kind = _kind(task)
    if kind == "pusher_reach":
        from .pusher_reach import PusherReachEnv

        return PusherReachEnv(terminate_on_success=terminate)
    if kind == "pusher_push":
        from .pusher_push import PushEnv

        return PushEnv(task, terminate, model=task_model(task))
    from .mujoco_task import MujocoTaskEnv

    return MujocoTaskEnv(task, terminate, model=task_model(task))


def task_expert(task: TaskSpec | str | os.PathLike | None) -> Expert:
    """The task's scripted expert: ``expert(positions, velocities, goal) -> action``."""
    task = load_task(task)
    key = _key(task)
    if key not in _experts:
        kind = _kind(task)
        if kind == "pusher_reach":
            from .expert import expert_action

            _experts[key] = lambda q, qdot, goal, points=None: expert_action(q, qdot, goal)  # goal: the target's x, y
        elif kind == "pusher_push":
            from .push_expert import PushExpert

            _experts[key] = PushExpert(task, task_model(task))
        else:
            from .jacobian_expert import ReachExpert

            _experts[key] = ReachExpert(task, task_model(task))
    return _experts[key]


def task_jog(task: TaskSpec | str | os.PathLike | None,
             point: str | None = None) -> tuple[Callable[..., np.ndarray], int]:
    """``(jog, dims)``: ``jog(positions, velocities, delta) -> action`` (float32, in [-1, 1]) moves
    the tracked point ``point`` (default: the task's first) by ``delta``, ``dims`` values in its
    axes (m), through damped least squares on the task's Jacobian: pusher_reach's two-link
    chain, a MuJoCo task's model. UserError naming the point when the task has no such point."""
    task = load_task(task)
    names = [p.name for p in task.points]
    name = point or (names[0] if names else None)
    if name not in names:
        raise UserError(f"{task.source_file()}: task {task.name} has no tracked point {name!r} to move "
                        f"(its points: {', '.join(names) or 'none'})")
    dims = len(task.point(name).axes)
    kind = _kind(task)
    if kind == "pusher_reach":
        from .expert import jog_action

        return (lambda q, qdot, delta: jog_action(q, qdot, delta)), dims
    from .jacobian_expert import CartesianJog, ReachExpert

    expert = ReachExpert(task, task_model(task))
    if name not in expert.index.points or task.point(name).kinematics is None:
        raise UserError(f"{task.source_file()}: point {name} of task {task.name} is no forward kinematics of the "
                        "arm: a stick cannot move it")
    return CartesianJog(expert, name), dims


def point_vectors(task: TaskSpec, points: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Tracked points' x, y, z (``env.point_positions()``) as the task's vectors (their axes)."""
    from .spec import AXES

    return {p.name: np.asarray(points[p.name], np.float64)[[AXES.index(a) for a in p.axes]]
            for p in task.points if p.name in points}


def expert_action(env) -> np.ndarray:
    """The task's expert's action for an env's current state."""
    return task_expert(env.task)(env.joint_positions, env.joint_velocities, env.goal,
                                 point_vectors(env.task, env.point_positions()))


def task_stick(task: TaskSpec | str | os.PathLike | None) -> Expert:
    """``stick(positions, velocities, goal, points=None) -> action``: the jog (``task_jog``) that
    moves the reward distance's tracked point by what separates it from the goal, every state:
    a proportional Cartesian law, unlike the expert's joint-space swing to an inverse-kinematics
    pose. Only for a reach: the reward distance is the goal against a point of the arm's
    kinematics in the goal's axes; UserError naming the task otherwise."""
    task = load_task(task)
    pair = tuple(task.reward.distance)
    point = next((v for v in pair if v != "goal"), None)
    spec = task.point(point) if point in [p.name for p in task.points] else None
    if ("goal" not in pair or spec is None or spec.kinematics is None or task.goal.type == JOINT_STATE
            or list(spec.axes) != list(task.goal.axes) or task.reward.terms):
        raise UserError(f"{task.source_file()}: steering with a Cartesian stick needs a reach task, its reward "
                        f"distance the goal against a point of the arm's kinematics in the goal's axes; task "
                        f"{task.name}'s is {' - '.join(pair)}")
    if _kind(task) == "pusher_reach":
        from .expert import jog_action
        from .pusher_reach import fingertip_from_joints

        return lambda q, qdot, goal, points=None: jog_action(
            q, qdot, np.asarray(goal, np.float64)[:2] - fingertip_from_joints(q)).astype(np.float32)
    from .jacobian_expert import CartesianJog, ReachExpert

    return CartesianJog(ReachExpert(task, task_model(task)), point).toward
