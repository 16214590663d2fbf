"""Training and scoring a success classifier from bags (``offline-rl classifier``).

A bag holds transitions, or a robot's raw topics (joined as its task says:
``data.raw_topics``). Labels come from each bag's ``episode_label`` topic (a person's,
``data.episode_labels``) or,
for simulated data, from the simulator's success at each episode's end; ``labels="auto"``
takes the topic where a bag has one. ``successes`` / ``failures`` keep the first that many of
each, in episode order (a classifier from a few labelled episodes, as a person would give
them). The task is the one the bags record (else ``--task``, else pusher_reach), kept in the
file: a classifier of one task is refused by another's learner.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..common.errors import UserError
from ..data.bag import read_transitions
from ..data.episode_labels import episode_labels, labels_from_success
from ..data.task_record import task_of_bag
from ..learners.success_classifier import ClassifierConfig, labelled_states, save_classifier, train_classifier

LABEL_SOURCES = ("auto", "topic", "simulator")


@dataclass
class LabelledBag:
    path: str
    data: object  # Transitions
    labels: dict[int, bool]
    source: str  # topic | simulator


def bag_transitions(path) -> tuple[object, list[int] | None]:
    """A bag's transitions: those it records, or (a robot's raw topics, a session of
    `hil --online --from-topics`) those the join builds from its topics as its task says, with
    when each episode's first state came (what a person's label without an episode is told by)."""
    from ..data.bag.reader import records_transitions

    if records_transitions(path):
        return read_transitions(path), None
    from ..data.raw_topics import transitions_from_topics

    data, report = transitions_from_topics(path)
    return data, report.episode_first_received


def labelled_bags(paths: list[str], labels: str = "auto", successes: int | None = None,
                  failures: int | None = None) -> list[LabelledBag]:
    """Each bag's transitions and labels, the first ``successes`` / ``failures`` kept over all bags."""
    if labels not in LABEL_SOURCES:
        raise UserError(f"--labels must be one of {', '.join(LABEL_SOURCES)}, got {labels!r}")
    out = []
    left = {True: successes, False: failures}
    for path in paths:
        data, starts = bag_transitions(path)
        found = episode_labels(path, starts) if labels in ("auto", "topic") else {}
        if labels == "topic" and not found:
            raise UserError(f"{path}: no episode_label messages (label episodes with the corrector's keys or a "
                            "gamepad, or give --labels simulator for simulated data)")
        source = "topic" if found else "simulator"
        chosen = {}
        for episode, success in sorted((found or labels_from_success(data)).items()):
            if left[success] is None or left[success] > 0:
                chosen[episode] = success
                if left[success] is not None:
                    left[success] -= 1
        out.append(LabelledBag(str(path), data, chosen, source))
    short = [f"{n} more {'successes' if k else 'failures'}" for k, n in left.items() if n]
    if short:
        raise UserError(f"the bags hold too few labelled episodes: {' and '.join(short)} wanted")
    return out


def train_from_bags(paths: list[str], out: str | os.PathLike, cfg: ClassifierConfig, seed: int = 0,
                    labels: str = "auto", successes: int | None = None, failures: int | None = None,
                    task=None) -> dict:
    """Train on the bags' labelled episodes and write the classifier to ``out``; its contents."""
    task = task_of_bag(paths[0], task)
    bags = labelled_bags(paths, labels, successes, failures)
    obs, ys = [], []
    for bag in bags:
        if bag.data.obs.shape[1] != task.obs_dim:
            raise UserError(f"{bag.path}: its transitions have {bag.data.obs.shape[1]} observations; task "
                            f"{task.name} has {task.obs_dim}")
        o, y = labelled_states(bag.data, bag.labels, cfg.tail, cfg.head)
        obs.append(o)
        ys.append(y)
    every = {f"{b.path}#{e}": s for b in bags for e, s in b.labels.items()}
    contents = train_classifier(np.concatenate(obs), np.concatenate(ys), cfg, seed, task, every)
    contents["trained_on"].update(bags=[b.path for b in bags], labels=sorted({b.source for b in bags}))
    save_classifier(out, contents)
    return contents


def score_on_bags(classifier, paths: list[str], labels: str = "auto") -> dict:
    """The classifier's judgement of each labelled episode's last state against its label:
    false-positive rate (failures judged successes) and false-negative rate (successes judged
    failures), with the counts."""
    fp = fn = pos = neg = 0
    for bag in labelled_bags(paths, labels):
        episodes = sorted(bag.labels)
        order = np.lexsort((bag.data.step, bag.data.episode))
        ep = bag.data.episode[order]
        last = order[np.r_[ep[1:] != ep[:-1], True]]
        last_of = dict(zip(bag.data.episode[last].tolist(), last.tolist()))
        judged = classifier.success(bag.data.next_obs[[last_of[e] for e in episodes]])
        truth = np.array([bag.labels[e] for e in episodes])
        fp += int((judged & ~truth).sum())
        fn += int((~judged & truth).sum())
        pos += int(truth.sum())
        neg += int((~truth).sum())
    return {"episodes": pos + neg, "successes": pos, "failures": neg, "false_positives": fp, "false_negatives": fn,
            "false_positive_rate": round(fp / neg, 6) if neg else None,
            "false_negative_rate": round(fn / pos, 6) if pos else None}


def default_out(out: str | None) -> Path:
    return Path(out or "runs/classifier.pt")
