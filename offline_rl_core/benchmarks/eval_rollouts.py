"""Evaluation figure: 100 rollouts batched (``rollout``) against the plain one-env loop.

Both run the same numpy policy (a ``LoadedPolicy``) on the same reset seeds; the note
says whether the per-episode success and lengths are the same and how far final
distances and returns drift (the policy's batched matmul rounds the last bits of the
actions differently, see ``offline_rl_core.evaluation.rollouts``). A second row runs the
chapter's sequential loop with its torch policy call per step, the cost the chapter
actually pays.
"""

from __future__ import annotations

import time

import numpy as np

from ..evaluation.rollouts import rollout
from ..common.seeds import HELD_OUT
from ..learners import TrainConfig, train_seeds
from ..data.transitions import Transitions
from ..runs import chapter_loop as chapter
from .harness import BenchSettings, figure, interleave, median


def _policy(s: BenchSettings):
    from ..data.collect import collect_transitions

    data: Transitions = collect_transitions(max(2, s.episodes // 20), 0.3, 0)
    res = train_seeds(data, TrainConfig(algo="bc", steps=max(2, s.train_steps // 5), hidden=s.hidden,
                                        batch_size=s.batch_size), [0])[0]
    return res.policy


def run(s: BenchSettings, log=print) -> list:
    policy = _policy(s)
    torch_policy = chapter.Policy(policy.obs_dim, policy.act_dim, policy.hidden)
    torch_policy.net.load_state_dict({k: v.float() for k, v in policy.checkpoint["policy_state"].items()})
    torch_act = chapter.policy_act_fn(torch_policy)
    seeds = list(range(HELD_OUT, HELD_OUT + s.eval_episodes))
    batched = rollout(policy.act, seeds, batched=True)
    sequential = rollout(policy.act, seeds, batched=False)
    same = np.array_equal(batched.success, sequential.success) and np.array_equal(batched.lengths, sequential.lengths)
    drift = (f"max |d final_dist| {np.abs(batched.final_dist - sequential.final_dist).max():.1e} m, "
             f"max |d return| {np.abs(batched.returns - sequential.returns).max():.1e}")

    def rate(fn, min_seconds=0.0 if s.tiny else 0.3):
        # Whole rollouts until min_seconds have passed: a ~40 ms batched run alone is
        # at the mercy of one preemption on a shared machine; the ~0.3 s sequential
        # one takes a single run either way.
        runs, t0 = 0, time.perf_counter()
        while runs == 0 or time.perf_counter() - t0 < min_seconds:
            fn()
            runs += 1
        return runs * s.eval_episodes / (time.perf_counter() - t0)

    got = {k: median(v) for k, v in interleave({
        "batched": lambda: rate(lambda: rollout(policy.act, seeds, batched=True)),
        "sequential": lambda: rate(lambda: rollout(policy.act, seeds, batched=False)),
        "chapter": lambda: rate(lambda: rollout(torch_act, seeds, batched=False)),
    }, s.eval_repeats).items()}
    log("  episodes/s: " + ", ".join(f"{k} {v:.1f}" for k, v in got.items())
        + f"; same success and lengths: {same}; {drift}")
    n = s.eval_episodes
    return [
        figure("eval", f"rollouts_{n}_episodes_per_s", "episodes/s", got["batched"], got["sequential"],
               "sequential one-env loop (same numpy policy)", target=lambda o, r, x: x >= 5.0, target_text=">= 5x",
               note=f"per-episode success and lengths identical: {same}; {drift}"),
        figure("eval", f"rollouts_{n}_vs_chapter_torch_loop", "episodes/s", got["batched"], got["chapter"],
               "sequential loop, torch policy per step (chapter)", target=lambda o, r, x: x >= 5.0, target_text=">= 5x"),
    ]
