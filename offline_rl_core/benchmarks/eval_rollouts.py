"""Evaluation figure: 100 rollouts batched (``rollout``) against the plain one-env loop.

Both run the same numpy policy (a ``LoadedPolicy``) on the same reset seeds and must
give the same per-episode outcomes; only the speed is compared. A second row runs the
chapter's sequential loop with its torch policy call per step, the cost the chapter
actually pays.
"""

from __future__ import annotations

import time

import numpy as np

from ..evaluation import rollout
from ..learners import TrainConfig, train_seeds
from ..transitions import Transitions
from . import reference_chapter as chapter
from .harness import BenchSettings, figure, interleave, median


def _policy(s: BenchSettings):
    from ..collect import collect_transitions

    data: Transitions = collect_transitions(max(2, s.episodes // 20), 0.3, 0)
    res = train_seeds(data, TrainConfig(algo="bc", steps=max(2, s.train_steps // 5), hidden=s.hidden,
                                        batch_size=s.batch_size), [0])[0]
    return res.policy


def run(s: BenchSettings, log=print) -> list:
    policy = _policy(s)
    torch_policy = chapter.Policy(policy.obs_dim, policy.act_dim, policy.hidden)
    torch_policy.net.load_state_dict({k: v.float() for k, v in policy.checkpoint["policy_state"].items()})
    torch_act = chapter.policy_act_fn(torch_policy)
    seeds = list(range(500000, 500000 + s.eval_episodes))
    batched = rollout(policy.act, seeds, batched=True)
    sequential = rollout(policy.act, seeds, batched=False)
    same = all(np.array_equal(getattr(batched, f), getattr(sequential, f))
               for f in ("success", "final_dist", "returns", "lengths"))

    def rate(fn):
        t0 = time.perf_counter()
        fn()
        return s.eval_episodes / (time.perf_counter() - t0)

    got = {k: median(v) for k, v in interleave({
        "batched": lambda: rate(lambda: rollout(policy.act, seeds, batched=True)),
        "sequential": lambda: rate(lambda: rollout(policy.act, seeds, batched=False)),
        "chapter": lambda: rate(lambda: rollout(torch_act, seeds, batched=False)),
    }, s.eval_repeats).items()}
    log("  episodes/s: " + ", ".join(f"{k} {v:.1f}" for k, v in got.items()) + f"; identical outcomes: {same}")
    n = s.eval_episodes
    return [
        figure("eval", f"rollouts_{n}_episodes_per_s", "episodes/s", got["batched"], got["sequential"],
               "sequential one-env loop (same numpy policy)", target=lambda o, r, x: x >= 5.0, target_text=">= 5x",
               note=f"per-episode outcomes identical: {same}"),
        figure("eval", f"rollouts_{n}_vs_chapter_torch_loop", "episodes/s", got["batched"], got["chapter"],
               "sequential loop, torch policy per step (chapter)", target=lambda o, r, x: x >= 5.0, target_text=">= 5x"),
    ]
