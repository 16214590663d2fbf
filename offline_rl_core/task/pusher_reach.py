"""The pusher-reach task: a planar two-link arm in MuJoCo reaching a target.

Faithful to the chapter's environment (see docs in README): 50 Hz control,
two 0.01 s physics steps per action, reward ``-dist`` plus a one-time success
bonus, success latched for the episode, truncation at 100 steps. The task file
``builtin/pusher_reach.yaml`` says all of that; this module is its MuJoCo env.

The task's maths is the task file's (``features``), in batch form over N arms: the
observation (:func:`batch_observations`), the action (:func:`clip_actions`,
:func:`apply_action`) and the reward / success latch / episode end (:func:`score_steps`).
``PusherReachEnv`` calls them with N = 1, ``evaluation.BatchedPusherEnv`` with N
episodes at once (its physics: :func:`apply_action`'s, stepped in one
``mujoco.batch``), so the two agree bit for bit. The ROS nodes build observations
from ``/pusher/state`` + ``/pusher/target`` with :func:`observation_from_joints`,
so a policy trained here drives any arm that publishes those topics.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from . import features
from .features import StepScore, wrap_angle  # noqa: F401 - part of this module's API
from .spec import load_task

TASK = load_task("pusher_reach")
OBS_DIM = TASK.obs_dim
ACT_DIM = TASK.act_dim
MAX_STEPS = TASK.episodes.max_steps
CONTROL_HZ = round(1.0 / TASK.control_period)
FRAME_SKIP = 2
LINK_LEN = TASK.point("fingertip").link_lengths[0]
SUCCESS_TOL = TASK.reward.success_within
SUCCESS_BONUS = TASK.reward.success_bonus
TARGET_RADIUS_RANGE = (0.05, 0.19)
JOINT_NAMES = TASK.state.joints

PUSHER_XML = """
<mujoco model="pusher_reach">
  <option timestep="0.01" integrator="implicitfast"/>
  <visual><global offwidth="640" offheight="640"/></visual>
  <default>
    <geom type="capsule" size="0.01" contype="0" conaffinity="0" rgba="0.3 0.5 0.8 1"/>
    <joint type="hinge" axis="0 0 1" damping="0.1" armature="0.01" limited="false"/>
  </default>
  <worldbody>
    <light pos="0 0 1" dir="0 0 -1"/>
    <camera name="top" pos="0 0 0.5" xyaxes="1 0 0 0 1 0"/>
    <geom name="floor" type="plane" pos="0 0 -0.02" size="0.3 0.3 0.01" rgba="0.92 0.92 0.9 1"/>
    <body name="link1" pos="0 0 0">
      <joint name="shoulder"/>
      <geom name="link1_geom" fromto="0 0 0 0.1 0 0"/>
      <body name="link2" pos="0.1 0 0">
        <joint name="elbow"/>
        <geom name="link2_geom" fromto="0 0 0 0.1 0 0"/>
        <site name="fingertip" pos="0.1 0 0" size="0.008" rgba="0.9 0.3 0.2 1"/>
      </body>
    </body>
    <body name="target" mocap="true" pos="0.1 0 0">
      <geom name="target_geom" type="sphere" size="0.012" rgba="0.2 0.8 0.3 1"/>
    </body>
  </worldbody>
  <actuator>
    <motor name="shoulder_motor" joint="shoulder" gear="0.5" ctrlrange="-1 1" ctrllimited="true"/>
    <motor name="elbow_motor" joint="elbow" gear="0.5" ctrlrange="-1 1" ctrllimited="true"/>
  </actuator>
</mujoco>
"""


def fingertip_from_joints(qpos) -> np.ndarray:
    """Planar forward kinematics of the fingertip (for arms that publish no site)."""
    sh, el = float(qpos[0]), float(qpos[1])
    return np.array(
        [LINK_LEN * (math.cos(sh) + math.cos(sh + el)), LINK_LEN * (math.sin(sh) + math.sin(sh + el))]
    )


def batch_observations(qpos, qvel, target_xy, fingertip_xy) -> np.ndarray:
    """The observation of N arms at once: (N, 8) float32, one row per arm.

    Row ``[cos sh, sin sh, cos el, sin el, sh_vel, el_vel, dx, dy]`` with the angles
    wrapped to [-pi, pi) and ``(dx, dy) = target - fingertip``, all computed in
    float64 and rounded to float32 once: the task file's observation (``features.observe``),
    which ``PusherReachEnv`` (N = 1), ``BatchedPusherEnv`` and :func:`observation_from_joints`
    all call through here.
    """
    return features.observe(TASK, np.asarray(qpos)[:, :2], np.asarray(qvel)[:, :2],
                            {"goal": np.asarray(target_xy)[:, :2], "fingertip": np.asarray(fingertip_xy)[:, :2]})


def observation_from_joints(qpos, qvel, target_xy, fingertip_xy=None) -> np.ndarray:
    """The 8-float observation of one arm (see :func:`batch_observations`).

    The env passes MuJoCo's fingertip site; a caller with only joint states (a ROS
    node) leaves it out and gets planar forward kinematics, which can differ from
    the site in the last float64 bit (float32 observation: see tests/test_env.py).
    """
    qpos = np.asarray(qpos, dtype=np.float64)
    if fingertip_xy is None:
        fingertip_xy = fingertip_from_joints(qpos)
    return batch_observations(
        qpos[None, :2], np.asarray(qvel, dtype=np.float64)[None, :2],
        np.asarray(target_xy, dtype=np.float64)[None, :2], np.asarray(fingertip_xy, dtype=np.float64)[None, :2],
    )[0]


def clip_actions(actions, n: int) -> np.ndarray:
    """N actions as float32 (N, 2), clipped to the actuators' [-1, 1]."""
    return np.clip(np.asarray(actions, dtype=np.float32).reshape(n, ACT_DIM), -1.0, 1.0)


def apply_action(model: mujoco.MjModel, data: mujoco.MjData, action: np.ndarray) -> None:
    """Hold ``action`` (already clipped) on the motors for one control step."""
    data.ctrl[:ACT_DIM] = action
    # As in the chapter, the fingertip is read from ``site_xpos`` as mj_step leaves it:
    # the kinematics computed at the start of its last physics substep, 0.01 s behind
    # qpos. Refreshing it would change the dataset and, measurably, the critics (the
    # chapter's Break-It |Q| ratio). The sim node publishes this fingertip on
    # /pusher/fingertip so a ROS policy sees exactly the training observation.
    mujoco.mj_step(model, data, FRAME_SKIP)


def planar_distances(target_xy, fingertip_xy) -> np.ndarray:
    """|target - fingertip| in the plane for N rows, float64 (N,) (``features.distances``)."""
    return features.distances(np.asarray(target_xy)[:, :2], np.asarray(fingertip_xy)[:, :2])


def score_steps(target_xy, fingertip_xy, steps, success_before, terminate_on_success: bool) -> StepScore:
    """Reward, success latch and episode end for N envs after their ``steps``-th step
    (the task file's rule, ``features.score``).

    ``target_xy``, ``fingertip_xy``: (N, 2); ``steps`` (int) and ``success_before``
    (bool, the latch before this step): (N,).
    """
    vectors = {"goal": np.asarray(target_xy)[:, :2], "fingertip": np.asarray(fingertip_xy)[:, :2]}
    return features.score(TASK, None, vectors, steps, success_before, terminate_on_success)


def sample_reset(seed: int):
    """Initial joint angles and target for reset ``seed``: all randomness in one place."""
    rng = np.random.Generator(np.random.PCG64(seed))
    joints = rng.uniform(-np.pi, np.pi, size=2)
    radius = rng.uniform(*TARGET_RADIUS_RANGE)
    phi = rng.uniform(0.0, 2.0 * np.pi)
    target = np.array([radius * np.cos(phi), radius * np.sin(phi), 0.0])
    return joints, target


class PusherReachEnv:
    """The chapter's pusher-reach env with the classic 4-tuple ``step`` API.

    ``reset(seed)`` returns the observation; ``step(action)`` returns
    ``(obs, reward, done, info)`` with ``info = {terminated, truncated, success, dist}``.
    """

    task = TASK
    obs_dim = OBS_DIM
    act_dim = ACT_DIM
    max_steps = MAX_STEPS

    def __init__(self, terminate_on_success: bool = False, model: mujoco.MjModel | None = None):
        self.model = model if model is not None else build_model()
        self.data = mujoco.MjData(self.model)
        self.terminate_on_success = terminate_on_success
        self._fingertip = self.model.site("fingertip").id
        self._target_body = self.model.body("target").id
        self._mocap = self.model.body_mocapid[self._target_body]
        self.steps = 0
        self.success = False
        self.seed = None

    # -- state accessors, also used by the expert and the ROS sim node --
    @property
    def qpos(self) -> np.ndarray:
        return self.data.qpos[:2]

    @property
    def qvel(self) -> np.ndarray:
        return self.data.qvel[:2]

    @property
    def target(self) -> np.ndarray:
        return self.data.mocap_pos[self._mocap]

    @property
    def fingertip(self) -> np.ndarray:
        return self.data.site_xpos[self._fingertip]

    # -- the state as a robot publishes it, under the names every task env has (task.envs) --
    @property
    def joint_positions(self) -> np.ndarray:
        return self.qpos

    @property
    def joint_velocities(self) -> np.ndarray:
        return self.qvel

    @property
    def joint_efforts(self) -> np.ndarray:
        """N·m at the joints: the motors' force times their gear (actuator_force is the action)."""
        return self.data.qfrc_actuator[:ACT_DIM]

    @property
    def goal(self) -> np.ndarray:
        """The task's goal vector: the target's x, y."""
        return self.target[:2]

    @property
    def goal_position(self) -> np.ndarray:
        return self.target

    def point_positions(self) -> dict[str, np.ndarray]:
        return {"fingertip": self.fingertip}

    def vectors(self) -> dict[str, np.ndarray]:
        """The goal and the fingertip in the task's axes: what its features read."""
        return {"goal": self.target[:2].copy(), "fingertip": self.fingertip[:2].copy()}

    def distance(self) -> float:
        return float(planar_distances(self.target[None, :2], self.fingertip[None, :2])[0])

    def observation(self) -> np.ndarray:
        return batch_observations(self.qpos[None], self.qvel[None], self.target[None, :2], self.fingertip[None, :2])[0]

    def reset(self, seed: int) -> np.ndarray:
        joints, target = sample_reset(seed)
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[:2] = joints
        self.data.qvel[:] = 0.0
        self.data.mocap_pos[self._mocap] = target
        self.data.ctrl[:] = 0.0
        mujoco.mj_forward(self.model, self.data)
        self.steps = 0
        self.success = False
        self.seed = seed
        return self.observation()

    def step(self, action):
        if self.seed is None:
            raise RuntimeError("call reset(seed) before step()")
        apply_action(self.model, self.data, clip_actions(action, 1)[0])
        self.steps += 1
        score = score_steps(
            self.target[None, :2], self.fingertip[None, :2], np.array([self.steps]), np.array([self.success]),
            self.terminate_on_success,
        )
        self.success = bool(score.success[0])
        terminated, truncated = bool(score.terminated[0]), bool(score.truncated[0])
        info = {"terminated": terminated, "truncated": truncated, "success": self.success, "dist": float(score.dist[0])}
        return self.observation(), float(score.reward[0]), terminated or truncated, info


def build_model() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_string(PUSHER_XML)
