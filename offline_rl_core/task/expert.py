"""The scripted expert: analytic inverse kinematics (elbow-down) plus a PD law."""

from __future__ import annotations

import math

import numpy as np

from .kinematics import damped_least_squares, planar_two_link_jacobian
from .pusher_reach import LINK_LEN, PusherReachEnv, wrap_angle

KP = 25.0
KD = 2.0
JOG_DAMPING = 0.02  # m: the damped least squares' lambda, small beside the links' length


def ik_joint_targets(target_xy) -> tuple[float, float]:
    """Joint angles that put the fingertip on ``target_xy`` (elbow-down branch)."""
    tx, ty = float(target_xy[0]), float(target_xy[1])
    two_l2 = 2.0 * LINK_LEN * LINK_LEN
    cos_elbow = min(max((tx * tx + ty * ty - two_l2) / two_l2, -1.0), 1.0)
    elbow = math.acos(cos_elbow)
    shoulder = math.atan2(ty, tx) - math.atan2(LINK_LEN * math.sin(elbow), LINK_LEN * (1.0 + cos_elbow))
    return shoulder, elbow


def expert_action(qpos, qvel, target_xy, kp: float = KP, kd: float = KD) -> np.ndarray:
    """PD torques toward the IK solution, clipped to [-1, 1], as float32.

    Works from joint states and the target alone, so the ROS corrector uses it too.
    """
    return pd_torques(np.array(ik_joint_targets(target_xy)), qpos, qvel, kp, kd)


def pd_torques(q_star, qpos, qvel, kp: float = KP, kd: float = KD) -> np.ndarray:
    """The expert's PD law toward the joint angles ``q_star``: torques clipped to [-1, 1], float32."""
    q = np.asarray(qpos, dtype=np.float64)[:2]
    qdot = np.asarray(qvel, dtype=np.float64)[:2]
    torque = kp * wrap_angle(q_star - q) - kd * qdot
    return np.clip(torque, -1.0, 1.0).astype(np.float32)


def jog_action(qpos, qvel, delta_xy, damping: float = JOG_DAMPING) -> np.ndarray:
    """Torques that move the fingertip by ``delta_xy`` (m): the expert's PD law toward the pose
    one damped-least-squares step on the two-link Jacobian away (a gamepad's Cartesian mode)."""
    q = np.asarray(qpos, dtype=np.float64)[:2]
    jac = planar_two_link_jacobian(q[0], q[1], LINK_LEN, LINK_LEN)
    return pd_torques(q + damped_least_squares(jac, np.asarray(delta_xy, np.float64)[:2], damping), qpos, qvel)


def reach_action(env: PusherReachEnv) -> np.ndarray:
    """The expert's action for the env's current state."""
    return expert_action(env.qpos, env.qvel, env.target[:2])
