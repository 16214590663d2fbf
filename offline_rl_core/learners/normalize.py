"""Observation normalisation for training, folded into the saved networks.

The observation mixes scales: joint cos/sin and velocities of order 1, the fingertip's
offset to the target (dx, dy) of a few centimetres. A network that must resolve the
last two centimetres to succeed learns that far faster from z-scored inputs
(bench/RESULTS.md, "Choosing the prior"). With ``--normalize-obs`` a run trains on
``(obs - mean) / std`` with the statistics of the rows it samples; the checkpoint then
folds them into each network's first layer (``W' = W / std``, ``b' = b - W' mean``), so
it takes raw observations like every other checkpoint: the policy node, ONNX export and
a warm start need nothing new.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from ..data.transitions import Transitions

MIN_STD = 1e-6  # a constant feature stays as it is


def obs_stats(data: Transitions, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(mean, std) of the observations in ``rows`` (default: all), float32."""
    if rows is not None and len(rows) == 0:
        rows = None
    obs = data.obs if rows is None else data.obs[rows]
    mean = obs.astype(np.float64).mean(0)
    std = obs.astype(np.float64).std(0)
    return mean.astype(np.float32), np.where(std < MIN_STD, 1.0, std).astype(np.float32)


def normalized(data: Transitions, mean: np.ndarray, std: np.ndarray) -> Transitions:
    """``data`` with obs and next_obs z-scored (a copy; everything else shared)."""
    return replace(data, obs=((data.obs - mean) / std).astype(np.float32),
                   next_obs=((data.next_obs - mean) / std).astype(np.float32))


def _map_first_layers(state: dict, fn) -> dict:
    """Apply ``fn(weight, bias)`` to the first layer of every network in ``state``: a
    network's state dict (``0.weight`` of shape (hidden, inputs), its first ``obs_dim``
    inputs the observation), or a dict of those (a learner's critics and value)."""
    if "0.weight" in state:
        return {**state, **dict(zip(("0.weight", "0.bias"), fn(state["0.weight"], state["0.bias"])))}
    return {k: _map_first_layers(v, fn) if isinstance(v, dict) else v for k, v in state.items()}


def fold(state: dict, mean: np.ndarray, std: np.ndarray) -> dict:
    """Networks trained on normalised observations as networks of raw observations."""
    mean_t, std_t = torch.from_numpy(mean), torch.from_numpy(std)
    n = len(mean)

    def one(w, b):
        w = w.clone()
        w[:, :n] = w[:, :n] / std_t
        return w, b - w[:, :n] @ mean_t

    return _map_first_layers(state, one)


def unfold(state: dict, mean: np.ndarray, std: np.ndarray) -> dict:
    """The inverse of ``fold``: raw-observation networks (a warm start) in normalised form."""
    mean_t, std_t = torch.from_numpy(mean), torch.from_numpy(std)
    n = len(mean)

    def one(w, b):
        w = w.clone()
        b = b + w[:, :n] @ mean_t
        w[:, :n] = w[:, :n] * std_t
        return w, b

    return _map_first_layers(state, one)
