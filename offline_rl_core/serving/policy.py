"""The policy that serves from a checkpoint: numpy inference, refused for a task it was not trained on."""

from __future__ import annotations

import os

import numpy as np
import torch
from torch import nn

from ..common.errors import UserError
from ..task.spec import DEFAULT_TASK, TaskSpec, load_task
from .checkpoint import checkpoint_layout, load_checkpoint


def policy_sequential(obs_dim: int, hidden: int, act_dim: int) -> nn.Sequential:
    """A single policy as ordinary layers (the form exported to ONNX; the checkpoint's
    ``policy_state`` loads into it); tanh is applied by the caller (``LoadedPolicy.torch_module``)."""
    return nn.Sequential(
        nn.Linear(obs_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, act_dim)
    )


class LoadedPolicy:
    """A trained policy ready to act: ``act(obs) -> actions`` in [-1, 1].

    Inference runs in numpy (float32): for one observation that is several times
    faster than a torch call, which is what the policy node serves.
    """

    def __init__(self, checkpoint: dict, source: str = "<memory>"):
        self.checkpoint = checkpoint
        self.source = source
        self.algorithm = str(checkpoint["algorithm"])
        self.obs_dim = int(checkpoint["obs_dim"])
        self.act_dim = int(checkpoint["act_dim"])
        self.hidden = int(checkpoint["hidden"])
        state = checkpoint["policy_state"]
        # Stored transposed once so a row of observations multiplies directly.
        self._w = [state[f"{i}.weight"].detach().float().numpy().T.copy() for i in (0, 2, 4)]
        self._b = [state[f"{i}.bias"].detach().float().numpy().copy() for i in (0, 2, 4)]
        # the online learner's Gaussian: exploration samples tanh(mean + std * eps)
        log_std = checkpoint.get("exploration_log_std")
        self.exploration_log_std = None if log_std is None else np.asarray(log_std, np.float32).reshape(-1)
        # the online learner's weights carry their version; a trained checkpoint has none
        self.versioned = "weights_version" in checkpoint
        self.weights_version = int(checkpoint.get("weights_version", 0) or 0)
        mean = checkpoint.get("obs_mean")
        std = checkpoint.get("obs_std")
        self._obs_mean = None if mean is None else np.asarray(mean, dtype=np.float32)
        self._obs_std = None if std is None else np.asarray(std, dtype=np.float32)

    def act(self, obs: np.ndarray) -> np.ndarray:
        """obs (obs_dim,) or (N, obs_dim) -> float32 actions of the same leading shape."""
        return np.tanh(self.pre_tanh(obs)).astype(np.float32, copy=False)

    def sample(self, obs: np.ndarray, rng: np.random.Generator, log_std: np.ndarray | float | None = None) -> np.ndarray:
        """An exploration action: tanh(mean + std * eps), eps ~ N(0, 1) from ``rng``, with
        the checkpoint's learnt std (or ``log_std``); in [-1, 1] like ``act``."""
        log_std = self.exploration_log_std if log_std is None else log_std
        mean = self.pre_tanh(obs)
        if log_std is None:
            return np.tanh(mean).astype(np.float32, copy=False)
        eps = rng.standard_normal(mean.shape).astype(np.float32)
        return np.tanh(mean + np.exp(np.asarray(log_std, np.float32)) * eps).astype(np.float32, copy=False)

    def pre_tanh(self, obs: np.ndarray) -> np.ndarray:
        """The network's output before the tanh: float32, shaped like ``act``'s."""
        x = np.asarray(obs, dtype=np.float32)
        single = x.ndim == 1
        if single:
            x = x[None, :]
        if x.shape[-1] != self.obs_dim:
            raise ValueError(f"observation has {x.shape[-1]} values, the policy expects {self.obs_dim}")
        if self._obs_mean is not None:
            x = (x - self._obs_mean) / self._obs_std
        h = np.maximum(x @ self._w[0] + self._b[0], 0.0)
        h = np.maximum(h @ self._w[1] + self._b[1], 0.0)
        y = (h @ self._w[2] + self._b[2]).astype(np.float32, copy=False)
        return y[0] if single else y

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return self.act(obs)

    def torch_module(self) -> torch.nn.Module:
        """The policy as a torch module (obs -> tanh action), e.g. for ONNX export."""
        net = policy_sequential(self.obs_dim, self.hidden, self.act_dim)
        net.load_state_dict({k: v.float() for k, v in self.checkpoint["policy_state"].items()})
        mean = self._obs_mean
        std = self._obs_std

        class TanhPolicy(torch.nn.Module):
            def __init__(self):
                super().__init__()
                self.net = net
                self.register_buffer("obs_mean", torch.as_tensor(mean if mean is not None else np.zeros(net[0].in_features, np.float32)))
                self.register_buffer("obs_std", torch.as_tensor(std if std is not None else np.ones(net[0].in_features, np.float32)))

            def forward(self, obs: torch.Tensor) -> torch.Tensor:
                return torch.tanh(self.net((obs - self.obs_mean) / self.obs_std))

        return TanhPolicy().eval()


def load_policy(path: str | os.PathLike, task: TaskSpec | str | os.PathLike | None = None) -> LoadedPolicy:
    """Load a checkpoint for acting; with ``task`` (a TaskSpec, a built-in name or a task
    file), refuse one of another task."""
    return policy_for_task(load_checkpoint(path), path, task)


def policy_for_task(ckpt: dict, source, task: TaskSpec | str | os.PathLike | None = None) -> LoadedPolicy:
    """A validated checkpoint as a policy; with ``task``, refused in one line naming both
    layouts unless the checkpoint is of that task (same digest and sizes). A checkpoint that
    records no task is pusher_reach's (and refused, without ``task``, when its sizes are not)."""
    if task is None and "task" not in ckpt:
        task = DEFAULT_TASK
    if task is not None:
        task = load_task(task)
        theirs = checkpoint_layout(ckpt)
        if theirs["digest"] != task.digest or int(ckpt["obs_dim"]) != task.obs_dim \
                or int(ckpt["act_dim"]) != task.act_dim:
            recorded = "" if "task" in ckpt else ", recording none"
            raise UserError(
                f"{source}: a checkpoint of task {theirs['task']} (digest {theirs['digest']}{recorded}, "
                f"obs_dim={ckpt['obs_dim']}, act_dim={ckpt['act_dim']}); the task here is {task.name} "
                f"(digest {task.digest}, obs_dim={task.obs_dim}, act_dim={task.act_dim})"
            )
    return LoadedPolicy(ckpt, source=str(source))
