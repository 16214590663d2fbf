"""The pusher-reach task: a planar two-link arm in MuJoCo reaching a target.

Faithful to the chapter's environment (see docs in README): 50 Hz control,
two 0.01 s physics steps per action, reward ``-dist`` plus a one-time success
bonus, success latched for the episode, truncation at 100 steps.

The observation is computed by :func:`observation_from_joints` from joint
positions, velocities, the fingertip and the target. The ROS nodes call the same
function on ``/pusher/state`` + ``/pusher/target`` so a policy trained here
drives any arm that publishes those topics.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

OBS_DIM = 8
ACT_DIM = 2
MAX_STEPS = 100
CONTROL_HZ = 50
FRAME_SKIP = 2
LINK_LEN = 0.1
SUCCESS_TOL = 0.02
SUCCESS_BONUS = 1.0
TARGET_RADIUS_RANGE = (0.05, 0.19)
JOINT_NAMES = ("shoulder", "elbow")

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


def wrap_angle(angle):
    """Wrap angles to [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


def fingertip_from_joints(qpos) -> np.ndarray:
    """Planar forward kinematics of the fingertip (for arms that publish no site)."""
    sh, el = float(qpos[0]), float(qpos[1])
    return np.array(
        [LINK_LEN * (math.cos(sh) + math.cos(sh + el)), LINK_LEN * (math.sin(sh) + math.sin(sh + el))]
    )


def observation_from_joints(qpos, qvel, target_xy, fingertip_xy=None) -> np.ndarray:
    """The 8-float observation ``[cos sh, sin sh, cos el, sin el, sh_vel, el_vel, dx, dy]``.

    ``(dx, dy) = target - fingertip``. The env passes MuJoCo's fingertip site; a
    caller with only joint states (a ROS node) leaves it out and gets the same
    planar forward kinematics.
    """
    qpos = np.asarray(qpos, dtype=np.float64)
    qvel = np.asarray(qvel, dtype=np.float64)
    if fingertip_xy is None:
        fingertip_xy = fingertip_from_joints(qpos)
    angles = wrap_angle(qpos[:2])
    obs = np.empty(OBS_DIM, dtype=np.float32)
    obs[0] = math.cos(angles[0])
    obs[1] = math.sin(angles[0])
    obs[2] = math.cos(angles[1])
    obs[3] = math.sin(angles[1])
    obs[4] = qvel[0]
    obs[5] = qvel[1]
    obs[6] = target_xy[0] - fingertip_xy[0]
    obs[7] = target_xy[1] - fingertip_xy[1]
    return obs


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

    def distance(self) -> float:
        return float(np.linalg.norm(self.target[:2] - self.fingertip[:2]))

    def observation(self) -> np.ndarray:
        return observation_from_joints(self.qpos, self.qvel, self.target[:2], self.fingertip[:2])

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
        action = np.clip(np.asarray(action, dtype=np.float32).reshape(ACT_DIM), -1.0, 1.0)
        self.data.ctrl[:] = action
        for _ in range(FRAME_SKIP):
            mujoco.mj_step(self.model, self.data)
        self.steps += 1
        dist = self.distance()
        reward = -dist
        if not self.success and dist < SUCCESS_TOL:
            self.success = True
            reward += SUCCESS_BONUS
        terminated = bool(self.terminate_on_success and self.success)
        truncated = bool(self.steps >= MAX_STEPS)
        info = {"terminated": terminated, "truncated": truncated, "success": self.success, "dist": dist}
        return self.observation(), float(reward), terminated or truncated, info


def build_model() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_string(PUSHER_XML)
