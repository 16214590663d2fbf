"""A task's scripted expert on the 100 held-out reset seeds: success (Wilson 95 % CI), final
distance, and the step at which each episode first succeeds, and (a task whose success is
judged at the episode's end, ``reward.success_at: end``) the step from which it stayed a
success: the room the episode length leaves it.

  .venv/bin/python bench/task_expert.py --task pusher7_reach --json bench/pusher7_expert.json
  .venv/bin/python bench/task_expert.py --task pusher_push --json bench/pusher_push_expert.json

The success and final distances are those of `offline-rl eval --task TASK --expert` (the same
rollouts: task.envs.expert_action on reset seeds 500000..500099).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from offline_rl_core.benchmarks.harness import machine_info, utc_now
from offline_rl_core.common.machine import cpu_model_and_flags
from offline_rl_core.common.seeds import HELD_OUT
from offline_rl_core.evaluation.rollouts import round6
from offline_rl_core.evaluation.stats import wilson_ci
from offline_rl_core.task.envs import expert_action, make_env
from offline_rl_core.task.spec import load_task


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", required=True)
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    task = load_task(args.task)
    env = make_env(task)
    first_success, settled, success, final, start = [], [], [], [], time.perf_counter()
    for seed in range(HELD_OUT, HELD_OUT + args.episodes):
        env.reset(seed)
        done, first, since = False, None, None
        while not done:
            _, _, done, info = env.step(expert_action(env))
            if info["success"] and first is None:
                first = env.steps
            since = (since or env.steps) if info["success"] else None
        first_success.append(first)
        settled.append(since)
        success.append(bool(info["success"]))
        final.append(info["dist"])
    wall = time.perf_counter() - start
    reached = [s for s in first_success if s is not None]
    stayed = [s for s in settled if s is not None]
    lo, hi = wilson_ci(sum(success), args.episodes)
    model, flags = cpu_model_and_flags()
    result = {
        "command": "python bench/task_expert.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "task": task.name, "task_digest": task.digest, "reset_seeds": [HELD_OUT, HELD_OUT + args.episodes - 1],
        "episodes": args.episodes, "successes": sum(success), "success_rate": round6(sum(success) / args.episodes),
        "wilson_ci_lo": round6(lo), "wilson_ci_hi": round6(hi),
        "mean_final_dist_m": round6(np.mean(final)), "max_final_dist_m": round6(np.max(final)),
        "success_within_m": task.reward.success_within, "max_steps": task.episodes.max_steps,
        "control_period_s": task.control_period,
        "first_success_step": {"median": float(np.median(reached)) if reached else None,
                               "p95": float(np.percentile(reached, 95)) if reached else None,
                               "max": int(max(reached)) if reached else None},
        **({"success_at": "end", "settled_step": {
            "median": float(np.median(stayed)) if stayed else None,
            "p95": float(np.percentile(stayed, 95)) if stayed else None,
            "max": int(max(stayed)) if stayed else None}} if task.reward.success_at == "end" else {}),
        "wall_s": round(wall, 1), "steps_per_s": round(args.episodes * task.episodes.max_steps / wall, 1),
        "machine": machine_info(), "measured_at": utc_now(),  # for bench/results_page.py
        "cpu": model, "cpu_flags": sorted(f for f in flags if f in ("avx2", "avx512f", "avx512_bf16", "amx_tile")),
    }
    print(json.dumps(result, indent=1))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
