"""pusher-rl's learning core: the pusher-reach env, rosbag2 datasets, offline learners,
evaluation and statistics. No ROS import anywhere in this package.

    from offline_rl_core import PusherReachEnv, reach_action, read_transitions
"""

from .data.bag import bag_info, read_transitions, write_transitions
from .task.pusher_reach import ACT_DIM, MAX_STEPS, OBS_DIM, PusherReachEnv, observation_from_joints
from .task.expert import expert_action, reach_action
from .task.gym_env import register_gym_envs
from .data.transitions import Transitions

__version__ = "0.1.0"


def __getattr__(name: str):
    # load_policy needs torch (~0.9 s to import): loaded when first asked for, not by
    # every node and command that only needs the env or the bag code
    if name == "load_policy":
        from .serving.policy import load_policy

        return load_policy
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# `gymnasium.make("offline_rl_core/PusherReach-v0")` works once this package is imported.
register_gym_envs()

__all__ = [
    "ACT_DIM",
    "MAX_STEPS",
    "OBS_DIM",
    "PusherReachEnv",
    "Transitions",
    "bag_info",
    "expert_action",
    "load_policy",
    "observation_from_joints",
    "reach_action",
    "read_transitions",
    "register_gym_envs",
    "write_transitions",
]
