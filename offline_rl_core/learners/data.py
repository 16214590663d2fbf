"""The fixed dataset as tensors, and the seeded batch sampler.

Every run ("member") of an ensemble has its own dataset view and its own index
stream. Indices are drawn ahead, a chunk of steps at a time, from the member's own
generator, so the hot loop never calls the RNG and a member's batches do not depend
on which other members train beside it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..task import features
from ..task.pusher_reach import SUCCESS_TOL
from ..data.transitions import SOURCE_HUMAN, SOURCE_POLICY, Transitions

INDEX_CHUNK_STEPS = 1000
OBS_GOAL = slice(6, 8)  # (dx, dy) in the observation: target minus fingertip
# derived columns that are often one value throughout (stored as a broadcast view then)
CONSTANT_COLUMNS = ("not_done", "actor_mask", "human")


def _constant(column: np.ndarray) -> bool:
    return len(column) > 0 and bool(np.all(column == column[0]))


@dataclass
class Batch:
    """A batch for all members: tensors shaped (members, batch, dim)."""

    obs: torch.Tensor
    action: torch.Tensor
    reward: torch.Tensor  # (M, B, 1)
    next_obs: torch.Tensor
    not_done: torch.Tensor  # (M, B, 1): 1 - terminated; truncation still bootstraps
    actor_mask: torch.Tensor  # (M, B, 1): 0 where the action must not be imitated
    human: torch.Tensor  # (M, B, 1): 1 where a person chose the action or labelled the state with one
    # (M, B, act_dim): the action to imitate there, the row's action or its label (None: the action)
    label: torch.Tensor | None = None

    def __post_init__(self) -> None:
        if self.label is None:
            self.label = self.action


class MemberData:
    """The tensors of the members' datasets, stacked on a leading member axis.

    When every member trains on the same Transitions object the arrays are shared,
    not copied (a view with a member axis of size 1 broadcast in gather).
    """

    FIELDS = ("obs", "action", "reward", "next_obs", "not_done", "actor_mask", "human", "label")

    def __init__(self, datasets: list[Transitions], device: str = "cpu", capacity: int | None = None,
                 fifo_from: int | None = None):
        """``capacity``: rows to allocate (one shared dataset only), so ``append`` can add
        transitions in place (the online learner's buffer) without new tensors.
        ``fifo_from``: the rows from this index on are a ring: once the buffer is full, each
        appended row replaces the oldest appended one (rows before it, the offline data,
        stay); without it, appending past ``capacity`` raises."""
        self.members = len(datasets)
        self.shared = all(d is datasets[0] for d in datasets)
        sources = [datasets[0]] if self.shared else datasets
        self.sizes = [len(d) for d in datasets]
        n_max = max(len(d) for d in sources)
        if capacity is not None:
            if not self.shared or capacity < n_max:
                raise ValueError("capacity needs one shared dataset and at least its rows")
            n_max = capacity
        self.capacity = n_max
        if fifo_from is not None and not 0 <= fifo_from < n_max:
            raise ValueError("fifo_from must leave at least one row of the capacity for the ring")
        self.fifo_from = fifo_from
        self.appended = 0  # rows appended so far (ring: also those since replaced)
        columns = [self.columns(d) for d in sources]
        for name in self.FIELDS:
            column = columns[0][name]
            if len(columns) == 1 and capacity is None and name in CONSTANT_COLUMNS and _constant(column):
                # one value for every row (no terminals, no takeovers, no person): a broadcast
                # view of it, not a column of a 2M-row bag's length
                out = torch.from_numpy(column[:1].copy()).unsqueeze(0).expand(1, len(column), column.shape[1])
            elif len(columns) == 1 and capacity is None:  # the arrays themselves, no copy
                out = torch.from_numpy(column).unsqueeze(0)
            else:
                out = torch.zeros(len(sources), n_max, columns[0][name].shape[1])
                for i, cols in enumerate(columns):
                    out[i, : len(cols[name])] = torch.from_numpy(cols[name])
            setattr(self, name, out.to(device) if torch.device(device).type != "cpu" else out)

    @staticmethod
    def columns(d: Transitions) -> dict[str, np.ndarray]:
        """The training tensors' columns of ``d``, float32 (N, width)."""
        n = len(d)
        f32 = lambda a, w: np.ascontiguousarray(a, dtype=np.float32).reshape(n, w)  # noqa: E731
        action = f32(d.action, d.action.shape[1])
        return {
            "obs": f32(d.obs, d.obs.shape[1]),
            "action": action,
            "reward": f32(d.reward, 1),
            "next_obs": f32(d.next_obs, d.obs.shape[1]),
            "not_done": f32(1.0 - d.terminated.astype(np.float32), 1),
            # Actions that must not be imitated: the policy's last steps before a human
            # takeover (see ``intervention_actor_mask``); the critic still learns from them.
            "actor_mask": f32(intervention_actor_mask(d), 1),
            "human": f32(d.source == SOURCE_HUMAN, 1),
            # the action a person would take: the row's own (the same array, no copy) unless a
            # label says otherwise (``append``'s labels)
            "label": action,
        }

    @property
    def ring_rows(self) -> int:
        """Rows of the ring (0 without one)."""
        return 0 if self.fifo_from is None else self.capacity - self.fifo_from

    def ring_slot(self, k: int) -> int:
        """The row that appended row ``k`` (counted from 0) is, or was, written to."""
        return self.fifo_from + k % self.ring_rows

    def append(self, rows: Transitions, labels: np.ndarray | None = None) -> None:
        """Write ``rows`` after the current rows, in place (one shared dataset); with a ring,
        over the oldest appended rows once it is full. ``labels`` (N, act_dim), NaN rows where
        none: the action a person (or the scripted corrector) labelled each state with while the
        policy acted; imitated in place of the executed action (the critic keeps that one)."""
        start, n = self.sizes[0], len(rows)
        if self.fifo_from is None and start + n > self.capacity:
            raise ValueError(f"buffer full: {start} + {n} rows > capacity {self.capacity}")
        cols = self.columns(rows)
        cols["actor_mask"][:] = 1.0  # takeovers are judged offline, over whole episodes
        if labels is not None:
            labels = np.asarray(labels, np.float32).reshape(n, -1)
            if labels.shape != cols["action"].shape:
                raise ValueError(f"labels of shape {labels.shape} for {n} rows of {cols['action'].shape[1]} actions")
            given = np.isfinite(labels).all(axis=1)
            cols["label"] = np.where(given[:, None], labels, cols["action"])
            cols["human"] = np.maximum(cols["human"], given[:, None].astype(np.float32))
        first, skip = self.appended, 0
        if self.fifo_from is not None and n > self.ring_rows:  # only the newest fit
            skip = n - self.ring_rows
        k = first + skip
        while k < first + n:
            slot = self.ring_slot(k) if self.fifo_from is not None else start + (k - first)
            run = first + n - k if self.fifo_from is None else min(first + n - k, self.capacity - slot)
            for name in self.FIELDS:
                chunk = torch.from_numpy(cols[name][k - first: k - first + run])
                getattr(self, name)[0, slot: slot + run] = chunk.to(self.obs.device)
            k += run
        self.appended += n
        held = start + n if self.fifo_from is None else self.fifo_from + min(self.appended, self.ring_rows)
        self.sizes = [held] * self.members

    def gather(self, idx: torch.Tensor) -> Batch:
        """idx: (M, B) row indices, one row of indices per member."""
        if self.shared:
            flat = idx.reshape(-1)
            m, b = idx.shape
            take = lambda t: t[0].index_select(0, flat).view(m, b, -1)  # noqa: E731
        else:
            rows = torch.arange(idx.shape[0], device=idx.device).unsqueeze(1)
            take = lambda t: t[rows, idx]  # noqa: E731
        return Batch(*(take(getattr(self, name)) for name in self.FIELDS))


class IndexSampler:
    """Uniform-with-replacement row indices, optionally from two pools at a set ratio.

    ``pools[m]`` is None (all rows of member m), or a tuple ``(main, extra)`` of index
    arrays: each batch takes ``round(ratio * batch)`` rows from ``extra`` (e.g. the
    correction transitions) and the rest from ``main``.
    """

    def __init__(self, sizes: list[int], batch_size: int, generators: list[torch.Generator],
                 pools: list | None = None, ratio: float | None = None, device: str = "cpu"):
        self.sizes = sizes
        self.device = torch.device(device)
        self.batch_size = batch_size
        self.generators = generators
        self.pools = pools or [None] * len(sizes)
        self.ratio = ratio
        self._chunk: torch.Tensor | None = None
        self._pos = 0

    def _draw(self, m: int, steps: int) -> torch.Tensor:
        gen = self.generators[m]
        pool = self.pools[m]
        if pool is None:
            return torch.randint(0, self.sizes[m], (steps, self.batch_size), generator=gen)
        main, extra = pool
        n_extra = 0 if extra is None or len(extra) == 0 else int(round((self.ratio or 0.0) * self.batch_size))
        if main is None or len(main) == 0:
            n_extra = self.batch_size
        parts = []
        if n_extra < self.batch_size:
            pick = torch.randint(0, len(main), (steps, self.batch_size - n_extra), generator=gen)
            parts.append(main[pick])
        if n_extra > 0:
            pick = torch.randint(0, len(extra), (steps, n_extra), generator=gen)
            parts.append(extra[pick])
        return torch.cat(parts, dim=1)

    def state(self) -> dict:
        return {"generators": [g.get_state() for g in self.generators], "chunk": self._chunk, "pos": self._pos}

    def load_state(self, state: dict) -> None:
        for g, s in zip(self.generators, state["generators"]):
            g.set_state(s)
        self._chunk = None if state["chunk"] is None else state["chunk"].to(self.device)
        self._pos = int(state["pos"])

    def next(self) -> torch.Tensor:
        """(M, B) indices for the next step."""
        if self._chunk is None or self._pos == self._chunk.shape[1]:
            # drawn on the CPU whatever the device, so a seed gives the same batches everywhere
            chunk = torch.stack([self._draw(m, INDEX_CHUNK_STEPS) for m in range(len(self.sizes))])
            self._chunk = chunk.to(self.device)
            self._pos = 0
        idx = self._chunk[:, self._pos]
        self._pos += 1
        return idx


def top_episode_rows(data: Transitions, top_frac: float) -> np.ndarray:
    """Row indices of the best ``top_frac`` of episodes by undiscounted return
    (at least one episode): the filtered-BC dataset."""
    ids, returns, _ = data.episode_returns()
    keep = max(1, int(np.ceil(top_frac * len(ids))))
    # stable sort on -return: ties keep episode order, so the choice is reproducible
    best = ids[np.argsort(-returns, kind="stable")[:keep]]
    return np.flatnonzero(np.isin(data.episode, best))


def episodes_at_goal(data: Transitions, task=None) -> tuple[np.ndarray, np.ndarray]:
    """(episode ids sorted, whether each ends at the goal): its last observation within
    the success tolerance of the target. A demonstration ends there; random actions that
    pass through the goal on the way almost never do.

    ``task`` (a ``TaskSpec``; default pusher_reach): the observation's columns of the success
    distance (``features.success_columns``); a task whose observation has none is judged by
    the last step's success flag (at the goal then, for a task that judges success at the
    episode's end)."""
    order = np.lexsort((data.step, data.episode))
    ep = data.episode[order]
    last = order[np.r_[ep[1:] != ep[:-1], True]] if len(data) else order
    columns, tolerance = (OBS_GOAL, SUCCESS_TOL) if task is None else \
        (features.success_columns(task), task.reward.success_within)
    if columns is None:
        return data.episode[last], data.success[last].astype(bool)
    goal = data.next_obs[last, columns].astype(np.float64)
    dist = np.hypot(goal[:, 0], goal[:, 1]) if goal.shape[1] == 2 else np.sqrt(np.sum(goal * goal, axis=1))
    return data.episode[last], dist < tolerance


def goal_episode_rows(data: Transitions, task=None) -> np.ndarray:
    """Row indices of the episodes that end at the goal: the filtered-BC dataset of
    ``--filter-by goal`` (``task``: as ``episodes_at_goal``)."""
    ids, at_goal = episodes_at_goal(data, task)
    if not at_goal.any():
        raise ValueError("filtered BC by goal: no episode of the data ends at the goal")
    return np.flatnonzero(np.isin(data.episode, ids[at_goal]))


# How many policy steps before a takeover count as the failure the person corrected.
PRE_TAKEOVER_STEPS = 5


def intervention_actor_mask(data: Transitions, pre_steps: int = PRE_TAKEOVER_STEPS) -> np.ndarray:
    """1.0 for rows whose action the actor may imitate, 0.0 for the policy's last
    ``pre_steps`` actions before each human takeover.

    A takeover is evidence that what the policy was doing was failing, so those
    actions are not regression targets (AWAC/IQL/BC). They stay in the critic's data:
    they teach Q what the failure cost. Rows are matched within an episode by step.
    """
    mask = np.ones(len(data), dtype=np.float32)
    if len(data) == 0 or not np.any(data.source == SOURCE_HUMAN):
        return mask
    order = np.lexsort((data.step, data.episode))
    src = data.source[order]
    ep = data.episode[order]
    # a takeover: a human row whose predecessor in the same episode is a policy row
    takeover = np.flatnonzero((src[1:] == SOURCE_HUMAN) & (src[:-1] == SOURCE_POLICY) & (ep[1:] == ep[:-1])) + 1
    for t in takeover:
        lo = t - 1
        while lo >= 0 and t - lo <= pre_steps and ep[lo] == ep[t] and src[lo] == SOURCE_POLICY:
            mask[order[lo]] = 0.0
            lo -= 1
    return mask


def correction_pools(data: Transitions) -> tuple[np.ndarray, np.ndarray]:
    """(offline prior rows, correction-run rows).

    Correction runs are the transitions logged while the served policy acted with a
    person (or the scripted corrector) ready to take over: sources policy and human.
    Sampling them at a fixed share of each batch is RLPD / HIL-SERL's symmetric
    sampling: the few new transitions are not drowned by the large prior dataset.
    """
    is_corr = (data.source == SOURCE_POLICY) | (data.source == SOURCE_HUMAN)
    return np.flatnonzero(~is_corr), np.flatnonzero(is_corr)
