"""pusher_push's figures from a `make push-demo` run: BC against AWAC offline (seed 0, held-out
rollouts, Wilson intervals, the Newcombe interval of the difference) and the online stage on
the success classifier's reward (success without intervention along the curve, and how often
the classifier ended an episode the simulator calls a failure, or missed a success).

    make push-demo && .venv/bin/python bench/push_demo_report.py --json bench/pusher_push_demo.json

The figures are read from the run's own files (``runs/push-demo/{bc,awac}/metrics.json``,
``runs/push-demo/online/summary.json``); the commands that made them are the Makefile's.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from offline_rl_core.benchmarks.harness import run_facts  # noqa: E402
from offline_rl_core.common.atomic import write_json_atomic  # noqa: E402
from offline_rl_core.evaluation.stats import newcombe_diff_ci, wilson_ci  # noqa: E402


def offline_figures(run: Path) -> dict:
    metrics = json.loads(run.read_text())
    ev = metrics["eval"]
    lo, hi = wilson_ci(ev["successes"], ev["episodes"])
    return {"algo": metrics["algorithm"], "steps": metrics["steps"], "seed": metrics["seed"],
            "transitions": metrics["transitions"],
            "successes": ev["successes"], "episodes": ev["episodes"], "success_rate": ev["success_rate"],
            "wilson_ci": [round(lo, 4), round(hi, 4)], "mean_final_dist_m": ev["mean_final_dist"],
            "first_reset_seed": ev["seed"]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", type=Path, default=ROOT / "runs" / "push-demo")
    ap.add_argument("--json", type=Path, required=True)
    args = ap.parse_args()
    recipe = subprocess.run(["make", "-n", "-o", "setup", "push-demo"], cwd=ROOT, capture_output=True, text=True)
    out: dict = {**run_facts(), "make_push_demo": [line.strip() for line in recipe.stdout.splitlines()
                                                    if "offline-rl" in line]}
    bc, awac = offline_figures(args.run / "bc" / "metrics.json"), offline_figures(args.run / "awac" / "metrics.json")
    lo, hi = newcombe_diff_ci(awac["successes"], awac["episodes"], bc["successes"], bc["episodes"])
    # the puck's distance to the goal at the held-out resets: a final distance equal to it is a puck never moved
    from offline_rl_core.task.envs import make_env

    env = make_env("pusher_push")
    start = []
    for seed in range(bc["first_reset_seed"], bc["first_reset_seed"] + bc["episodes"]):
        env.reset(seed)
        start.append(env.distance())
    out["offline"] = {"mean_start_dist_m": round(sum(start) / len(start), 5), "bc": bc, "awac": awac, "awac_minus_bc": round(awac["success_rate"] - bc["success_rate"], 4),
                      "newcombe_ci": [round(lo, 4), round(hi, 4)]}
    summary_path = args.run / "online" / "summary.json"
    if summary_path.exists():
        summary = json.loads(summary_path.read_text())
        out["online"] = {
            "where": summary["where"], "success": summary["config"].get("success"),
            "end_on_success": summary["config"].get("end_on_success"),
            "env_steps": summary["config"]["env_steps"], "prior": summary["prior"],
            "curve": [{k: p[k] for k in ("env_steps", "robot_s", "wall_s", "success", "successes", "ci",
                                         "intervention_rate") if k in p} for p in summary["curve"]],
            "counts": summary["counts"], "intervention_rate": summary["intervention_rate"],
            "wall_seconds": summary["wall_seconds"],
        }
    write_json_atomic(args.json, out)
    print(json.dumps({k: out[k] for k in ("offline",)}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
