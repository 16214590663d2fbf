"""The dataset's unit: a batch of transitions as flat numpy arrays, plus the bag layout.

One row per environment step. The field order and sizes are the `/pusher/transition`
layout of the design (25 float32 values per message, each field labelled).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, fields

import numpy as np

from ..task.pusher_reach import ACT_DIM, OBS_DIM

# Who chose the action of a transition (the `source` field).
SOURCE_EXPERT = 0
SOURCE_RANDOM = 1
SOURCE_POLICY = 2
SOURCE_HUMAN = 3
SOURCE_NAMES = {SOURCE_EXPERT: "expert", SOURCE_RANDOM: "random", SOURCE_POLICY: "policy", SOURCE_HUMAN: "human"}
SOURCE_BY_NAME = {name: code for code, name in SOURCE_NAMES.items()}


def source_from_tag(tag: str) -> int | None:
    """The source a tag names: 'expert', 'random', 'policy', 'human' or the digit 0-3
    (a command's deprecated ``header.frame_id`` tag); None for anything else."""
    tag = tag.strip().lower()
    if tag in SOURCE_BY_NAME:
        return SOURCE_BY_NAME[tag]
    if tag.isdigit() and int(tag) in SOURCE_NAMES:
        return int(tag)
    return None

# (label, size) in message order; readers check the labels, not just the length.
TRANSITION_LAYOUT: tuple[tuple[str, int], ...] = (
    ("obs", OBS_DIM),
    ("action", ACT_DIM),
    ("reward", 1),
    ("next_obs", OBS_DIM),
    ("terminated", 1),
    ("truncated", 1),
    ("success", 1),
    ("episode", 1),
    ("step", 1),
    ("source", 1),
)
TRANSITION_WIDTH = sum(size for _, size in TRANSITION_LAYOUT)  # 25

# Column slices into one 25-float row.
_offsets = np.cumsum([0] + [size for _, size in TRANSITION_LAYOUT])
LAYOUT_SLICES = {label: slice(int(_offsets[i]), int(_offsets[i + 1])) for i, (label, _) in enumerate(TRANSITION_LAYOUT)}


@dataclass
class Transitions:
    """Flat arrays of N transitions. Vector fields are (N, dim); scalars are (N,)."""

    obs: np.ndarray  # float32 (N, 8)
    action: np.ndarray  # float32 (N, 2)
    reward: np.ndarray  # float32 (N,)
    next_obs: np.ndarray  # float32 (N, 8)
    terminated: np.ndarray  # bool (N,)
    truncated: np.ndarray  # bool (N,)
    success: np.ndarray  # bool (N,)
    episode: np.ndarray  # int64 (N,)
    step: np.ndarray  # int64 (N,)
    source: np.ndarray  # int64 (N,)

    def __len__(self) -> int:
        return int(self.obs.shape[0])

    def to_rows(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """The (N, 25) float32 matrix (or rows start..stop of it), one bag message per row."""
        stop = len(self) if stop is None else min(stop, len(self))
        rows = np.empty((max(stop - start, 0), TRANSITION_WIDTH), dtype=np.float32)
        for label, _ in TRANSITION_LAYOUT:
            rows[:, LAYOUT_SLICES[label]] = getattr(self, label)[start:stop].reshape(len(rows), -1)
        return rows

    @classmethod
    def empty(cls, n: int) -> "Transitions":
        """N uninitialised rows with the right dtypes (filled with ``fill_rows``)."""
        def column(label: str, size: int) -> np.ndarray:
            if label in ("terminated", "truncated", "success"):
                return np.empty(n, dtype=bool)
            if label in ("episode", "step", "source"):
                return np.empty(n, dtype=np.int64)
            return np.empty((n, size) if label in ("obs", "action", "next_obs") else n, dtype=np.float32)
        return cls(**{label: column(label, size) for label, size in TRANSITION_LAYOUT})

    def fill_rows(self, start: int, rows: np.ndarray) -> None:
        """Write an (k, 25) float32 block of rows into rows start..start+k."""
        stop = start + len(rows)
        for label, _ in TRANSITION_LAYOUT:
            block = rows[:, LAYOUT_SLICES[label]]
            target = getattr(self, label)
            if target.ndim == 1:
                block = block[:, 0]
                target[start:stop] = (block != 0) if target.dtype == bool else block
            else:
                target[start:stop] = block

    @classmethod
    def from_rows(cls, rows: np.ndarray) -> "Transitions":
        """Split an (N, 25) float32 matrix into typed columns (copies, contiguous)."""
        rows = np.asarray(rows, dtype=np.float32)
        out = cls.empty(len(rows))
        out.fill_rows(0, rows)
        return out

    @classmethod
    def concatenate(cls, parts: list["Transitions"]) -> "Transitions":
        return cls(**{f.name: np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(cls)})

    def select(self, mask_or_index) -> "Transitions":
        return Transitions(**{f.name: getattr(self, f.name)[mask_or_index] for f in fields(self)})

    def episode_returns(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(episode ids, undiscounted returns, source of each episode), sorted by id."""
        ids, inverse = np.unique(self.episode, return_inverse=True)
        returns = np.zeros(len(ids), dtype=np.float64)
        np.add.at(returns, inverse, self.reward.astype(np.float64))
        source = np.zeros(len(ids), dtype=np.int64)
        source[inverse] = self.source
        return ids, returns, source

    def content_hash(self, chunk: int = 65536) -> str:
        """sha256 of the rows: identifies the dataset a checkpoint was trained on.
        Hashed a block of rows at a time, so a large dataset is never copied whole."""
        digest = hashlib.sha256()
        for start in range(0, len(self), chunk):
            digest.update(self.to_rows(start, start + chunk).data)
        return digest.hexdigest()
