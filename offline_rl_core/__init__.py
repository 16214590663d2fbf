"""pusher-rl's learning core: tasks, rosbag2 datasets, offline learners, serving,
evaluation and statistics, in layers (ARCHITECTURE.md). No ROS import anywhere in it.

    from offline_rl_core import PusherReachEnv, reach_action, read_transitions, load_policy

The names below are loaded when first used, so a node that imports one layer's module
does not load the others (the bag code, torch, gymnasium).
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys

__version__ = "0.1.0"

# public name -> the module that defines it
_EXPORTS = {
    "ACT_DIM": "task.pusher_reach",
    "MAX_STEPS": "task.pusher_reach",
    "OBS_DIM": "task.pusher_reach",
    "PusherReachEnv": "task.pusher_reach",
    "observation_from_joints": "task.pusher_reach",
    "expert_action": "task.expert",
    "reach_action": "task.expert",
    "register_gym_envs": "task.gym_env",
    "load_task": "task.spec",
    "make_env": "task.envs",
    "Transitions": "data.transitions",
    "bag_info": "data.bag",
    "read_transitions": "data.bag",
    "write_transitions": "data.bag",
    "load_policy": "serving.policy",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))


class _RegisterWithGymnasium(importlib.abc.MetaPathFinder):
    """``gymnasium.make("offline_rl_core/PusherReach-v0")`` works once this package is
    imported, as with any Gymnasium env package, without this package importing gymnasium
    (half a second) for every node and command: the env is registered when gymnasium
    itself is first imported."""

    def find_spec(self, name, path=None, target=None):
        if name != "gymnasium":
            return None
        sys.meta_path.remove(self)  # once; and so that the search below finds the real spec
        spec = importlib.util.find_spec(name)
        if spec is None or spec.loader is None:
            return spec
        exec_module = spec.loader.exec_module

        def exec_then_register(module):
            exec_module(module)
            from .task.gym_env import register_gym_envs

            register_gym_envs()

        spec.loader.exec_module = exec_then_register
        return spec


if "gymnasium" in sys.modules:
    from .task.gym_env import register_gym_envs as _register

    _register()
else:
    sys.meta_path.insert(0, _RegisterWithGymnasium())
