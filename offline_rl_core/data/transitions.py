"""The dataset's unit: a batch of transitions as flat numpy arrays, plus the bag layout.

One row per environment step. The field order is the `/pusher/transition` layout of the
design, each field labelled with its size: ``obs`` and ``next_obs`` have the task's
observation size, ``action`` its action size (8 and 2 on pusher-reach: 25 float32 values a
message), every other field one value.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, fields
from functools import cached_property

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

FIELD_NAMES = ("obs", "action", "reward", "next_obs", "terminated", "truncated", "success", "episode", "step",
               "source")


@dataclass(frozen=True)
class Layout:
    """The fields of one transition row, in message order, sized for a task."""

    obs_dim: int
    act_dim: int

    @cached_property
    def fields(self) -> tuple[tuple[str, int], ...]:
        """(label, size) in message order; readers check the labels, not just the length."""
        sizes = {"obs": self.obs_dim, "action": self.act_dim, "next_obs": self.obs_dim}
        return tuple((name, sizes.get(name, 1)) for name in FIELD_NAMES)

    @cached_property
    def width(self) -> int:
        return sum(size for _, size in self.fields)

    @cached_property
    def slices(self) -> dict[str, slice]:
        """Column slices into one row."""
        offsets = np.cumsum([0] + [size for _, size in self.fields])
        return {label: slice(int(offsets[i]), int(offsets[i + 1])) for i, (label, _) in enumerate(self.fields)}

    @classmethod
    def of_fields(cls, fields: tuple[tuple[str, int], ...]) -> "Layout | None":
        """The layout whose labelled fields these are, or None (other labels, order or sizes)."""
        if tuple(label for label, _ in fields) != FIELD_NAMES:
            return None
        sizes = dict(fields)
        if sizes["obs"] < 1 or sizes["action"] < 1 or sizes["next_obs"] != sizes["obs"] or any(
                sizes[n] != 1 for n in FIELD_NAMES if n not in ("obs", "action", "next_obs")):
            return None
        return cls(sizes["obs"], sizes["action"])

    def describe(self) -> str:
        return ", ".join(f"{label} {size}" for label, size in self.fields)

    def field_of_column(self, column: int) -> str:
        """The label of a column of a row."""
        return next(label for label, _ in self.fields if column < self.slices[label].stop)


PUSHER_LAYOUT = Layout(OBS_DIM, ACT_DIM)  # the chapter's pusher-reach: 25 values
# The pusher-reach layout under its old names (the layout of bags that record no task).
TRANSITION_LAYOUT = PUSHER_LAYOUT.fields
TRANSITION_WIDTH = PUSHER_LAYOUT.width
LAYOUT_SLICES = PUSHER_LAYOUT.slices


@dataclass
class Transitions:
    """Flat arrays of N transitions. Vector fields are (N, dim); scalars are (N,)."""

    obs: np.ndarray  # float32 (N, obs_dim)
    action: np.ndarray  # float32 (N, act_dim)
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

    @property
    def layout(self) -> Layout:
        return Layout(int(self.obs.shape[1]), int(self.action.shape[1]))

    def to_rows(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """The (N, width) float32 matrix (or rows start..stop of it), one bag message per row."""
        layout = self.layout
        stop = len(self) if stop is None else min(stop, len(self))
        rows = np.empty((max(stop - start, 0), layout.width), dtype=np.float32)
        for label, _ in layout.fields:
            rows[:, layout.slices[label]] = getattr(self, label)[start:stop].reshape(len(rows), -1)
        return rows

    @classmethod
    def empty(cls, n: int, layout: Layout = PUSHER_LAYOUT) -> "Transitions":
        """N uninitialised rows with the right dtypes (filled with ``fill_rows``)."""
        def column(label: str, size: int) -> np.ndarray:
            if label in ("terminated", "truncated", "success"):
                return np.empty(n, dtype=bool)
            if label in ("episode", "step", "source"):
                return np.empty(n, dtype=np.int64)
            return np.empty((n, size) if label in ("obs", "action", "next_obs") else n, dtype=np.float32)
        return cls(**{label: column(label, size) for label, size in layout.fields})

    def fill_rows(self, start: int, rows: np.ndarray) -> None:
        """Write a (k, width) float32 block of rows into rows start..start+k."""
        layout = self.layout
        stop = start + len(rows)
        for label, _ in layout.fields:
            block = rows[:, layout.slices[label]]
            target = getattr(self, label)
            if target.ndim == 1:
                block = block[:, 0]
                target[start:stop] = (block != 0) if target.dtype == bool else block
            else:
                target[start:stop] = block

    @classmethod
    def from_rows(cls, rows: np.ndarray, layout: Layout = PUSHER_LAYOUT) -> "Transitions":
        """Split an (N, width) float32 matrix into typed columns (copies, contiguous)."""
        rows = np.asarray(rows, dtype=np.float32)
        if rows.ndim != 2 or rows.shape[1] != layout.width:
            raise ValueError(f"expected ({layout.width},)-wide rows of the layout [{layout.describe()}], "
                             f"got shape {rows.shape}")
        out = cls.empty(len(rows), layout)
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
