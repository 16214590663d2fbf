"""Forward kinematics of a task's tracked points: where a point is, from the joints alone.

A tracked point (``points.NAME`` of a task file) comes from its topic when one is heard, and
otherwise from here: ``planar_two_link`` (the chapter's arm: the first two state joints and
the point's ``link_lengths``), or ``site:NAME`` / ``body:NAME`` of the task's MuJoCo model
(``mj_kinematics`` on the joint positions; other joints of the model stay at their
reference position). One row at a time in plain floats, as the policy node asks for it, so
its observation is value for value what a recording's join computes.
"""

from __future__ import annotations

import math

import numpy as np

from .spec import AXES, PointSpec, TaskSpec


def planar_two_link(q0: float, q1: float, l1: float, l2: float) -> tuple[float, float]:
    """The end of a planar two-link chain (joint angles in rad, link lengths in m)."""
    return l1 * math.cos(q0) + l2 * math.cos(q0 + q1), l1 * math.sin(q0) + l2 * math.sin(q0 + q1)


def planar_two_link_jacobian(q0: float, q1: float, l1: float, l2: float) -> np.ndarray:
    """d(x, y) / d(q0, q1) of :func:`planar_two_link`'s end, a 2 x 2 float64 array."""
    s0, c0 = math.sin(q0), math.cos(q0)
    s01, c01 = math.sin(q0 + q1), math.cos(q0 + q1)
    return np.array([[-l1 * s0 - l2 * s01, -l2 * s01], [l1 * c0 + l2 * c01, l2 * c01]])


def damped_least_squares(jac: np.ndarray, delta: np.ndarray, damping: float) -> np.ndarray:
    """The joint step ``dq = Jᵀ (J Jᵀ + λ² I)⁻¹ delta`` that moves a point by ``delta``.

    The damping ``λ`` (in the point's units) bounds the step near a singular pose, where the
    plain pseudo-inverse would ask for unbounded joint motion; ``λ > 0`` keeps it finite.
    """
    return jac.T @ np.linalg.solve(jac @ jac.T + np.eye(len(jac)) * damping**2, delta)


class PointKinematics:
    """``positions`` (in ``task.state.joints`` order) -> the points that have kinematics.

    ``model``: the task's ``mujoco.MjModel``, needed for ``site:`` and ``body:`` points.
    """

    def __init__(self, task: TaskSpec, model=None):
        self.task = task
        self.points = [p for p in task.points if p.kinematics is not None]
        self._model = model
        self._data = None
        self._qpos_adr: list[int] = []
        if any(p.kinematics != "planar_two_link" for p in self.points):
            if model is None:
                names = ", ".join(p.name for p in self.points if p.kinematics != "planar_two_link")
                raise ValueError(f"{task.source_file()}: points {names} need the task's MuJoCo model for their kinematics")
            import mujoco

            self._data = mujoco.MjData(model)
            self._qpos_adr = [int(model.jnt_qposadr[model.joint(j).id]) for j in task.state.joints]

    def __bool__(self) -> bool:
        return bool(self.points)

    def point(self, spec: PointSpec, positions) -> np.ndarray:
        """One point (its axes) of one state, float64."""
        axes = [AXES.index(a) for a in spec.axes]
        if spec.kinematics == "planar_two_link":
            xy = planar_two_link(float(positions[0]), float(positions[1]), *spec.link_lengths)
            return np.array([(xy[0], xy[1], 0.0)[i] for i in axes])
        import mujoco

        for adr, q in zip(self._qpos_adr, positions):
            self._data.qpos[adr] = q
        mujoco.mj_kinematics(self._model, self._data)
        kind, name = spec.kinematics.split(":", 1)
        where = self._data.site(name).xpos if kind == "site" else self._data.body(name).xpos
        return np.array(where, dtype=np.float64)[axes]

    def all(self, positions) -> dict[str, np.ndarray]:
        """Every point with kinematics, for one state."""
        return {p.name: self.point(p, positions) for p in self.points}
