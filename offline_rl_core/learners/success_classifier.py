"""A success classifier: whether a state is a success, learned from labelled episodes.

On a real arm no simulator says whether the puck reached the goal; a person labels a few
episodes (success or failure: ``data.episode_labels``) and a small network learns to tell
from the task's observation alone, as HIL-SERL's and LeRobot's reward classifiers do (those
on images; this one on the state). What an episode's label says about its states:

- a success ends at the goal: its last ``tail`` states are successes; its earlier ones may
  or may not be (the puck may have been there a while), so they are not trained on;
- a failure never ended at the goal: every state of it is a failure;
- with ``head``, the first ``head`` states of every episode are failures too, a success's
  included (a task whose resets draw the goal away from where the object starts: pusher_push's),
  so that the approach and the push itself are seen as not yet a success.

``train_classifier`` fits an MLP (``hidden`` x 2, ReLU, one logit) by cross-entropy with
the classes weighted equally, on z-scored observations, seeded (``torch.Generator``), so a
fixed seed gives the same weights. The file (``save_classifier``, ``load_classifier``) is
written like a checkpoint, with the task it judges; ``SuccessClassifier.success(obs)`` is
its judgement (probability >= ``threshold``), which the online stage uses as the success
of each state: the reward's success and the episode's end.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from ..common.errors import UserError
from ..data.transitions import Transitions
from ..serving.checkpoint import read_torch_file, save_checkpoint

CLASSIFIER_FORMAT = "pusher-rl/success-classifier"
CLASSIFIER_VERSION = 1


@dataclass(frozen=True)
class ClassifierConfig:
    hidden: int = 64
    steps: int = 2000
    batch_size: int = 256
    lr: float = 1e-3
    weight_decay: float = 1e-4
    tail: int = 10  # the last states of a success episode that are successes
    head: int = 0  # the first states of every episode that are failures (0: only a failure's)
    threshold: float = 0.5  # probability at and above which a state is judged a success


def labelled_states(data: Transitions, labels: dict[int, bool], tail: int,
                    head: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(observations (N, obs_dim) float32, success (N,) bool) of the labelled episodes: the
    last ``tail`` next-observations of each success, every next-observation of each failure,
    and the first ``head`` of each success as failures."""
    if tail < 1 or head < 0:
        raise ValueError(f"tail must be >= 1 and head >= 0, got tail {tail}, head {head}")
    obs, ys = [], []
    for episode, success in sorted(labels.items()):
        rows = np.flatnonzero(data.episode == episode)
        if not len(rows):
            raise UserError(f"episode {episode} is labelled but holds no transitions")
        rows = rows[np.argsort(data.step[rows], kind="stable")]
        if success:
            first = rows[:max(0, min(head, len(rows) - tail))]  # never a tail state
            obs.append(data.next_obs[first])
            ys.append(np.zeros(len(first), bool))
            rows = rows[-tail:]
        obs.append(data.next_obs[rows])
        ys.append(np.full(len(rows), bool(success)))
    if not obs:
        raise UserError("no labelled episodes to train a success classifier on")
    return np.concatenate(obs).astype(np.float32), np.concatenate(ys)


def _network(obs_dim: int, hidden: int) -> torch.nn.Sequential:
    return torch.nn.Sequential(torch.nn.Linear(obs_dim, hidden), torch.nn.ReLU(), torch.nn.Linear(hidden, hidden),
                               torch.nn.ReLU(), torch.nn.Linear(hidden, 1))


def train_classifier(obs: np.ndarray, success: np.ndarray, cfg: ClassifierConfig, seed: int, task=None,
                     labels: dict | None = None) -> dict:
    """Fit the classifier; returns its file's contents (``save_classifier``)."""
    success = np.asarray(success, bool)
    if success.all() or not success.any():
        raise UserError(f"a success classifier needs labelled successes and failures; got "
                        f"{int(success.sum())} success states and {int((~success).sum())} failure states")
    gen = torch.Generator().manual_seed(int(seed))
    x = torch.from_numpy(np.asarray(obs, np.float32))
    mean, std = x.mean(0), x.std(0).clamp_min(1e-6)
    x = (x - mean) / std
    y = torch.from_numpy(success.astype(np.float32))
    # each class weighs as much as the other, however many states it has
    weight = torch.where(y > 0, 0.5 / y.mean(), 0.5 / (1 - y.mean()))
    torch.manual_seed(int(seed))  # the layers' initial weights
    net = _network(x.shape[1], cfg.hidden)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    loss_fn = torch.nn.BCEWithLogitsLoss(reduction="none")
    for _ in range(cfg.steps):
        idx = torch.randint(0, len(x), (cfg.batch_size,), generator=gen)
        loss = (loss_fn(net(x[idx]).squeeze(1), y[idx]) * weight[idx]).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        judged = torch.sigmoid(net(x).squeeze(1)).numpy() >= cfg.threshold
    return {
        "format": CLASSIFIER_FORMAT, "version": CLASSIFIER_VERSION, "obs_dim": int(x.shape[1]),
        "config": asdict(cfg), "seed": int(seed), "state": net.state_dict(), "obs_mean": mean, "obs_std": std,
        "trained_on": {"states": int(len(y)), "success_states": int(success.sum()),
                       "episodes": None if labels is None else len(labels),
                       "success_episodes": None if labels is None else int(sum(labels.values())),
                       "train_accuracy": round(float((judged == success).mean()), 6)},
        **({} if task is None else {"task": {**task.layout(), "spec": task.describe()}}),
    }


def save_classifier(path: str | os.PathLike, contents: dict) -> Path:
    return save_checkpoint(path, contents)


class SuccessClassifier:
    """A loaded classifier: ``probability(obs)`` and ``success(obs)`` for (N, obs_dim) rows."""

    def __init__(self, contents: dict, source: str = "classifier"):
        self.source = source
        self.contents = contents
        self.cfg = ClassifierConfig(**contents["config"])
        self.threshold = self.cfg.threshold
        self.net = _network(int(contents["obs_dim"]), self.cfg.hidden)
        self.net.load_state_dict(contents["state"])
        self.net.eval()
        self.mean, self.std = contents["obs_mean"], contents["obs_std"]

    @property
    def obs_dim(self) -> int:
        return int(self.contents["obs_dim"])

    def probability(self, obs) -> np.ndarray:
        x = torch.as_tensor(np.asarray(obs, np.float32).reshape(-1, self.obs_dim))
        with torch.no_grad():
            return torch.sigmoid(self.net((x - self.mean) / self.std).squeeze(1)).numpy().astype(np.float64)

    def success(self, obs) -> np.ndarray:
        return self.probability(obs) >= self.threshold


def load_classifier(path: str | os.PathLike, task=None) -> SuccessClassifier:
    """A classifier file, refused in one line when it is none or judges another task than ``task``."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no success classifier there (expected a file of `offline-rl classifier train`)")
    contents = read_torch_file(path)
    if not isinstance(contents, dict) or contents.get("format") != CLASSIFIER_FORMAT:
        raise UserError(f"{path}: not a success classifier (format {contents.get('format') if isinstance(contents, dict) else None!r}, "
                        f"expected {CLASSIFIER_FORMAT!r})")
    if task is not None:
        theirs = contents.get("task") or {}
        if theirs.get("digest") not in (None, task.digest) or int(contents["obs_dim"]) != task.obs_dim:
            raise UserError(f"{path}: the classifier judges task {theirs.get('task')} (digest {theirs.get('digest')}, "
                            f"{contents['obs_dim']} observations); this is task {task.name} (digest {task.digest}, "
                            f"{task.obs_dim} observations)")
    return SuccessClassifier(contents, str(path))
