"""Several robots, one learner: wall time to a success rate with 1, 2 and 4 actors at one budget.

    nice -n 5 python bench/multi_actor.py [--actors 1 2 4] [--env-steps 20000] [--threshold 0.95]
        [--eval-every 2500] [--seed 0] [--out runs/multi-actor] [--json bench/multi_actor.json]

Each arm is ``offline-rl hil --online --actors N --no-prior`` over ROS (lockstep, scripted
corrector, the learner from scratch: from the auto prior the reach starts near 1.00 and there
is nothing to time), with the same total of environment steps over its actors. The learning
curve is the stage's own: the learner's snapshots every ``--eval-every`` steps, each scored
without intervention on the held-out resets. For each arm: the learner's wall time (and
environment steps, gradient updates) at the first snapshot at or past the threshold, the
session's wall time, the share of the learner's wall time spent in gradient steps, and the
machine's load average sampled while it ran (the actors' nodes and the learner share this
machine's cores with whatever else runs on it). A run whose
``summary.json`` exists is not run again. Writes the JSON and prints the table of
bench/RESULTS.md's "Several actors, one learner" (``results_page.multi_actor_table``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

from offline_rl_core.benchmarks.harness import run_facts
from offline_rl_core.common.atomic import write_json_atomic
from results_page import multi_actor_table


class LoadSampler:
    """The 1-minute load average every ``period`` seconds while a run goes."""

    def __init__(self, period: float = 5.0):
        self.period, self.samples = period, []
        self.done = threading.Event()
        self.thread = threading.Thread(target=self.sample, daemon=True)

    def sample(self) -> None:
        while not self.done.wait(self.period):
            self.samples.append(os.getloadavg()[0])

    def __enter__(self) -> "LoadSampler":
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.done.set()
        self.thread.join()

    def summary(self) -> dict:
        s = self.samples or [os.getloadavg()[0]]
        return {"mean": round(sum(s) / len(s), 2), "max": round(max(s), 2), "samples": len(s)}


def first_at(curve: list[dict], threshold: float) -> dict | None:
    """The first point of the learning curve at or past ``threshold``."""
    point = next((p for p in curve if p["success"] >= threshold), None)
    if point is None:
        return None
    return {k: point[k] for k in ("env_steps", "wall_s", "updates", "success", "ci")}


def arm_row(actors: int, summary: dict, load: dict | None, threshold: float, progress: dict) -> dict:
    final = summary["curve"][-1]
    return {"actors": actors,
            # the share of the learner's wall time spent in gradient steps: near 1, the learner bounds the session
            "learner_train_s": progress["train_s"], "learner_wall_s": progress["wall_s"], "threshold": threshold, "reached": first_at(summary["curve"], threshold),
            "final": {k: final[k] for k in ("env_steps", "wall_s", "updates", "success", "ci")},
            "session_wall_s": summary["learner_wall_seconds"], "wall_seconds": summary["wall_seconds"],
            "counts": summary["counts"], "per_actor": summary.get("actors"), "load": load,
            "curve": [{k: p[k] for k in ("env_steps", "wall_s", "updates", "success")} for p in summary["curve"]]}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--actors", type=int, nargs="+", default=[1, 2, 4])
    p.add_argument("--env-steps", type=int, default=20_000, help="total over the actors, every arm alike")
    p.add_argument("--threshold", type=float, default=0.95)
    p.add_argument("--eval-every", type=int, default=2500)
    p.add_argument("--eval-episodes", type=int, default=100)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="runs/multi-actor")
    p.add_argument("--json", default="bench/multi_actor.json")
    p.add_argument("--note", help="what bounded the measurement (a smaller budget or threshold), for the page")
    args = p.parse_args()
    facts = run_facts()
    rows = []
    for n in args.actors:
        out = Path(args.out) / f"actors{n}"
        cmd = [sys.executable, "-m", "offline_rl_core", "hil", "--online", "--actors", str(n), "--no-prior",
               "--seed", str(args.seed), "--env-steps", str(args.env_steps), "--eval-every", str(args.eval_every),
               "--eval-episodes", str(args.eval_episodes), "--logger", "none", "--out", str(out)]
        load = None
        if not (out / "summary.json").exists():
            print("$ " + " ".join(cmd), file=sys.stderr, flush=True)
            t0 = time.monotonic()
            with LoadSampler() as sampler:
                subprocess.run(cmd, check=True)
            load = sampler.summary()
            write_json_atomic(out / "load.json", load)
            print(f"  ({time.monotonic() - t0:.0f} s, load {load['mean']} mean)", file=sys.stderr, flush=True)
        elif (out / "load.json").exists():
            load = json.loads((out / "load.json").read_text())
        progress = json.loads((out / "learner" / "progress.jsonl").read_text().splitlines()[-1])
        rows.append(arm_row(n, json.loads((out / "summary.json").read_text()), load, args.threshold, progress))
        write_json_atomic(args.json, {
            "title": "several actors, one learner", "arms": rows,
            "settings": {"env_steps": args.env_steps, "threshold": args.threshold, "eval_every": args.eval_every,
                         "eval_episodes": args.eval_episodes, "seed": args.seed, "prior": "none", "mode": "lockstep",
                         "corrector": "scripted", "task": "pusher_reach"},
            **({"note": args.note} if args.note else {}), **facts})
    print(multi_actor_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
