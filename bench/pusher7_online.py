"""The HIL-SERL stage on pusher7_reach (Gymnasium's 7-joint arm) over raw topics, per seed.

    python bench/pusher7_online.py [--seeds 0 1 2] [--env-steps 20000] [--out runs/p7-online]
                                   [--json bench/pusher7_online.json] [--in-process]
                                   [--utd N] [--end-on-success] [--imitate-expert] [--normalize-obs]
                                   [--bc-weight W] [--lr-decay] [--offline-ratio R] [--steer stick]
                                   [--corrector-noise STD]
                                   [--rescore]

The stage as a user of a ros2_control arm runs it: ``offline-rl hil --online --from-topics
--task pusher7_reach`` (lockstep, scripted corrector), the learner joining the arm's raw topics
(joint_states, the controller's commands, the goal) live, from the ``--algo auto`` prior the
stage trains on the task's recorded mix of that seed (``offline-rl collect --task pusher7_reach
--episodes 200 --expert-frac 0.3 --seed 0``, the same bag for every seed, as bench/hil_online.py
uses bags/mix.db3). The curve: success without intervention of the deterministic policy on the
task's 100 held-out resets every ``--eval-every`` environment steps, with the intervention rate
of each window. ``--in-process`` runs the same stage without ROS (no topics: a quicker look).
A seed whose ``summary.json`` exists is not run again, so the script can be resumed. An arm is
named by where it ran and the options it changed (``online_raw_topics_normalize_obs``); the JSON
keeps the other arms it already holds, and the commands that made them, with the digest of the
task each arm ran on (``arm_task_digests``): once the task file changes, the arms measured
on its earlier version stay as ``ARM@DIGEST``. Writes the JSON (each seed's summary, the
command and the machine), the plot beside it, and prints the table of bench/RESULTS.md's
section.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from hil_online import curve_of, run
from offline_rl_core.benchmarks.harness import add_run_facts
from offline_rl_core.common.atomic import write_json_atomic
from offline_rl_core.pipelines.hil_online import rescore
from offline_rl_core.task.spec import load_task
from results_page import hil_table

TASK = "pusher7_reach"
ARM = "online_raw_topics"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--env-steps", type=int, default=20_000)
    p.add_argument("--eval-every", type=int, default=2_500)
    p.add_argument("--out", default="runs/p7-online")
    p.add_argument("--json", default="bench/pusher7_online.json")
    p.add_argument("--in-process", action="store_true", help="the same stage without ROS (no raw topics)")
    p.add_argument("--eval-episodes", type=int, default=100, help="held-out resets per curve point")
    p.add_argument("--task", default=TASK, help="pusher7_reach, or a task file of the same arm")
    p.add_argument("--bag", help="the offline mix (default: OUT/pusher7.db3, collected if absent)")
    p.add_argument("--prior", help="the prior checkpoint (default: the stage trains its --algo auto prior)")
    p.add_argument("--utd", type=int, help="the stage's gradient steps per environment step (default: the stage's)")
    p.add_argument("--imitate-expert", action="store_true",
                   help="the actor's BC term also on the mix's expert episodes (offline-rl hil --imitate-expert)")
    p.add_argument("--normalize-obs", action="store_true",
                   help="actor and critic on observations z-scored by the mix's statistics (offline-rl hil --normalize-obs)")
    p.add_argument("--bc-weight", type=float,
                   help="the actor's BC weight (offline-rl hil --bc-weight; default: the stage's)")
    p.add_argument("--lr-decay", action="store_true",
                   help="learning rates along a cosine to zero over the budget (offline-rl hil --lr-decay)")
    p.add_argument("--offline-ratio", type=float,
                   help="share of each batch from the mix (offline-rl hil --offline-ratio; default: the stage's)")
    p.add_argument("--corrector-noise", type=float,
                   help="std of noise on the scripted corrector's actions (offline-rl hil --corrector-noise)")
    p.add_argument("--steer", choices=("expert", "stick"),
                   help="how the scripted corrector takes over (offline-rl hil --steer; default: the stage's)")
    p.add_argument("--rescore", action="store_true",
                   help="score each finished session's kept weights again, its final weights too (sessions scored "
                        "before the stage scored its final weights), rewriting its summary.json")
    p.add_argument("--end-on-success", action="store_true",
                   help="with --in-process: an episode ends where the simulator judges success (HIL-SERL's rule)")
    args = p.parse_args()
    offline_rl = [sys.executable, "-m", "offline_rl_core"]
    out = Path(args.out)
    bag = Path(args.bag) if args.bag else out / "pusher7.db3"
    if not bag.exists():  # the task's mix, as `make bag` is pusher_reach's
        bag.parent.mkdir(parents=True, exist_ok=True)
        subprocess.run([*offline_rl, "collect", "--task", args.task, "--episodes", "200", "--expert-frac", "0.3",
                        "--seed", "0", "--out", str(bag)], check=True)
    # an arm is named by where it ran and the options it changed, so one JSON holds several
    arm = "_".join(["online_in_process" if args.in_process else ARM,
                    *(name for name in ("normalize_obs", "imitate_expert", "end_on_success") if getattr(args, name)),
                    *([f"bc{args.bc_weight:g}"] if args.bc_weight is not None else []),
                    *(["lr_decay"] if args.lr_decay else []),
                    *([f"offline{args.offline_ratio:g}"] if args.offline_ratio is not None else []),
                    *([f"noise{args.corrector_noise:g}"] if args.corrector_noise else []),
                    *([args.steer] if args.steer and args.steer != "expert" else [])])
    previous = Path(args.json)
    store: dict = json.loads(previous.read_text()) if previous.exists() else {}
    add_run_facts(store)  # the file's arms come from several commands: each joins its `commands`
    results: dict = store.setdefault("arms", {})
    task = load_task(args.task)
    digests: dict = store.setdefault("arm_task_digests", {})
    mark_older_task_records(results, digests, task.digest, store.get("task_digest"))
    results.pop(arm, None)  # this arm's seeds come from their summaries (a seed already run is read back)
    for seed in args.seeds:
        run_dir = out / f"seed{seed}" / arm
        cmd = [*offline_rl, "hil", "--online", "--task", args.task, "--bag", str(bag), "--seed", str(seed),
               "--env-steps", str(args.env_steps), "--eval-every", str(args.eval_every),
               "--eval-episodes", str(args.eval_episodes), "--logger", "none", "--out", str(run_dir)]
        cmd += ["--prior", args.prior] if args.prior else []
        cmd += ["--utd", str(args.utd)] if args.utd else []
        cmd += ["--end-on-success"] if args.end_on_success else []
        cmd += ["--imitate-expert"] if args.imitate_expert else []
        cmd += ["--normalize-obs"] if args.normalize_obs else []
        cmd += ["--bc-weight", str(args.bc_weight)] if args.bc_weight is not None else []
        cmd += ["--lr-decay"] if args.lr_decay else []
        cmd += ["--offline-ratio", str(args.offline_ratio)] if args.offline_ratio is not None else []
        cmd += ["--steer", args.steer] if args.steer else []
        cmd += ["--corrector-noise", str(args.corrector_noise)] if args.corrector_noise else []
        cmd += ["--in-process"] if args.in_process else ["--from-topics"]
        if args.rescore and (run_dir / "summary.json").exists() and not args.in_process:
            rescore(run_dir)
        results.setdefault(arm, {})[str(seed)] = run(cmd, run_dir / "summary.json")
        store.update(task=task.name, task_digest=task.digest)
        digests[arm] = task.digest
        write_json_atomic(args.json, store)
    print(hil_table(results))
    plot(results, Path(args.json).with_suffix(".png"), newest=arm)
    return 0


def mark_older_task_records(records: dict, digests: dict, digest: str, default: str | None = None) -> None:
    """A record (an arm, a probe) is its settings on one version of the task: one measured on
    another (``digests[name]``, else ``default``: the file's digest from before they were
    kept per record) stays as ``NAME@DIGEST``, so that it is neither overwritten by nor read
    as the same settings on this task file."""
    for name in list(records):
        older = digests.setdefault(name, default)
        if older not in (None, digest) and "@" not in name:
            records[f"{name}@{older}"] = records.pop(name)
            digests[f"{name}@{older}"] = digests.pop(name)


def plot(results: dict, path: Path, newest: str | None = None) -> None:
    """Success (and the intervention rate) against environment steps per seed: the arm
    ``newest`` (default: the last) drawn bold, the JSON's other arms faint beside it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10.5, 5.0))
    newest = newest or list(results)[-1]
    for arm in results:
        bold = arm == newest  # the arm this run measured stands out
        short = arm.replace("online_raw_topics", "raw topics").replace("online_in_process", "in process")
        for i, (seed, summary) in enumerate(sorted(results[arm].items(), key=lambda kv: int(kv[0]))):
            steps, success = curve_of(arm, summary)
            ax.plot(steps, success, "o-" if bold else ".:", color=f"C{i}", lw=2 if bold else 1,
                    alpha=1.0 if bold else 0.35, label=f"{short}, seed {seed}")
            if bold:
                ax.plot(steps, [p["intervention_rate"] for p in summary["curve"]], "s--", color=f"C{i}", lw=1,
                        alpha=0.6, label=f"seed {seed}: intervention rate (window)")
    ax.axhline(0.95, color="grey", ls=":", lw=1)
    period = load_task(TASK).control_period
    ax.set_xlabel(f"environment steps ({1 / period:g} Hz: 20,000 = {20_000 * period:g} s of robot time)")
    ax.set_ylabel("100 held-out resets / share of steps")
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6, loc="center left", bbox_to_anchor=(1.01, 0.5))
    ax.set_title(f"{TASK}: the online stage over raw topics (auto prior, scripted corrector, lockstep)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight")  # the legend beside the axes
    print(f"wrote {path}", file=sys.stderr)


if __name__ == "__main__":
    sys.exit(main())
