"""A 7-joint arm nobody here modelled, as a task file and a synthetic data set of its layout:
what the tests of serving a policy on another arm train and serve.

Its velocity controller takes the joints in another order than joint_states names them,
each with its own scale and offset; the goal is a Cartesian point on a topic, the tip is a
tracked point heard on its topic only, and the elbow a point from planar forward kinematics
of the first two joints.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

JOINTS = ("j1", "j2", "j3", "j4", "j5", "j6", "j7")
CONTROLLER_ORDER = ("j7", "j3", "j1", "j2", "j6", "j4", "j5")
SCALE = (0.5, 1.0, 1.5, 2.0, 0.25, 0.75, 1.25)
OFFSET = (0.1, 0.0, -0.2, 0.0, 0.05, 0.0, 0.3)

ARM7_TASK = f"""
name: test_arm7
description: a 7-joint velocity-controlled arm reaching a Cartesian goal (the tests' own)
control_period: 0.02
robot:
  state: {{topic: arm/joint_states, joints: [{", ".join(JOINTS)}], revolute: [j1, j2]}}
  command:
    interface: velocity
    controller: arm_velocity_controller
    joints: [{", ".join(CONTROLLER_ORDER)}]
    scale: [{", ".join(map(str, SCALE))}]
    offset: [{", ".join(map(str, OFFSET))}]
goal: {{topic: arm/goal, type: geometry_msgs/PointStamped, axes: [x, y, z]}}
points:
  tip: {{topic: arm/tip, axes: [x, y, z]}}
  elbow: {{kinematics: planar_two_link, link_lengths: [0.3, 0.2], axes: [x, y]}}
observation:
  - cos_sin: [j1, j2]
  - positions: [j3, j4, j5, j6, j7]
  - velocities: [{", ".join(JOINTS)}]
  - difference: [goal, tip]
  - vector: elbow
reward: {{distance: [goal, tip], success_within: 0.05}}
"""
OBS_DIM = 4 + 5 + 7 + 3 + 2
ACT_DIM = 7


def write_task(directory: Path) -> Path:
    path = Path(directory) / "arm7.yaml"
    path.write_text(ARM7_TASK)
    return path


def synthetic_transitions(episodes: int = 10, steps: int = 20, seed: int = 0):
    """Transitions of the arm's layout: random observations, and actions a smooth function
    of them (something a policy can learn)."""
    from offline_rl_core.data.transitions import SOURCE_EXPERT, Layout, Transitions

    rng = np.random.default_rng(seed)
    n = episodes * steps
    data = Transitions.empty(n, Layout(OBS_DIM, ACT_DIM))
    data.obs[:] = rng.uniform(-1, 1, (n, OBS_DIM)).astype(np.float32)
    data.next_obs[:] = rng.uniform(-1, 1, (n, OBS_DIM)).astype(np.float32)
    data.action[:] = np.tanh(data.obs[:, :ACT_DIM] - data.obs[:, ACT_DIM:2 * ACT_DIM]).astype(np.float32)
    data.reward[:] = -np.abs(data.obs[:, -5]).astype(np.float32)
    data.terminated[:] = False
    data.success[:] = False
    data.step[:] = np.tile(np.arange(steps), episodes)
    data.truncated[:] = data.step == steps - 1
    data.episode[:] = np.repeat(np.arange(episodes), steps)
    data.source[:] = SOURCE_EXPERT
    return data
