"""pusher-rl's learning core: the pusher-reach env, rosbag2 datasets, offline learners,
evaluation and statistics. No ROS import anywhere in this package."""

from .env import (
    ACT_DIM,
    MAX_STEPS,
    OBS_DIM,
    PusherReachEnv,
    observation_from_joints,
)
from .expert import expert_action, reach_action

__version__ = "0.1.0"

__all__ = [
    "ACT_DIM",
    "MAX_STEPS",
    "OBS_DIM",
    "PusherReachEnv",
    "expert_action",
    "observation_from_joints",
    "reach_action",
]
