"""Pushing a puck: the chapter's two-link arm (colliding links and fingertip) on a table with a
puck to push to a goal (``builtin/pusher_push.yaml`` and its model ``builtin/pusher_push.xml``).

``PushEnv`` is a ``MujocoTaskEnv`` (the task's state, command interface, tracked points,
observation, reward and success) whose reset also places the puck: every reset draws, from
one ``numpy.random.Generator(PCG64(seed))``, the puck, then the goal, then the arm's start
pose (``PushSettings`` says within what, field by field in the task file's ``sim.push``):

- the puck at a distance from the shoulder within ``radius``, at any angle;
- the goal at ``distance`` from the puck, in any direction, also within ``radius``, and
  such that the arm can get behind the puck and push it there: the point ``standoff``
  behind the puck's far side on the line from the goal (where a push starts) and the
  fingertip's place when the puck sits on the goal both lie within ``reach`` of the
  shoulder, and with the elbow on one side or the other the links keep ``margin`` from the
  puck at the push's start and touch it with nothing but the fingertip along the push
  (``PushGeometry.push_is_clear``);
- the arm's joints uniform in [-pi, pi], again while the arm touches the puck.

The puck's position is a tracked point with a topic (``PoseStamped``, as a tracker publishes
it); the sim reads it from the puck's body (``sim.points``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from ..common.errors import UserError
from .mujoco_task import MAX_TRIES, MujocoTaskEnv
from .spec import FieldReader, TaskSpec


APPROACHES = ("wave", "orbit")  # how the scripted expert gets behind the puck


@dataclass(frozen=True)
class PushSettings:
    """The ``sim.push`` section: what is pushed and where resets put it (m)."""

    puck: str  # the pushed body; its slide joints along x and y are its place on the table
    goal_marker: str | None  # a mocap body drawn at the goal (for the eye), or None
    point: str  # the tracked point that is the puck
    radius: tuple[float, float]  # the puck's and the goal's distance from the shoulder
    distance: tuple[float, float]  # the goal's distance from the puck
    reach: tuple[float, float]  # where the fingertip must be able to go (from the shoulder)
    standoff: float  # room behind the puck where a push starts
    margin: float  # the links this far from the puck at the push's start
    approach: str = "wave"  # how the scripted expert gets behind the puck (task/push_expert.py)

    @classmethod
    def of(cls, task: TaskSpec) -> "PushSettings":
        r = FieldReader(task.source_file(), task.path)
        doc = r.mapping("sim.push", (task.sim or {}).get("push"),
                        ("puck", "goal_marker", "point", "radius", "distance", "reach", "standoff", "margin",
                         "approach"))
        point = r.text("sim.push.point", doc.get("point"), "puck")
        if point not in {p.name for p in task.points}:
            raise r.error("sim.push.point", "the tracked point (points.NAME) that is the puck", point)
        return cls(r.text("sim.push.puck", doc.get("puck"), "puck"), r.text("sim.push.goal_marker", doc.get("goal_marker")),
                   point, _range(r, "sim.push.radius", doc.get("radius"), (0.08, 0.17)),
                   _range(r, "sim.push.distance", doc.get("distance"), (0.05, 0.1)),
                   _range(r, "sim.push.reach", doc.get("reach"), (0.04, 0.19)),
                   r.number("sim.push.standoff", doc.get("standoff"), 0.02, 0.0),
                   r.number("sim.push.margin", doc.get("margin"), 0.005, 0.0),
                   r.choice("sim.push.approach", doc.get("approach"), APPROACHES, "wave"))


def _range(r, label, value, default) -> tuple[float, float]:
    if value is None:
        return default
    if not (isinstance(value, list) and len(value) == 2 and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0 for v in value)
            and value[0] < value[1]):
        raise r.error(label, "[low, high], 0 <= low < high (m)", value)
    return float(value[0]), float(value[1])


@dataclass(frozen=True)
class PushGeometry:
    """What plane geometry needs of the model: the arm's link lengths, the fingertip's and
    the puck's radii (m). Read from the model, so the task file states each once."""

    links: tuple[float, float]
    tip_radius: float
    puck_radius: float

    @classmethod
    def of(cls, task: TaskSpec, model: mujoco.MjModel, settings: PushSettings) -> "PushGeometry":
        data = mujoco.MjData(model)
        mujoco.mj_kinematics(model, data)
        joints = [model.joint(j).id for j in task.state.joints]
        if len(joints) != 2:
            raise UserError(f"{task.source_file()}: field robot.state.joints: the push env drives a planar "
                            f"two-link arm (two joints), got {len(joints)}")
        fingertip = next((p for p in task.points if p.name != settings.point), None)
        if fingertip is None:
            raise UserError(f"{task.source_file()}: field points: the push env needs the arm's tool point beside "
                            f"the puck ({settings.point})")
        from .mujoco_task import ArmIndex, SimSettings

        index = ArmIndex(task, model, SimSettings.of(task))
        shoulder, elbow = (np.array(data.xanchor[j]) for j in joints)
        tip = index.point_xyz(data, fingertip.name)
        tip_body = model.body_geomadr[model.site_bodyid[index.points[fingertip.name][1]]] \
            if index.points[fingertip.name][0] == "site" else -1
        puck_body = model.body(settings.puck).id
        if model.body_geomnum[puck_body] < 1:
            raise UserError(f"{task.source_file()}: field sim.push.puck: body {settings.puck!r} has no geom")
        tip_radius = float(model.geom_size[tip_body, 0]) if tip_body >= 0 else 0.0
        return cls((float(np.linalg.norm(elbow - shoulder)), float(np.linalg.norm(tip - elbow))), tip_radius,
                   float(model.geom_size[model.body_geomadr[puck_body], 0]))

    @property
    def contact(self) -> float:
        """Centre of puck to fingertip (or to a link's axis) when they touch."""
        return self.puck_radius + self.tip_radius

    # -- the planar arm: forward and inverse kinematics, and how near its links come to the puck
    def elbow_and_tip(self, q0, q1) -> tuple[np.ndarray, np.ndarray]:
        """The elbow's and the fingertip's x, y (..., 2) for joint angles of any shape."""
        l1, l2 = self.links
        q0, q1 = np.asarray(q0, np.float64), np.asarray(q1, np.float64)
        elbow = np.stack([l1 * np.cos(q0), l1 * np.sin(q0)], axis=-1)
        tip = elbow + np.stack([l2 * np.cos(q0 + q1), l2 * np.sin(q0 + q1)], axis=-1)
        return elbow, tip

    def inverse(self, xy, elbow_sign: float) -> tuple[float, float]:
        """Joint angles putting the fingertip on ``xy`` (the nearest reachable point), the elbow's
        angle of sign ``elbow_sign``."""
        l1, l2 = self.links
        x, y = float(xy[0]), float(xy[1])
        c = (x * x + y * y - l1 * l1 - l2 * l2) / (2.0 * l1 * l2)
        elbow = math.copysign(math.acos(min(max(c, -1.0), 1.0)), elbow_sign)
        return math.atan2(y, x) - math.atan2(l2 * math.sin(elbow), l1 + l2 * math.cos(elbow)), elbow

    def clearance(self, q0, q1, puck) -> tuple[np.ndarray, np.ndarray]:
        """How far the upper arm's and the forearm's axes pass from the puck's centre (m), minus
        ``contact``: negative where they touch it."""
        return self.clearance_of(*self.elbow_and_tip(q0, q1), puck)

    def clearance_of(self, elbow, tip, puck) -> tuple[np.ndarray, np.ndarray]:
        """``clearance`` of the poses with these elbows and fingertips."""
        puck = np.asarray(puck, np.float64)
        return (_segment_distance(np.zeros_like(elbow), elbow, puck) - self.contact,
                _segment_distance(elbow, tip, puck) - self.contact)

    def push_is_clear(self, puck, goal, standoff: float, margin: float) -> list[float]:
        """The elbow signs (+1, -1) with which the arm can push the puck from ``puck`` to
        ``goal``: its links at least ``margin`` from the puck where the push starts
        (``standoff`` behind it), and not touching it with more than the fingertip along the
        push."""
        puck, goal = np.asarray(puck, np.float64), np.asarray(goal, np.float64)
        u = (goal - puck) / np.linalg.norm(goal - puck)
        signs = []
        for sign in (1.0, -1.0):
            start = self.inverse(puck - (self.contact + standoff) * u, sign)
            upper, fore = self.clearance(*start, puck)
            if min(float(upper), float(fore)) < margin:
                continue
            ok = True
            for f in PUSH_CHECKS:
                at = puck + f * (goal - puck)
                upper, fore = self.clearance(*self.inverse(at - self.contact * u, sign), at)
                if float(upper) < margin or float(fore) < -1e-6:
                    ok = False
                    break
            if ok:
                signs.append(sign)
        return signs


PUSH_CHECKS = (0.0, 0.25, 0.5, 0.75, 1.0)  # points along a push where the links are checked


def _segment_distance(a: np.ndarray, b: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Distance from point ``p`` (2,) to the segments ``a``-``b`` (..., 2)."""
    ab = b - a
    t = np.clip(np.sum((p - a) * ab, axis=-1) / np.maximum(np.sum(ab * ab, axis=-1), 1e-18), 0.0, 1.0)
    closest = a + t[..., None] * ab
    return np.sqrt(np.sum((closest - p) ** 2, axis=-1))


class PushEnv(MujocoTaskEnv):
    """``MujocoTaskEnv`` with a puck placed at every reset (see the module's docstring)."""

    def __init__(self, task: TaskSpec, terminate_on_success: bool | None = None,
                 model: mujoco.MjModel | None = None):
        super().__init__(task, terminate_on_success, model)
        self.push = PushSettings.of(task)
        m = self.model
        try:
            body = m.body(self.push.puck)
        except KeyError:
            raise UserError(f"{task.source_file()}: field sim.push.puck: the model has no body "
                            f"{self.push.puck!r}") from None
        slides = {tuple(np.round(m.jnt_axis[j], 9)): j for j in range(m.njnt) if m.jnt_bodyid[j] == body.id
                  and int(m.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_SLIDE)}
        if (1.0, 0.0, 0.0) not in slides or (0.0, 1.0, 0.0) not in slides:
            raise UserError(f"{task.source_file()}: field sim.push.puck: body {self.push.puck!r} needs slide "
                            "joints along x and along y (its place on the table)")
        self.puck_qpos = np.array([m.jnt_qposadr[slides[(1.0, 0.0, 0.0)]], m.jnt_qposadr[slides[(0.0, 1.0, 0.0)]]])
        self.puck_origin = np.array(body.pos[:2], np.float64)  # slide joints move the body from here
        self.marker = None
        if self.push.goal_marker is not None:
            mocap = int(m.body_mocapid[m.body(self.push.goal_marker).id])
            if mocap < 0:
                raise UserError(f"{task.source_file()}: field sim.push.goal_marker: {self.push.goal_marker!r} is "
                                "not a mocap body")
            self.marker = mocap
        self.geometry = PushGeometry.of(task, m, self.push)
        self.puck_start = np.zeros(2)
        self._scratch_puck = np.zeros(2)

    # ------------------------------------------------------------ resets
    def sample_reset(self, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(arm joints, goal vector, goal x/y/z) of reset ``seed``; the puck's x, y in ``puck_start``."""
        start, goal, self.puck_start = self.sample_push(seed)
        return start, goal, np.array([goal[0], goal[1], 0.0])

    def sample_push(self, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(arm joints, goal x/y, puck x/y) of reset ``seed``: all its randomness."""
        rng = np.random.Generator(np.random.PCG64(seed))
        s, g = self.push, self.geometry
        within = lambda p, lo_hi: lo_hi[0] <= math.hypot(p[0], p[1]) <= lo_hi[1]  # noqa: E731
        for _ in range(MAX_TRIES):
            rho, phi = rng.uniform(*s.radius), rng.uniform(0.0, 2.0 * np.pi)
            puck = np.array([rho * math.cos(phi), rho * math.sin(phi)])
            dist, theta = rng.uniform(*s.distance), rng.uniform(0.0, 2.0 * np.pi)
            u = np.array([math.cos(theta), math.sin(theta)])
            goal = puck + dist * u
            if within(goal, s.radius) and within(puck - (g.contact + s.standoff) * u, s.reach) \
                    and within(goal - g.contact * u, s.reach) and g.push_is_clear(puck, goal, s.standoff, s.margin):
                break
        else:
            raise UserError(f"{self.task.source_file()}: field sim.push: no puck and goal met radius, distance and "
                            f"reach in {MAX_TRIES} draws (reset seed {seed})")
        self._scratch_puck = puck
        return self._free_pose(rng, "reset"), goal, puck

    def _set_pose(self, pose: np.ndarray) -> None:
        super()._set_pose(pose)
        self._scratch.qpos[self.puck_qpos] = self._scratch_puck - self.puck_origin

    def reset(self, seed: int) -> np.ndarray:
        start, self.goal, self.goal_position = self.sample_reset(seed)
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[self.index.qpos] = start
        self.data.qpos[self.puck_qpos] = self.puck_start - self.puck_origin
        if self.marker is not None:
            self.data.mocap_pos[self.marker, :2] = self.goal
        self.drive.hold(self.data)
        mujoco.mj_forward(self.model, self.data)
        self.steps = 0
        self.success = False
        self.seed = seed
        return self.observation()

    @property
    def puck(self) -> np.ndarray:
        """The puck's x, y now (m)."""
        return self.data.qpos[self.puck_qpos] + self.puck_origin
