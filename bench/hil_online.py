"""The HIL-SERL stage's table: the online stage over ROS on seeds 0, 1, 2 beside its ablations.

    python bench/hil_online.py [--seeds 0 1 2] [--env-steps 20000] [--out runs/hil-table] [--json bench/hil_online.json]

For each seed, with the same environment-step budget:
- ``online``: ``offline-rl hil --online`` over ROS (lockstep, scripted corrector, the
  8000-step AWAC prior of that seed);
- ``no_prior``: the same stage with the learner started from scratch;
- ``no_corrections``: the same stage without the corrector (the prior + online RL alone);
- ``offline_rounds``: issue 6's loop, ``offline-rl hil`` (offline retraining between rounds
  of corrected episodes), with rounds x episodes x 100 steps = the same budget.
The ablations run in one process (``--in-process``), which gives the same bytes as the ROS
stage (tests/test_ros_online.py); the offline rounds run over ROS. A run whose
``summary.json`` exists is not run again, so the script can be resumed. Writes the JSON (the
arms' summaries, the command and the machine) and prints the table of bench/RESULTS.md's
"The HIL-SERL stage" (``results_page.hil_table``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from offline_rl_core.benchmarks.harness import run_facts
from offline_rl_core.common.atomic import write_json_atomic
from results_page import hil_table


def run(cmd: list[str], summary: Path) -> dict:
    if not summary.exists():
        print("$ " + " ".join(cmd), file=sys.stderr, flush=True)
        t0 = time.monotonic()
        subprocess.run(cmd, check=True)
        print(f"  ({time.monotonic() - t0:.0f} s)", file=sys.stderr, flush=True)
    return json.loads(summary.read_text())


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--env-steps", type=int, default=20_000)
    p.add_argument("--out", default="runs/hil-table")
    p.add_argument("--json", default="bench/hil_online.json")
    p.add_argument("--only", nargs="+", choices=("online", "no_prior", "no_corrections", "offline_rounds"))
    args = p.parse_args()
    facts = run_facts()
    offline_rl = [sys.executable, "-m", "offline_rl_core"]
    results: dict = {}
    for seed in args.seeds:
        out = Path(args.out) / f"seed{seed}"
        prior = out / "prior" / "policy.pt"
        if not prior.exists():  # the chapter's 8000-step AWAC prior of this seed
            subprocess.run([*offline_rl, "train", "--bag", "bags/mix.db3", "--algo", "awac", "--steps", "8000",
                            "--seed", str(seed), "--eval-episodes", "0", "--out", str(prior.parent)], check=True)
        stage = [*offline_rl, "hil", "--online", "--seed", str(seed), "--env-steps", str(args.env_steps)]
        arms = {
            "online": [*stage, "--prior", str(prior), "--out", str(out / "online")],
            "no_prior": [*stage, "--no-prior", "--in-process", "--out", str(out / "no_prior")],
            "no_corrections": [*stage, "--prior", str(prior), "--corrector", "none", "--in-process",
                               "--out", str(out / "no_corrections")],
        }
        episodes = 50
        rounds = args.env_steps // (episodes * 100)
        arms["offline_rounds"] = [*offline_rl, "hil", "--rounds", str(rounds), "--episodes", str(episodes), "--seed",
                                  str(seed), "--prior", str(prior), "--out", str(out / "offline_rounds")]
        for arm, cmd in arms.items():
            if args.only and arm not in args.only:
                continue
            summary = run(cmd, Path(cmd[cmd.index("--out") + 1]) / "summary.json")
            results.setdefault(arm, {})[str(seed)] = summary
            write_json_atomic(args.json, {"arms": results, **facts})
    print(hil_table(results))
    plot(results, Path(args.json).with_suffix(".png"))
    return 0


def curve_of(arm: str, summary: dict, episode_steps: int = 100) -> tuple[list[int], list[float]]:
    """(environment steps, success without intervention) along a run (``episode_steps``: the
    task's steps per episode; the chapter's 100)."""
    if arm == "offline_rounds":  # success of the served policy at the start of each round, then the final one
        per_round = summary["rounds"][0]["episodes"] * episode_steps
        steps = [per_round * i for i in range(len(summary["rounds"]) + 1)]
        return steps, [r["success_without_intervention"] for r in summary["rounds"]] + [summary["final_success"]]
    return [p["env_steps"] for p in summary["curve"]], [p["success"] for p in summary["curve"]]


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    labels = {"online": "online stage (prior + corrections), over ROS", "no_prior": "no prior (from scratch)",
              "no_corrections": "no corrections (prior + online RL)", "offline_rounds": "offline rounds (issue 6)"}
    for i, (arm, by_seed) in enumerate(results.items()):
        color = f"C{i}"
        curves = [curve_of(arm, s) for _, s in sorted(by_seed.items())]
        for steps, success in curves:
            ax.plot(steps, success, color=color, alpha=0.35, lw=1)
        steps = curves[0][0]
        if all(c[0] == steps for c in curves):
            ax.plot(steps, [sum(c[1][j] for c in curves) / len(curves) for j in range(len(steps))], "o-",
                    color=color, lw=2, label=f"{labels.get(arm, arm)} (mean of {len(curves)} seeds)")
    ax.axhline(0.95, color="grey", ls=":", lw=1)
    ax.set_xlabel("environment steps (50 Hz: 20,000 = 400 s of robot time)")
    ax.set_ylabel("success without intervention (100 held-out resets)")
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}", file=sys.stderr)


if __name__ == "__main__":
    sys.exit(main())
