"""Choosing the prior (issue 16): learning curves of candidate learners on VALIDATION data.

Nothing here touches the report's data or resets. Each candidate trains on the chapter's
dataset recipe (200 episodes, 30 % expert) collected with data seeds 10 and 11 (the report
uses 0, 1, 2) and is scored on the validation reset seeds 600000..600199 (the report's
held-out resets start at 500000 and never exceed 500000 + 2 + 99).

A constant-rate candidate is trained once and its policy kept at every checkpoint step;
a candidate with a schedule depending on its length (cosine) is trained once per length.
Every record is appended to the JSON file at once, so an interrupted run resumes where it
stopped: ``flock /tmp/pusher-cpu.lock .venv/bin/python bench/prior_selection.py --json
bench/prior_selection.json [--only NAME ...]``. The file also says the commands that filled it
and the machine (one per file); ``--table`` prints bench/RESULTS.md's table of it.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from offline_rl_core.benchmarks.harness import add_run_facts
from offline_rl_core.common.atomic import write_json_atomic
from offline_rl_core.data.collect import collect_transitions
from offline_rl_core.evaluation.rollouts import rollout
from offline_rl_core.learners import TrainConfig, train
from offline_rl_core.serving.policy import LoadedPolicy
from results_page import selection_table

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
    "goal_lr3e3_cos": ({"algo": "filtered_bc", "filter_by": "goal", "lr": 3e-3, "lr_schedule": "cosine"},
                       [8000, 15000, 30000, 60000]),
    "goal_lr3e3": ({"algo": "filtered_bc", "filter_by": "goal", "lr": 3e-3}, [2000, 4000, 8000, 15000, 30000, 60000]),
    "goal_norm_lr1e3": ({"algo": "filtered_bc", "filter_by": "goal", "lr": 1e-3, "normalize": True},
                        [500, 1000, 2000, 4000, 8000, 15000, 30000, 60000]),
    "goal_norm": ({"algo": "filtered_bc", "filter_by": "goal", "normalize": True}, [500, 1000, 2000, 4000, 8000, 15000, 30000]),
    "goal_norm_long": ({"algo": "filtered_bc", "filter_by": "goal", "normalize": True}, [60000, 100000]),
    "goal_norm_cos": ({"algo": "filtered_bc", "filter_by": "goal", "normalize": True, "lr_schedule": "cosine"},
                      [4000, 100000]),
    "goal_norm_lr1e3_cos": ({"algo": "filtered_bc", "filter_by": "goal", "lr": 1e-3, "lr_schedule": "cosine",
                             "normalize": True}, [2000, 8000, 30000]),
    "fbc30_norm_lr1e3": ({"algo": "filtered_bc", "filter_top_frac": 0.3, "lr": 1e-3, "normalize": True},
                         [500, 1000, 2000, 4000, 8000, 15000, 30000]),
    "bc_norm": ({"algo": "bc", "normalize": True}, [2000, 4000, 8000, 15000, 30000]),
    "awac_norm": ({"algo": "awac", "normalize": True}, [2000, 4000, 8000, 15000]),
    "iql_norm": ({"algo": "iql", "normalize": True}, [2000, 4000, 8000, 15000]),
    "goal_b1024_lr2e3": ({"algo": "filtered_bc", "filter_by": "goal", "batch_size": 1024, "lr": 2e-3},
                         [2000, 4000, 8000, 15000]),
    "fbc30_b1024": ({"algo": "filtered_bc", "filter_top_frac": 0.3, "batch_size": 1024}, [2000, 4000, 8000, 15000]),
    "fbc30_b1024_lr1e3_cos": ({"algo": "filtered_bc", "filter_top_frac": 0.3, "batch_size": 1024, "lr": 1e-3,
                               "lr_schedule": "cosine"}, [4000, 8000, 15000]),
    "bc": ({"algo": "bc"}, [2000, 4000, 8000, 15000, 30000, 50000]),
    "bc_norm_long": ({"algo": "bc", "normalize": True}, [2000, 4000, 8000, 15000, 30000, 50000]),
    "awac": ({"algo": "awac"}, [2000, 4000, 8000, 15000]),
    "iql": ({"algo": "iql"}, [2000, 4000, 8000, 15000]),
}


def key(name: str, data_seed: int, length: int | None, expert_frac: float = 0.3) -> str:
    return f"{name}|data{data_seed}" + ("" if length is None else f"|len{length}") + \
        ("" if expert_frac == 0.3 else f"|expert{expert_frac}")


def score(policy_state_ckpt: dict) -> dict:
    res = rollout(LoadedPolicy(policy_state_ckpt).act, VALIDATION_RESETS)
    return {"successes": res.successes, "episodes": res.episodes, "success_rate": res.success_rate,
            "mean_final_dist": round(res.mean_final_dist, 6)}


def run_candidate(name: str, overrides: dict, steps: int, checkpoints: list[int], data, data_seed: int) -> list[dict]:
    overrides = dict(overrides)
    overrides["normalize_obs"] = overrides.pop("normalize", False)  # the first runs z-scored outside the loop
    cfg = TrainConfig(**{**overrides, "steps": steps, "log_every": 500})
    kept: dict[int, tuple[float, dict]] = {}

    def snapshot(step, elapsed, policy_state):
        if step in checkpoints:
            kept[step] = (elapsed, policy_state(0))

    result = train(data, cfg, seed=data_seed, snapshot=snapshot)
    records = []
    for step, (elapsed, state) in sorted(kept.items()):
        ckpt = dict(result.checkpoint, policy_state=state)
        records.append({"candidate": name, "config": CANDIDATES[name][0], "data_seed": data_seed, "steps": step,
                        "run_steps": steps, "train_s": round(elapsed, 3), "kernels": result.checkpoint["kernels"],
                        "train_step": result.step_kind, **score(ckpt)})
    return records


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", default="bench/prior_selection.json")
    ap.add_argument("--only", nargs="*", help="candidate names (default: all)")
    ap.add_argument("--data-seeds", type=int, nargs="*", default=list(DATA_SEEDS))
    ap.add_argument("--expert-frac", type=float, default=0.3, help="share of expert episodes of the datasets")
    ap.add_argument("--table", action="store_true", help="print the results as a markdown table and exit")
    args = ap.parse_args()
    path = Path(args.json)
    done = json.loads(path.read_text()) if path.exists() else {"records": []}
    if args.table:
        print(selection_table(done["records"]))
        return 0
    add_run_facts(done)
    have = {r["key"] for r in done["records"]}
    datasets = {}
    for name in args.only or CANDIDATES:
        overrides, lengths = CANDIDATES[name]
        scheduled = overrides.get("lr_schedule", "constant") != "constant"
        for ds in args.data_seeds:
            if ds not in datasets:
                datasets[ds] = collect_transitions(200, args.expert_frac, ds)
            runs = [(n, [n]) for n in lengths] if scheduled else [(max(lengths), lengths)]
            for steps, checkpoints in runs:
                k = key(name, ds, steps if scheduled else None, args.expert_frac)
                if k in have:
                    continue
                t0 = time.perf_counter()
                recs = run_candidate(name, overrides, steps, checkpoints, datasets[ds], ds)
                for r in recs:
                    r["key"], r["expert_frac"] = k, args.expert_frac
                    print(f"{name:>16} data {ds} {r['steps']:>6} steps {r['train_s']:7.1f}s  "
                          f"success {r['success_rate']:.3f}  dist {r['mean_final_dist']:.4f}", flush=True)
                done["records"].extend(recs)
                have.add(k)
                write_json_atomic(path, done)
                print(f"  ({time.perf_counter() - t0:.0f}s)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
