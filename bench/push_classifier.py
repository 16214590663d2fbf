"""The success classifier's error rates on pusher_push's held-out episodes (issue 26).

A person labels 20 successes and 20 failures; the classifier (``offline-rl classifier train``)
learns from them and is judged on episodes it never saw, against the simulator's success:

- training episodes (reset seeds ``TRAIN_SEED`` + ep): the expert's, the expert's with noise
  on its actions (near misses: the puck pushed close to the goal, not onto it) and random
  actions, each labelled by the simulator at its end (standing in for the person); the first
  20 of each label are kept;
- held-out episodes (``HELD_OUT_SEED`` + ep, never a training reset): the same three kinds.

Reported: episode false-positive rate (failures whose last state is judged a success) and
false-negative rate (successes whose last state is judged a failure), and the same per state
(every state against the simulator's success of that state): the online stage judges every
state, so a state's false positive is a reward (and an episode's end) it should not have had.

    .venv/bin/python bench/push_classifier.py --json bench/pusher_push_classifier.json
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from offline_rl_core.common.atomic import write_json_atomic
from offline_rl_core.benchmarks.harness import run_facts
from offline_rl_core.data.bag.writer import write_transitions
from offline_rl_core.data.episode_labels import labels_from_success
from offline_rl_core.data.transitions import Layout, Transitions
from offline_rl_core.evaluation.stats import wilson_ci
from offline_rl_core.learners.success_classifier import ClassifierConfig, load_classifier
from offline_rl_core.runs.classifier_run import score_on_bags, train_from_bags
from offline_rl_core.runs.online_loop import transition_row
from offline_rl_core.task.envs import make_env, point_vectors, task_expert
from offline_rl_core.task.spec import load_task

TRAIN_SEED = 700000
HELD_OUT_SEED = 800000
KINDS = {"expert": 0.0, "noisy_expert": 0.6, "random": None}  # std of the noise on the expert's actions


def episodes(task, n_per_kind: int, seed: int) -> Transitions:
    """``n_per_kind`` episodes of each kind, interleaved, on reset seeds seed, seed + 1, ..."""
    env = make_env(task, terminate_on_success=False)
    expert = task_expert(task)
    rng = np.random.default_rng(seed)
    rows = []
    for ep in range(n_per_kind * len(KINDS)):
        noise = list(KINDS.values())[ep % len(KINDS)]
        obs = env.reset(seed + ep)
        done, step = False, 0
        while not done:
            if noise is None:
                action = rng.uniform(-1, 1, task.act_dim)
            else:
                action = expert(env.joint_positions, env.joint_velocities, env.goal,
                                point_vectors(task, env.point_positions()))
                action = np.clip(action + rng.normal(0, noise, task.act_dim), -1, 1) if noise else action
            next_obs, reward, done, info = env.step(np.asarray(action, np.float32))
            rows.append(transition_row(obs, action, reward, next_obs, info, ep, step, 0))
            obs, step = next_obs, step + 1
    return Transitions.from_rows(np.stack(rows), Layout(task.obs_dim, task.act_dim))


def ends_at_first_success(data: Transitions, judged: np.ndarray, truth: np.ndarray) -> dict:
    """The classifier ending episodes (--end-on-success): each held-out episode cut at its first
    state judged a success. A false end: that state is no success by the simulator; a missed
    success: an episode that reaches one and is never judged one (it runs to its time limit)."""
    ends = false_ends = missed = reaching = 0
    for e in np.unique(data.episode):
        at = np.flatnonzero(data.episode == e)
        first = np.flatnonzero(judged[at])
        reaching += bool(truth[at].any())
        if first.size:
            ends += 1
            false_ends += not truth[at[first[0]]]
        elif truth[at].any():
            missed += 1
    return {"episodes": int(np.unique(data.episode).size), "ended": ends,
            "false_ends": rate(false_ends, ends), "missed": rate(missed, reaching)}


def rate(k: int, n: int) -> dict:
    lo, hi = wilson_ci(k, n) if n else (None, None)
    return {"count": k, "of": n, "rate": round(k / n, 6) if n else None,
            "wilson_ci": None if lo is None else [round(lo, 4), round(hi, 4)]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--successes", type=int, default=20)
    ap.add_argument("--failures", type=int, default=20)
    ap.add_argument("--train-per-kind", type=int, default=30, help="training episodes of each kind")
    ap.add_argument("--held-out-per-kind", type=int, default=40, help="held-out episodes of each kind")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--head", type=int, default=0, help="classifier train --head: first states of every episode "
                    "that are failures")
    ap.add_argument("--threshold", type=float, default=0.5, help="classifier train --threshold: the probability "
                    "from which a state is judged a success")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    task = load_task("pusher_push")
    t0 = time.perf_counter()
    train_data = episodes(task, args.train_per_kind, TRAIN_SEED)
    held_out = episodes(task, args.held_out_per_kind, HELD_OUT_SEED)
    rollout_s = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        train_bag, held_bag = Path(tmp) / "train.db3", Path(tmp) / "held_out.db3"
        # the simulator's word stands in for the person's labels, recorded as a person's are
        write_transitions(train_bag, train_data, task=task, labels=labels_from_success(train_data))
        write_transitions(held_bag, held_out, task=task, labels=labels_from_success(held_out))
        t1 = time.perf_counter()
        contents = train_from_bags([str(train_bag)], Path(tmp) / "cls.pt", ClassifierConfig(head=args.head, threshold=args.threshold), args.seed,
                                   labels="topic", successes=args.successes, failures=args.failures)
        train_s = time.perf_counter() - t1
        judge = load_classifier(Path(tmp) / "cls.pt", task)
        by_episode = score_on_bags(judge, [str(held_bag)], labels="topic")
    judged = judge.success(held_out.next_obs)
    truth = held_out.success.astype(bool)
    kinds = list(KINDS)
    kind_of = held_out.episode % len(KINDS)
    labels = labels_from_success(held_out)
    per_kind = {kinds[k]: int(sum(labels[e] for e in labels if e % len(KINDS) == k)) for k in range(len(KINDS))}
    result = {
        **run_facts(),  # command, machine (CPU model and flags), measured_at
        "task": task.name, "task_digest": task.digest,
        "trained_on": {k: v for k, v in contents["trained_on"].items() if k != "bags"},
        "classifier": contents["config"], "seed": args.seed,
        "train_reset_seeds": [TRAIN_SEED, TRAIN_SEED + args.train_per_kind * len(KINDS) - 1],
        "held_out_reset_seeds": [HELD_OUT_SEED, HELD_OUT_SEED + args.held_out_per_kind * len(KINDS) - 1],
        "held_out_episodes": {"episodes": by_episode["episodes"], "successes": by_episode["successes"],
                              "failures": by_episode["failures"], "successes_by_kind": per_kind,
                              "false_positive": rate(by_episode["false_positives"], by_episode["failures"]),
                              "false_negative": rate(by_episode["false_negatives"], by_episode["successes"])},
        "held_out_states": {"states": int(len(truth)), "success_states": int(truth.sum()),
                            "false_positive": rate(int((judged & ~truth).sum()), int((~truth).sum())),
                            "false_negative": rate(int((~judged & truth).sum()), int(truth.sum())),
                            "false_positive_noisy_expert": rate(int((judged & ~truth & (kind_of == 1)).sum()),
                                                                int((~truth & (kind_of == 1)).sum()))},
        "as_the_episodes_end": ends_at_first_success(held_out, judged, truth),
        "rollout_s": round(rollout_s, 1), "train_s": round(train_s, 1),
    }
    if args.json:
        write_json_atomic(args.json, result)
    print({k: result[k] for k in ("held_out_episodes", "held_out_states", "as_the_episodes_end")})
    return 0


if __name__ == "__main__":
    sys.exit(main())
