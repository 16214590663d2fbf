"""Any task with a MuJoCo model: the arm a task file's ``sim`` section names, as an env.

``MujocoTaskEnv`` hosts a task whose ``sim`` section names a model (``sim.model``): the
state joints are the model's joints of those names, the command drives the actuators of the
command joints as the task's ros2_control interface would, and the observation, reward and
success are the task file's (``features``). What each ``sim`` field means, with its
default, is written out in ``builtin/pusher7_reach.yaml``; ``SimSettings`` reads and
checks them (one-line errors naming the file and the field).

The command interface, per command joint (command = offset + scale * action):

- ``effort``: ``ctrl = command``, in the actuator's units (a motor of gear 1: N·m);
- ``velocity`` / ``position`` on MuJoCo ``velocity`` / ``position`` actuators: ``ctrl =
  command``; on motors, a PD stand-in for the hardware's loop, recomputed every physics
  step: ``force = kp * (position - q) - kd * qdot`` or ``kd * (velocity - qdot)`` (gains
  ``sim.gains``), clipped to the actuator's range, as ros2_control's effort-to-position
  adapters do.

Every reset is drawn from one ``numpy.random.Generator(PCG64(seed))``: the joints uniform
within their ranges (resampled while an arm body touches anything, where asked), then the
goal from its sampler, so a reset seed names one episode on any machine. Tracked points are
read after ``mj_kinematics`` on the new joint positions, so they are exactly the forward
kinematics of the published joint states (``kinematics.PointKinematics``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from importlib.machinery import PathFinder
from pathlib import Path

import mujoco
import numpy as np

from ..common.errors import UserError
from . import features
from .spec import AXES, JOINT_STATE, FieldReader, TaskSpec

SIM_FIELDS = ("model", "frame_skip", "sites", "points", "reset", "goal", "gains", "expert",
              # read by the env that sim.env names (task.envs), not here
              "env", "push")
POINT_SOURCES = ("site", "body")
GOAL_SAMPLERS = ("reachable", "box")
# Tries of a rejection sampler before the settings are called impossible.
MAX_TRIES = 10_000


@dataclass(frozen=True)
class ExpertSettings:
    """The scripted expert's gains (``sim.expert``; see jacobian_expert)."""

    kp: float = 25.0  # 1/s²: joint-space stiffness, per unit of inertia
    kd: float = 10.0  # 1/s: joint-space damping, per unit of inertia
    damping: float = 0.05  # the damped least-squares lambda (m)
    restarts: int = 5  # further starting poses of the IK, tried when the current pose does not converge


@dataclass(frozen=True)
class SimSettings:
    """The ``sim`` section of a task with a model, checked."""

    model: str
    frame_skip: int | None  # None: control_period / the model's timestep
    sites: tuple[tuple[str, str, tuple[float, float, float]], ...]  # (name, body, pos)
    points: dict  # tracked point -> "site:NAME" / "body:NAME": where the sim reads it (sim.points)
    collision_free: bool
    joint_range: tuple[float, float]  # for joints without a range of their own
    goal_sampler: str
    goal_point: str | None  # reachable: the point placed at a random pose
    goal_low: tuple[float, ...] | None  # box per goal axis
    goal_high: tuple[float, ...] | None
    min_distance: float
    kp: tuple[float, ...] | None  # PD stand-in gains, per command joint
    kd: tuple[float, ...] | None
    expert: ExpertSettings

    @classmethod
    def of(cls, task: TaskSpec) -> "SimSettings":
        r = FieldReader(task.source_file(), task.path)
        doc = r.mapping("sim", task.sim, SIM_FIELDS)
        model = doc.get("model")
        if not isinstance(model, str) or not model.strip():
            raise r.error("sim.model", "a MuJoCo model: a file (relative to the task file) or PACKAGE:PATH", model)
        frame_skip = r.count("sim.frame_skip", doc.get("frame_skip"), None)
        sites = []
        if not isinstance(doc.get("sites") or {}, dict):
            raise r.error("sim.sites", "a mapping of site names to {body, pos}", doc.get("sites"))
        for name, site in (doc.get("sites") or {}).items():
            site = r.mapping(f"sim.sites.{name}", site, ("body", "pos"))
            body = r.text(f"sim.sites.{name}.body", site.get("body"))
            if body is None:
                raise r.error(f"sim.sites.{name}.body", "the body the site is fixed to", None)
            sites.append((name, body, _vector(r, f"sim.sites.{name}.pos", site.get("pos"), 3, (0.0, 0.0, 0.0))))
        points = r.mapping("sim.points", doc.get("points"), tuple(p.name for p in task.points))
        for name, where in points.items():
            if not (isinstance(where, str) and where.count(":") == 1 and where.split(":")[0] in POINT_SOURCES
                    and where.split(":")[1]):
                raise r.error(f"sim.points.{name}", "site:NAME or body:NAME of the model", where)
        reset = r.mapping("sim.reset", doc.get("reset"), ("collision_free", "joint_range"))
        joint_range = _vector(r, "sim.reset.joint_range", reset.get("joint_range"), 2, (-math.pi, math.pi))
        if not joint_range[0] < joint_range[1]:
            raise r.error("sim.reset.joint_range", "[low, high] with low < high", list(joint_range))
        goal = r.mapping("sim.goal", doc.get("goal"), ("sampler", "point", "low", "high", "min_distance"))
        sampler = r.choice("sim.goal.sampler", goal.get("sampler"), GOAL_SAMPLERS, "reachable")
        point = r.text("sim.goal.point", goal.get("point"))
        if task.goal.type != JOINT_STATE:
            point = point or next((v for v in task.reward.distance if v != "goal"), None)
            if sampler == "reachable" and (point is None or point not in {p.name for p in task.points}):
                raise r.error("sim.goal.point", "a tracked point (points.NAME) placed at random poses", point)
        n = task.goal.size
        low = _vector(r, "sim.goal.low", goal.get("low"), n, None)
        high = _vector(r, "sim.goal.high", goal.get("high"), n, None)
        if sampler == "box" and (low is None or high is None):
            raise r.error("sim.goal", f"low and high ({n} values each) for the box sampler", goal)
        if low is not None and high is not None and not all(a <= b for a, b in zip(low, high)):
            raise r.error("sim.goal.high", f"values >= sim.goal.low {list(low)}", list(high))
        gains = r.mapping("sim.gains", doc.get("gains"), ("kp", "kd"))
        k = len(task.command.joints)
        kp = None if gains.get("kp") is None else r.numbers("sim.gains.kp", gains["kp"], k, 0.0)
        kd = None if gains.get("kd") is None else r.numbers("sim.gains.kd", gains["kd"], k, 0.0)
        ex = r.mapping("sim.expert", doc.get("expert"), ("kp", "kd", "damping", "restarts"))
        default = ExpertSettings()
        expert = ExpertSettings(r.number("sim.expert.kp", ex.get("kp"), default.kp, 0.0, True),
                                r.number("sim.expert.kd", ex.get("kd"), default.kd, 0.0),
                                r.number("sim.expert.damping", ex.get("damping"), default.damping, 0.0, True),
                                _whole(r, "sim.expert.restarts", ex.get("restarts"), default.restarts))
        return cls(model, frame_skip, tuple(sites), dict(points),
                   r.flag("sim.reset.collision_free", reset.get("collision_free"), True), joint_range, sampler, point,
                   low, high, r.number("sim.goal.min_distance", goal.get("min_distance"), 0.0, 0.0), kp, kd, expert)


def _vector(r, label, value, n, default):
    if value is None:
        return default
    if not isinstance(value, list) or len(value) != n or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value):
        raise r.error(label, f"a list of {n} numbers", value)
    return tuple(float(v) for v in value)


def _whole(r, label, value, default):
    if value is None:
        return default
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise r.error(label, "a whole number >= 0", value)
    return value


# ------------------------------------------------------------------------ the model

def model_path(task: TaskSpec, text: str) -> Path:
    """The model file ``sim.model`` names: ``PACKAGE:PATH`` (a file inside an installed
    Python package, e.g. ``gymnasium:envs/mujoco/assets/pusher_v5.xml``), or a path, relative
    to the task file's folder (to the working directory for a task without a file)."""
    where = f"{task.source_file()}: field sim.model"
    package, sep, inner = text.partition(":")
    if sep and package.replace(".", "").replace("_", "").isalnum() and not Path(inner).is_absolute():
        # PathFinder, not importlib.util.find_spec: nothing is imported, and no import hook runs
        locations = None
        for part in package.split("."):
            spec = PathFinder.find_spec(part, locations)
            if spec is None or not spec.submodule_search_locations:
                raise UserError(f"{where}: {text!r} names package {package!r}, which is not installed here")
            locations = list(spec.submodule_search_locations)
        path = Path(locations[0]) / inner
    else:
        path = Path(text)
        if not path.is_absolute() and task.path is not None and task.path.is_file():
            path = task.path.parent / path
    if not path.is_file():
        raise UserError(f"{where}: {text!r}: no model file at {path}")
    return path


def load_model(task: TaskSpec) -> mujoco.MjModel:
    """The task's model, compiled with the sites ``sim.sites`` adds (tool points the model lacks)."""
    settings = SimSettings.of(task)
    path = model_path(task, settings.model)
    try:
        spec = mujoco.MjSpec.from_file(str(path))
        for name, body, pos in settings.sites:
            parent = spec.body(body)
            if parent is None:
                raise UserError(f"{task.source_file()}: field sim.sites.{name}.body: the model {path.name} has no "
                                f"body {body!r}")
            parent.add_site(name=name, pos=list(pos), size=[0.01, 0.0, 0.0])
        return spec.compile()
    except (ValueError, mujoco.FatalError) as exc:  # MuJoCo's parse and compile errors
        raise UserError(f"{task.source_file()}: field sim.model: {path}: {' '.join(str(exc).split())[:300]}") from None


def _joint_id(task: TaskSpec, model: mujoco.MjModel, name: str, field: str) -> int:
    jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
    if jid < 0:
        raise UserError(f"{task.source_file()}: field {field} names joint {name!r}, which the sim's model has not")
    if int(model.jnt_type[jid]) not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
        raise UserError(f"{task.source_file()}: field {field}: joint {name!r} is not a hinge or slide joint")
    return int(jid)


class ArmIndex:
    """Where a task's joints, actuators and points are in the model."""

    def __init__(self, task: TaskSpec, model: mujoco.MjModel, settings: SimSettings):
        self.task = task
        state_ids = [_joint_id(task, model, j, "robot.state.joints") for j in task.state.joints]
        self.qpos = np.array([model.jnt_qposadr[j] for j in state_ids])
        self.dof = np.array([model.jnt_dofadr[j] for j in state_ids])
        self.ranges = np.array([model.jnt_range[j] if model.jnt_limited[j] else settings.joint_range
                                for j in state_ids], np.float64)
        command_ids = [_joint_id(task, model, j, "robot.command.joints") for j in task.command.joints]
        self.command_qpos = np.array([model.jnt_qposadr[j] for j in command_ids])
        self.command_dof = np.array([model.jnt_dofadr[j] for j in command_ids])
        self.actuators = np.array([self._actuator(model, j, task.command.joints[k])
                                   for k, j in enumerate(command_ids)])
        # bodies that the state joints move: contacts of these are the arm's
        moved = set()
        for body in range(model.nbody):
            b = body
            while b > 0:
                if any(model.jnt_bodyid[j] == b for j in state_ids):
                    moved.add(body)
                    break
                b = model.body_parentid[b]
        self.arm_bodies = np.array(sorted(moved), np.int64)
        self.points = {}  # name -> ("site" | "body", id)
        for p in task.points:
            # sim.points: where the sim finds a point that is no forward kinematics of the arm
            # (an object a tracker follows), or that it reads from the model all the same
            where, label = (settings.points[p.name], f"sim.points.{p.name}") if p.name in settings.points else \
                (p.kinematics, f"points.{p.name}.kinematics")
            if where is None or where == "planar_two_link":
                raise UserError(f"{task.source_file()}: field points.{p.name}.kinematics: the sim reads tracked "
                                f"points from its model: give site:NAME or body:NAME (or sim.points.{p.name})")
            kind, name = where.split(":", 1)
            obj = mujoco.mjtObj.mjOBJ_SITE if kind == "site" else mujoco.mjtObj.mjOBJ_BODY
            pid = mujoco.mj_name2id(model, obj, name)
            if pid < 0:
                raise UserError(f"{task.source_file()}: field {label}: the sim's model has no {kind} {name!r}")
            self.points[p.name] = (kind, int(pid))
        self.axes = {p.name: [AXES.index(a) for a in p.axes] for p in task.points}
        self.goal_axes = [AXES.index(a) for a in task.goal.axes]
        self.goal_joints = np.array([task.state.joints.index(j) for j in task.goal.joints], np.int64) \
            if task.goal.type == JOINT_STATE else None

    def _actuator(self, model, joint_id: int, name: str) -> int:
        on_joint = int(mujoco.mjtTrn.mjTRN_JOINT)
        for a in range(model.nu):
            if int(model.actuator_trntype[a]) == on_joint and model.actuator_trnid[a, 0] == joint_id:
                return a
        raise UserError(f"{self.task.source_file()}: field robot.command.joints: no actuator of the sim's model "
                        f"drives joint {name!r}")

    def point_xyz(self, data: mujoco.MjData, name: str) -> np.ndarray:
        kind, pid = self.points[name]
        return np.array(data.site_xpos[pid] if kind == "site" else data.xpos[pid], np.float64)

    def arm_touches(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        """Whether an arm body is in contact (within the geoms' margins) with anything."""
        if data.ncon == 0:
            return False
        bodies = model.geom_bodyid[np.stack([data.contact.geom1[:data.ncon], data.contact.geom2[:data.ncon]])]
        return bool(np.isin(bodies, self.arm_bodies).any())


def _actuator_kind(model: mujoco.MjModel, a: int) -> str:
    """motor, position or velocity: what a MuJoCo actuator's gain and bias make it."""
    if int(model.actuator_biastype[a]) == int(mujoco.mjtBias.mjBIAS_NONE):
        return "motor"
    gain, bias = model.actuator_gainprm[a, 0], model.actuator_biasprm[a, :3]
    if bias[0] == 0 and bias[1] == -gain:
        return "position"
    if bias[0] == 0 and bias[1] == 0 and bias[2] == -gain:
        return "velocity"
    return "other"


class CommandDrive:
    """The command interface as the actuators take it: ``apply(command)`` once per control
    step, then ``before_substep()`` before each physics step (the PD stand-in's update)."""

    def __init__(self, task: TaskSpec, model: mujoco.MjModel, index: ArmIndex, settings: SimSettings):
        interface = task.command.interface
        kinds = [_actuator_kind(model, a) for a in index.actuators]
        self.index, self.model, self.interface = index, model, interface
        self.direct = all(k == ("motor" if interface == "effort" else interface) for k in kinds)
        if interface == "effort" and not self.direct:
            bad = task.command.joints[[k != "motor" for k in kinds].index(True)]
            raise UserError(f"{task.source_file()}: field robot.command.interface: effort, but the actuator of "
                            f"{bad!r} is no motor (its ctrl would not be the joint's effort)")
        self.pd = None
        if not self.direct:
            if any(k != "motor" for k in kinds):
                raise UserError(f"{task.source_file()}: field robot.command.interface: {interface} needs "
                                f"{interface} actuators or motors (a PD stand-in); the model has {', '.join(kinds)}")
            if settings.kd is None or (interface == "position" and settings.kp is None):
                need = "kp and kd" if interface == "position" else "kd"
                raise UserError(f"{task.source_file()}: field sim.gains: the {interface} interface on motors needs "
                                f"{need} (the PD stand-in for the hardware's loop)")
            self.pd = (interface, np.array(settings.kp or [0.0] * len(kinds)), np.array(settings.kd))
            self.gear = model.actuator_gear[index.actuators, 0].copy()
            self.ctrl_range = model.actuator_ctrlrange[index.actuators].copy()
            self.ctrl_limited = model.actuator_ctrllimited[index.actuators].astype(bool)
        self.command = np.zeros(len(kinds))

    def hold(self, data: mujoco.MjData) -> None:
        """The command of a controller just started: hold the pose (position), stand still
        (velocity), no effort."""
        if self.interface == "position":
            self.apply(data, data.qpos[self.index.command_qpos].copy())
        else:
            self.apply(data, np.zeros(len(self.index.actuators)))

    def apply(self, data: mujoco.MjData, command: np.ndarray) -> None:
        self.command = np.asarray(command, np.float64)
        if self.direct:
            data.ctrl[self.index.actuators] = self.command

    def before_substep(self, data: mujoco.MjData) -> None:
        if self.pd is None:
            return
        interface, kp, kd = self.pd
        q, qdot = data.qpos[self.index.command_qpos], data.qvel[self.index.command_dof]
        if interface == "position":
            force = kp * (self.command - q) - kd * qdot
        else:
            force = kd * (self.command - qdot)
        ctrl = force / self.gear
        lo, hi = self.ctrl_range[:, 0], self.ctrl_range[:, 1]
        data.ctrl[self.index.actuators] = np.where(self.ctrl_limited, np.clip(ctrl, lo, hi), ctrl)


class MujocoTaskEnv:
    """A task's MuJoCo arm with the classic 4-tuple ``step`` API (as ``PusherReachEnv``).

    ``reset(seed)`` returns the observation; ``step(action)`` (in [-1, 1], command-joint
    order) returns ``(obs, reward, done, info)``, ``info = {terminated, truncated, success,
    dist}``. The state as a robot publishes it: ``joint_positions``, ``joint_velocities``,
    ``joint_efforts`` (state-joint order; N·m or N applied by the actuators), ``goal`` (the
    task's goal vector), ``goal_position`` (a Cartesian goal's x, y, z), ``point_positions``.
    """

    def __init__(self, task: TaskSpec, terminate_on_success: bool | None = None,
                 model: mujoco.MjModel | None = None):
        self.task = task
        self.settings = SimSettings.of(task)
        self.model = model if model is not None else load_model(task)
        timestep = float(self.model.opt.timestep)
        skip = self.settings.frame_skip or round(task.control_period / timestep)
        if skip < 1 or abs(skip * timestep - task.control_period) > 1e-9:
            raise UserError(f"{task.source_file()}: field sim.frame_skip: {skip} physics steps of the model's "
                            f"{timestep:g} s are {skip * timestep:g} s, but control_period is "
                            f"{task.control_period:g} s")
        self.frame_skip = skip
        self.data = mujoco.MjData(self.model)
        self._scratch = mujoco.MjData(self.model)  # the reset sampler's poses
        self.index = ArmIndex(task, self.model, self.settings)
        self.drive = CommandDrive(task, self.model, self.index, self.settings)
        self.scale = np.array(task.command.scale, np.float64)
        self.offset = np.array(task.command.offset, np.float64)
        self.terminate_on_success = task.reward.terminate_on_success if terminate_on_success is None \
            else bool(terminate_on_success)
        self.obs_dim, self.act_dim, self.max_steps = task.obs_dim, task.act_dim, task.episodes.max_steps
        self.goal_position = np.zeros(3)
        self.goal = np.zeros(task.goal.size)
        self.steps = 0
        self.success = False
        self.seed = None

    # ------------------------------------------------------------ the state, as published
    @property
    def joint_positions(self) -> np.ndarray:
        return self.data.qpos[self.index.qpos]

    @property
    def joint_velocities(self) -> np.ndarray:
        return self.data.qvel[self.index.dof]

    @property
    def joint_efforts(self) -> np.ndarray:
        """What the actuators applied at the state joints in the last physics step (N·m, N)."""
        return self.data.qfrc_actuator[self.index.dof]

    def point_positions(self) -> dict[str, np.ndarray]:
        """Each tracked point's x, y, z (m, world frame)."""
        return {name: self.index.point_xyz(self.data, name) for name in self.index.points}

    def vectors(self) -> dict[str, np.ndarray]:
        """The goal and each point in their axes: what the task's features read."""
        out = {"goal": self.goal.copy()}
        for name in self.index.points:
            out[name] = self.index.point_xyz(self.data, name)[self.index.axes[name]]
        return out

    def observation(self) -> np.ndarray:
        return features.observe(self.task, self.joint_positions[None], self.joint_velocities[None],
                                {k: v[None] for k, v in self.vectors().items()})[0]

    def distance(self) -> float:
        """The reward's distance now."""
        vectors = self.vectors()
        return self._goal_distance(vectors.pop("goal"), self.joint_positions, vectors)

    # ------------------------------------------------------------ episodes
    def sample_reset(self, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(joint positions, goal vector, goal x/y/z) of reset ``seed``: all its randomness."""
        rng = np.random.Generator(np.random.PCG64(seed))
        start = self._free_pose(rng, "reset")
        start_vectors = self._pose_vectors(start)
        s = self.settings
        for _ in range(MAX_TRIES):
            if s.goal_sampler == "box":
                goal = rng.uniform(s.goal_low, s.goal_high)
                position = np.zeros(3)
                if self.index.goal_joints is None:
                    position[self.index.goal_axes] = goal
            else:
                pose = self._free_pose(rng, "goal")
                self._pose_vectors(pose)  # the point at that pose, in the scratch data
                if self.index.goal_joints is not None:
                    goal, position = pose[self.index.goal_joints], np.zeros(3)
                else:
                    position = self.index.point_xyz(self._scratch, s.goal_point)
                    goal = position[self.index.goal_axes]
                if s.goal_low is not None and not (np.all(goal >= s.goal_low) and np.all(goal <= s.goal_high)):
                    continue
            if s.min_distance <= 0 or self._goal_distance(goal, start, start_vectors) >= s.min_distance:
                return start, np.asarray(goal, np.float64), position
        raise UserError(f"{self.task.source_file()}: field sim.goal: no goal met its bounds in {MAX_TRIES} draws "
                        f"(reset seed {seed}): widen sim.goal.low/high or lower sim.goal.min_distance")

    def _free_pose(self, rng: np.random.Generator, what: str) -> np.ndarray:
        low, high = self.index.ranges[:, 0], self.index.ranges[:, 1]
        for _ in range(MAX_TRIES):
            pose = rng.uniform(low, high)
            if not self.settings.collision_free:
                return pose
            self._set_pose(pose)
            mujoco.mj_forward(self.model, self._scratch)
            if not self.index.arm_touches(self.model, self._scratch):
                return pose
        raise UserError(f"{self.task.source_file()}: field sim.reset.collision_free: no {what} pose free of "
                        f"contacts in {MAX_TRIES} draws")

    def _set_pose(self, pose: np.ndarray) -> None:
        self._scratch.qpos[:] = self.model.qpos0  # (mj_resetData clears the whole arena: slow)
        self._scratch.qpos[self.index.qpos] = pose

    def _pose_vectors(self, pose: np.ndarray) -> dict[str, np.ndarray]:
        self._set_pose(pose)
        mujoco.mj_kinematics(self.model, self._scratch)
        return {name: self.index.point_xyz(self._scratch, name)[self.index.axes[name]] for name in self.index.points}

    def _goal_distance(self, goal: np.ndarray, pose: np.ndarray, vectors: dict[str, np.ndarray]) -> float:
        """The reward's distance between ``goal`` and the arm at ``pose``."""
        vectors = {"goal": goal[None], **{k: v[None] for k, v in vectors.items()}}
        a, b = self.task.reward.distance
        return float(features.distances(features.vector(self.task, a, pose[None], vectors),
                                        features.vector(self.task, b, pose[None], vectors))[0])

    def reset(self, seed: int) -> np.ndarray:
        start, self.goal, self.goal_position = self.sample_reset(seed)
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[self.index.qpos] = start
        self.drive.hold(self.data)
        mujoco.mj_forward(self.model, self.data)
        self.steps = 0
        self.success = False
        self.seed = seed
        return self.observation()

    def command_of(self, action) -> np.ndarray:
        """The controller's command for an action (clipped to [-1, 1]): offset + scale * action."""
        action = np.clip(np.asarray(action, dtype=np.float32).reshape(self.act_dim), -1.0, 1.0)
        return self.offset + self.scale * action.astype(np.float64)

    def step(self, action):
        if self.seed is None:
            raise RuntimeError("call reset(seed) before step()")
        self.drive.apply(self.data, self.command_of(action))
        if self.drive.pd is None:
            mujoco.mj_step(self.model, self.data, self.frame_skip)
        else:
            for _ in range(self.frame_skip):
                self.drive.before_substep(self.data)
                mujoco.mj_step(self.model, self.data)
        # the points at the new joint positions (mj_step leaves them one physics step behind)
        mujoco.mj_kinematics(self.model, self.data)
        self.steps += 1
        vectors = {k: v[None] for k, v in self.vectors().items()}
        score = features.score(self.task, self.joint_positions[None], vectors, np.array([self.steps]),
                               np.array([self.success]), self.terminate_on_success)
        self.success = bool(score.success[0])
        terminated, truncated = bool(score.terminated[0]), bool(score.truncated[0])
        info = {"terminated": terminated, "truncated": truncated, "success": self.success, "dist": float(score.dist[0])}
        return self.observation(), float(score.reward[0]), terminated or truncated, info
