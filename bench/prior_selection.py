"""Choosing the prior (issue 16): learning curves of candidate learners on VALIDATION data.

Nothing here touches the report's data or resets. Each candidate trains on the chapter's
dataset recipe (200 episodes, 30 % expert) collected with data seeds 10 and 11 (the report
uses 0, 1, 2) and is scored on the validation reset seeds 600000..600199 (the report's
held-out resets start at 500000 and never exceed 500000 + 2 + 99).

A constant-rate candidate is trained once and its policy kept at every checkpoint step;
a candidate with a schedule depending on its length (cosine) is trained once per length.
Every record is appended to the JSON file at once, so an interrupted run resumes where it
stopped: ``flock /tmp/pusher-cpu.lock .venv/bin/python bench/prior_selection.py --json
bench/prior_selection.json [--only NAME ...]``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from offline_rl_core.atomic import write_json_atomic
from offline_rl_core.collect import collect_transitions
from offline_rl_core.evaluation import rollout
from offline_rl_core.learners import TrainConfig, train
from offline_rl_core.policy import LoadedPolicy

VALIDATION_RESETS = range(600000, 600200)
DATA_SEEDS = (10, 11)

# name -> (TrainConfig overrides, checkpoint steps (constant rate) or run lengths (scheduled))
CANDIDATES: dict[str, tuple[dict, list[int]]] = {
    "fbc30": ({"algo": "filtered_bc", "filter_top_frac": 0.3}, [2000, 4000, 8000, 15000, 30000, 60000]),
    "fbc30_cos": ({"algo": "filtered_bc", "filter_top_frac": 0.3, "lr_schedule": "cosine"}, [8000, 15000, 30000, 60000]),
    "fbc10": ({"algo": "filtered_bc", "filter_top_frac": 0.1}, [2000, 4000, 8000, 15000, 30000, 60000]),
    "fbc20": ({"algo": "filtered_bc", "filter_top_frac": 0.2}, [2000, 4000, 8000, 15000, 30000, 60000]),
    "fbc50": ({"algo": "filtered_bc", "filter_top_frac": 0.5}, [2000, 4000, 8000, 15000, 30000, 60000]),
    "fbc30_lr1e3": ({"algo": "filtered_bc", "filter_top_frac": 0.3, "lr": 1e-3}, [2000, 4000, 8000, 15000, 30000, 60000]),
    "fbc30_lr1e3_cos": ({"algo": "filtered_bc", "filter_top_frac": 0.3, "lr": 1e-3, "lr_schedule": "cosine"},
                        [8000, 15000, 30000, 60000]),
    "fbc30_lr3e3_cos": ({"algo": "filtered_bc", "filter_top_frac": 0.3, "lr": 3e-3, "lr_schedule": "cosine"},
                        [8000, 15000, 30000]),
    "fbc30_norm": ({"algo": "filtered_bc", "filter_top_frac": 0.3, "normalize": True}, [2000, 4000, 8000, 15000, 30000]),
    "fbc30_norm_lr1e3_cos": ({"algo": "filtered_bc", "filter_top_frac": 0.3, "lr": 1e-3, "lr_schedule": "cosine",
                              "normalize": True}, [8000, 15000, 30000]),
    "goal": ({"algo": "filtered_bc", "filter_by": "goal"}, [2000, 4000, 8000, 15000, 30000, 60000]),
    "goal_lr1e3": ({"algo": "filtered_bc", "filter_by": "goal", "lr": 1e-3}, [2000, 4000, 8000, 15000, 30000, 60000]),
    "goal_lr1e3_cos": ({"algo": "filtered_bc", "filter_by": "goal", "lr": 1e-3, "lr_schedule": "cosine"},
                       [15000, 30000, 60000]),
    "goal_lr3e3": ({"algo": "filtered_bc", "filter_by": "goal", "lr": 3e-3}, [2000, 4000, 8000, 15000, 30000, 60000]),
    "goal_norm_lr1e3": ({"algo": "filtered_bc", "filter_by": "goal", "lr": 1e-3, "normalize": True},
                        [2000, 4000, 8000, 15000, 30000, 60000]),
    "goal_b1024_lr2e3": ({"algo": "filtered_bc", "filter_by": "goal", "batch_size": 1024, "lr": 2e-3},
                         [2000, 4000, 8000, 15000]),
    "fbc30_b1024": ({"algo": "filtered_bc", "filter_top_frac": 0.3, "batch_size": 1024}, [2000, 4000, 8000, 15000]),
    "fbc30_b1024_lr1e3_cos": ({"algo": "filtered_bc", "filter_top_frac": 0.3, "batch_size": 1024, "lr": 1e-3,
                               "lr_schedule": "cosine"}, [4000, 8000, 15000]),
    "bc": ({"algo": "bc"}, [2000, 4000, 8000, 15000, 30000]),
    "awac": ({"algo": "awac"}, [2000, 4000, 8000, 15000]),
    "iql": ({"algo": "iql"}, [2000, 4000, 8000, 15000]),
}


def key(name: str, data_seed: int, length: int | None) -> str:
    return f"{name}|data{data_seed}" + ("" if length is None else f"|len{length}")


def score(policy_state_ckpt: dict, norm=None) -> dict:
    policy = LoadedPolicy(policy_state_ckpt)
    if norm is not None:
        policy = Normalized(policy, *norm)
    res = rollout(policy.act, VALIDATION_RESETS)
    return {"successes": res.successes, "episodes": res.episodes, "success_rate": res.success_rate,
            "mean_final_dist": round(res.mean_final_dist, 6)}


class Normalized:
    """Exploration only: the policy of a run trained on z-scored observations."""

    def __init__(self, policy, mean, std):
        self.policy, self.mean, self.std = policy, mean, std

    def act(self, obs):
        return self.policy.act((obs - self.mean) / self.std)


def normalized(data):
    from dataclasses import replace as dc_replace

    mean, std = data.obs.mean(0), data.obs.std(0) + 1e-6
    return dc_replace(data, obs=((data.obs - mean) / std).astype("float32"),
                      next_obs=((data.next_obs - mean) / std).astype("float32")), mean, std


def run_candidate(name: str, overrides: dict, steps: int, checkpoints: list[int], data, data_seed: int) -> list[dict]:
    overrides = dict(overrides)
    norm = None
    if overrides.pop("normalize", False):
        data, *norm = normalized(data)
    cfg = TrainConfig(**{**overrides, "steps": steps, "log_every": 500})
    kept: dict[int, tuple[float, dict]] = {}

    def snapshot(step, elapsed, learner):
        if step in checkpoints:
            kept[step] = (elapsed, learner.policy.member_state(0))

    result = train(data, cfg, seed=data_seed, snapshot=snapshot)
    records = []
    for step, (elapsed, state) in sorted(kept.items()):
        ckpt = dict(result.checkpoint, policy_state=state)
        records.append({"candidate": name, "config": CANDIDATES[name][0], "data_seed": data_seed, "steps": step,
                        "run_steps": steps, "train_s": round(elapsed, 3), "kernels": result.checkpoint["kernels"],
                        "train_step": result.step_kind, **score(ckpt, norm)})
    return records


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", default="bench/prior_selection.json")
    ap.add_argument("--only", nargs="*", help="candidate names (default: all)")
    ap.add_argument("--data-seeds", type=int, nargs="*", default=list(DATA_SEEDS))
    args = ap.parse_args()
    path = Path(args.json)
    done = json.loads(path.read_text()) if path.exists() else {"records": []}
    have = {r["key"] for r in done["records"]}
    datasets = {}
    for name in args.only or CANDIDATES:
        overrides, lengths = CANDIDATES[name]
        scheduled = overrides.get("lr_schedule", "constant") != "constant"
        for ds in args.data_seeds:
            if ds not in datasets:
                datasets[ds] = collect_transitions(200, 0.3, ds)
            runs = [(n, [n]) for n in lengths] if scheduled else [(max(lengths), lengths)]
            for steps, checkpoints in runs:
                k = key(name, ds, steps if scheduled else None)
                if k in have:
                    continue
                t0 = time.perf_counter()
                recs = run_candidate(name, overrides, steps, checkpoints, datasets[ds], ds)
                for r in recs:
                    r["key"] = k
                    print(f"{name:>16} data {ds} {r['steps']:>6} steps {r['train_s']:7.1f}s  "
                          f"success {r['success_rate']:.3f}  dist {r['mean_final_dist']:.4f}", flush=True)
                done["records"].extend(recs)
                have.add(k)
                write_json_atomic(path, done)
                print(f"  ({time.perf_counter() - t0:.0f}s)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
