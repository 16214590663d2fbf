"""The chapter's experiment, reproduced: the figures of bench/RESULTS.md's first section.

    python bench/chapter_report.py [--out runs/chapter] [--json bench/chapter_report.json] [--only ARM ...]

Each arm is one ``offline-rl experiment --seeds 0 1 2`` (per seed: the chapter's dataset, BC
beside the offline learner, 8000 steps, the chapter's 100 pooled held-out rollouts): AWAC,
IQL and filtered BC on the chapter's mix, AWAC and naive max-Q on expert-only data (the
Break-It). An arm whose metrics are all under ``--out`` is not run again, so the script can
be resumed. Writes each seed's metrics.json per arm with the arm's command, the commands of
this script that filled the file and the machine (one per file: success rates depend on the
CPU's kernels).
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
from pathlib import Path

from offline_rl_core.benchmarks.harness import add_run_facts
from offline_rl_core.common.atomic import write_json_atomic

SEEDS = ("0", "1", "2")
ARMS = {  # arm -> the experiment's flags beyond --seeds and --out; the chapter's own arms first
    "mix_awac": [],
    "expert_awac": ["--expert-frac", "1.0"],
    "expert_naive": ["--algo", "naive", "--expert-frac", "1.0"],
    "mix_iql": ["--algo", "iql"],
    "mix_filtered_bc": ["--algo", "filtered_bc"],
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="runs/chapter", help="the experiments' directories (one per arm)")
    ap.add_argument("--json", default="bench/chapter_report.json")
    ap.add_argument("--only", nargs="+", choices=list(ARMS))
    args = ap.parse_args()
    path = Path(args.json)
    store = json.loads(path.read_text()) if path.exists() else {}
    add_run_facts(store)
    arms = store.setdefault("arms", {})
    for arm, flags in ARMS.items():
        if args.only and arm not in args.only:
            continue
        out = Path(args.out) / arm
        command = ["experiment", "--seeds", *SEEDS, *flags, "--out", str(out)]
        metrics = [out / f"seed_{s}" / "metrics.json" for s in SEEDS]
        if not all(m.exists() for m in metrics):
            print("$ offline-rl " + shlex.join(command), file=sys.stderr, flush=True)
            subprocess.run([sys.executable, "-m", "offline_rl_core", *command], check=True)
        arms[arm] = {"command": shlex.join(["offline-rl", *command]),
                     "seeds": {s: json.loads(m.read_text()) for s, m in zip(SEEDS, metrics)}}
        write_json_atomic(path, store)
    print(f"wrote {args.json}; python bench/results_page.py puts it on bench/RESULTS.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
